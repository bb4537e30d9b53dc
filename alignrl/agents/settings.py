"""The learners' settings, without their algorithms: what a config needs to know of a
learner (its title, its settings and their defaults) before torch is imported.

`LearnerConfig` (alignrl/config/learner.py) checks an experiment file against these, so a
command that only reads a config (`alignrl baselines`, `record`, `scenarios`, `--help`) never
loads torch. Each learner's class (alignrl/agents/sac.py, ppo.py) takes its `config_type` and
`schedule_defaults` from here; `SHIPPED` names where each class lives, and
alignrl/agents/learners.py imports it there on first use.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

__all__ = ["SAC_SCHEDULE", "SHIPPED", "LearnerSettings", "PPOConfig", "SACConfig"]

# How a SAC member gathers experience and how often it learns (not part of SACConfig, which
# is one gradient step): uniform random actions first, then updates per env step.
SAC_SCHEDULE = {
    "updates_per_step": 1.0,
    "buffer_size": 200_000,
    "learning_starts": 1000,
    "random_steps": 2000,
}


@dataclass(frozen=True)
class SACConfig:
    encoder: str = "mlp"  # history encoder of every network: mlp, gru or gtrxl
    encoder_kwargs: dict[str, Any] = field(default_factory=dict)
    # Hidden layers of the heads. The critics' action and secret join the encoding here, so
    # they need hidden layers: a linear head makes Q linear in the action, and the policy
    # is then pushed to the bounds of the action box.
    hidden: tuple[int, ...] = (256, 256)
    learning_rate: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005  # target V follows at this rate per update
    batch_size: int = 256
    initial_alpha: float = 0.2
    target_entropy: float | None = None  # default: -(action dimensions)
    secret_critics: bool = True  # critics see optimum - setting (training only)
    # Q1, Q2 and V read one history encoder (trained by all three losses) instead of one
    # each: 3 encoder passes per update instead of 5, what makes GTrXL affordable on a CPU.
    # The twin Qs keep separate heads; the policy always has its own encoder.
    shared_critic_encoder: bool = False
    max_grad_norm: float = 10.0


@dataclass(frozen=True)
class PPOConfig:
    # The network settings every learner shares default alike (alignrl/config/learner.py reads
    # them from here and from SACConfig, and refuses a disagreement).
    encoder: str = "mlp"  # history encoder of the policy and the value network
    encoder_kwargs: dict[str, Any] = field(default_factory=dict)
    hidden: tuple[int, ...] = (256, 256)  # hidden widths of the heads
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2  # the surrogate's ratio is clipped to 1 +- clip_range
    entropy_coef: float = 0.0
    value_coef: float = 0.5
    epochs: int = 10  # passes over each rollout
    batch_size: int = 256  # transitions per minibatch
    rollout_steps: int = 64  # env steps per env slot between updates
    initial_log_std: float = -0.5
    secret_critics: bool = True  # the value network sees optimum - setting (training only)
    max_grad_norm: float = 0.5


class LearnerSettings(NamedTuple):
    """What the registry tells of a learner before its class is imported. A shipped
    learner's class takes its `title`, `config_type` and `schedule_defaults` from here."""

    title: str
    config_type: type
    schedule_defaults: Mapping[str, float]


# The learners alignrl ships: name -> (where the class is, "module:attribute"; its settings).
SHIPPED: dict[str, tuple[str, LearnerSettings]] = {
    "sac": ("alignrl.agents.sac:SACLearner", LearnerSettings("SAC", SACConfig, SAC_SCHEDULE)),
    "ppo": ("alignrl.agents.ppo:PPOLearner", LearnerSettings("PPO", PPOConfig, {})),
}

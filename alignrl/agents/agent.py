"""A member of a team: one learner with its identity, its hyperparameters and its experience.

The trainer and the league see members only through this class: `explore` during training,
`act` for evaluation and deployment, `observe` to store what happened, `learn` to run the
updates that are due, `update` for one learner step on a batch, and state that saves and
loads without unpickling (tensors, numbers, strings, lists and dicts only).

    spec = MemberSpec(id="aligner-0", team="aligner", algorithm="sac", ...)
    agent = Agent(spec)
    action = agent.explore(observation, rng)
    agent.observe(observation, secret, action, reward, next_observation, next_secret, done)
    for metrics in agent.learn(rng): ...
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from alignrl.agents.ppo import PPO, PPOConfig, RolloutBuffer
from alignrl.agents.replay import Batch, ReplayBuffer
from alignrl.agents.sac import SAC, SACConfig

__all__ = ["ALGORITHMS", "TEAMS", "Agent", "MemberSpec"]

TEAMS = ("aligner", "misaligner")
ALGORITHMS = ("sac", "ppo")
MEMBER_FORMAT = "alignrl-member-1"

# How a SAC member gathers experience and how often it learns (not part of SACConfig, which
# is one gradient step): uniform random actions first, then updates per env step.
SAC_SCHEDULE = {
    "updates_per_step": 1.0,
    "buffer_size": 200_000,
    "learning_starts": 1000,
    "random_steps": 2000,
}
UPDATE_METRICS = {
    "sac": ("policy_loss", "q1_loss", "q2_loss", "v_loss", "entropy", "alpha"),
    "ppo": ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction"),
}


def _learner_fields(algorithm: str) -> set[str]:
    config = SACConfig if algorithm == "sac" else PPOConfig
    return {f.name for f in dataclasses.fields(config)}


@dataclass(frozen=True)
class MemberSpec:
    """Who a member is: identity, team, learner, shapes and hyperparameters.

    `hyperparameters` holds the learner's settings (SACConfig or PPOConfig fields, encoder
    included) and, for SAC, its schedule (SAC_SCHEDULE); anything else is an error.
    """

    id: str
    team: str
    algorithm: str
    observation_shape: tuple[int, int]
    action_dim: int
    secret_dim: int
    hyperparameters: dict[str, Any] = field(default_factory=dict)
    parent: str | None = None  # the member this one was copied from (population lineage)

    def __post_init__(self) -> None:
        where = f"member {self.id!r}"
        if not self.id:
            raise ValueError("a member needs a non-empty id")
        if self.team not in TEAMS:
            raise ValueError(f"{where}: team {self.team!r} is not one of {', '.join(TEAMS)}")
        if self.algorithm not in ALGORITHMS:
            raise ValueError(
                f"{where}: algorithm {self.algorithm!r} is not one of {', '.join(ALGORITHMS)}"
            )
        known = _learner_fields(self.algorithm) | (
            set(SAC_SCHEDULE) if self.algorithm == "sac" else set()
        )
        unknown = sorted(set(self.hyperparameters) - known)
        if unknown:
            raise ValueError(
                f"{where}: {self.algorithm} has no hyperparameter {', '.join(map(repr, unknown))}"
                f"; known: {', '.join(sorted(known))}"
            )
        object.__setattr__(self, "observation_shape", tuple(int(n) for n in self.observation_shape))

    @property
    def encoder(self) -> str:
        default = SACConfig.encoder if self.algorithm == "sac" else PPOConfig.encoder
        return str(self.hyperparameters.get("encoder", default))

    @property
    def architecture(self) -> str:
        """E.g. 'gtrxl(d_model=32, heads=2, layers=1)' or 'mlp'."""
        options = self.hyperparameters.get("encoder_kwargs") or {}
        inner = ", ".join(f"{key}={value}" for key, value in sorted(options.items()))
        return f"{self.encoder}({inner})" if inner else self.encoder

    def learner_config(self) -> SACConfig | PPOConfig:
        fields = _learner_fields(self.algorithm)
        chosen = {k: v for k, v in self.hyperparameters.items() if k in fields}
        if "hidden" in chosen:
            chosen["hidden"] = tuple(chosen["hidden"])
        return (SACConfig if self.algorithm == "sac" else PPOConfig)(**chosen)

    def schedule(self) -> dict[str, float]:
        """The SAC schedule (SAC_SCHEDULE with this member's values); empty for PPO."""
        if self.algorithm != "sac":
            return {}
        own = self.hyperparameters
        return {key: own.get(key, default) for key, default in SAC_SCHEDULE.items()}

    def to_dict(self) -> dict[str, Any]:
        """Plain data: strings, numbers, lists and dicts (safe to store and to print)."""
        data = dataclasses.asdict(self)
        data["observation_shape"] = list(self.observation_shape)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MemberSpec:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"member record has unknown fields {', '.join(unknown)}")
        return cls(**data)


class Agent:
    """A member: its spec, its learner (SAC or PPO) and its experience store."""

    def __init__(self, spec: MemberSpec, envs: int = 1, device: str | torch.device = "cpu") -> None:
        self.spec = spec
        self.envs = envs
        config = spec.learner_config()
        shape, actions, secrets = spec.observation_shape, spec.action_dim, spec.secret_dim
        self.learner: SAC | PPO
        if spec.algorithm == "sac":
            self.learner = SAC(shape, actions, secrets, config, device)
            schedule = spec.schedule()
            self.replay = ReplayBuffer(int(schedule["buffer_size"]), shape, secrets, actions)
        else:
            self.learner = PPO(shape, actions, secrets, config, device)
            self.rollout = RolloutBuffer(config.rollout_steps, envs, shape, secrets, actions)
            self._pending_pre_tanh: np.ndarray | None = None
        self.steps_seen = 0  # transitions observed (env steps x slots)
        self._update_debt = 0.0

    @property
    def id(self) -> str:
        return self.spec.id

    @property
    def metric_names(self) -> tuple[str, ...]:
        return UPDATE_METRICS[self.spec.algorithm]

    @property
    def updates(self) -> int:
        return self.learner.updates

    # --- acting -------------------------------------------------------------------------

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Actions in (-1, 1) for a batch (B, H, F) or one history (H, F); no side effects."""
        return self.learner.act(observation, deterministic)

    def explore(self, observation: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Training actions for a batch of histories: SAC samples its policy after its random
        warm-up; PPO samples and keeps the pre-squash sample for `observe`."""
        if isinstance(self.learner, SAC):
            if self.steps_seen < self.spec.schedule()["random_steps"]:
                return rng.uniform(-1.0, 1.0, (len(observation), self.spec.action_dim))
            return self.learner.act(observation, deterministic=False)
        pre_tanh = self.learner.sample(observation)
        self._pending_pre_tanh = pre_tanh
        return np.tanh(pre_tanh)

    # --- experience and learning ------------------------------------------------------

    def observe(
        self,
        observation: np.ndarray,
        secret: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        next_observation: np.ndarray,
        next_secret: np.ndarray,
        done: np.ndarray,
        slots: np.ndarray | None = None,
    ) -> None:
        """Store one env step of every slot, or of the env slots `slots` where only some
        moved (next_observation of a done slot: the episode's last history, not the reset
        one)."""
        done = done.astype(np.float32)
        if isinstance(self.learner, SAC):
            self.replay.add(
                observation, secret, action, reward, next_observation, next_secret, done
            )
        else:
            if self._pending_pre_tanh is None:
                raise RuntimeError(f"member {self.id}: observe() needs the explore() before it")
            self.rollout.add(
                observation,
                secret,
                self._pending_pre_tanh,
                reward,
                next_observation,
                next_secret,
                done,
                slots,
            )
            self._pending_pre_tanh = None
        self.steps_seen += len(reward)

    def learn(
        self, rng: np.random.Generator, new_steps: int | None = None
    ) -> list[dict[str, float]]:
        """The updates due after the last `observe`: SAC runs updates_per_step per new
        transition once past learning_starts; PPO updates when its rollout is full."""
        rows = []
        if isinstance(self.learner, SAC):
            schedule = self.spec.schedule()
            batch = self.learner.config.batch_size
            if self.steps_seen < schedule["learning_starts"] or self.replay.size < batch:
                return rows
            self._update_debt += (new_steps or self.envs) * schedule["updates_per_step"]
            while self._update_debt >= 1.0:
                rows.append(self.update(self.replay.sample(batch, rng)))
                self._update_debt -= 1.0
        elif self.rollout.full:
            rows.append(self.learner.update(self.rollout.rollout(), rng, self.id))
            self.rollout.clear()
        return rows

    def update(self, batch: Any, rng: np.random.Generator | None = None) -> dict[str, float]:
        """One learner step: a SAC gradient step on a replay Batch, or PPO's epochs on a
        Rollout. A non-finite loss raises NonFiniteError naming this member."""
        if isinstance(self.learner, SAC):
            if not isinstance(batch, Batch):
                raise TypeError(f"member {self.id}: SAC updates on a replay Batch")
            return self.learner.update(batch, self.id)
        return self.learner.update(batch, rng or np.random.default_rng(self.updates), self.id)

    def set_learning_rate(self, learning_rate: float) -> None:
        """Every optimizer of the learner steps at `learning_rate` from now on (PBT)."""
        if isinstance(self.learner, SAC):
            optimizers = [
                self.learner.actor_optimizer,
                self.learner.critic_optimizer,
                self.learner.alpha_optimizer,
            ]
        else:
            optimizers = [self.learner.optimizer]
        for optimizer in optimizers:
            for group in optimizer.param_groups:
                group["lr"] = learning_rate

    # --- state --------------------------------------------------------------------------

    def state_dict(self, replay: bool = False) -> dict[str, Any]:
        """Spec, weights, optimizers and counters; with replay=True, the experience too
        (SAC's replay, PPO's rollout in progress)."""
        state: dict[str, Any] = {
            "format": MEMBER_FORMAT,
            "spec": self.spec.to_dict(),
            "learner": self.learner.state_dict(),
            "steps_seen": self.steps_seen,
            "update_debt": self._update_debt,
        }
        if replay:
            store = self.replay if isinstance(self.learner, SAC) else self.rollout
            state["replay"] = store.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("format") != MEMBER_FORMAT:
            raise ValueError(f"member state format {state.get('format')!r} is not {MEMBER_FORMAT}")
        saved = MemberSpec.from_dict(state["spec"])
        if (saved.algorithm, saved.observation_shape, saved.action_dim, saved.secret_dim) != (
            self.spec.algorithm,
            self.spec.observation_shape,
            self.spec.action_dim,
            self.spec.secret_dim,
        ):
            raise ValueError(
                f"member {self.id}: the saved state is of {saved.algorithm} with observation "
                f"{saved.observation_shape}, {saved.action_dim} actions; this member is "
                f"{self.spec.algorithm} with {self.spec.observation_shape}, "
                f"{self.spec.action_dim} actions"
            )
        self.learner.load_state_dict(state["learner"])
        self.steps_seen = int(state["steps_seen"])
        self._update_debt = float(state["update_debt"])
        if "replay" in state:
            replay = {
                key: value.numpy() if isinstance(value, torch.Tensor) else value
                for key, value in state["replay"].items()
            }
            store = self.replay if isinstance(self.learner, SAC) else self.rollout
            store.load_state_dict(replay)

    def save(self, path: str | Path, replay: bool = False) -> None:
        """Atomically write this member (weights_only-loadable)."""
        from alignrl.checkpoints import save_checkpoint

        save_checkpoint(path, self.state_dict(replay=replay))

    @classmethod
    def load(cls, path: str | Path, envs: int = 1, device: str | torch.device = "cpu") -> Agent:
        """A member as saved by `save` (its spec travels in the file)."""
        from alignrl.checkpoints import CheckpointError, load_checkpoint

        state = load_checkpoint(path, device)
        try:
            agent = cls(MemberSpec.from_dict(state["spec"]), envs, device)
            agent.load_state_dict(state)
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CheckpointError(f"{path}: not a usable member checkpoint: {error}") from None
        return agent

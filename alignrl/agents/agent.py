"""A member of a team: one learner with its identity, its hyperparameters and its experience.

The trainer and the league see members only through this class: `explore` during training,
`act` for evaluation and deployment, `observe` to store what happened, `learn` to run the
updates that are due, `update` for one learner step on a batch, and state that saves and
loads without unpickling (tensors, numbers, strings, lists and dicts only).

    spec = MemberSpec(id="aligner-0", team="aligner", algorithm="sac", ...)
    agent = Agent(spec)
    action = agent.explore(observation, rng)
    step = Transition(observation, secret, action, reward, next_observation, next_secret, done)
    agent.observe(step)
    for metrics in agent.learn(rng): ...

What is particular to a learner (SAC, PPO, ...) lives with the learner and is found by the
spec's algorithm in `alignrl.agents.learners.LEARNERS`; the Agent delegates to it.

Where the acting happens elsewhere (a Ray worker at a microscope), `policy_state` is what
acting needs, `from_policy_state` builds the acting copy there, `explore_rows` draws each
row's randomness from its own generator, and `observe` stores what came back (a Transition
with its `pre_tanh`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from alignrl.agents.learners import LEARNERS, Learner, learner_class, learner_defaults
from alignrl.agents.records import (
    check_learner_state,
    check_record,
    check_tensors,
    finite_problem,
    is_integer,
    is_number,
    tensor_problem,
)
from alignrl.transitions import Transition

__all__ = [
    "MEMBER_FORMAT",
    "POLICY_FORMAT",
    "TEAMS",
    "Agent",
    "MemberSpec",
    "check_learner_state",
    "check_tensors",
    "finite_problem",
    "tensor_problem",
]

TEAMS = ("aligner", "misaligner")
MEMBER_FORMAT = "alignrl-member-1"
POLICY_FORMAT = "alignrl-policy-1"  # the acting network alone (Agent.policy_state)
OPTIONAL_FIELDS = ("hyperparameters", "parent")
STATE_KEYS = ("format", "spec", "learner", "steps_seen", "update_debt")  # + "replay"


@dataclass(frozen=True)
class MemberSpec:
    """Who a member is: identity, team, learner, shapes and hyperparameters.

    `hyperparameters` holds the learner's settings (the fields of its config dataclass,
    encoder included) and its schedule (SAC: updates_per_step, buffer_size, ...); anything
    else is an error. A setting left out takes the learner's default.
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
        if self.algorithm not in LEARNERS:
            raise ValueError(
                f"{where}: algorithm {self.algorithm!r} is not one of {', '.join(LEARNERS)}"
            )
        known = set(learner_defaults(self.algorithm))
        unknown = sorted(set(self.hyperparameters) - known)
        if unknown:
            raise ValueError(
                f"{where}: {self.algorithm} has no hyperparameter {', '.join(map(repr, unknown))}"
                f"; known: {', '.join(sorted(known))}"
            )
        object.__setattr__(self, "observation_shape", tuple(int(n) for n in self.observation_shape))

    @property
    def learner_type(self) -> type[Learner]:
        return learner_class(self.algorithm)

    @property
    def encoder(self) -> str:
        default = learner_defaults(self.algorithm).get("encoder", "none")
        return str(self.hyperparameters.get("encoder", default))

    @property
    def architecture(self) -> str:
        """E.g. 'gtrxl(d_model=32, heads=2, layers=1)' or 'mlp'."""
        options = self.hyperparameters.get("encoder_kwargs") or {}
        inner = ", ".join(f"{key}={value}" for key, value in sorted(options.items()))
        return f"{self.encoder}({inner})" if inner else self.encoder

    def learner_config(self) -> Any:
        """The learner's config dataclass with this member's settings."""
        config_type = self.learner_type.config_type
        fields = {f.name for f in dataclasses.fields(config_type)}
        chosen = {k: v for k, v in self.hyperparameters.items() if k in fields}
        if "hidden" in chosen:
            chosen["hidden"] = tuple(chosen["hidden"])
        return config_type(**chosen)

    def schedule(self) -> dict[str, float]:
        """The learner's schedule (how it gathers experience) with this member's values;
        empty for a learner without one (PPO)."""
        own = self.hyperparameters
        defaults = self.learner_type.schedule_defaults
        return {key: own.get(key, default) for key, default in defaults.items()}

    def to_dict(self) -> dict[str, Any]:
        """Plain data: strings, numbers, lists and dicts (safe to store and to print)."""
        data = dataclasses.asdict(self)
        data["observation_shape"] = list(self.observation_shape)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MemberSpec:
        """The spec a saved record holds, its fields checked by type (a record comes from a
        file: a hand-edited or foreign one is refused here, not deep inside a network)."""
        if not isinstance(data, dict):
            raise ValueError(f"member record is a {type(data).__name__}, not a mapping")
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(map(str, data)) - set(names))
        if unknown:
            raise ValueError(f"member record has unknown fields {', '.join(unknown)}")
        missing = [name for name in names if name not in data and name not in OPTIONAL_FIELDS]
        if missing:
            raise ValueError(f"member record has no field {', '.join(missing)}")
        check_record(data)
        return cls(**data)


class Agent:
    """A member: its spec and its learner (LEARNERS[spec.algorithm]), which holds the
    networks, the optimizers and the experience."""

    def __init__(self, spec: MemberSpec, envs: int = 1, device: str | torch.device = "cpu") -> None:
        self.spec = spec
        self.envs = envs
        self.learner: Learner = spec.learner_type(
            spec.observation_shape,
            spec.action_dim,
            spec.secret_dim,
            spec.learner_config(),
            spec.schedule(),
            envs,
            device,
        )
        self.steps_seen = 0  # transitions observed (env steps x slots)

    def __getattr__(self, name: str) -> Any:
        # The experience under its learner's own name too (`agent.replay` of a SAC member,
        # `agent.rollout` of a PPO one), as code written before the registry reads it.
        learner = self.__dict__.get("learner")
        if learner is not None and name == learner.experience_name:
            return learner.experience
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def id(self) -> str:
        return self.spec.id

    @property
    def experience(self) -> Any:
        """What the learner has stored (SAC: its replay; PPO: the rollout in progress)."""
        return self.learner.experience

    @property
    def metric_names(self) -> tuple[str, ...]:
        return self.learner.metric_names

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
        return self.learner.explore(observation, rng, self.steps_seen)

    def explore_rows(
        self,
        observation: np.ndarray,
        generators: Sequence[np.random.Generator],
        warm_up: bool = True,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Stochastic actions for a batch whose row i draws its randomness from
        `generators[i]` alone (one generator per match): a row's action then does not depend
        on the rows beside it nor on the process that computed it. With `warm_up`, a SAC
        member still in its random warm-up acts uniformly at random, as in `explore`.
        Returns the actions and, for PPO, the pre-squash sample `observe` stores (a
        Transition's `pre_tanh`; None for SAC)."""
        return self.learner.explore_rows(observation, generators, self.steps_seen, warm_up)

    # --- experience and learning ------------------------------------------------------

    def observe(self, transition: Transition) -> None:
        """Store one env step of every slot, or of the env slots `transition.slots` where
        only some moved (next_observation of a done slot: the episode's last history, not the
        reset one). PPO stores the pre-squash sample of the `explore` before, or the
        transition's `pre_tanh` where the actions were sampled elsewhere (`explore_rows` in a
        Ray worker)."""
        done = transition.done.astype(np.float32)
        self.learner.observe(dataclasses.replace(transition, done=done), self.id)
        self.steps_seen += len(transition)

    def learn(
        self,
        rng: np.random.Generator,
        new_steps: int | None = None,
        train_policy: bool = True,
    ) -> list[dict[str, float]]:
        """The updates due after the last `observe`: SAC runs updates_per_step per new
        transition once past learning_starts; PPO updates when its rollout is full.
        `train_policy=False`: the critics learn, the policy stays as it is."""
        new = new_steps or self.envs
        return self.learner.learn(rng, self.steps_seen, new, self.id, train_policy)

    def update(
        self, batch: Any, rng: np.random.Generator | None = None, train_policy: bool = True
    ) -> dict[str, float]:
        """One learner step: a SAC gradient step on a Transition batch of its replay, or PPO's
        epochs on a Rollout. A non-finite loss raises NonFiniteError naming this member."""
        return self.learner.learn_from(batch, rng, self.id, train_policy)

    def set_learning_rate(self, learning_rate: float) -> None:
        """Every optimizer of the learner steps at `learning_rate` from now on (PBT)."""
        for optimizer in self.learner.optimizers:
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
            "update_debt": self.learner.update_debt,
        }
        if replay:
            state["replay"] = self.learner.experience.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take a saved state (state_dict) whole, or refuse it untouched: a ValueError
        naming the first key or tensor that does not fit this member's networks (wrong
        shape or dtype, missing, unexpected, not a tensor, NaN or infinite)."""
        if not isinstance(state, dict):
            raise ValueError(f"member state is a {type(state).__name__}, not a mapping")
        if state.get("format") != MEMBER_FORMAT:
            raise ValueError(f"member state format {state.get('format')!r} is not {MEMBER_FORMAT}")
        missing = [key for key in STATE_KEYS if key not in state]
        unexpected = sorted(set(map(str, state)) - {*STATE_KEYS, "replay"})
        if missing or unexpected:
            raise ValueError(
                f"member state has no {', '.join(missing)}"
                if missing
                else f"member state has unexpected key(s) {', '.join(unexpected)}"
            )
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
        check_learner_state(state["learner"], self.learner)
        steps_seen, update_debt = state["steps_seen"], state["update_debt"]
        if not (is_integer(steps_seen) and steps_seen >= 0):
            raise ValueError(f"steps_seen is {steps_seen!r}, not a whole number >= 0")
        if not (is_number(update_debt) and math.isfinite(update_debt) and update_debt >= 0):
            raise ValueError(f"update_debt is {update_debt!r}, not a finite number >= 0")
        if "replay" in state and not isinstance(state["replay"], dict):
            raise ValueError(f"replay is a {type(state['replay']).__name__}, not a mapping")
        self.learner.load_state_dict(state["learner"])
        self.steps_seen = steps_seen
        self.learner.update_debt = float(update_debt)
        if "replay" in state:
            replay = {
                key: value.numpy() if isinstance(value, torch.Tensor) else value
                for key, value in state["replay"].items()
            }
            self.learner.experience.load_state_dict(replay)

    def policy_state(self) -> dict[str, Any]:
        """What acting needs, and no more: the spec, the acting network's weights (SAC's
        actor, PPO's policy; on the CPU) and steps_seen (SAC's random warm-up)."""
        network = self.learner.acting_network
        return {
            "format": POLICY_FORMAT,
            "spec": self.spec.to_dict(),
            "policy": {k: v.cpu() for k, v in network.state_dict().items()},
            "steps_seen": self.steps_seen,
        }

    def load_policy_state(self, state: dict[str, Any]) -> None:
        """Take the acting network's weights and steps_seen of `policy_state`; critics,
        optimizers and experience are left as they are."""
        if not isinstance(state, dict) or state.get("format") != POLICY_FORMAT:
            found = state.get("format") if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"policy state format {found!r} is not {POLICY_FORMAT}")
        spec = state.get("spec")
        if spec != self.spec.to_dict():
            owner = spec.get("id") if isinstance(spec, dict) else None
            raise ValueError(
                f"member {self.id}: the policy state is of another member or other settings "
                f"({owner!r})"
            )
        network = self.learner.acting_network
        check_tensors(state.get("policy"), network.state_dict(), "policy")
        steps_seen = state.get("steps_seen")
        if not (is_integer(steps_seen) and steps_seen >= 0):
            raise ValueError(f"steps_seen is {steps_seen!r}, not a whole number >= 0")
        network.load_state_dict(state["policy"])
        self.steps_seen = steps_seen

    @classmethod
    def from_policy_state(cls, state: dict[str, Any], device: str | torch.device = "cpu") -> Agent:
        """An acting copy of a member (its critics untrained): `act` and `explore_rows` as
        the member would, nothing to learn with."""
        agent = cls(MemberSpec.from_dict(state["spec"]), 1, device)
        agent.load_policy_state(state)
        return agent

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

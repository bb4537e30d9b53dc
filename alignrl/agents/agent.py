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

Where the acting happens elsewhere (a Ray worker at a microscope), `policy_state` is what
acting needs, `from_policy_state` builds the acting copy there, `explore_rows` draws each
row's randomness from its own generator, and `observe(..., pre_tanh=...)` stores what came
back.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from alignrl.agents.ppo import PPO, PPOConfig, RolloutBuffer
from alignrl.agents.replay import Batch, ReplayBuffer
from alignrl.agents.sac import SAC, SACConfig

__all__ = [
    "ALGORITHMS",
    "TEAMS",
    "Agent",
    "MemberSpec",
    "check_learner_state",
    "check_tensors",
    "finite_problem",
    "tensor_problem",
]

TEAMS = ("aligner", "misaligner")
ALGORITHMS = ("sac", "ppo")
MEMBER_FORMAT = "alignrl-member-1"
POLICY_FORMAT = "alignrl-policy-1"  # the acting network alone (Agent.policy_state)

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
        _check_record(data)
        return cls(**data)


# --- what a saved member may hold -------------------------------------------------------

OPTIONAL_FIELDS = ("hyperparameters", "parent")
STATE_KEYS = ("format", "spec", "learner", "steps_seen", "update_debt")  # + "replay"
MAX_SIZE = 1 << 16  # rows, features, actions or hidden units: beyond it a record is not ours


def _is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_record(data: dict[str, Any]) -> None:
    """The types of a member record's fields (MemberSpec.from_dict); ValueError naming the
    first field that is wrong."""

    def size(value: Any, low: int) -> bool:
        return _is_integer(value) and low <= value <= MAX_SIZE

    for name in ("id", "team", "algorithm"):
        if not isinstance(data[name], str):
            raise ValueError(f"member record field {name} is {data[name]!r}, not a string")
    shape = data["observation_shape"]
    if not (isinstance(shape, list | tuple) and len(shape) == 2 and all(size(n, 1) for n in shape)):
        raise ValueError(
            f"member record field observation_shape is {shape!r}: it must be [history rows, "
            f"features], two whole numbers from 1 to {MAX_SIZE}"
        )
    if not size(data["action_dim"], 1):
        raise ValueError(
            f"member record field action_dim is {data['action_dim']!r}: it must be a whole "
            f"number from 1 to {MAX_SIZE}"
        )
    if not size(data["secret_dim"], 0):
        raise ValueError(
            f"member record field secret_dim is {data['secret_dim']!r}, not a whole number >= 0"
        )
    hyperparameters = data.get("hyperparameters", {})
    if not isinstance(hyperparameters, dict) or not all(map(_is_name, hyperparameters)):
        raise ValueError("member record field hyperparameters is not a mapping of names")
    hidden = hyperparameters.get("hidden", [1])
    if not (isinstance(hidden, list | tuple) and all(size(n, 1) for n in hidden)):
        raise ValueError(
            f"member record field hyperparameters.hidden is {hidden!r}: it must be a list of "
            f"layer widths, whole numbers from 1 to {MAX_SIZE}"
        )
    for name, value in hyperparameters.items():
        if _is_number(value) and not math.isfinite(value):
            raise ValueError(f"member record field hyperparameters.{name} is {value}")
    parent = data.get("parent")
    if parent is not None and not isinstance(parent, str):
        raise ValueError(f"member record field parent is {parent!r}, not a string or null")


def _is_name(key: Any) -> bool:
    return isinstance(key, str)


def _shape(shape: Sequence[int]) -> str:
    return "(" + ", ".join(str(n) for n in shape) + ("," if len(shape) == 1 else "") + ")"


def tensor_problem(name: str, held: Any, wanted: torch.Tensor) -> str | None:
    """What is wrong with the saved `held` where the network has `wanted`, in words naming
    the tensor; None where it fits (same shape and dtype, every value finite)."""
    if not isinstance(held, torch.Tensor):
        return (
            f"{name} is a {type(held).__name__}, where the spec needs a tensor of shape "
            f"{_shape(wanted.shape)}"
        )
    if held.shape != wanted.shape:
        return f"{name} has shape {_shape(held.shape)}, the spec needs {_shape(wanted.shape)}"
    if held.dtype != wanted.dtype:
        dtypes = (str(held.dtype), str(wanted.dtype))
        found, needed = (text.removeprefix("torch.") for text in dtypes)
        return f"{name} is {found}, the spec needs {needed}"
    return finite_problem(name, held)


def finite_problem(name: str, tensor: torch.Tensor) -> str | None:
    """A tensor holding NaN or infinity, in words; None where every value is finite. A
    network with such a weight answers NaN: it is refused when loaded, never run."""
    if not (tensor.is_floating_point() or tensor.is_complex()):
        return None
    bad = int((~torch.isfinite(tensor)).sum())
    if not bad:
        return None
    return f"{name} contains non-finite values ({bad} of {tensor.numel()} are NaN or infinite)"


def check_tensors(held: Any, wanted: Mapping[str, torch.Tensor], where: str) -> None:
    """The saved tensors `held` are exactly a network's `wanted` ones (names, shapes,
    dtypes, finite values); else ValueError naming the first that is not."""
    if not isinstance(held, dict):
        raise ValueError(f"{where} is a {type(held).__name__}, where the spec needs tensors")
    for name, tensor in wanted.items():
        if name not in held:
            raise ValueError(
                f"{where}.{name} is missing: the spec needs a tensor of shape "
                f"{_shape(tensor.shape)}"
            )
        problem = tensor_problem(f"{where}.{name}", held[name], tensor)
        if problem:
            raise ValueError(problem)
    unexpected = sorted(set(map(str, held)) - set(wanted))
    if unexpected:
        raise ValueError(f"{where}.{unexpected[0]} is not a tensor of the spec's network")


def _check_optimizer(held: Any, optimizer: torch.optim.Optimizer, where: str) -> None:
    """A saved optimizer state fits `optimizer`: as many parameters per group, and each
    parameter's running statistics shaped as the parameter and finite."""
    if not isinstance(held, dict) or set(held) != {"state", "param_groups"}:
        raise ValueError(f"{where} is not an optimizer state (keys state and param_groups)")
    groups = held["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(optimizer.param_groups):
        count = len(groups) if isinstance(groups, list) else type(groups).__name__
        raise ValueError(
            f"{where}.param_groups holds {count} group(s), the spec's optimizer has "
            f"{len(optimizer.param_groups)}"
        )
    parameters: dict[Any, torch.Tensor] = {}
    for index, (saved, own) in enumerate(zip(groups, optimizer.param_groups, strict=True)):
        ids = saved.get("params") if isinstance(saved, dict) else None
        if not isinstance(ids, list) or len(ids) != len(own["params"]):
            count = len(ids) if isinstance(ids, list) else "no list of"
            raise ValueError(
                f"{where}.param_groups[{index}] holds {count} parameters, the spec's network "
                f"has {len(own['params'])}"
            )
        for name, value in saved.items():
            if _is_number(value) and not math.isfinite(value):
                raise ValueError(f"{where}.param_groups[{index}].{name} is {value}")
        parameters.update(zip(ids, own["params"], strict=True))
    state = held["state"]
    if not isinstance(state, dict):
        raise ValueError(f"{where}.state is a {type(state).__name__}, not a mapping")
    for key, entry in state.items():
        if key not in parameters or not isinstance(entry, dict):
            raise ValueError(f"{where}.state[{key!r}] belongs to no parameter of the network")
        for name, value in entry.items():
            if not isinstance(value, torch.Tensor):
                continue
            label = f"{where}.state[{key}].{name}"
            if value.ndim and value.shape != parameters[key].shape:
                raise ValueError(
                    f"{label} has shape {_shape(value.shape)}, the spec needs "
                    f"{_shape(parameters[key].shape)}"
                )
            problem = finite_problem(label, value)
            if problem:
                raise ValueError(problem)


def check_learner_state(held: Any, learner: SAC | PPO) -> None:
    """A saved learner state (SAC.state_dict, PPO.state_dict) fits `learner`: the same keys,
    each network's tensors shaped as this learner's, finite, and its optimizers' statistics
    shaped as their parameters; else ValueError naming the first key or tensor that does
    not ("learner.actor.head.0.weight has shape (64, 256), the spec needs (16, 256)")."""
    wanted = learner.state_dict()
    if not isinstance(held, dict):
        raise ValueError(f"learner is a {type(held).__name__}, not a learner's state")
    for key, value in wanted.items():
        where = f"learner.{key}"
        if key not in held:
            raise ValueError(f"{where} is missing from the saved state")
        own = getattr(learner, key, None)
        if isinstance(own, torch.nn.Module):
            check_tensors(held[key], value, where)
        elif isinstance(own, torch.optim.Optimizer):
            _check_optimizer(held[key], own, where)
        elif isinstance(value, torch.Tensor):
            problem = tensor_problem(where, held[key], value)
            if problem:
                raise ValueError(problem)
        elif _is_integer(value) and not (_is_integer(held[key]) and held[key] >= 0):
            raise ValueError(f"{where} is {held[key]!r}, not a whole number >= 0")
        elif isinstance(value, dict) and not isinstance(held[key], dict):
            raise ValueError(f"{where} is a {type(held[key]).__name__}, not a mapping")
    unexpected = sorted(set(map(str, held)) - set(wanted))
    if unexpected:
        raise ValueError(f"learner.{unexpected[0]} is not part of a {learner_name(learner)} state")


def learner_name(learner: SAC | PPO) -> str:
    return "SAC" if isinstance(learner, SAC) else "PPO"


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
        Returns the actions and, for PPO, the pre-squash sample `observe(pre_tanh=...)`
        stores (None for SAC)."""
        actions = self.spec.action_dim
        if isinstance(self.learner, SAC):
            if warm_up and self.steps_seen < self.spec.schedule()["random_steps"]:
                return np.stack([g.uniform(-1.0, 1.0, actions) for g in generators]), None
        noise = np.stack([g.standard_normal(actions) for g in generators]).astype(np.float32)
        mean, std = self._policy_gaussian(observation)
        # The same reparameterised sample as SAC's Actor.sample and PPO's Normal.sample.
        pre_tanh = mean + std * noise
        return np.tanh(pre_tanh), None if isinstance(self.learner, SAC) else pre_tanh

    @torch.no_grad()
    def _policy_gaussian(self, observation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation of the policy's Gaussian over pre-squash actions."""
        batch = torch.as_tensor(observation, dtype=torch.float32, device=self.learner.device)
        if isinstance(self.learner, SAC):
            mean, log_std = self.learner.actor(batch)
            std = log_std.exp()
        else:
            distribution = self.learner.policy(batch)
            mean, std = distribution.mean, distribution.stddev
        return mean.cpu().numpy(), std.cpu().numpy()

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
        pre_tanh: np.ndarray | None = None,
    ) -> None:
        """Store one env step of every slot, or of the env slots `slots` where only some
        moved (next_observation of a done slot: the episode's last history, not the reset
        one). PPO stores the pre-squash sample of the `explore` before, or `pre_tanh` where
        the actions were sampled elsewhere (`explore_rows` in a Ray worker)."""
        done = done.astype(np.float32)
        if isinstance(self.learner, SAC):
            self.replay.add(
                observation, secret, action, reward, next_observation, next_secret, done
            )
        else:
            sample = pre_tanh if pre_tanh is not None else self._pending_pre_tanh
            if sample is None:
                raise RuntimeError(
                    f"member {self.id}: observe() needs the explore() before it, or pre_tanh"
                )
            self.rollout.add(
                observation,
                secret,
                sample,
                reward,
                next_observation,
                next_secret,
                done,
                slots,
            )
            self._pending_pre_tanh = None
        self.steps_seen += len(reward)

    def learn(
        self,
        rng: np.random.Generator,
        new_steps: int | None = None,
        train_policy: bool = True,
    ) -> list[dict[str, float]]:
        """The updates due after the last `observe`: SAC runs updates_per_step per new
        transition once past learning_starts; PPO updates when its rollout is full.
        `train_policy=False`: the critics learn, the policy stays as it is."""
        rows = []
        if isinstance(self.learner, SAC):
            schedule = self.spec.schedule()
            batch = self.learner.config.batch_size
            if self.steps_seen < schedule["learning_starts"] or self.replay.size < batch:
                return rows
            self._update_debt += (new_steps or self.envs) * schedule["updates_per_step"]
            while self._update_debt >= 1.0:
                rows.append(self.update(self.replay.sample(batch, rng), train_policy=train_policy))
                self._update_debt -= 1.0
        elif self.rollout.full:
            rows.append(self.learner.update(self.rollout.rollout(), rng, self.id, train_policy))
            self.rollout.clear()
        return rows

    def update(
        self, batch: Any, rng: np.random.Generator | None = None, train_policy: bool = True
    ) -> dict[str, float]:
        """One learner step: a SAC gradient step on a replay Batch, or PPO's epochs on a
        Rollout. A non-finite loss raises NonFiniteError naming this member."""
        if isinstance(self.learner, SAC):
            if not isinstance(batch, Batch):
                raise TypeError(f"member {self.id}: SAC updates on a replay Batch")
            return self.learner.update(batch, self.id, train_policy)
        rng = rng or np.random.default_rng(self.updates)
        return self.learner.update(batch, rng, self.id, train_policy)

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
        if not (_is_integer(steps_seen) and steps_seen >= 0):
            raise ValueError(f"steps_seen is {steps_seen!r}, not a whole number >= 0")
        if not (_is_number(update_debt) and math.isfinite(update_debt) and update_debt >= 0):
            raise ValueError(f"update_debt is {update_debt!r}, not a finite number >= 0")
        if "replay" in state and not isinstance(state["replay"], dict):
            raise ValueError(f"replay is a {type(state['replay']).__name__}, not a mapping")
        self.learner.load_state_dict(state["learner"])
        self.steps_seen = steps_seen
        self._update_debt = float(update_debt)
        if "replay" in state:
            replay = {
                key: value.numpy() if isinstance(value, torch.Tensor) else value
                for key, value in state["replay"].items()
            }
            store = self.replay if isinstance(self.learner, SAC) else self.rollout
            store.load_state_dict(replay)

    @property
    def _acting_network(self) -> torch.nn.Module:
        return self.learner.actor if isinstance(self.learner, SAC) else self.learner.policy

    def policy_state(self) -> dict[str, Any]:
        """What acting needs, and no more: the spec, the acting network's weights (SAC's
        actor, PPO's policy; on the CPU) and steps_seen (SAC's random warm-up)."""
        return {
            "format": POLICY_FORMAT,
            "spec": self.spec.to_dict(),
            "policy": {k: v.cpu() for k, v in self._acting_network.state_dict().items()},
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
        check_tensors(state.get("policy"), self._acting_network.state_dict(), "policy")
        steps_seen = state.get("steps_seen")
        if not (_is_integer(steps_seen) and steps_seen >= 0):
            raise ValueError(f"steps_seen is {steps_seen!r}, not a whole number >= 0")
        self._acting_network.load_state_dict(state["policy"])
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

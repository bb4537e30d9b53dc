"""The learners a member can train with, by name: the `Learner` protocol and `LEARNERS`.

A learner is one module (alignrl/agents/sac.py, alignrl/agents/ppo.py) holding the algorithm
and its member-facing class, plus one entry in `LEARNERS`. `Agent` looks its learner up here
once and delegates to it; `MemberSpec` and `LearnerConfig` read from the learner class what
settings it has and their defaults, so neither keeps its own list:

    LEARNERS["sac"].config_type        SACConfig: its field defaults are SAC's defaults
    LEARNERS["sac"].schedule_defaults  how a member gathers experience (replay size, warm-up)
    learner_defaults("sac")            both, as one mapping of hyperparameter -> default

The shipped learners' modules import torch, so `LEARNERS` imports each on first use; until
then what a config checks (`learner_defaults`, `learner_title`) comes from their settings in
alignrl/agents/settings.py, and this module needs no torch.

A new learner: a class that satisfies `Learner` in a module of its own, and one entry in
`SHIPPED` (alignrl/agents/settings.py), or `LEARNERS[name] = cls` at run time, as
tests/test_learners.py does with a toy learner.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Iterator, Mapping, MutableMapping, Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from alignrl.agents.settings import SHIPPED, LearnerSettings

if TYPE_CHECKING:
    import numpy as np
    import torch
    from torch import nn

    from alignrl.transitions import Transition

__all__ = [
    "LEARNERS",
    "Experience",
    "Learner",
    "learner_class",
    "learner_defaults",
    "learner_title",
]


class Experience(Protocol):
    """A learner's store of what happened (SAC's replay, PPO's rollout in progress)."""

    size: int

    def state_dict(self) -> dict[str, Any]: ...  # numpy arrays and numbers only
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class Learner(Protocol):
    """What a member's learner does for its `Agent`.

    The class attributes describe the learner to the registry, the member spec, the config
    and the trainer; an instance holds the networks, the optimizers and the experience of
    one member. Numbers of the member itself (transitions seen, its id for messages) are
    passed in by the Agent.
    """

    name: ClassVar[str]  # its key in LEARNERS and in configs: `algorithm: sac`
    title: ClassVar[str]  # its name in messages: "SAC"
    config_type: ClassVar[type]  # a frozen dataclass of its settings; its defaults are the defaults
    # Settings of how a member gathers experience and how often it learns, beside config_type
    # (which is one update); their defaults. Empty where the learner has none.
    schedule_defaults: ClassVar[Mapping[str, float]]
    metric_names: ClassVar[tuple[str, ...]]  # the figures `learn` returns per update, in order
    experience_name: ClassVar[str]  # what its experience is called: `agent.replay` for SAC
    # Its experience is a replay of past transitions: a transition may be stored late or
    # come from another run (hindsight secrets, a warm start's init_replay).
    keeps_replay: ClassVar[bool]
    # Each update is worth a row of the metrics (PPO: one per rollout), not every n-th.
    logs_every_update: ClassVar[bool]

    config: Any  # an instance of config_type
    device: torch.device
    updates: int  # updates done so far
    update_debt: float  # updates owed but not yet run (0 where env steps do not pace learning)
    experience: Experience

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: Any,
        schedule: Mapping[str, float],
        envs: int,
        device: str | torch.device,
    ) -> None: ...

    @property
    def optimizers(self) -> list[torch.optim.Optimizer]: ...  # all of them (PBT sets their rate)

    @property
    def acting_network(self) -> nn.Module:
        """The network that acts (SAC's actor, PPO's policy): all that `policy_state`
        carries. Export reads its `encoder` and `head`; the head's first action_dim outputs
        are the mean of the pre-squash Gaussian."""
        ...

    def act(self, observation: np.ndarray, deterministic: bool = False) -> np.ndarray: ...

    def explore(
        self, observation: np.ndarray, rng: np.random.Generator, steps_seen: int
    ) -> np.ndarray:
        """Training actions in (-1, 1) for a batch of histories."""
        ...

    def explore_rows(
        self,
        observation: np.ndarray,
        generators: Sequence[np.random.Generator],
        steps_seen: int,
        warm_up: bool,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Training actions whose row i draws from generators[i] alone, and what `observe`
        needs besides them (`pre_tanh`; None where it needs nothing)."""
        ...

    def observe(self, transition: Transition, member: str) -> None:
        """Store one env step of the slots `transition.slots` (all where None); its done is
        float32."""
        ...

    def learn(
        self,
        rng: np.random.Generator,
        steps_seen: int,
        new_steps: int,
        member: str,
        train_policy: bool,
    ) -> list[dict[str, float]]:
        """The updates due now that `new_steps` more transitions are stored."""
        ...

    def learn_from(
        self, batch: Any, rng: np.random.Generator | None, member: str, train_policy: bool
    ) -> dict[str, float]:
        """One update on a batch of its own experience."""
        ...

    def state_dict(self) -> dict[str, Any]: ...  # tensors, numbers, strings, lists, dicts
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class _Registry(MutableMapping[str, "type[Learner]"]):
    """Learner classes by name, in the order registered. A shipped learner is an import path
    until its class is first asked for; `settings` answers for it without importing it."""

    def __init__(self, shipped: Mapping[str, tuple[str, LearnerSettings]]) -> None:
        self._entries: dict[str, type[Learner] | str] = {
            name: where for name, (where, _) in shipped.items()
        }
        self._settings = {name: settings for name, (_, settings) in shipped.items()}

    def __getitem__(self, name: str) -> type[Learner]:
        entry = self._entries[name]
        if isinstance(entry, str):
            module, _, attribute = entry.partition(":")
            entry = self._entries[name] = getattr(importlib.import_module(module), attribute)
        return entry

    def __setitem__(self, name: str, learner: type[Learner]) -> None:
        self._entries[name] = learner

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries  # without importing it

    def __len__(self) -> int:
        return len(self._entries)

    def settings(self, name: str) -> LearnerSettings:
        """The title, settings type and schedule of the learner `name`, imported or not."""
        entry = self._entries[name]
        if isinstance(entry, str):
            return self._settings[name]
        return LearnerSettings(entry.title, entry.config_type, entry.schedule_defaults)


LEARNERS = _Registry(SHIPPED)


def _known(name: str) -> None:
    if name not in LEARNERS:
        raise ValueError(f"unknown learner {name!r}; known learners: {', '.join(LEARNERS)}")


def learner_class(name: str) -> type[Learner]:
    """The learner registered as `name` (a shipped one's module is imported here)."""
    _known(name)
    return LEARNERS[name]


def learner_title(name: str) -> str:
    """The learner's name in messages: "SAC"."""
    _known(name)
    return LEARNERS.settings(name).title


def learner_defaults(name: str) -> dict[str, Any]:
    """Every hyperparameter the learner `name` takes, with its default: the fields of its
    config dataclass, then its schedule. Imports no learner module."""
    _known(name)
    settings = LEARNERS.settings(name)
    defaults = {
        field.name: field.default
        if field.default_factory is dataclasses.MISSING
        else field.default_factory()
        for field in dataclasses.fields(settings.config_type)
    }
    return {**defaults, **settings.schedule_defaults}

"""Where a league's matches are played: the `Backend` contract and the registry of
`backend:` values. `InProcessBackend` steps `envs` apparatus in this process; the Ray backend
(alignrl.league.ray_backend, docs/scaling.md) plays on workers where the microscopes are and
is imported only when a league names it. League sees only the MatchResult either returns.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from alignrl.agents.agent import Agent
from alignrl.config_reading import ConfigError
from alignrl.envs import make_apparatus_copies
from alignrl.envs.core import AlignmentEpisodes
from alignrl.league.config import LeagueConfig
from alignrl.league.matches import (
    Chooser,
    MatchResult,
    learn_from_starts,
    make_anchors,
    make_duel,
    play_round,
)
from alignrl.transitions import Transition

__all__ = ["BACKENDS", "Backend", "InProcessBackend", "backend_class"]


class Backend(Protocol):
    """Where matches are played: in this process, or on Ray workers where the microscopes
    are (docs/scaling.md). League sees only this and the MatchResult it returns."""

    @property
    def complexity(self) -> float: ...

    def set_complexity(self, level: float) -> None: ...

    def play(
        self,
        aligner: Agent,
        misaligner: Agent,
        matches: int,
        rng: np.random.Generator,
        learning: set[str],
        on_episode: Callable[[bool], None] | None = None,
        deterministic: bool = False,
        anchored: bool = False,
    ) -> MatchResult: ...

    def close(self) -> None: ...


class InProcessBackend:
    """Plays matches on `envs` apparatus in this process, in rounds of a DuelBatch: every
    slot starts a match, the aligner steps the unfinished ones until all are done; learning
    members store and learn after every step. The anchors (classical controllers of fixed
    rating) play beside the aligner where asked, if the apparatus can give twins."""

    def __init__(self, config: LeagueConfig) -> None:
        apparatus = make_apparatus_copies(config.apparatus, config.apparatus_args, config.envs)
        self.task = config.resolved_task()
        self.episodes = AlignmentEpisodes(apparatus, self.task, config.history)
        self.duel = make_duel(self.episodes, config.design, config.payoff, config.reference)
        self.duel.set_complexity(config.complexity)
        self.anchors = make_anchors(list(config.anchor_ratings()), apparatus)

    @property
    def complexity(self) -> float:
        return self.duel.complexity

    def set_complexity(self, level: float) -> None:
        self.duel.set_complexity(level)

    def play(
        self,
        aligner: Agent,
        misaligner: Agent,
        matches: int,
        rng: np.random.Generator,
        learning: set[str],
        on_episode: Callable[[bool], None] | None = None,
        deterministic: bool = False,
        anchored: bool = False,
    ) -> MatchResult:
        """`matches` matches; members whose id is in `learning` store and learn, the others
        act with their stochastic policy (their mean action if `deterministic`: how they are
        judged) and change nothing. `anchored`: the anchors align the same columns too."""
        duel, result = self.duel, MatchResult()
        result.updates = {member.id: [] for member in (aligner, misaligner)}

        def chooser(agent: Agent) -> Chooser:
            if agent.id in learning:
                return lambda inputs, slots: (agent.explore(inputs, rng), None)
            return lambda inputs, slots: (agent.act(inputs, deterministic=deterministic), None)

        def learn_step(step: Transition) -> None:
            if aligner.id in learning:
                aligner.observe(step)
                result.updates[aligner.id] += aligner.learn(rng, new_steps=len(step))

        remaining = matches
        while remaining > 0:
            count = min(duel.n, remaining)
            remaining -= count
            seeds = [int(s) for s in rng.integers(0, 2**31 - 1, count)]
            played = play_round(
                duel,
                seeds,
                chooser(misaligner),
                chooser(aligner),
                learn_step,
                self.anchors if anchored else (),
            )
            # The curriculum's complexity is read when a round begins: reporting each match
            # at the end of its round changes nothing.
            for slot in played.finish_order:
                payoff = played.returns[slot] - played.scores[slot]
                result.add(
                    played.successes[slot],
                    played.acquisitions[slot],
                    played.returns[slot],
                    payoff,
                    played.rated[slot],
                    played.designs[slot],
                    played.anchors_of(slot),
                )
                if on_episode:
                    on_episode(bool(played.successes[slot]))
            if misaligner.id in learning:
                result.updates[misaligner.id] += learn_from_starts(
                    misaligner,
                    played.rows,
                    played.starts,
                    played.scores - played.returns,
                    rng,
                    slots=np.arange(count),
                    pre_tanh=played.starts_pre_tanh,
                )
        return result

    def close(self) -> None:
        """Nothing to release: the apparatus live in this process."""


def _ray_backend() -> type[Backend]:
    try:
        from alignrl.league.ray_backend import RayBackend
    except ImportError as error:
        raise ConfigError(
            f"backend: ray needs the ray package ({error}): pip install 'alignrl[ray]'"
        ) from None
    return RayBackend


# One entry per `backend:` value; each gives the backend class (the Ray one imported only
# when it is chosen).
BACKENDS: dict[str, Callable[[], type[Backend]]] = {
    "inprocess": lambda: InProcessBackend,
    "ray": _ray_backend,
}


def backend_class(name: str) -> type[Backend]:
    """The backend a league's `backend:` names (ConfigError where it cannot run here)."""
    return BACKENDS[name]()

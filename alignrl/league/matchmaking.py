"""Who plays whom: each team's opponent pool, and the matchmaker that picks an iteration's pair.

A team's pool holds its active members, which learn, and frozen snapshots of them taken on the
league's schedule, which never learn: playing old selves keeps a learner from forgetting how to
beat strategies it once beat. An iteration's pair is chosen in two steps (seed section 3): the
learner, an active member, in a fixed rotation over teams and members; then its opponent from
the other team's pool, drawn from a mixture of strategies:

- pfsp: prioritized fictitious self-play (Vinyals et al. 2019, AlphaStar): each candidate is
  weighted by f(p), p the learner's win rate against it (0.5 if they never played);
- uniform: every candidate alike;
- latest: the other team's active members only, the opponents as they are now.

Everything random goes through the caller's `numpy.random.Generator`; the pool's state is
plain data.
"""

from __future__ import annotations

import bisect
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from alignrl.config_reading import Count, _Strict
from alignrl.league.ratings import PayoffTable

__all__ = [
    "PFSP_WEIGHTINGS",
    "STRATEGIES",
    "TEAMS",
    "Matchmaker",
    "MatchmakingConfig",
    "OpponentPool",
    "Pairing",
    "Snapshot",
    "latest_probabilities",
    "pfsp_probabilities",
    "uniform_probabilities",
]

# The team names of alignrl.agents.agent.TEAMS, repeated so that the league's pure logic
# imports no torch.
ALIGNER, MISALIGNER = "aligner", "misaligner"
TEAMS = (ALIGNER, MISALIGNER)
# The most members of a team: in its roster, kept best, frozen snapshots kept.
MAX_MEMBERS = 1000
Members = Annotated[Count, Field(le=MAX_MEMBERS)]
SNAPSHOT_MARK = "@"  # "aligner-0@3": member aligner-0 frozen at iteration 3
UNPLAYED_WIN_RATE = 0.5  # PFSP's prior for an opponent the learner never met


def _other_team(team: str) -> str:
    return MISALIGNER if team == ALIGNER else ALIGNER


# PFSP weightings f(p) of the learner's win rate p (Vinyals et al. 2019, Methods).
def _hard(win_rates: np.ndarray) -> np.ndarray:
    """Mostly opponents the learner loses to."""
    return (1.0 - win_rates) ** 2


def _variance(win_rates: np.ndarray) -> np.ndarray:
    """Opponents of about equal strength: the most informative matches."""
    return win_rates * (1.0 - win_rates)


def _linear(win_rates: np.ndarray) -> np.ndarray:
    """A softer `hard`."""
    return 1.0 - win_rates


PFSP_WEIGHTINGS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "hard": _hard,
    "variance": _variance,
    "linear": _linear,
}
PFSPWeighting = Literal[tuple(PFSP_WEIGHTINGS)]  # type: ignore[valid-type]


# A strategy maps the learner's win rate against each candidate and which candidates are
# active members to a probability for each candidate.
def pfsp_probabilities(
    win_rates: np.ndarray,
    is_active: np.ndarray,
    *,
    weighting: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray:
    """Candidates in proportion to weighting(win rate); uniform if every weight is zero (a
    learner that beats everyone under "hard" still needs an opponent)."""
    weights = weighting(np.asarray(win_rates, dtype=float))
    total = weights.sum()
    if total <= 0.0:
        return uniform_probabilities(win_rates, is_active)
    return weights / total


def uniform_probabilities(win_rates: np.ndarray, is_active: np.ndarray) -> np.ndarray:
    return np.full(len(win_rates), 1.0 / len(win_rates))


def latest_probabilities(win_rates: np.ndarray, is_active: np.ndarray) -> np.ndarray:
    """Uniform over the active members, never a snapshot."""
    active = np.asarray(is_active, dtype=float)
    if active.sum() == 0.0:
        raise ValueError("strategy 'latest' needs an active member in the opponent team")
    return active / active.sum()


STRATEGIES: dict[str, Callable[..., np.ndarray]] = {
    "pfsp": pfsp_probabilities,
    "uniform": uniform_probabilities,
    "latest": latest_probabilities,
}


class MatchmakingConfig(_Strict):
    """How each match's opponent is drawn: the mixture weights of the opponent strategies
    (normalised; a strategy weighted 0 is left out), PFSP's weighting, and how many frozen
    snapshots a team's pool keeps (the `matchmaking:` section of a league experiment)."""

    pfsp: float = Field(0.5, ge=0, description="share of prioritized fictitious self-play")
    uniform: float = Field(0.3, ge=0, description="share of uniform opponents")
    latest: float = Field(0.2, ge=0, description="share of the other team's active members")
    weighting: PFSPWeighting = Field(
        "hard", description="PFSP weight of an opponent beaten at rate p: (1-p)^2, p(1-p), 1-p"
    )
    max_snapshots: Members = Field(8, ge=0, description="frozen snapshots kept per team")

    @model_validator(mode="after")
    def _some_weight(self) -> MatchmakingConfig:
        if self.pfsp + self.uniform + self.latest <= 0:
            raise ValueError("matchmaking: pfsp, uniform and latest cannot all be 0")
        return self

    @property
    def strategy_weights(self) -> dict[str, float]:
        """The weight of each strategy of STRATEGIES, by name."""
        return {"pfsp": self.pfsp, "uniform": self.uniform, "latest": self.latest}


@dataclass(frozen=True)
class Snapshot:
    """A frozen copy of a member: its own id, the member it came from, when it was frozen."""

    id: str
    member: str
    team: str
    iteration: int


class OpponentPool:
    """Per team, the active members and at most `max_snapshots` frozen snapshots of them.

    A new snapshot beyond the cap pushes out the team's oldest (earliest frozen); active
    members are never dropped. Snapshots outlive their member's removal: the frozen policy is
    still a valid opponent. The caller keeps each snapshot's weights under its id and may
    release those of ids that leave `candidates`.
    """

    def __init__(self, max_snapshots: int = 10) -> None:
        if max_snapshots < 1:
            raise ValueError(
                f"an opponent pool keeps at least 1 snapshot per team, got {max_snapshots}; "
                "to play without snapshots, never freeze"
            )
        self.max_snapshots = max_snapshots
        self._active: dict[str, list[str]] = {team: [] for team in TEAMS}
        self._snapshots: dict[str, list[Snapshot]] = {team: [] for team in TEAMS}

    def __contains__(self, player: str) -> bool:
        return any(player in self.candidates(team) for team in TEAMS)

    def add_member(self, member_id: str, team: str) -> None:
        if team not in TEAMS:
            raise ValueError(f"member {member_id!r}: team {team!r} is not one of {TEAMS}")
        if not member_id or SNAPSHOT_MARK in member_id:
            raise ValueError(
                f"member id {member_id!r} must be non-empty and free of {SNAPSHOT_MARK!r}, "
                "which marks snapshots"
            )
        if member_id in self:
            raise ValueError(f"{member_id!r} is already in the opponent pool")
        self._active[team].append(member_id)

    def remove_member(self, member_id: str) -> None:
        """Retire an active member; its snapshots stay in the pool."""
        self._active[self._active_team(member_id)].remove(member_id)

    def active(self, team: str) -> list[str]:
        return list(self._active[team])

    def snapshots(self, team: str) -> list[Snapshot]:
        """The team's snapshots, oldest first."""
        return list(self._snapshots[team])

    def candidates(self, team: str) -> list[str]:
        """Everyone the team can field as an opponent: active members, then snapshots."""
        return self._active[team] + [snapshot.id for snapshot in self._snapshots[team]]

    def team_of(self, player: str) -> str:
        for team in TEAMS:
            if player in self.candidates(team):
                return team
        raise KeyError(f"{player!r} is neither a member nor a snapshot in the opponent pool")

    def is_snapshot(self, player: str) -> bool:
        return any(player == snapshot.id for team in TEAMS for snapshot in self._snapshots[team])

    def freeze(self, member_id: str, iteration: int) -> str:
        """Add a snapshot of an active member as it is at `iteration`; returns its id."""
        team, iteration = self._active_team(member_id), int(iteration)
        snapshot = Snapshot(f"{member_id}{SNAPSHOT_MARK}{iteration}", member_id, team, iteration)
        if snapshot.id in self:
            raise ValueError(f"{member_id!r} was already frozen at iteration {iteration}")
        pool = self._snapshots[team]
        bisect.insort_right(pool, snapshot, key=lambda s: s.iteration)
        del pool[: max(0, len(pool) - self.max_snapshots)]
        return snapshot.id

    def _active_team(self, member_id: str) -> str:
        for team in TEAMS:
            if member_id in self._active[team]:
                return team
        raise KeyError(f"{member_id!r} is not an active member of the opponent pool")

    def state_dict(self) -> dict[str, Any]:
        return {
            "active": {team: list(members) for team, members in self._active.items()},
            "snapshots": [
                [snapshot.id, snapshot.member, snapshot.team, snapshot.iteration]
                for team in TEAMS
                for snapshot in self._snapshots[team]
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        active = {team: [str(m) for m in state["active"][team]] for team in TEAMS}
        snapshots: dict[str, list[Snapshot]] = {team: [] for team in TEAMS}
        for player, member, team, iteration in state["snapshots"]:
            snapshots[team].append(Snapshot(str(player), str(member), str(team), int(iteration)))
        for team, kept in snapshots.items():
            if len(kept) > self.max_snapshots:
                raise ValueError(
                    f"saved opponent pool holds {len(kept)} {team} snapshots, more than this "
                    f"pool's max_snapshots={self.max_snapshots}"
                )
        self._active, self._snapshots = active, snapshots


@dataclass(frozen=True)
class Pairing:
    """An iteration's match-up. The learner team's member is the one whose opponent was drawn;
    the opponent learns too only if the league loop wants it and it is not a snapshot."""

    aligner: str
    misaligner: str
    learner_team: str

    @property
    def learner(self) -> str:
        return self.aligner if self.learner_team == ALIGNER else self.misaligner

    @property
    def opponent(self) -> str:
        return self.misaligner if self.learner_team == ALIGNER else self.aligner


class Matchmaker:
    """Chooses each iteration's learner and its opponent; holds no state besides its config.

    Learners rotate round-robin, not at random, so that every active member gets the same
    share of updates and a resumed run continues the rotation from the iteration number alone:
    even iterations pick an aligner, odd ones a misaligner, and each team cycles through its
    active members in pool order. The opponent is drawn from the mixture of strategies in
    `opponent_probabilities`.
    """

    def __init__(self, config: MatchmakingConfig | None = None) -> None:
        self.config = config or MatchmakingConfig()
        weighting = PFSP_WEIGHTINGS[self.config.weighting]
        self._strategies = {
            name: (
                functools.partial(pfsp_probabilities, weighting=weighting)
                if name == "pfsp"
                else STRATEGIES[name]
            )
            for name, weight in self.config.strategy_weights.items()
            if weight > 0
        }

    def learner_for(self, iteration: int, pool: OpponentPool) -> str:
        team = TEAMS[iteration % len(TEAMS)]
        members = pool.active(team)
        if not members:
            raise ValueError(f"the {team} team has no active member to learn at {iteration=}")
        return members[(iteration // len(TEAMS)) % len(members)]

    def opponent_probabilities(
        self, learner: str, payoff: PayoffTable, pool: OpponentPool
    ) -> dict[str, float]:
        """The probability of drawing each of the other team's candidates against `learner`."""
        team = pool.team_of(learner)
        if pool.is_snapshot(learner):
            raise ValueError(f"{learner!r} is a snapshot; only active members learn")
        candidates = pool.candidates(_other_team(team))
        if not candidates:
            raise ValueError(f"the {_other_team(team)} team has no one to play {learner!r}")
        win_rates = np.array([self._win_rate(payoff, team, learner, c) for c in candidates])
        active = set(pool.active(_other_team(team)))
        is_active = np.array([c in active for c in candidates])
        weights = self.config.strategy_weights
        mixture = sum(
            weights[name] * strategy(win_rates, is_active)
            for name, strategy in self._strategies.items()
        ) / sum(weights[name] for name in self._strategies)
        return dict(zip(candidates, mixture.tolist(), strict=True))

    def choose_opponent(
        self, rng: np.random.Generator, learner: str, payoff: PayoffTable, pool: OpponentPool
    ) -> str:
        probabilities = self.opponent_probabilities(learner, payoff, pool)
        candidates = list(probabilities)
        return candidates[rng.choice(len(candidates), p=list(probabilities.values()))]

    def select_pair(
        self, rng: np.random.Generator, payoff: PayoffTable, pool: OpponentPool, iteration: int
    ) -> Pairing:
        learner = self.learner_for(iteration, pool)
        opponent = self.choose_opponent(rng, learner, payoff, pool)
        if pool.team_of(learner) == ALIGNER:
            return Pairing(aligner=learner, misaligner=opponent, learner_team=ALIGNER)
        return Pairing(aligner=opponent, misaligner=learner, learner_team=MISALIGNER)

    @staticmethod
    def _win_rate(payoff: PayoffTable, team: str, learner: str, opponent: str) -> float:
        """The learner's win rate against the opponent, whichever side it plays."""
        if team == ALIGNER:
            rate = payoff.win_rate(learner, opponent)
            return UNPLAYED_WIN_RATE if rate is None else rate
        rate = payoff.win_rate(opponent, learner)
        return UNPLAYED_WIN_RATE if rate is None else 1.0 - rate

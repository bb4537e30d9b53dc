"""How strong each league player is: Elo ratings and the aligner-versus-misaligner payoff table.

Ratings are Elo-style (logistic, base 10, scale 400): a player rated 400 points above another
is expected to score 10:1 against it. One league iteration plays a batch of matches between one
aligner and one misaligner; the batch's mean score (the aligner's success rate, in [0, 1])
updates both ratings once, by equal and opposite amounts, because the game is zero-sum (seed
section 3). A player is any id: an active member ("aligner-0") or a frozen snapshot of one
("aligner-0@3", frozen at iteration 3).

The payoff table keeps, per (aligner, misaligner) pair, how many matches they played and the
aligner's total score, so the aligner's win rate against each misaligner is exact rather than
inferred from ratings; prioritized fictitious self-play (matchmaking.py) samples from it.

Both keep their state as plain data (str, int, float, lists, dicts), stored in checkpoints and
JSON alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["EloConfig", "PayoffTable", "Ratings", "expected_score"]


def expected_score(rating_a: float, rating_b: float, scale: float = 400.0) -> float:
    """Elo's expected score of a against b, in (0, 1); expected(a, b) + expected(b, a) = 1."""
    return 1.0 / (1.0 + 10.0 ** ((rating_b - rating_a) / scale))


def _check_iteration(iteration: int, last: int | None, what: str) -> int:
    iteration = int(iteration)
    if last is not None and iteration <= last:
        raise ValueError(
            f"{what}: iteration {iteration} recorded after iteration {last}; record each "
            "iteration once, in increasing order"
        )
    return iteration


@dataclass(frozen=True)
class EloConfig:
    initial: float = 1200.0  # rating of a player before its first match
    k_factor: float = 16.0  # largest change one update can make (score 1 against a sure loss)
    scale: float = 400.0  # rating difference at which the stronger is expected to score 10:1

    def __post_init__(self) -> None:
        if not math.isfinite(self.initial):
            raise ValueError(f"Elo initial rating must be a finite number, got {self.initial}")
        if not (math.isfinite(self.k_factor) and self.k_factor > 0):
            raise ValueError(f"Elo k_factor must be a positive number, got {self.k_factor}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Elo scale must be a positive number, got {self.scale}")


class Ratings:
    """Elo ratings of league players, with a history of them for the report's rating plot.

    Every id counts as rated at `config.initial` until it plays; `update` then stores it.
    `add` seeds a player explicitly, e.g. a member copied by population-based training or a
    fresh snapshot, which should start from its source's rating rather than the initial one.
    """

    def __init__(self, config: EloConfig | None = None) -> None:
        self.config = config or EloConfig()
        self._ratings: dict[str, float] = {}
        self.history: list[tuple[int, str, float]] = []  # (iteration, id, rating) rows
        self._last_recorded: int | None = None

    def __contains__(self, player: str) -> bool:
        return player in self._ratings

    def __len__(self) -> int:
        return len(self._ratings)

    def rating(self, player: str) -> float:
        """The player's rating; the initial one for a player not rated yet."""
        return self._ratings.get(player, self.config.initial)

    def add(self, player: str, rating: float | None = None) -> float:
        """Rate a new player at `rating` (default: the initial rating); returns it."""
        if player in self._ratings:
            raise ValueError(
                f"{player!r} is already rated ({self._ratings[player]:.1f}); give a copied "
                "member or a snapshot an id of its own"
            )
        value = self.config.initial if rating is None else float(rating)
        if not math.isfinite(value):
            raise ValueError(f"rating of {player!r} must be a finite number, got {rating}")
        self._ratings[player] = value
        return value

    def expected(self, a: str, b: str) -> float:
        """The score a is expected to make against b, in (0, 1)."""
        return expected_score(self.rating(a), self.rating(b), self.config.scale)

    def update(self, a: str, b: str, score_a: float) -> tuple[float, float]:
        """Rate one batch of matches in which a scored `score_a` (b scored 1 - score_a).

        Returns the new ratings of a and b. What a gains b loses: the league is zero-sum.
        """
        if a == b:
            raise ValueError(f"{a!r} cannot be rated against itself")
        score = float(score_a)
        if not 0.0 <= score <= 1.0:  # NaN fails this too
            raise ValueError(
                f"score of {a!r} against {b!r} must be in [0, 1] (a success rate), got {score_a}"
            )
        delta = self.config.k_factor * (score - self.expected(a, b))
        self._ratings[a] = self.rating(a) + delta
        self._ratings[b] = self.rating(b) - delta
        return self._ratings[a], self._ratings[b]

    def ranking(self, ids: Iterable[str] | None = None) -> list[tuple[str, float]]:
        """(id, rating) best first, ties by id; `ids` limits it (unrated ones at the initial)."""
        chosen = self._ratings if ids is None else ids
        return sorted(((i, self.rating(i)) for i in chosen), key=lambda row: (-row[1], row[0]))

    def record(self, iteration: int) -> None:
        """Append every rated player's current rating to `history`, stamped `iteration`."""
        self._last_recorded = _check_iteration(iteration, self._last_recorded, "ratings")
        self.history.extend((self._last_recorded, i, r) for i, r in self._ratings.items())

    def state_dict(self) -> dict[str, Any]:
        return {
            "ratings": dict(self._ratings),
            "history": [[iteration, i, r] for iteration, i, r in self.history],
            "last_recorded": self._last_recorded,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._ratings = {str(i): float(r) for i, r in state["ratings"].items()}
        self.history = [(int(it), str(i), float(r)) for it, i, r in state["history"]]
        last = state["last_recorded"]
        self._last_recorded = None if last is None else int(last)


class PayoffTable:
    """Matches played and the aligner's total score for each (aligner, misaligner) pair.

    The aligner's win rate against a misaligner is its total score over its matches; the
    misaligner's is one minus that. `record` keeps a compact history for plots: at each
    recorded iteration, the running totals of only the pairs that changed since the last one.
    """

    def __init__(self) -> None:
        self._totals: dict[tuple[str, str], tuple[int, float]] = {}  # pair -> (matches, score)
        self.history: list[tuple[int, str, str, int, float]] = []  # (iteration, a, m, n, score)
        self._last_recorded: int | None = None
        self._recorded_totals: dict[tuple[str, str], tuple[int, float]] = {}

    def add(self, aligner: str, misaligner: str, matches: int, aligner_score_sum: float) -> None:
        """Count `matches` more matches in which the aligner scored `aligner_score_sum` in all."""
        pair = f"aligner {aligner!r} against misaligner {misaligner!r}"
        if isinstance(matches, bool) or not isinstance(matches, int | np.integer) or matches < 1:
            raise ValueError(f"{pair}: matches must be a whole number >= 1, got {matches}")
        score = float(aligner_score_sum)
        if not 0.0 <= score <= matches:  # NaN fails this too
            raise ValueError(
                f"{pair}: aligner_score_sum must be in [0, matches={matches}] (each match "
                f"scores 0 to 1), got {aligner_score_sum}"
            )
        played, total = self._totals.get((aligner, misaligner), (0, 0.0))
        self._totals[(aligner, misaligner)] = (played + int(matches), total + score)

    def matches(self, aligner: str, misaligner: str) -> int:
        return self._totals.get((aligner, misaligner), (0, 0.0))[0]

    def win_rate(self, aligner: str, misaligner: str) -> float | None:
        """The aligner's mean score against the misaligner; None if they never played."""
        if (aligner, misaligner) not in self._totals:
            return None
        played, total = self._totals[(aligner, misaligner)]
        return total / played

    def matrix(self, aligners: list[str], misaligners: list[str]) -> np.ndarray:
        """Aligner win rates, rows = aligners, columns = misaligners; NaN where never played."""
        return _win_rate_matrix(self._totals, aligners, misaligners)

    def matrix_at(self, iteration: int, aligners: list[str], misaligners: list[str]) -> np.ndarray:
        """`matrix` as it stood at the last `record` at or before `iteration`."""
        totals: dict[tuple[str, str], tuple[int, float]] = {}
        for recorded, aligner, misaligner, played, score in self.history:
            if recorded > iteration:
                break
            totals[(aligner, misaligner)] = (played, score)
        return _win_rate_matrix(totals, aligners, misaligners)

    def record(self, iteration: int) -> None:
        """Append to `history` the running totals of the pairs that changed since last time."""
        self._last_recorded = _check_iteration(iteration, self._last_recorded, "payoff table")
        for (aligner, misaligner), totals in self._totals.items():
            if self._recorded_totals.get((aligner, misaligner)) != totals:
                self.history.append((self._last_recorded, aligner, misaligner, *totals))
        self._recorded_totals = dict(self._totals)

    def state_dict(self) -> dict[str, Any]:
        return {
            "pairs": [[a, m, played, score] for (a, m), (played, score) in self._totals.items()],
            "history": [list(row) for row in self.history],
            "last_recorded": self._last_recorded,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._totals = {
            (str(a), str(m)): (int(played), float(score)) for a, m, played, score in state["pairs"]
        }
        self.history = [
            (int(it), str(a), str(m), int(played), float(score))
            for it, a, m, played, score in state["history"]
        ]
        last = state["last_recorded"]
        self._last_recorded = None if last is None else int(last)
        # What was last recorded follows from the history (its latest row per pair).
        self._recorded_totals = {(a, m): (played, score) for _, a, m, played, score in self.history}


def _win_rate_matrix(
    totals: dict[tuple[str, str], tuple[int, float]], aligners: list[str], misaligners: list[str]
) -> np.ndarray:
    rates = np.full((len(aligners), len(misaligners)), np.nan)
    for row, aligner in enumerate(aligners):
        for column, misaligner in enumerate(misaligners):
            if (aligner, misaligner) in totals:
                played, score = totals[(aligner, misaligner)]
                rates[row, column] = score / played
    return rates

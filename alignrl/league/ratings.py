"""How strong each league player is: ratings with their uncertainty, the fixed-rating anchors
they are measured against, and the aligner-versus-misaligner payoff table.

Ratings are openskill's Plackett-Luce (Weng & Lin 2011, "A Bayesian approximation method for
online ranking"): a player's skill is a normal belief, mean mu and spread sigma, and every
match moves the mean by how surprising its outcome was and shrinks the spread. Before each
match the spread grows by `tau`, so that a rating follows a member that learns. A rating is
shown as mu ± sigma and sorted by its ordinal, mu - 3 sigma: a member rated on few matches
ranks below one that earned the same mu on many.

One league iteration plays a batch of matches between one aligner and one misaligner; each
match is one rating update, its outcome the aligner's rated score of that match (1 a win, 0
a loss, 1/2 a draw: its success, or under the regret payoff how it fared against the
reference, alignrl.envs.design). A player is any id: an active member ("aligner-0") or a
frozen snapshot of one ("aligner-0@3", frozen at iteration 3).

Anchors are classical controllers (the hyperbola fit ...) with a rating fixed for good: they
align twins of the same columns from the same starts as the aligners (alignrl.league.matches),
and every aligner-versus-anchor match (`anchor_scores`) moves the aligner's rating only. An
aligner rated above the hyperbola anchor does better than the hyperbola fit on the starts it
played; without anchors the two teams' ratings would float against each other only.

The payoff table keeps, per (aligner, misaligner) pair, how many matches they played and the
aligner's total score, so the aligner's win rate against each misaligner is exact rather than
inferred from ratings; prioritized fictitious self-play (matchmaking.py) samples from it.

All of it keeps its state as plain data (str, int, float, lists, dicts), stored in checkpoints
and JSON alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np
from openskill.models import PlackettLuce
from pydantic import Field

from alignrl.config_reading import _Strict

__all__ = [
    "ALIKE_RELATIVE",
    "PayoffTable",
    "Rating",
    "RatingConfig",
    "Ratings",
    "anchor_scores",
]

# openskill's defaults: a new player at 25 ± 25/3; beta, the spread of one match's
# performance, 25/6; tau, the spread added before every match, 25/300.
DEFAULT_MU = 25.0
ANCHOR_SIGMA = 0.0  # an anchor's rating is known exactly: it never learns
SPREADS = 3.0  # ordinal = mu - SPREADS sigma: 99.9 % sure the skill is at least that
# Where neither met the spec, final widths within 5 % of each other count alike (a draw):
# beyond the 2 % re-measurement noise of the shipped recordings.
ALIKE_RELATIVE = 0.05
SCORES = (0.0, 0.5, 1.0)  # a match's outcome for its first player: loss, draw, win


class Rating(NamedTuple):
    """A player's skill belief: mean `mu` and spread `sigma`, rating points."""

    mu: float
    sigma: float

    @property
    def ordinal(self) -> float:
        """mu - 3 sigma: what sorts the leaderboard (a conservative estimate of the skill)."""
        return self.mu - SPREADS * self.sigma

    def text(self) -> str:
        """`27.3 ± 1.4`."""
        return f"{self.mu:.1f} ± {self.sigma:.1f}"


class RatingConfig(_Strict):
    """openskill Plackett-Luce ratings and their anchors (the `ratings:` section of a league
    experiment); the defaults are openskill's."""

    mu: float = Field(DEFAULT_MU, allow_inf_nan=False, description="mean rating of a new member")
    sigma: float = Field(
        DEFAULT_MU / 3,
        gt=0,
        allow_inf_nan=False,
        description="spread (uncertainty) of a new rating",
    )
    beta: float = Field(
        DEFAULT_MU / 6, gt=0, allow_inf_nan=False, description="spread of one match's performance"
    )
    tau: float = Field(
        DEFAULT_MU / 300,
        ge=0,
        allow_inf_nan=False,
        description="spread added before every match, so that a rating follows a member "
        "that learns",
    )
    anchors: dict[str, float] | None = Field(
        None,
        description="classical controllers rated beside the aligners at a fixed mean, each "
        "aligning the same columns from the same starts; null: the hyperbola fit at mu on a "
        "one-knob task, none on the others; {}: none",
    )

    @property
    def initial(self) -> Rating:
        return Rating(self.mu, self.sigma)


def _check_iteration(iteration: int, last: int | None, what: str) -> int:
    iteration = int(iteration)
    if last is not None and iteration <= last:
        raise ValueError(
            f"{what}: iteration {iteration} recorded after iteration {last}; record each "
            "iteration once, in increasing order"
        )
    return iteration


def anchor_scores(
    aligner_success: np.ndarray,
    aligner_width: np.ndarray,
    anchor_success: np.ndarray,
    anchor_width: np.ndarray,
    alike: float = ALIKE_RELATIVE,
) -> np.ndarray:
    """The aligner's score against an anchor on each of the same columns from the same
    starts: 1 where only the aligner met the spec, 0 where only the anchor did, 1/2 where
    both did. Where neither did, the narrower final width wins, by more than `alike` of the
    wider one; else 1/2. Widths in px (the task's cost; NaN, no image: wider than any)."""
    mine, theirs = np.asarray(aligner_success, bool), np.asarray(anchor_success, bool)
    mine_px = np.nan_to_num(np.asarray(aligner_width, float), nan=np.inf)
    theirs_px = np.nan_to_num(np.asarray(anchor_width, float), nan=np.inf)
    wider = np.maximum(mine_px, theirs_px)
    with np.errstate(invalid="ignore", divide="ignore"):  # unmeasured ones: inf - inf
        difference = theirs_px - mine_px  # > 0: the aligner ended narrower
        # Both measured: relative to the wider; one unmeasured: the measured one is
        # narrower; both unmeasured (NaN): alike.
        gap = np.where(np.isfinite(wider), difference / wider, np.sign(difference))
    gap = np.nan_to_num(gap, nan=0.0)
    narrower = np.where(gap > alike, 1.0, np.where(gap < -alike, 0.0, 0.5))
    return np.where(mine == theirs, np.where(mine, 0.5, narrower), mine.astype(float))


class Ratings:
    """The ratings of league players and anchors, with a history for the report's plot.

    Every id counts as rated at the config's initial rating until it plays; `update` then
    stores it. `add` seeds a player explicitly, e.g. a member copied by population-based
    training or a fresh snapshot, which starts from its source's rating; `pin` adds an anchor,
    whose rating no match changes.
    """

    def __init__(self, config: RatingConfig | None = None) -> None:
        self.config = config or RatingConfig()
        self._model = PlackettLuce(
            mu=self.config.mu, sigma=self.config.sigma, beta=self.config.beta, tau=self.config.tau
        )
        self._ratings: dict[str, Rating] = {}
        self._anchors: set[str] = set()
        self.history: list[tuple[int, str, float, float]] = []  # (iteration, id, mu, sigma)
        self._last_recorded: int | None = None

    def __contains__(self, player: str) -> bool:
        return player in self._ratings

    def __len__(self) -> int:
        return len(self._ratings)

    @property
    def anchors(self) -> list[str]:
        """The anchors, in the order they were pinned."""
        return [player for player in self._ratings if player in self._anchors]

    def is_anchor(self, player: str) -> bool:
        return player in self._anchors

    def rating(self, player: str) -> Rating:
        """The player's rating; the initial one for a player not rated yet."""
        return self._ratings.get(player, self.config.initial)

    def add(self, player: str, rating: Rating | None = None) -> Rating:
        """Rate a new player at `rating` (default: the initial rating); returns it."""
        if player in self._ratings:
            raise ValueError(
                f"{player!r} is already rated ({self._ratings[player].text()}); give a copied "
                "member or a snapshot an id of its own"
            )
        value = self.config.initial if rating is None else Rating(*map(float, rating))
        if not (math.isfinite(value.mu) and math.isfinite(value.sigma) and value.sigma >= 0):
            raise ValueError(f"rating of {player!r} must be finite numbers, got {rating}")
        self._ratings[player] = value
        return value

    def pin(self, anchor: str, mu: float) -> Rating:
        """Add an anchor whose rating stays `mu` (spread 0) whatever it plays."""
        rating = self.add(anchor, Rating(float(mu), ANCHOR_SIGMA))
        self._anchors.add(anchor)
        return rating

    def win_probability(self, a: str, b: str) -> float:
        """The chance that a beats b, by their ratings."""
        return float(self._model.predict_win([[self._skill(a)], [self._skill(b)]])[0])

    def update(self, a: str, b: str, scores: Sequence[float]) -> tuple[Rating, Rating]:
        """Rate matches between a and b, one update per match in order; `scores` are a's (1
        a win, 0 a loss, 1/2 a draw). An anchor's rating never moves. Returns the new
        ratings of a and b."""
        if a == b:
            raise ValueError(f"{a!r} cannot be rated against itself")
        if self.is_anchor(a) and self.is_anchor(b):
            raise ValueError(f"{a!r} and {b!r} are both anchors: no match between them is rated")
        outcomes = [float(score) for score in scores]
        wrong = [score for score in outcomes if score not in SCORES]  # NaN is wrong too
        if wrong:
            raise ValueError(
                f"scores of {a!r} against {b!r} must each be 1 (a win), 0 (a loss) or 0.5 "
                f"(a draw), got {wrong[0]}"
            )
        first, second = self.rating(a), self.rating(b)
        for score in outcomes:
            ranks = [0, 0] if score == 0.5 else ([0, 1] if score == 1.0 else [1, 0])
            [[new_first], [new_second]] = self._model.rate(
                [[self._model.rating(*first)], [self._model.rating(*second)]], ranks=ranks
            )
            if not self.is_anchor(a):
                first = Rating(float(new_first.mu), float(new_first.sigma))
            if not self.is_anchor(b):
                second = Rating(float(new_second.mu), float(new_second.sigma))
        self._ratings[a], self._ratings[b] = first, second
        return first, second

    def _skill(self, player: str) -> Any:
        return self._model.rating(*self.rating(player))

    def ranking(self, ids: Iterable[str] | None = None) -> list[tuple[str, Rating]]:
        """(id, rating) best first by ordinal, ties by id; `ids` limits it (unrated ones at
        the initial rating)."""
        chosen = self._ratings if ids is None else ids
        return sorted(
            ((i, self.rating(i)) for i in chosen), key=lambda row: (-row[1].ordinal, row[0])
        )

    def record(self, iteration: int) -> None:
        """Append every rated player's current rating to `history`, stamped `iteration`."""
        self._last_recorded = _check_iteration(iteration, self._last_recorded, "ratings")
        self.history.extend(
            (self._last_recorded, i, r.mu, r.sigma) for i, r in self._ratings.items()
        )

    def state_dict(self) -> dict[str, Any]:
        return {
            "ratings": {i: [r.mu, r.sigma] for i, r in self._ratings.items()},
            "anchors": self.anchors,
            "history": [list(row) for row in self.history],
            "last_recorded": self._last_recorded,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        ratings = state["ratings"]
        if any(not isinstance(value, list | tuple) for value in ratings.values()):
            raise ValueError(
                "ratings were saved as single numbers (Elo, an alignrl before openskill "
                "ratings): this league cannot be resumed; start it again"
            )
        self._ratings = {
            str(i): Rating(float(mu), float(sigma)) for i, (mu, sigma) in ratings.items()
        }
        self._anchors = {str(anchor) for anchor in state["anchors"]}
        self.history = [
            (int(it), str(i), float(mu), float(sigma)) for it, i, mu, sigma in state["history"]
        ]
        last = state["last_recorded"]
        self._last_recorded = None if last is None else int(last)


class PayoffTable:
    """Matches played and the aligner's total score for each (aligner, opponent) pair (a
    misaligner; the league keeps a second table for the anchors).

    The aligner's win rate against an opponent is its total score over its matches; the
    opponent's is one minus that. `record` keeps a compact history for plots: at each
    recorded iteration, the running totals of only the pairs that changed since the last one.
    """

    def __init__(self) -> None:
        self._totals: dict[tuple[str, str], tuple[int, float]] = {}  # pair -> (matches, score)
        self.history: list[tuple[int, str, str, int, float]] = []  # (iteration, a, m, n, score)
        self._last_recorded: int | None = None
        self._recorded_totals: dict[tuple[str, str], tuple[int, float]] = {}

    def add(self, aligner: str, misaligner: str, matches: int, aligner_score_sum: float) -> None:
        """Count `matches` more matches in which the aligner scored `aligner_score_sum` in all."""
        pair = f"aligner {aligner!r} against {misaligner!r}"
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

    def pairs(self) -> list[tuple[str, str]]:
        """Every (aligner, opponent) pair that played, in the order they first met."""
        return list(self._totals)

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

"""What a column's focus readings say of its optimum, knowing the model of the instrument
family: the inference of the Bayesian autofocus (issue 21).

`FamilyPosterior(family)` follows the focus knob of a column drawn from `family`
(alignrl/apparatus/family.py, "The instrument family"). It knows the model of the analytic
readings and the box the column came from; it never sees the column's optimum, its specimen's
scale or its noise. It keeps a posterior over

* where the optimum lies: a grid over the knob's interval (or the box's `optimum_fraction`
  range), as fractions of the interval, padded so that drift can carry it out;
* which column it is on: `draws` columns drawn from the box where the box has ranges (one
  where it is a single instrument, as the files of alignrl/apparatus/instruments are), the
  width of a flat bottom weighed on a log scale (FLAT_DECADES);
* the specimen's per-episode scale: a Gauss-Hermite grid over its normal draw;

and after every reading multiplies in that reading's likelihood (a frame without edges: the
model's chance of one; a width: the model's mean, with a spread of the model's noise and
`model_noise` more, for what the model does not know of a real column), then lets drift blur
the optimum. Where the readings have left few of the columns likely, it draws the columns
again around the likely ones and weighs every reading on them (a resample-move step), so
that a box of a dozen parameters is searched where the readings point. Each probe goes
where the expected posterior variance of the optimum is least (or, `probe_rule` "entropy",
where its expected entropy over the optimum's grid is least; "chance", where the final
setting's expected chance of passing is greatest one reading ahead), over a
grid of settings and settings around the posterior's quantiles; it is done once the setting
most likely to pass the session's verification (`spec_relative` x the best width) passes
with probability `confidence` (with `relative_stop`, `confidence` x the chance a setting at
the optimum itself would: no reading can do better), and ends there.

With `scale_free` the readings' pixel scale is unknown too: every reading is the model's
times a factor of the episode, flat on a log scale, marginalised per state in closed form
(`ScaleSums`: the precision-weighted sums of log residuals; each reading is weighed by its
predictive given the earlier ones, so the first one's pixels say nothing). The posterior then
decides on ratios of readings and the curve's shape alone, alike at any magnification.

Every setting is approached from below (the same lag on every reading, as the hyperbola fit
does), so the model's backlash shifts the optimum by a known amount; a reading on an unknown
side (the column as it was found: `observe`, side 0) is the mixture of the backlash's branches.

Given a single instrument's own file it is an oracle: it knows that instrument exactly, and
what it reaches shows what the readings allow when the column's model is known (a greedy
choice of one probe at a time: a controller that plans further may need fewer). Given the
training box (alignrl/apparatus/families/focus.yaml) it knows what training knows.
`python -m benchmarks.bound` runs both on every instrument of a set. On images its reading
model is approximate (an edge width measured on a rendered frame is not the analytic
reading): `model_noise` is what covers the difference.

Three parts of alignrl ask it: the Bayesian autofocus (alignrl/evaluation/posterior.py,
`BayesianAutofocus`, which writes its settings to an apparatus: `alignrl evaluate --policy
posterior`), the teacher of cloned aligners (benchmarks/imitation.py), and an episode's end
(Ending.at "posterior", alignrl/envs/ending.py: a trained aligner's probes, ended where
the posterior over the training box puts the best setting).

What it costs (issue 61, item 4; `python -m benchmarks.posterior_cost`): every reading is
weighed on every state ((K, Z, N): 1,024 columns x 1,836 optimum points for champion:focus-v2)
and again, with every reading so far, where the columns are drawn again. The numbers are the
plain formulas' (ColumnModels.reading, ScaleSums) bit for bit, computed a chunk of columns at
a time (CHUNK_STATES) in buffers kept near the processor (`reading_into`, `scratch`), into
two posterior buffers each instance owns (PosteriorBuffers; a copy makes its own); the
first draw of columns and the prior are made once per process (`first_draw`, read-only),
and the states that still count found once per reading for the stop and the probe alike.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from alignrl.apparatus.family_box import FocusFamily
from alignrl.posterior.models import (
    FLAT_DECADES,
    ColumnModels,
    ReadingConstants,
    first_draw,
    narrowest_spec,
    reading_into,
    reading_work,
)
from alignrl.posterior.scale_sums import ScaleSums
from alignrl.posterior.scoring import StateReadings, expected_entropy, outcome_chances
from alignrl.posterior.workspace import PosteriorBuffers, read_only, remembered, scratch

__all__ = ["PROBE_RULES", "SCALE_FREE", "SCORED_STATES", "STOP_STATES", "FamilyPosterior"]

SCORED_STATES = 2000  # states the probe choice is scored on (a systematic resample beyond)
STOP_STATES = 20000  # states a stop is judged on (a systematic resample beyond)
LIVE = 1e-12  # states below this share of the largest posterior weight are left out
GRID_POINTS_PER_WINDOW = 3  # optimum grid points across the half-width that passes the spec
MAX_GRID = 4000
PROBE_RULES = ("variance", "chance", "entropy")
FINAL_SETTINGS = 41  # final settings a "chance" probe is scored against
STOP_SETTINGS = 81  # final settings a stop chooses among
# Where a reading's approach is unknown, the branches of the backlash it may lie on (x the
# lag): from below, from above, and the middle (a column left between them)
BRANCHES = (1.0, -1.0, 0.0)
# States weighed at a time (whole columns, at least one): a dozen buffers of this many numbers
# stay near a core (its 1 MiB of L2 and the L3 on the 2-core machine this was measured on)
CHUNK_STATES = 16384
_priors: OrderedDict = OrderedDict()  # grids and priors, made once (`remembered`)


def _systematic(weights: np.ndarray, draws: int, offset: float) -> np.ndarray:
    """Indices of `draws` systematic picks from `weights`, the first at `offset` (in [0, 1))
    of a pick's share."""
    return _picks(np.cumsum(weights / weights.sum()), draws, offset)


def _picks(edges: np.ndarray, draws: int, offset: float) -> np.ndarray:
    """`_systematic` given the cumulative shares `edges`."""
    return np.minimum(np.searchsorted(edges, (np.arange(draws) + offset) / draws), edges.size - 1)


def _quantiles(u: np.ndarray, weight: np.ndarray, shares: list[float]) -> np.ndarray:
    """The weighted quantiles of `u` at `shares`."""
    order = np.argsort(u)
    cumulative = np.cumsum(weight[order])
    return u[order][np.minimum(np.searchsorted(cumulative, shares), u.size - 1)]


@dataclass
class FamilyPosterior:
    """The posterior of the module docstring, for columns of `family`: `begin`, then
    `observe` every reading, `decide` where the next goes or whether to stop, `final`: where
    to end (alignrl/evaluation/posterior.py, BayesianAutofocus, writes them to an apparatus)."""

    family: FocusFamily
    name: str = "posterior"
    confidence: float = 0.99  # stop once the final setting passes with this probability
    spec_relative: float = 1.15  # the session's success rule (alignrl/envs/task.py)
    draws: int = 256  # columns drawn from the box where it has ranges
    specimen_points: int = 3  # Gauss-Hermite points over the specimen's scale
    max_acquisitions: int = 20
    reading_bins: int = 24
    seed: int = 0
    # where the optimum may lie before the first reading: "box", the family's
    # optimum_fraction range; "interval", anywhere in the knob's interval (what an operator
    # knows of a column whose focus has moved)
    optimum_prior: str = "interval"
    model_noise: float = 0.03  # spread of a reading beyond the model's, x its mean
    # and far from focus this x log(the reading / the in-focus one) more (ColumnModels.reading)
    far_noise: float = 0.0
    # where the readings leave fewer than this share of the columns' weight effective, the
    # columns are drawn again around the likely ones (jittered by `jitter` of the box's
    # ranges) and every reading so far is weighed again on them
    renew_below: float = 0.5
    jitter: float = 0.05
    # the flat bottom weighed log-uniformly over this many decades (0: as the box draws it)
    flat_decades: float = FLAT_DECADES
    # Readings in any pixel scale: every reading is the model's times an unknown factor of
    # the episode, flat on a log scale, marginalised per state (module docstring): the
    # posterior then learns only from ratios of readings and the curve's shape, as a unit-free
    # policy must (benchmarks/imitation.py), and aligns a column imaged at any magnification.
    scale_free: bool = False
    # where the next reading goes: "variance", where it leaves the least expected variance of
    # the optimum; "entropy", the least expected entropy of it over the grid (the most
    # information: no reading spent telling two far modes apart where one near focus tells
    # both); "chance", where it leaves the final setting the greatest expected chance of
    # passing the verification (one reading ahead: the stop's own question)
    probe_rule: str = "variance"
    # stop at `confidence` x the chance at the optimum: one known column too noisy to pass
    # surely at focus still ends (not a box: there it mixes columns not yet told apart)
    relative_stop: bool = False
    resample: tuple[int, int] = (SCORED_STATES, STOP_STATES)  # the probe's states, the stop's
    # Evidence of given columns (alignrl/posterior/calibration.py): the columns set by
    # `use_columns`, never drawn again, each column's filter normalised apart, and after
    # `begin` and every `observe` `log_evidence` holds per column the log of the chance of
    # its readings (up to a constant the same for every column)
    columns_apart: bool = False
    models: ColumnModels = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must lie in (0, 1), got {self.confidence}")
        if not self.spec_relative > 1.0:
            raise ValueError(f"spec_relative must exceed 1, got {self.spec_relative}")
        if min(self.draws, self.specimen_points, self.max_acquisitions, *self.resample) < 1:
            raise ValueError("draws, specimen_points, max_acquisitions, resample: at least 1")
        if self.optimum_prior not in ("box", "interval"):
            raise ValueError(f"optimum_prior must be box or interval, got {self.optimum_prior!r}")
        if not (math.isfinite(self.far_noise) and self.far_noise >= 0.0):
            raise ValueError(f"far_noise must be a finite share >= 0, got {self.far_noise}")
        if self.probe_rule not in PROBE_RULES:
            raise ValueError(f"probe_rule must be one of {PROBE_RULES}, got {self.probe_rule!r}")
        if not (math.isfinite(self.flat_decades) and self.flat_decades >= 0.0):
            raise ValueError(f"flat_decades must be finite and >= 0, got {self.flat_decades}")
        drawn = (self.draws, self.seed, self.model_noise, self.far_noise, self.flat_decades)
        self.models = first_draw(self.family, *drawn)
        self._initial = self.models
        nodes, _ = np.polynomial.hermite_e.hermegauss(self.specimen_points)
        self._scale_nodes = nodes[None, :, None]  # (1, Z, 1), x specimen_rel: the log scale
        shaped = (self.spec_relative, self.optimum_prior, self.specimen_points)
        key = (self.family.model_dump_json(), *drawn, *shaped)
        self._grid, self._spacing, self._prior = remembered(_priors, key, self._grid_and_prior)
        self._scale: ScaleSums | None = None
        self._version = 0  # one more at every change of the posterior (what `_memo` keeps)

    def _grid_and_prior(self) -> tuple[np.ndarray, float, np.ndarray]:
        """The optimum's grid (N,), its spacing, and the prior (K, Z, N): flat over the
        optimum's range, the specimen's scale as Gauss-Hermite weighs it (read-only)."""
        low, high = self.family.optimum_fraction if self.optimum_prior == "box" else (0.0, 1.0)
        spacing = float(
            min(
                self.models.spec_half_width(self.spec_relative).min(),
                narrowest_spec(self.family, self.spec_relative),
            )
        )
        spacing /= GRID_POINTS_PER_WINDOW
        spacing = max(spacing, (high - low + 0.1) / MAX_GRID)
        pad = 0.05 + 3.0 * spacing
        grid = np.arange(low - pad, high + pad + spacing / 2, spacing)
        _, weights = np.polynomial.hermite_e.hermegauss(self.specimen_points)
        prior_u = ((grid >= low) & (grid <= high)).astype(float)
        prior = (weights / weights.sum())[None, :, None] * prior_u[None, None, :]
        prior = np.broadcast_to(prior, (self.models.count, *prior.shape[1:])).copy()
        prior /= prior.sum()
        read_only(grid, prior)
        return grid, spacing, prior

    def __getstate__(self) -> dict:
        """A copy (copy.copy, pickle) takes the state but not the buffers: it makes its own
        (`_own`) before it writes, and keeps nothing of this one's `_memo`."""
        state = self.__dict__.copy()
        state.pop("_owned", None)
        state.pop("_cache", None)
        return state

    # --- one reading at a time -------------------------------------------------------------

    def begin(self) -> None:
        """Forget every reading: a new alignment starts from the prior."""
        self.models = self._initial
        self._rng = np.random.default_rng(self.seed)
        owned = self._own()
        self._posterior = owned.posteriors[0]
        np.copyto(self._posterior, self._prior)
        self._readings: list[tuple[float, float, float]] = []
        self._scale = self._fresh_scale() if self.scale_free else None
        self.log_evidence = np.zeros(self.models.count)
        self._version += 1

    def use_columns(self, rows: np.ndarray, far_noise: np.ndarray | None = None) -> None:
        """Weigh the columns at `rows` (K, len(PAIR_FIELDS)) of fractions of the box, equally
        likely, each read with its own far noise where `far_noise` (K,) is given, from the
        next `begin` on (with `columns_apart`: the evidence of each)."""
        far = self.far_noise if far_noise is None else far_noise
        self._initial = ColumnModels.at(self.family, rows, self.model_noise, far)
        self._prior = np.broadcast_to(self._prior[:1], (len(rows), *self._prior.shape[1:])).copy()
        self._prior /= self._prior.sum()
        self._version += 1

    def observe(self, setting: float, reading: float, side: float = 1.0) -> None:
        """A reading (px; NaN: no edges) taken at `setting`, a fraction of the interval,
        approached from `side`: +1 from below (as BayesianAutofocus writes every setting), -1
        from above, 0 unknown (a column as it was found, anywhere within its backlash: read
        as the mixture of both branches and their middle, BRANCHES)."""
        self._readings.append((float(setting), float(reading), float(side)))
        self._own(keep=True)
        posterior = self._weigh(self._posterior, *self._readings[-1])
        if self.columns_apart:
            posterior = self._weighed_apart(posterior)
        posterior = self._drifted(posterior)
        if self._renewable(posterior):
            posterior = self._renew(posterior, self._readings, self._rng)
        self._posterior = posterior
        self._version += 1

    def decide(self) -> tuple[float, bool]:
        """(setting, done): where to take the next reading, or, done, the setting most likely
        to pass the verification once it is as sure as `confidence` asks (`final`)."""
        setting, chance = self._final(self._posterior)
        if chance >= self.confidence:
            return setting, True
        return self.probe(), False

    def probe(self) -> float:
        """Where the next reading goes (`probe_rule`)."""
        return self._next_probe(self._posterior)

    def final(self) -> tuple[float, float]:
        """The setting most likely to pass the verification now, and that chance (with
        `relative_stop`, as a share of the chance at the optimum itself)."""
        return self._final(self._posterior)

    # --- the buffers ----------------------------------------------------------------------

    def _own(self, keep: bool = False) -> PosteriorBuffers:
        """This instance's buffers, made where it has none (new, or a copy of another: with
        `keep`, the posterior and the scale's sums copied into them)."""
        owned = self.__dict__.get("_owned")
        shape = self._posterior.shape if keep else self._prior.shape
        if owned is not None and owned.posteriors[0].shape == shape:
            return owned
        owned = self._owned = PosteriorBuffers.make(shape, self.scale_free)
        if keep:
            self._posterior = owned.holding(self._posterior)
            if self._scale is not None and owned.sums is not None:
                sums = (self._scale.sum0, self._scale.sum1)
                self._scale = ScaleSums(*owned.holding_sums(*sums), self._scale.readings)
        return owned

    def _fresh_scale(self) -> ScaleSums:
        """ScaleSums.empty in this instance's buffers."""
        return ScaleSums(*self._owned.holding_sums(0.0, 0.0))

    def _memo(self) -> dict:
        """What is kept of the present posterior (`_version`) and its states."""
        return self.__dict__.setdefault("_cache", {})

    # --- the model ------------------------------------------------------------------------

    def _errors(
        self, setting: np.ndarray | float, grid: np.ndarray, side: float = 1.0
    ) -> np.ndarray:
        """Focus errors of a setting approached from `side` (+1: below), against optimum grid
        points."""
        return np.asarray(setting)[..., None, None, None] - side * self.models.lag - grid

    def _likelihood(self, setting: float, reading: float, side: float = 1.0) -> np.ndarray:
        """Per state, the chance of `reading` (px; NaN: no edges) at `setting` approached
        from `side` (0: unknown, _on_branches); scale_free, given the readings before it,
        which it then joins. The plain formulas, whole arrays at a time: `_weigh` computes
        the same numbers chunk by chunk (side 0: with these)."""
        if side == 0.0:
            return self._on_branches(setting, reading)
        return self._on_branch(setting, reading, side)

    def _on_branches(self, setting: float, reading: float) -> np.ndarray:
        """_likelihood of a reading on an unknown side: the mean over BRANCHES; scale_free,
        of each one's predictive, the reading joining the scale's sums once
        (ScaleSums.add_either)."""
        if self._scale is None:
            chances = [self._on_branch(setting, reading, branch) for branch in BRANCHES]
            return sum(chances) / len(BRANCHES)
        scales = self.models.specimen_rel * self._scale_nodes
        branches = [
            self.models.reading(self._errors(setting, self._grid, branch), scales)
            for branch in BRANCHES
        ]
        if not math.isfinite(reading):
            return sum(none for none, _, _ in branches) / len(BRANCHES)
        return self._scale.add_either(
            [math.log(reading) - np.log(mean) for _, mean, _ in branches],
            [(spread / mean) ** 2 for _, mean, spread in branches],
            [1.0 - none for none, _, _ in branches],
        )

    def _on_branch(self, setting: float, reading: float, side: float) -> np.ndarray:
        """_likelihood on one side's branch (0: the middle)."""
        none, mean, spread = self.models.reading(
            self._errors(setting, self._grid, side), self.models.specimen_rel * self._scale_nodes
        )
        if not math.isfinite(reading):
            return none
        if self._scale is not None:  # and the reading joins the scale's sums
            residual, variance = math.log(reading) - np.log(mean), (spread / mean) ** 2
            density = self._scale.predictive(residual, variance)
            self._scale.add(residual, variance)
            return (1.0 - none) * density
        density = np.exp(-0.5 * ((reading - mean) / spread) ** 2) / spread
        return (1.0 - none) * density

    def _chunks(self) -> list[tuple[slice, ReadingConstants]]:
        """The columns a few at a time (CHUNK_STATES states), with their reading constants."""
        _, specimens, points = self._prior.shape
        return self.models.chunks(max(1, CHUNK_STATES // (specimens * points)))

    def _weigh(self, posterior: np.ndarray, setting: float, reading: float, side: float):
        """`posterior` x the _likelihood of a reading, into the other posterior buffer: the
        same numbers as the plain formulas, a chunk of columns at a time (module docstring);
        scale_free, the reading joins the scale's sums."""
        weighed = self._owned.other(posterior)
        if side == 0.0:  # an alignment's first reading at most: the plain formulas
            return np.multiply(posterior, self._on_branches(setting, reading), out=weighed)
        start = np.asarray(setting)[..., None, None, None] - side * self.models.lag
        factor = np.exp(self.models.specimen_rel * self._scale_nodes)  # (K, Z, 1)
        if factor.shape[1] == 1 and np.all(factor == 1.0):
            factor = None  # x 1: the same numbers
        scale, measured = self._scale, math.isfinite(reading)
        chunks = self._chunks()
        size = chunks[0][0].stop  # columns in a chunk (the last may hold fewer)
        shape, states = (size, 1, self._grid.size), (size, *posterior.shape[1:])
        buffers = [*reading_work(shape, states, extra=3), scratch("error", shape)]
        for rows, constants in chunks:
            count = rows.stop - rows.start
            work = buffers if count == size else [buffer[:count] for buffer in buffers]
            error = np.subtract(start[rows], self._grid, out=work[9])
            none, mean, spread = reading_into(
                constants, error, None if factor is None else factor[rows], work
            )
            if not measured:
                chance = none
            elif scale is not None:
                residual = np.subtract(math.log(reading), np.log(mean, out=work[6]), out=work[6])
                variance = np.square(np.divide(spread, mean, out=spread), out=spread)
                density = scale.predictive_into(rows, residual, variance, [work[5], work[7]])
                scale.add_into(rows, residual, variance, work[8])
                chance = np.subtract(1.0, none, out=none)
                if density is not None:
                    chance = np.multiply(chance, density, out=density)
            else:
                density = np.divide(np.subtract(reading, mean, out=work[6]), spread, out=work[6])
                np.square(density, out=density)
                np.multiply(-0.5, density, out=density)
                np.exp(density, out=density)
                np.divide(density, spread, out=density)
                chance = np.multiply(np.subtract(1.0, none, out=none), density, out=density)
            np.multiply(posterior[rows], chance, out=weighed[rows])
        if measured and scale is not None:
            scale.counted()
        return weighed

    def _weighed_apart(self, posterior: np.ndarray) -> np.ndarray:
        """`columns_apart`: each column's chance of the reading joins its `log_evidence`, and
        each column holds its own share again (a column that ruled its every state out
        starts from the prior; its evidence says how unlikely it is). In place."""
        totals = posterior.sum(axis=(1, 2))
        # each column held 1 / K of the weight before the reading: its own chance is K x
        self.log_evidence += np.log(np.maximum(totals, 1e-300)) + math.log(self.models.count)
        kept = (totals > 0)[:, None, None]
        np.divide(posterior, np.where(kept, totals[:, None, None], 1.0), out=posterior)
        if not kept.all():
            np.copyto(posterior, self._prior * self.models.count, where=~kept)
        return posterior

    def _drifted(self, posterior: np.ndarray) -> np.ndarray:
        """The posterior normalised, then each column's optimum blurred by its drift over
        one acquisition: passes of a three-point kernel whose variances add up to the
        drift's (in grid steps squared). In place, a chunk of columns at a time."""
        total = posterior.sum()
        if not total > 0:  # every state ruled out: the model is wrong here; start again
            np.copyto(posterior, self._prior)
            return posterior
        variance = (self.models.drift / self._spacing) ** 2  # (K, 1, 1)
        passes = math.ceil(float(variance.max()))  # at most 1 grid step squared per pass
        if variance.max() < 0.01:
            return np.divide(posterior, total, out=posterior)
        share = 0.5 * variance / passes  # to each neighbour, per pass
        keep = 1.0 - 2.0 * share
        chunks = self._chunks()
        neighbours = scratch("spread", posterior[chunks[0][0]].shape)  # two, summed
        for rows, _ in chunks:
            part = np.divide(posterior[rows], total, out=posterior[rows])
            spread = neighbours[: rows.stop - rows.start]
            for _ in range(passes):
                np.add(part[..., :-2], part[..., 2:], out=spread[..., 1:-1])
                spread[..., 0], spread[..., -1] = part[..., 1], part[..., -2]
                np.multiply(share[rows], spread, out=spread)
                np.add(np.multiply(keep[rows], part, out=part), spread, out=part)
        return np.divide(posterior, posterior.sum(), out=posterior)

    def _renewable(self, posterior: np.ndarray) -> bool:
        """Whether the columns' weights have collapsed onto a few (module docstring)."""
        if self.models.count == 1 or self.columns_apart:
            return False
        weights = posterior.sum(axis=(1, 2))
        return 1.0 / float(np.sum(weights**2)) < self.renew_below * self.models.count

    def _renew(
        self, posterior: np.ndarray, readings: list[tuple[float, ...]], rng: np.random.Generator
    ) -> np.ndarray:
        """Columns drawn again around the likely ones, every reading weighed on them (in
        this instance's buffers, `posterior` one of them)."""
        picks = _systematic(posterior.sum(axis=(1, 2)), self.models.count, rng.random())
        rows = self.models.rows[picks] + self.jitter * rng.standard_normal(
            self.models.rows[picks].shape
        )
        self.models = ColumnModels.at(
            self.family,
            np.clip(rows, 0.0, 1.0),
            self.model_noise,
            self.far_noise,
            self.flat_decades,
        )
        np.copyto(posterior, self._prior)
        if self._scale is not None:
            self._scale = self._fresh_scale()
        for reading in readings:
            posterior = self._drifted(self._weigh(posterior, *reading))
        return posterior

    # --- the states that count, and what the next reading would tell -----------------------

    def _live_states(self, posterior: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
        """The flat indices (C order) and weights of the states that still count, and a list
        that holds their cumulative shares once `_scored` asks: found once per posterior
        (`_memo`) for the stop and the probe alike."""
        key = (self._version, id(posterior))
        memo = self._memo() if posterior is self.__dict__.get("_posterior") else {}
        if memo.get("live", (None,))[0] != key:
            flat = np.flatnonzero(posterior > LIVE * posterior.max())
            memo["live"] = (key, (flat, posterior.reshape(-1)[flat], []))
        return memo["live"][1]

    def _scored(self, posterior: np.ndarray, most: int) -> tuple[np.ndarray, ...]:
        """The live states and their weights, systematically resampled to at most `most`."""
        flat, weight, edges = self._live_states(posterior)
        if flat.size > most:
            if not edges:
                edges.append(np.cumsum(weight / weight.sum()))
            flat = flat[_picks(edges[0], most, 0.5)]
            weight = np.full(most, 1.0 / most)
        return (*np.unravel_index(flat, posterior.shape), weight / weight.sum())

    def _states(self, k: np.ndarray, z: np.ndarray, n: np.ndarray) -> StateReadings:
        """The reading model of states (k, z, n), gathered once for those arrays (`_memo`:
        the stop's chunks, the probe's)."""
        memo = self._memo().get("states", (None,) * 5)
        if all(
            mine is theirs for mine, theirs in zip(memo[:4], (k, z, n, self.models), strict=True)
        ):
            return memo[4]
        states = StateReadings.of(
            self.models, k, self._grid[n], self._scale_nodes[0, z, 0], self.spec_relative
        )
        self._memo()["states"] = (k, z, n, self.models, states)
        return states

    def _state_reading(
        self,
        settings: np.ndarray | None,
        k: np.ndarray,
        z: np.ndarray,
        n: np.ndarray,
        scaled: bool = False,
    ) -> tuple[np.ndarray, ...]:
        """The reading model at `settings` (M,) for states (S,): arrays (M, S), or (1, S) at
        each state's optimum (`settings` None); `scaled` (scale_free): in the pixels of the
        readings so far, as each state's scale puts them. Buffers the next call overwrites."""
        scaled = scaled and self._scale is not None
        shift = self._scale.estimate(k, z, n) if scaled else None
        return self._states(k, z, n).reading(settings, shift)

    def _candidates(self, u: np.ndarray, weight: np.ndarray, lag: float) -> np.ndarray:
        """Settings a probe may go to: a grid over the interval, and around the quantiles
        of the optimum's posterior (as approached from below)."""
        quantiles = _quantiles(u, weight, [0.02, 0.1, 0.25, 0.5, 0.75, 0.9, 0.98])
        window = float(self.models.spec_half_width(self.spec_relative).mean())
        offsets = np.array([-6.0, -3.0, -1.5, 0.0, 1.5, 3.0, 6.0]) * window
        around = (quantiles[:, None] + lag + offsets[None, :]).ravel()
        return np.unique(np.clip(np.concatenate([np.linspace(0.0, 1.0, 17), around]), 0, 1))

    def _next_probe(self, posterior: np.ndarray) -> float:
        """The next reading's setting: the least expected variance of the optimum, or the
        greatest expected chance of the final setting (`probe_rule`)."""
        k, z, n, weight = self._scored(posterior, self.resample[0])
        u = self._grid[n]
        lag = float(np.sum(weight * self.models.lag[k, 0, 0]))
        settings = self._candidates(u, weight, lag)
        top = 1.5 * float(self.models.saturation.max())
        bottom = 0.2 * float(self.models.best_px().min())
        if self._scale is not None:  # the readings' own pixels: around the states' scales
            shift = self._scale.estimate(k, z, n)[0]
            top, bottom = top * math.exp(shift.max()), bottom * math.exp(shift.min())
        edges = np.geomspace(bottom, top, self.reading_bins - 1)
        passes = cells = None
        if self.probe_rule == "entropy":  # the states by their optimum's grid point
            order = np.argsort(n, kind="stable")
            k, z, n, weight, u = k[order], z[order], n[order], weight[order], u[order]
            cells = np.flatnonzero(np.diff(n, prepend=-1))
        if self.probe_rule == "chance":  # the final settings after the reading, per state
            finals = self._final_settings(k, n, weight, FINAL_SETTINGS)
            passes = self._passes(finals, k, z, n).copy()
        best, best_value = float(settings[0]), math.inf
        for chunk in np.array_split(settings, max(1, settings.size // 16)):
            joint = outcome_chances(
                *self._state_reading(chunk, k, z, n, scaled=True), edges, weight
            )
            if passes is not None:  # minus the expected chance of the best final setting
                value = -np.einsum("msb,fs->mbf", joint, passes).max(axis=2).sum(axis=1)
            elif cells is not None:  # the optimum's expected entropy over its grid points
                value = expected_entropy(joint, cells)
            else:
                mass = joint.sum(axis=1)
                first = np.einsum("msb,s->mb", joint, u)
                second = np.einsum("msb,s->mb", joint, u * u)
                value = (second - first**2 / np.maximum(mass, 1e-300)).sum(axis=1)
            index = int(np.argmin(value))
            if value[index] < best_value:
                best, best_value = float(chunk[index]), float(value[index])
        return best

    def _final_settings(self, k: np.ndarray, n: np.ndarray, weight: np.ndarray, count: int):
        """`count` final settings across the optimum's posterior (states k, n weighted by
        `weight`), as approached from below."""
        u = self._grid[n]
        lag = float(np.sum(weight * self.models.lag[k, 0, 0]))
        span = _quantiles(u, weight, [0.005, 0.995])
        return np.linspace(span[0], span[1], count) + lag

    def _passes(self, settings: np.ndarray, k: np.ndarray, z: np.ndarray, n: np.ndarray):
        """Each state's chance of passing at `settings` (None: its optimum): (M, S), a buffer
        the next call overwrites."""
        return self._states(k, z, n).passing(settings)

    def _final(self, posterior: np.ndarray) -> tuple[float, float]:
        """The setting most likely to pass the verification, and that chance (`final`)."""
        k, z, n, weight = self._scored(posterior, self.resample[1])
        settings = self._final_settings(k, n, weight, STOP_SETTINGS)
        chances = np.zeros(settings.size)
        for chunk in np.array_split(np.arange(settings.size), 9):
            chances[chunk] = self._passes(settings[chunk], k, z, n) @ weight
        index = int(np.argmax(chances))
        if not self.relative_stop:
            return float(settings[index]), float(chances[index])
        attainable = float(self._passes(None, k, z, n)[0] @ weight)
        return float(settings[index]), float(min(chances[index] / max(attainable, 1e-300), 1.0))


# FamilyPosterior in any pixel scale: one specimen point, the unknown factor covers the
# specimen's scale too.
SCALE_FREE = {"scale_free": True, "specimen_points": 1}

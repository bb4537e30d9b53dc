"""Calibrating the focus posterior to one column from alignments on it (issue 21: adapting a
champion to a microscope it never saw).

A champion that walks and ends by a posterior over the training box (Task.finish_at_posterior,
alignrl/envs/ending.py) knows of the column in front of it only what the box knows: every
alignment starts from the whole box and spends readings telling which column it is on. A few
dozen alignments on one column say much more: which reading model, the same in all of them,
makes all their readings likely, each alignment's optimum unknown and marginalised over the
interval (as the hindsight posterior does). `calibrate` finds that model; the posterior over
that one column (`calibrated_posterior`: an oracle whose model was measured on the column,
not written in a file) then walks and ends the champion's alignments (Task.posterior_column,
`alignrl calibrate`).

* The evidence of a column (`column_evidence`): per alignment the filter of FamilyPosterior
  (a grid over the optimum, its drift, the specimen's scale), each column kept apart
  (`ColumnEvidence`): the log of the product of every reading's predictive given the ones
  before, summed over the alignments.
* The search: a cross-entropy search over the training box widened by `reach` x every range
  (a column steeper, wider or noisier than any the box holds is found too): a population of
  columns (a scrambled Sobol' sequence first), the best `elite` share of all seen kept, the
  next population drawn from a normal around them, for `rounds`; the column of the highest
  evidence is the calibration.
* The readings are in the column's own pixels (the detector and magnification as they were
  during the alignments: calibrate again after changing them), and far from focus trusted
  less (`CALIBRATED`, with which the calibrated posterior reads too): the fitted noise is
  then what the model does not explain near focus, where the verification is taken.

Every reading but an alignment's first must have been approached from below
(Task.approach_from_below, PosteriorFocus), so that backlash shifts them all alike; the first
(an aligner's opening reading: the column as it was found, on whichever branch of its
backlash) is read on every branch (FamilyPosterior.observe, side 0), and the offset between
it and the rest is what tells the backlash (`sweeps_of`). Each alignment's verification image,
taken where the policy ended it, is read last: near focus as no other reading is, it tells
the column's in-focus width, the width the success rule is measured against (on val-backlash
without it: a floor of 1.23 px and a flat bottom of 0.8 % of the interval, where the file has
1.2 px and 0.1 %; with it 1.21 px and 0.3 %: docs/benchmarks.md, nineteenth session).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.family import PAIR_FIELDS, FocusFamily, even_fractions
from alignrl.apparatus.family_posterior import (
    _FAMILY_NAMES,
    ColumnModels,
    FamilyPosterior,
    focus_box,
    widened,
)

__all__ = [
    "ALIGNMENTS",
    "BACKLASH_SEARCHED",
    "CALIBRATED",
    "CALIBRATED_STOP",
    "COLUMN_FIELDS",
    "FAR_NOISE_SEARCHED",
    "FROM_ABOVE",
    "Calibration",
    "ColumnEvidence",
    "calibrate",
    "calibrated_posterior",
    "check_far_noise",
    "check_search",
    "column_evidence",
    "column_family",
    "column_problem",
    "column_values",
    "sweeps_of",
]

# The reading model's parameters (the family's names), in the order Task.posterior_column
# keeps them
COLUMN_FIELDS = tuple(_FAMILY_NAMES.values())
# How a calibration, and the posterior over the column it found, read: far from focus a
# reading is trusted less (as posterior-robust does on images); what the fit leaves near
# focus is the column's noise, and the model's own spread beyond it small. The export keeps
# its far noise (Task.posterior_far_noise), with which its column was fitted. 0.05: on the
# validation instruments' ten-alignment calibrations every reading was likelier than with
# the box posterior's 0.1 (per reading, val-backlash -0.58 against -0.78, val-steep -0.69
# against -0.79), and their policies aligned as many columns in as many acquisitions or
# fewer (val-steep 100/100 at 5 against 6; docs/benchmarks.md, twenty-seventh session).
CALIBRATED = {"far_noise": 0.05, "model_noise": 0.01}
# The far noises a calibration weighs (`calibrate`): its search done at CALIBRATED's 0.05,
# the best column it kept is weighed with each, then the columns it kept with the likeliest,
# and the likeliest of them is the calibration (at least as likely as the search's best at
# 0.05, one of these). How much a far reading tells depends on the specimen and the
# detector as much as on the column, so the column's own readings say it, rather than the
# simulator's images that chose 0.05 (which stays the far noise of a column given without
# one). None below 0.05: a posterior too sure of far readings loses columns where one not
# sure enough only spends an image more (at 0.03, val-steep 94/100 where 0.05 aligned all;
# searched from 0.01, near-bound and narrow-interval took 0.03 and 0.02 and near-bound lost
# a column: docs/benchmarks.md, twenty-seventh and twenty-eighth sessions).
FAR_NOISE_SEARCHED = (0.05, 0.07, 0.1, 0.15, 0.2, 0.3)
# The chance (x the chance at the optimum itself) at which a calibrated policy stops, and
# before which its stops are readings (Task.stop_when_sure, probe_until_sure), where the
# champion's box stops at 0.98. One known column's posterior, trusting far readings less,
# states less than it should: on val-steep, calibrated on ten alignments, every setting it
# gave 0.8-0.98 passed (benchmarks/reliability.py). Chosen on the validation instruments
# with ten alignments (docs/benchmarks.md, twenty-sixth session): 0.9 aligned all 600
# columns in two sessions at medians of 3, 3, 3, 2, 6, 3, where 0.98 aligned them at 4, 3, 3,
# 2, 6, 4; 0.8 lost one.
CALIBRATED_STOP = 0.9
# The search looks this share of every range beyond the box: a column may be steeper, wider
# or noisier than any the box holds. 1.5 (strong-hysteresis's backlash) left the search of
# 256 x 10 short of the best column it found at 0.5 (docs/benchmarks.md).
CALIBRATION_REACH = 0.5
POPULATION, ROUNDS, ELITE = 256, 8, 0.1
# Alignments a calibration runs by default. Ten: with the champion of 2026-12-06 on the
# validation instruments, ten (71-96 images) aligned all 600 columns at medians of 4, 3, 3, 2,
# 6, 4, and thirty (214-284 images) all 600 at 4, 3, 3, 2, 11, 4: on val-steep the column
# thirty found never let the posterior be sure, and every alignment read to its budget
# (docs/benchmarks.md, twenty-fifth session).
ALIGNMENTS = 10
# Readings approached from above after each alignment (alignrl/deploy/calibrate.py), and the
# backlash the search then reaches, a share of the interval: beyond the box's, since readings
# from both sides tell it. Two by default: with the champion of 2026-12-06 on the validation
# instruments they aligned all 600 columns against 596 without (val-backlash 100 against 96),
# one acquisition later on val-steep, for 60 images more per calibration (docs/benchmarks.md,
# twenty-second session; with the seventeenth session's champion they aligned one more).
FROM_ABOVE, BACKLASH_SEARCHED = 2, 0.03
MIN_SPREAD = 0.005  # the least spread of the search's normal, a share of the widened box

# One alignment's readings: (setting as a fraction of the knob's interval, width in px (NaN
# or inf: a frame without edges), the side it was approached from: +1 below, -1 above, 0
# unknown)
Sweep = Sequence[tuple[float, float, float]]


@dataclass
class ColumnEvidence(FamilyPosterior):
    """FamilyPosterior over columns set by `use` (rows of the box, never drawn again), each
    column's filter normalised apart: after `begin` and every `observe` of an alignment,
    `log_evidence` holds per column the log of the chance of its readings (up to a constant
    the same for every column)."""

    def use(self, rows: np.ndarray, far_noise: np.ndarray | None = None) -> None:
        """Columns at `rows` (K, len(PAIR_FIELDS)) of fractions of the box, equally likely,
        each read with its own far noise where `far_noise` (K,) is given."""
        far = self.far_noise if far_noise is None else far_noise
        self._initial = ColumnModels.at(self.family, rows, self.model_noise, far)
        self._prior = np.broadcast_to(self._prior[:1], (len(rows), *self._prior.shape[1:])).copy()
        self._prior /= self._prior.sum()

    def begin(self) -> None:
        super().begin()
        self.log_evidence = np.zeros(self.models.count)

    def _renewable(self, posterior: np.ndarray) -> bool:
        return False

    def _drifted(self, posterior: np.ndarray) -> np.ndarray:
        totals = posterior.sum(axis=(1, 2))
        # each column held 1 / K of the weight before the reading: its own chance is K x
        self.log_evidence += np.log(np.maximum(totals, 1e-300)) + math.log(self.models.count)
        kept = (totals > 0)[:, None, None]
        # each column its own share again (a column that ruled its every state out starts
        # from the prior; its evidence says how unlikely it is)
        posterior = posterior / np.where(kept, totals[:, None, None], 1.0)
        if not kept.all():
            posterior = np.where(kept, posterior, self._prior * self.models.count)
        return super()._drifted(posterior)


def column_evidence(
    evidence: ColumnEvidence,
    rows: np.ndarray,
    sweeps: Sequence[Sweep],
    far_noise: np.ndarray | None = None,
):
    """The log evidence (K,) of the columns at `rows` (each read with its own `far_noise`
    where given) for every reading of `sweeps`."""
    evidence.use(rows, far_noise)
    total = np.zeros(len(rows))
    for sweep in sweeps:
        evidence.begin()
        for setting, width, side in sweep:
            evidence.observe(setting, width, side)
        total += evidence.log_evidence
    return total


@dataclass(frozen=True)
class Calibration:
    """What `calibrate` found: the column's reading model (COLUMN_FIELDS: the family's
    units), the log evidence of every reading under it, what it read, and the best log
    evidence after each round (the search's progress)."""

    column: dict[str, float]
    log_evidence: float
    alignments: int
    readings: int
    progress: tuple[float, ...]
    far_noise: float = CALIBRATED["far_noise"]  # with which the column reads (fitted or given)
    far_noise_searched: tuple[float, ...] | None = None  # those weighed; None: given

    def per_reading(self) -> float:
        """The mean log evidence per reading (comparable across calibrations of a column)."""
        return self.log_evidence / max(self.readings, 1)


def check_search(population: int, rounds: int, elite: float = ELITE) -> None:
    """ValueError for a search `calibrate` cannot run: a population below 8, rounds below 1,
    an elite share outside (0, 1)."""
    if population < 8 or rounds < 1 or not 0.0 < elite < 1.0:
        raise ValueError(
            f"a calibration's population must be at least 8, its rounds at least 1 and its "
            f"elite a share in (0, 1); got {population}, {rounds}, {elite}"
        )


def check_far_noise(far_noise: float | None) -> None:
    """ValueError for a far noise a calibration cannot read with: not a share in [0, 1]
    (None: searched)."""
    if far_noise is not None and not (math.isfinite(far_noise) and 0.0 <= far_noise <= 1.0):
        raise ValueError(f"a calibration's far noise is a share in [0, 1], got {far_noise}")


def calibrate(
    sweeps: Sequence[Sweep],
    family: FocusFamily | None = None,
    reach: float = CALIBRATION_REACH,
    population: int = POPULATION,
    rounds: int = ROUNDS,
    elite: float = ELITE,
    seed: int = 0,
    on_round: Callable[[int, int, float], None] | None = None,
    far_noise: float | None = None,
) -> Calibration:
    """The column of `family` (default: the focus training box) widened by `reach` whose
    reading model makes `sweeps` most likely (module docstring), and with it the far noise
    its far readings are read with (FAR_NOISE_SEARCHED: after the search, the best column's
    likeliest; `far_noise`: that one throughout instead); where some reading was
    approached from above, backlash up to BACKLASH_SEARCHED at least. `on_round(done, steps,
    best log evidence)` after each round and after the far noise's (steps: `rounds`, one
    more where the far noise is searched).
    ValueError for no reading in focus's sense (fewer than two measured widths in all), a
    population below 8, rounds below 1, an elite share outside (0, 1) or a far noise
    outside [0, 1]."""
    measured = sum(1 for sweep in sweeps for _, width, _ in sweep if math.isfinite(width))
    if measured < 2:
        raise ValueError(
            f"a calibration needs measured readings: {len(sweeps)} alignments hold {measured}"
        )
    check_search(population, rounds, elite)
    check_far_noise(far_noise)
    box = widened(family if family is not None else focus_box(0.0), reach)
    if any(side < 0 for sweep in sweeps for _, _, side in sweep):  # backlash tells
        lowest, highest = box.hysteresis_fraction
        reach_to = {"hysteresis_fraction": (lowest, max(highest, BACKLASH_SEARCHED))}
        box = FocusFamily.model_validate({**box.model_dump(), **reach_to})
    searching = far_noise is None
    far = CALIBRATED["far_noise"] if searching else far_noise
    evidence = ColumnEvidence(box, draws=population, seed=seed, **{**CALIBRATED, "far_noise": far})
    rng = np.random.default_rng(seed)
    # only the reading model's parameters are searched; the rest (interval, optimum, dose)
    # say nothing of the readings and stay in the box's middle
    searched = [PAIR_FIELDS.index(name) for name in COLUMN_FIELDS]
    rows = np.full((population, len(PAIR_FIELDS)), 0.5)
    rows[:, searched] = even_fractions(len(searched), population, seed)
    kept_rows, kept_log = rows[:0], np.zeros(0)
    keep = max(2, round(elite * population))
    progress = []
    steps = rounds + searching
    for done in range(1, rounds + 1):
        log = column_evidence(evidence, rows, sweeps)
        every_rows, every_log = np.concatenate([kept_rows, rows]), np.concatenate([kept_log, log])
        order = np.argsort(-every_log, kind="stable")[:keep]
        kept_rows, kept_log = every_rows[order], every_log[order]
        progress.append(float(kept_log[0]))
        if on_round is not None:
            on_round(done, steps, progress[-1])
        spread = np.maximum(kept_rows[:, searched].std(axis=0), MIN_SPREAD)
        drawn = kept_rows[:, searched].mean(axis=0) + spread * rng.standard_normal(
            (population, len(searched))
        )
        rows = rows.copy()
        rows[:, searched] = np.clip(drawn, 0.0, 1.0)
    if searching:  # the best column with each far noise, the kept ones with the likeliest
        shares = np.array(FAR_NOISE_SEARCHED)
        log = column_evidence(
            evidence, np.repeat(kept_rows[:1], shares.size, axis=0), sweeps, shares
        )
        likeliest = float(shares[int(np.argmax(log))])
        if likeliest == far:  # the search's own: its best stands as found (weighed again in
            progress.append(progress[-1])  # another batch, its evidence moves by ~1e-7)
        else:
            far = likeliest
            log = column_evidence(evidence, kept_rows, sweeps, np.full(len(kept_rows), far))
            kept_rows = kept_rows[np.argsort(-log, kind="stable")]
            progress.append(float(log.max()))
        if on_round is not None:
            on_round(steps, steps, progress[-1])
    best = ColumnModels.at(box, kept_rows[:1], 0.0)
    column = {
        name: float(getattr(best, attribute)[0, 0, 0]) for attribute, name in _FAMILY_NAMES.items()
    }
    return Calibration(
        column=column,
        log_evidence=progress[-1],
        alignments=len(sweeps),
        readings=sum(len(sweep) for sweep in sweeps),
        progress=tuple(progress),
        far_noise=float(far),
        far_noise_searched=FAR_NOISE_SEARCHED if searching else None,
    )


def column_problem(column: Mapping[str, float]) -> str | None:
    """What is wrong with a calibrated column (a mapping of COLUMN_FIELDS), or None."""
    missing = [name for name in COLUMN_FIELDS if name not in column]
    unknown = [name for name in column if name not in COLUMN_FIELDS]
    if missing or unknown:
        return (
            f"a calibrated column names {', '.join(COLUMN_FIELDS)}; "
            f"missing: {', '.join(missing) or 'none'}, unknown: {', '.join(unknown) or 'none'}"
        )
    try:
        column_family(column)
    except ValueError as error:
        return f"a calibrated column outside what a focus column may be: {error}"
    return None


def column_values(column: Mapping[str, float]) -> tuple[float, ...]:
    """A calibrated column (a mapping of COLUMN_FIELDS) as Task.posterior_column keeps it:
    its values in COLUMN_FIELDS' order. ValueError naming what is wrong with it."""
    problem = column_problem(column)
    if problem is not None:
        raise ValueError(f"posterior_column: {problem}")
    return tuple(float(column[name]) for name in COLUMN_FIELDS)


def column_family(column: Mapping[str, float]) -> FocusFamily:
    """The focus family that is the one column (every reading parameter a point), the rest
    (interval, specimens) as the training box has it. pydantic's ValidationError (a
    ValueError) for a value no focus column may take."""
    update = {name: (float(column[name]), float(column[name])) for name in COLUMN_FIELDS}
    data = {**focus_box(0.0).model_dump(), **update, "name": "calibrated-column"}
    return FocusFamily.model_validate(data)


def calibrated_posterior(
    column: Mapping[str, float], spec_relative: float, far_noise: float | None = None
) -> FamilyPosterior:
    """The posterior over the one calibrated column (in its own pixels), as it read during
    the calibration (CALIBRATED; `far_noise` in place of its far noise where given: the one
    the column was fitted with), its stop relative to the chance at the optimum (a column
    whose fitted noise keeps that below the confidence still ends: `relative_stop`)."""
    family = column_family(column)
    reads = CALIBRATED if far_noise is None else {**CALIBRATED, "far_noise": far_noise}
    return FamilyPosterior(family, spec_relative=spec_relative, relative_stop=True, **reads)


def sweeps_of(records: Sequence, low: float, high: float) -> list[list[tuple[float, ...]]]:
    """The sweeps (Sweep) of a one-knob session's alignments (ScenarioResult records: their
    trajectory and verification), settings as fractions of [low, high]: each one's first
    reading on an unknown side (the column as it was found), the rest from below, and last
    the session's verification image where the alignment ended (from below, as the policy
    ends; on its last reading's side where it ended there without a write): the image
    nearest focus, which tells the column's in-focus width as no other reading does."""

    def width(reading: float | None) -> float:
        return math.nan if reading is None else float(reading)

    sweeps = []
    for record in records:
        sides = [0.0] + [1.0] * (len(record.trajectory) - 1)
        readings = [
            (float(setting), width(reading), side)
            for (setting, reading), side in zip(record.trajectory, sides, strict=True)
        ]
        final = float(record.final_setting)
        stayed = bool(readings) and final == readings[-1][0]
        readings.append((final, width(record.final_width_px), readings[-1][2] if stayed else 1.0))
        sweeps.append([((setting - low) / (high - low), *rest) for setting, *rest in readings])
    return sweeps

"""Calibrating the focus posterior to one column from alignments on it (issue 21: adapting a
champion to a microscope it never saw).

A champion that walks and ends by a posterior over the training box (Ending.at "posterior",
alignrl/envs/ending.py) knows of the column in front of it only what the box knows: every
alignment starts from the whole box and spends readings telling which column it is on. A few
dozen alignments on one column say much more: which reading model, the same in all of them,
makes all their readings likely, each alignment's optimum unknown and marginalised over the
interval (as the hindsight posterior does). `calibrate` finds that model; the posterior over
that one column (`calibrated_posterior`: an oracle whose model was measured on the column,
not written in a file) then walks and ends the champion's alignments (PosteriorSettings.column,
`alignrl calibrate`).

* The evidence of a column (`column_evidence`): per alignment the filter of FamilyPosterior
  (a grid over the optimum, its drift, the specimen's scale), each column kept apart
  (`evidence_of`, FamilyPosterior's `columns_apart`): the log of the product of every
  reading's predictive given the ones before, summed over the alignments.
* The search: a cross-entropy search over the training box widened by `reach` x every range
  (a column steeper, wider or noisier than any the box holds is found too): a population of
  columns (a scrambled Sobol' sequence first), the best `elite` share of all seen kept, the
  next population drawn from a normal around them, for `rounds`; the column of the highest
  evidence is the calibration.
* The readings are in the column's own pixels (the detector and magnification as they were
  during the alignments: calibrate again after changing them), and far from focus trusted
  less (`CALIBRATED`, with which the calibrated posterior reads too): the fitted noise is
  then what the model does not explain near focus, where the verification is taken.
* What it believes (issue 60): a width below MIN_EDGE_WIDTH_PX is no reading; a search is
  bounded by the memory it states (`search_memory`, MAX_SEARCH_BYTES); readings support a
  column only where their widths follow the setting (`support_p`) and each alignment's
  fitted focus lies inside the limits it was read within (`check_support`:
  UncalibratedError otherwise); a calibrated column, and every posterior setting a card
  gives, lies within the physical ranges of an instrument family (`column_bound_problem`,
  `posterior_options_problem`: alignrl/apparatus/family_box.py, PHYSICAL).

Every reading but an alignment's first must have been approached from below
(Ending.approach_from_below, BayesianAutofocus), so that backlash shifts them all alike; the first
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
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from alignrl.apparatus.family import even_fractions
from alignrl.apparatus.family_box import PAIR_FIELDS, PHYSICAL, FocusFamily
from alignrl.apparatus.guard import MIN_EDGE_WIDTH_PX
from alignrl.posterior.inference import FamilyPosterior
from alignrl.posterior.models import MODEL_FIELDS, ColumnModels, focus_box, widened

__all__ = [
    "ALIGNMENTS",
    "BACKLASH_SEARCHED",
    "CALIBRATED",
    "CALIBRATED_STOP",
    "COLUMN_FIELDS",
    "FAR_NOISE_SEARCHED",
    "FROM_ABOVE",
    "MAX_SEARCH_BYTES",
    "SUPPORT_P",
    "Calibration",
    "UncalibratedError",
    "calibrate",
    "calibrated_posterior",
    "check_far_noise",
    "check_search",
    "check_support",
    "column_bound_problem",
    "column_evidence",
    "column_family",
    "column_problem",
    "column_values",
    "evidence_of",
    "measured_sweeps",
    "posterior_options_problem",
    "search_memory",
    "support_p",
    "sweeps_of",
]

# The reading model's parameters (the family's names), in the order PosteriorSettings.column
# keeps them
COLUMN_FIELDS = tuple(MODEL_FIELDS.values())
# How a calibration, and the posterior over the column it found, read: far from focus a
# reading is trusted less (as posterior-robust does on images); what the fit leaves near
# focus is the column's noise, and the model's own spread beyond it small. The export keeps
# its far noise (PosteriorSettings.far_noise), with which its column was fitted. 0.05: on the
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
# before which its stops are readings (PosteriorSettings.stop_when_sure, probe_until_sure),
# where the champion's box stops at 0.98. One known column's posterior, trusting far readings less,
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
# What the search may hold: each column's evidence keeps about SEARCH_ARRAYS arrays of the
# posterior's shape (specimen scales x optimum grid points, float64) alive at its peak
# (measured with tracemalloc: 9.7; 0.93 MB per column of the widened box, whose grid is
# 3 x 4,007), so the default 256 columns take about 250 MB; at most MAX_SEARCH_BYTES (4 GiB:
# some 4,400 columns), where a machine of a few GiB would otherwise swap or be killed.
SEARCH_ARRAYS, MAX_SEARCH_BYTES = 10, 4 << 30
# Readings support a calibration where, in each alignment, the widths grow with the distance
# from its narrowest reading (a frame without edges the widest) more than the same widths
# shuffled among its settings do: Kendall's concordance of distance and width, summed over the
# alignments, beyond all but a share SUPPORT_P of SUPPORT_SHUFFLES shuffles (the narrowest
# found again in each). Not the fitted column's likelihood: a small search (8 columns, one
# round) fits a column that explains a lens's clean curve little better than shuffled widths,
# and the question is the readings'. A lens's readings reach the smallest p there is (1 / 1000)
# in three alignments; random widths, one width everywhere or widths that shrink away from
# focus do not (tests/test_calibrate_checks.py).
SUPPORT_SHUFFLES, SUPPORT_P = 999, 0.01
# An alignment's fitted focus within this share of the interval of a limit (or half the
# column's spec half-width, if less) is at it: where the limit is the interval's own end, a
# focus beyond it piles there (near-bound's, at 94-98 % of its interval, stays clear).
FOCUS_GUARD = 0.01

# One alignment's readings: (setting as a fraction of the knob's interval, width in px (NaN
# or inf: a frame without edges), the side it was approached from: +1 below, -1 above, 0
# unknown)
Sweep = Sequence[tuple[float, float, float]]


class UncalibratedError(ValueError):
    """Readings that support no calibration: too few measured, widths that do not follow the
    setting as a focus column's do, or a focus the limits keep out of reach."""


def evidence_of(family: FocusFamily, columns: int, seed: int = 0, **settings) -> FamilyPosterior:
    """A FamilyPosterior that weighs the evidence of `columns` columns of `family` apart
    (`columns_apart`; the columns set by `column_evidence`)."""
    return FamilyPosterior(family, draws=columns, seed=seed, columns_apart=True, **settings)


def column_evidence(
    evidence: FamilyPosterior,
    rows: np.ndarray,
    sweeps: Sequence[Sweep],
    far_noise: np.ndarray | None = None,
):
    """The log evidence (K,) of the columns at `rows` (each read with its own `far_noise`
    where given) for every reading of `sweeps`."""
    evidence.use_columns(rows, far_noise)
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


def search_memory(population: int, reach: float = CALIBRATION_REACH) -> tuple[int, int]:
    """(bytes, bytes per column) the search over the focus box widened by `reach` holds at
    its peak with `population` columns (SEARCH_ARRAYS arrays of the posterior's shape each)."""
    probe = FamilyPosterior(widened(focus_box(0.0), reach), draws=1, **CALIBRATED)
    per_column = int(probe._prior[0].size) * 8 * SEARCH_ARRAYS
    return population * per_column, per_column


def check_search(population: int, rounds: int, elite: float = ELITE) -> None:
    """ValueError for a search `calibrate` cannot run: a population below 8, rounds below 1,
    an elite share outside (0, 1), or a population whose arrays would take more than
    MAX_SEARCH_BYTES."""
    if population < 8 or rounds < 1 or not 0.0 < elite < 1.0:
        raise ValueError(
            f"a calibration's population must be at least 8, its rounds at least 1 and its "
            f"elite a share in (0, 1); got {population}, {rounds}, {elite}"
        )
    total, per_column = search_memory(population)
    if total > MAX_SEARCH_BYTES:
        raise ValueError(
            f"a calibration's population of {population} columns would take about "
            f"{total / 2**30:.3g} GiB ({per_column / 1e6:.2g} MB per column: the posterior's "
            f"grid, {SEARCH_ARRAYS} arrays of it), more than the {MAX_SEARCH_BYTES / 2**30:g} "
            f"GiB a calibration may take: give at most {MAX_SEARCH_BYTES // per_column} columns"
        )


def check_far_noise(far_noise: float | None) -> None:
    """ValueError for a far noise a calibration cannot read with: not a share in [0, 1]
    (None: searched)."""
    if far_noise is not None and not (math.isfinite(far_noise) and 0.0 <= far_noise <= 1.0):
        raise ValueError(f"a calibration's far noise is a share in [0, 1], got {far_noise}")


def measured_sweeps(sweeps: Sequence[Sweep]) -> list[list[tuple[float, float, float]]]:
    """`sweeps` with every width below MIN_EDGE_WIDTH_PX (or not finite) a frame without edges
    (NaN): no detector resolves a tenth of a pixel, so such a width is no reading."""
    return [
        [
            (float(u), float(w) if math.isfinite(w) and w >= MIN_EDGE_WIDTH_PX else math.nan, side)
            for u, w, side in sweep
        ]
        for sweep in sweeps
    ]


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
    A width below MIN_EDGE_WIDTH_PX is read as a frame without edges (`measured_sweeps`).
    UncalibratedError (a ValueError) for no reading in focus's sense (fewer than two
    measured widths in all); ValueError for a population below 8 or beyond MAX_SEARCH_BYTES,
    rounds below 1, an elite share outside (0, 1) or a far noise outside [0, 1]."""
    sweeps = measured_sweeps(sweeps)
    measured = sum(1 for sweep in sweeps for _, width, _ in sweep if math.isfinite(width))
    if measured < 2:
        total = sum(len(sweep) for sweep in sweeps)
        raise UncalibratedError(
            f"a calibration needs measured readings: {len(sweeps)} alignments hold {measured} "
            f"of {total} (a frame without edges, or a width below {MIN_EDGE_WIDTH_PX:g} px, is "
            "none)"
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
    evidence = evidence_of(box, population, seed, **{**CALIBRATED, "far_noise": far})
    rng = np.random.default_rng(seed)
    # only the reading model's parameters are searched; the rest (interval, optimum, dose)
    # say nothing of the readings and stay in the box's middle
    searched = [PAIR_FIELDS.index(name) for name in COLUMN_FIELDS]
    rows = np.full((population, len(PAIR_FIELDS)), 0.5)
    with warnings.catch_warnings():  # any population: Sobol' balance is not needed here
        warnings.filterwarnings("ignore", message=".*balance properties.*")
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
        name: float(getattr(best, attribute)[0, 0, 0]) for attribute, name in MODEL_FIELDS.items()
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


def column_bound_problem(column: Mapping[str, Any]) -> tuple[str, str] | None:
    """The first parameter of a calibrated column (a mapping of COLUMN_FIELDS) that is not a
    number within the physical range an instrument family may give it (`PHYSICAL`, the
    family box's: blur and probe of 0.1 px to 10,000 px, say), and what is wrong with it in
    words; None where every one is."""
    for name in COLUMN_FIELDS:
        if name not in column:
            continue
        value = column[name]
        lowest, highest, unit = PHYSICAL[name]
        if isinstance(value, bool) or not isinstance(value, int | float):
            return name, f"is {str(value)[:40]!r}, not a number"
        try:
            number = float(value)
        except OverflowError:  # an integer of hundreds of digits
            return name, f"is a number of {len(str(value))} digits, beyond any column's"
        if not (math.isfinite(number) and lowest <= number <= highest):
            return name, (
                f"is {number:g}, outside the physical range of a focus column, "
                f"[{lowest:g}, {highest:g}] {unit}"
            )
    return None


def posterior_options_problem(options: Mapping[str, Any]) -> tuple[str, str] | None:
    """The first posterior setting of task options (as a file gives them: a card's) beyond
    what an instrument family can give it (`PHYSICAL`): a calibrated column's parameter
    (`posterior_column.NAME`), or where its readings level off (`posterior_saturation_px[i]`),
    with what is wrong in words; None where none is, or where the value is of another type
    (the options' own model names that). The far noise, draws and chances: TaskOptions."""
    column = options.get("posterior_column")
    if isinstance(column, Mapping):
        bound = column_bound_problem(column)
        if bound is not None:
            return f"posterior_column.{bound[0]}", bound[1]
    saturation = options.get("posterior_saturation_px")
    if isinstance(saturation, list | tuple):
        for index, value in enumerate(saturation):
            bound = column_bound_problem({"saturation_px": value})
            if bound is not None:
                return f"posterior_saturation_px[{index}]", bound[1].replace(
                    "a focus column", "where a focus column's readings level off"
                )
    return None


def column_problem(column: Mapping[str, Any]) -> str | None:
    """What is wrong with a calibrated column (a mapping of COLUMN_FIELDS), in one line, or
    None."""
    missing = [name for name in COLUMN_FIELDS if name not in column]
    unknown = [str(name)[:40] for name in column if name not in COLUMN_FIELDS]
    if missing or unknown:
        return (
            f"a calibrated column names {', '.join(COLUMN_FIELDS)}; "
            f"missing: {', '.join(missing) or 'none'}, unknown: {', '.join(unknown[:8]) or 'none'}"
        )
    bound = column_bound_problem(column)
    if bound is not None:
        return f"a calibrated column outside what a focus column may be: {bound[0]} {bound[1]}"
    try:
        column_family(column)
    except ValueError as error:  # pydantic's ValidationError: its first message alone
        errors = getattr(error, "errors", None)
        problem = errors()[0]["msg"] if callable(errors) else str(error)
        return f"a calibrated column outside what a focus column may be: {problem[:300]}"
    return None


def column_values(column: Mapping[str, float]) -> tuple[float, ...]:
    """A calibrated column (a mapping of COLUMN_FIELDS) as PosteriorSettings.column keeps it:
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


def _concordance(settings: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Per row of `widths` (R, n: one alignment's widths in some order, a frame without edges
    inf), Kendall's concordance of each reading's distance from the row's narrowest and its
    width: the pairs ordered alike less those ordered otherwise (R,)."""
    nearest = settings[np.argmin(widths, axis=1)]
    distance = np.abs(settings[None, :] - nearest[:, None])
    wider = (widths[:, :, None] > widths[:, None, :]).astype(np.int8)
    wider -= widths[:, :, None] < widths[:, None, :]
    further = (distance[:, :, None] > distance[:, None, :]).astype(np.int8)
    further -= distance[:, :, None] < distance[:, None, :]
    return (wider * further).sum(axis=(1, 2)) // 2


def support_p(sweeps: Sequence[Sweep], seed: int = 0) -> float:
    """The share of SUPPORT_SHUFFLES shuffles of each alignment's widths among its settings
    (and the readings as read) whose widths grow away from the alignment's narrowest reading
    as much as the readings' do (`_concordance` summed over the alignments): small where the
    widths follow a focus curve, near 1/2 where they do not depend on the setting."""
    rng = np.random.default_rng(seed)
    total = np.zeros(SUPPORT_SHUFFLES + 1, np.int64)
    for sweep in measured_sweeps(sweeps):
        settings = np.array([u for u, _, _ in sweep], float)
        widths = np.array([w for _, w, _ in sweep], float)
        widths[np.isnan(widths)] = math.inf  # no edges: wider than any measured
        if settings.size < 3 or not np.isfinite(widths).any():
            continue
        orders = rng.permuted(np.tile(np.arange(settings.size), (SUPPORT_SHUFFLES, 1)), axis=1)
        total += _concordance(settings, np.vstack([widths, widths[orders]]))
    return float((1 + np.sum(total[1:] >= total[0])) / (SUPPORT_SHUFFLES + 1))


def check_support(
    sweeps: Sequence[Sweep],
    calibration: Calibration,
    interval: tuple[float, float] = (0.0, 1.0),
    limits: tuple[float, float] | None = None,
    knob: str = "defocus",
    spec_relative: float = 1.15,
    seed: int = 0,
) -> None:
    """UncalibratedError where `sweeps` (settings as fractions of `interval`, the knob's in
    its units) do not support `calibration`: their widths do not follow the setting as a
    focus curve's do (`support_p` above SUPPORT_P), or an alignment's fitted focus (the
    median of its optimum under the calibrated column) lies at or beyond the `limits`
    written within (its units; default: the interval): past one, or within half the
    column's spec half-width of it (at most FOCUS_GUARD of the interval). Its readings then
    saw one flank of the curve."""
    share = support_p(sweeps, seed)
    if share > SUPPORT_P:
        raise UncalibratedError(
            f"the readings do not follow a focus curve: their widths grow away from each "
            f"alignment's narrowest reading no more than the same widths shuffled among its "
            f"settings do in {100 * share:.3g} % of {SUPPORT_SHUFFLES} shuffles (a column's: "
            f"at most {100 * SUPPORT_P:g} %); the widths do not depend on the {knob} setting "
            "as a focus column's do, so no calibrated policy was written"
        )
    low, high = interval
    lowest, highest = limits if limits is not None else interval
    posterior = calibrated_posterior(calibration.column, spec_relative, calibration.far_noise)
    half_width = float(posterior.models.spec_half_width(spec_relative).min())
    guard = min(0.5 * half_width, FOCUS_GUARD)
    inside = ((lowest - low) / (high - low) + guard, (highest - low) / (high - low) - guard)
    outside = []
    for index, sweep in enumerate(measured_sweeps(sweeps)):
        if not any(math.isfinite(width) for _, width, _ in sweep):
            continue  # nothing measured: it tells no focus
        posterior.begin()
        for setting, width, side in sweep:
            posterior.observe(setting, width, side)
        mass = posterior._posterior.sum(axis=(0, 1))
        median = float(posterior._grid[np.searchsorted(np.cumsum(mass), 0.5 * mass.sum())])
        if not inside[0] < median < inside[1]:
            outside.append((index, low + median * (high - low)))
    if outside:
        index, focus = outside[0]
        raise UncalibratedError(
            f"the fitted focus of {len(outside)} of {len(sweeps)} alignments lies at or "
            f"beyond the limits [{lowest:g}, {highest:g}] of {knob} (alignment {index + 1}: "
            f"at {focus:.4g}): their readings saw one flank of the focus curve, which tells "
            "no column, so no calibrated policy was written; widen the limits to hold focus"
        )


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

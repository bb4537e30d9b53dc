"""Classical controllers: what a microscopist would run instead of a trained agent.

Focus (one knob, see alignrl.evaluation.controllers for the protocol): three controllers,
each a small frozen dataclass whose defaults were measured on `synthetic` and on
`csv:default` (split "train"); docs/evaluation.md gives their figures. Each works on any
apparatus with one knob to focus, counts on nothing but edge widths (px, smaller is sharper)
and stops by its own rule:

* `GoldenSection`: shrinks a bracket around the sharpest setting by the golden ratio per
  acquisition, starting from the whole interval; stops when the bracket is narrow enough.
* `HyperbolaFit`: a Gaussian probe gives the focus curve  w^2 = a (V - b)^2 + c  (a
  hyperbola in w). Three probes spread over the interval, a least-squares fit, a jump to the
  vertex b, probes around it, refits on the sharpest points; stops when b settles. Every
  setting is approached from below, so lens hysteresis shifts all of them alike.
* `HillClimb`: fixed steps in the direction that sharpens the image, until a step blurs it;
  then one step back.

The first two also search a bracket inside the interval (`search`): the multi-knob routines
reuse them for stigmators and refocusing.

Stigmation, aperture and the whole column (task controllers, `align_task`), the routines an
operator follows, with defaults measured on `synthetic` in analytic mode (seeds 1 and 2):

* `StigmatorSearch` (task `stigmation`): alternating 1-D searches of stigmator_x and
  stigmator_y on the mean edge width, in shrinking brackets, refocusing between rounds.
* `WobbleCenter` (task `aperture`): wobble, calibrate the shift-per-micrometre response with
  two moves, correct along its inverse until the image stands still.
* `ColumnSequence` (task `column`): focus, aperture, stigmators, a final focus touch-up.

A failed measurement (no edges, a driver fault) reads as +inf: "blurred beyond measure"; a
failed wobble ends the aperture routine at the best setting it has seen.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.apparatus.focus_curve import fit_focus_curve
from alignrl.apparatus.measures import measure_wobble
from alignrl.envs.task import Task
from alignrl.evaluation.column_solve import ColumnSolve
from alignrl.evaluation.controllers import (
    Controller,
    TaskController,
    approach_from_below,
    check_task_knobs,
    clip_to_knob,
    knob_interval,
    measure_width,
    probe,
)
from alignrl.evaluation.model_based import (
    APERTURE,
    FOCUS_KNOB,
    STIGMATORS,
    StigmatorSolve,
    WobbleSolve,
)

__all__ = [
    "BASELINES",
    "CLASSICAL",
    "MODEL_BASED",
    "TASK_BASELINES",
    "BracketSearch",
    "ColumnSequence",
    "GoldenSection",
    "HillClimb",
    "HyperbolaFit",
    "StigmatorSearch",
    "WobbleCenter",
    "get_baseline",
    "task_baselines",
]

GOLDEN_RATIO_CONJUGATE = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618: bracket shrink per acquisition


# --- golden-section search -----------------------------------------------------------------


@dataclass(frozen=True)
class GoldenSection:
    """Golden-section search for the sharpest setting over the whole interval.

    Two probes at the golden points of the bracket; the blurrier one's outer part is cut
    away, and the surviving probe is reused, so each further acquisition shrinks the bracket
    by 0.618. Stops when the bracket is at most `tolerance_fraction` of the interval and
    leaves the knob at the bracket's centre: 1 + ceil(log(tolerance) / log(0.618))
    acquisitions whatever the start (9 for the default 0.03, 11 for 0.01), and on a smooth
    curve within half the final bracket of the focus.
    """

    tolerance_fraction: float = 0.03  # final bracket width, share of the searched bracket
    name: str = "golden-section"

    def __post_init__(self) -> None:
        if not 0 < self.tolerance_fraction < 1:
            raise ValueError(
                f"golden-section: tolerance_fraction must be in (0, 1), got "
                f"{self.tolerance_fraction}"
            )

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        low, high, _ = knob_interval(apparatus, knob)
        self.search(apparatus, knob, low, high)

    def search(self, apparatus: Apparatus, knob: str, low: float, high: float) -> None:
        """The search within [low, high] (inside the knob's interval); the knob is left at
        the final bracket's centre."""
        lower, upper = low, high
        tolerance = self.tolerance_fraction * (upper - lower)
        inner_low = upper - GOLDEN_RATIO_CONJUGATE * (upper - lower)
        inner_high = lower + GOLDEN_RATIO_CONJUGATE * (upper - lower)
        width_low = probe(apparatus, knob, inner_low)
        width_high = probe(apparatus, knob, inner_high)
        while True:
            # Ties (both blind) cut the lower side: any consistent rule keeps the search going.
            keep_lower = width_low < width_high
            if keep_lower:
                upper, inner_high, width_high = inner_high, inner_low, width_low
            else:
                lower, inner_low, width_low = inner_low, inner_high, width_high
            if upper - lower <= tolerance:
                break
            if keep_lower:
                inner_low = upper - GOLDEN_RATIO_CONJUGATE * (upper - lower)
                width_low = probe(apparatus, knob, inner_low)
            else:
                inner_high = lower + GOLDEN_RATIO_CONJUGATE * (upper - lower)
                width_high = probe(apparatus, knob, inner_high)
        apparatus.write({knob: clip_to_knob(apparatus, knob, 0.5 * (lower + upper))})


# --- hyperbola fit -------------------------------------------------------------------------


@dataclass(frozen=True)
class HyperbolaFit:
    """Fit the focus curve w^2 = a (V - b)^2 + c and jump to its vertex b.

    Three probes at `probe_fractions` of the interval and a least-squares fit
    (alignrl.apparatus.focus_curve) give a first vertex; probes at that vertex +
    `refine_fractions` of the interval sample the curve where its model holds (far from focus
    the edge width saturates). Then refits on the `fit_points` sharpest points: the alignment
    stops as soon as a refit moves the vertex by less than `tolerance_fraction` of the interval,
    else the new vertex is probed and refitted. Where no fit is possible (too few measurable
    points, no minimum) the next target halves the gap between the sharpest point and its
    sharper neighbour. Every setting, the final one included, is approached from
    `approach_fraction` of the interval below, so a lagging lens field (hysteresis) shifts them
    all alike.
    On a noise-free hyperbola: 3 + len(refine_fractions) acquisitions, exactly at focus.
    """

    probe_fractions: tuple[float, ...] = (1 / 6, 1 / 2, 5 / 6)  # first probes, share of interval
    refine_fractions: tuple[float, ...] = (-0.07, 0.07)  # probes at first vertex + share
    fit_points: int = 4  # refits use this many of the sharpest points
    tolerance_fraction: float = 0.03  # stop when the vertex moves less than this share
    approach_fraction: float = 0.03  # approach every setting from this share below
    max_refits: int = 6  # stop after this many refits even if the vertex still moves
    name: str = "hyperbola"

    def __post_init__(self) -> None:
        if len(self.probe_fractions) < 3 or not all(0 <= f <= 1 for f in self.probe_fractions):
            raise ValueError("hyperbola: probe_fractions needs three or more shares in [0, 1]")
        if self.fit_points < 3:
            raise ValueError("hyperbola: fit_points must be at least 3")
        if not all(-1 < f < 1 for f in self.refine_fractions):
            raise ValueError("hyperbola: refine_fractions must be shares in (-1, 1)")
        for field_name in ("tolerance_fraction", "approach_fraction"):
            if not 0 < getattr(self, field_name) < 1:
                raise ValueError(f"hyperbola: {field_name} must be in (0, 1)")

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        low, high, _ = knob_interval(apparatus, knob)
        self.search(apparatus, knob, low, high)

    def search(self, apparatus: Apparatus, knob: str, low: float, high: float) -> None:
        """The fit within [low, high] (inside the knob's interval): probe and tolerance
        fractions are shares of this bracket, the approach margin a share of the knob's
        interval (hysteresis is the lens's, whatever the bracket). The knob is left at the
        vertex."""
        span = high - low
        margin = self.approach_fraction * knob_interval(apparatus, knob)[2]
        settings: list[float] = []
        widths: list[float] = []

        def probe_at(value: float) -> None:
            value = clip_to_knob(apparatus, knob, value)
            widths.append(probe(apparatus, knob, value, from_below_v=margin))
            settings.append(value)

        for fraction in self.probe_fractions:
            probe_at(low + fraction * span)
        target = self._next_target(settings, widths, low, high)
        for fraction in self.refine_fractions:
            probe_at(target + fraction * span)
        for _ in range(self.max_refits):
            vertex = self._next_target(settings, widths, low, high)
            moved = abs(vertex - target)
            target = vertex
            if moved < self.tolerance_fraction * span:
                break
            probe_at(target)
        approach_from_below(apparatus, knob, target, margin)

    def _next_target(
        self, settings: list[float], widths: list[float], low: float, high: float
    ) -> float:
        """The fitted vertex, or where a probe would narrow the search without a fit."""
        order = np.argsort(widths, kind="stable")[: self.fit_points]
        curve = fit_focus_curve(np.array(settings)[order], np.array(widths)[order])
        if curve is not None and curve.floor > 0:  # a minimum, and a positive width there
            return float(min(max(curve.optimum, low), high))
        return _split_towards_sharper(settings, widths, low, high)


def _split_towards_sharper(
    settings: list[float], widths: list[float], low: float, high: float
) -> float:
    """Midpoint between the sharpest setting and its sharper neighbour (a bound counts as a
    blind neighbour); ties go to the wider gap."""
    points = sorted(zip(settings, widths, strict=True))
    values = [low, *(v for v, _ in points), high]
    measured = [math.inf, *(w for _, w in points), math.inf]
    best = 1 + int(np.argmin(measured[1:-1]))
    left, right = best - 1, best + 1
    if measured[left] < measured[right]:
        neighbour = left
    elif measured[right] < measured[left]:
        neighbour = right
    else:
        gap_left = values[best] - values[left]
        gap_right = values[right] - values[best]
        neighbour = left if gap_left >= gap_right else right
    return 0.5 * (values[best] + values[neighbour])


# --- hill climb ----------------------------------------------------------------------------


@dataclass(frozen=True)
class HillClimb:
    """Fixed-step hill climb on the edge width.

    Acquire at the start, then one step up; if that is not sharper, one step down; go on in
    the sharper direction while each step sharpens the image, then step back to the
    sharpest setting. Needs about (distance to focus) / step + 3 acquisitions and stops
    within half a step of the focus on a smooth curve.
    """

    step_fraction: float = 0.04  # step, share of the knob interval
    name: str = "hill-climb"

    def __post_init__(self) -> None:
        if not 0 < self.step_fraction < 1:
            raise ValueError(
                f"hill-climb: step_fraction must be in (0, 1), got {self.step_fraction}"
            )

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        step = self.step_fraction * knob_interval(apparatus, knob)[2]
        best = clip_to_knob(apparatus, knob, float(apparatus.read()[knob]))
        apparatus.write({knob: best})
        best_width = measure_width(apparatus)
        direction = 0.0
        for trial in (1.0, -1.0):
            candidate = clip_to_knob(apparatus, knob, best + trial * step)
            if candidate == best:
                continue  # at a bound: nothing to try on this side
            width = probe(apparatus, knob, candidate)
            if width < best_width:
                best, best_width, direction = candidate, width, trial
                break
        while direction:
            candidate = clip_to_knob(apparatus, knob, best + direction * step)
            if candidate == best:
                break
            width = probe(apparatus, knob, candidate)
            if not width < best_width:
                break
            best, best_width = candidate, width
        apparatus.write({knob: best})


# --- stigmation, aperture and the whole column ---------------------------------------------


class BracketSearch(Protocol):
    """A 1-D search for the sharpest setting of one knob within a bracket inside its interval
    (GoldenSection, HyperbolaFit): it leaves the knob at its estimate."""

    def search(self, apparatus: Apparatus, knob: str, low: float, high: float) -> None: ...


def _bracket(
    apparatus: Apparatus, knob: str, centre: float, half_width: float
) -> tuple[float, float]:
    """[centre - half_width, centre + half_width], shifted (not cut) to lie inside the knob's
    interval, so that a search near a bound keeps its full bracket; the whole interval
    where it is narrower than the bracket."""
    low, high, span = knob_interval(apparatus, knob)
    if 2.0 * half_width >= span:
        return low, high
    start = min(max(centre - half_width, low), high - 2.0 * half_width)
    return start, start + 2.0 * half_width


@dataclass(frozen=True)
class StigmatorSearch:
    """The operator's stigmation: one stigmator at a time, for the sharpest mean edge width.

    Each round searches stigmator_x, then stigmator_y, with a 1-D bracket search of the focus
    baselines: with a Gaussian probe, width^2 grows with the square of the astigmatism
    residual, so the hyperbola fit applies to a stigmator as it does to a lens. The first
    round (`first`) searches the whole interval, since the start may be anywhere; each further
    round (`search`, three probes and a fit: cheaper, for a bracket already near the minimum)
    searches `shrink` x the previous bracket around where the last round left the knob, since
    the first estimate of stigmator_x was taken with stigmator_y still off. Before each further
    round the focus is touched up (`refocus`, within `refocus_fraction` of the defocus interval
    around its value), as an operator does: a stigmation task's knobs are only the
    stigmators, but its session verifies the column wherever the controller left it, and a
    focus that the stigmators moved would spoil the result. `refocus=None` leaves the defocus
    alone. Each round ends with one image at its estimate; when that is not `min_improvement`
    sharper than the best round's, the search stops (back at the best round's settings where
    this one is blurrier); it stops after `rounds` in any case.
    """

    first: BracketSearch = HyperbolaFit()
    search: BracketSearch = HyperbolaFit(refine_fractions=())
    rounds: int = 3
    shrink: float = 0.5  # bracket of round r+1 = shrink x that of round r
    refocus: BracketSearch | None = HyperbolaFit(refine_fractions=())
    refocus_fraction: float = 0.05  # refocus within +/- this share of the defocus interval
    min_improvement: float = 0.02  # stop when a round sharpens the image by less than this
    knobs: tuple[str, ...] = STIGMATORS
    name: str = "stigmator-search"

    def __post_init__(self) -> None:
        if self.rounds < 1:
            raise ValueError("stigmator-search: rounds must be at least 1")
        for field_name in ("shrink", "refocus_fraction", "min_improvement"):
            if not 0 < getattr(self, field_name) < 1:
                raise ValueError(f"stigmator-search: {field_name} must be in (0, 1)")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, self.knobs, task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        refocus = self.refocus if FOCUS_KNOB in apparatus.knobs else None
        moved = (*self.knobs, FOCUS_KNOB) if refocus is not None else self.knobs
        half_width = {knob: knob_interval(apparatus, knob)[2] for knob in self.knobs}
        best_width, best_settings = math.inf, None
        for number in range(self.rounds):
            if number and refocus is not None:
                centre = float(apparatus.read()[FOCUS_KNOB])
                reach = self.refocus_fraction * knob_interval(apparatus, FOCUS_KNOB)[2]
                refocus.search(
                    apparatus, FOCUS_KNOB, *_bracket(apparatus, FOCUS_KNOB, centre, reach)
                )
            search = self.search if number else self.first
            for knob in self.knobs:
                centre = float(apparatus.read()[knob])
                bracket = _bracket(apparatus, knob, centre, half_width[knob])
                search.search(apparatus, knob, *bracket)
                half_width[knob] = self.shrink * 0.5 * (bracket[1] - bracket[0])
            width = measure_width(apparatus)
            if not width < (1.0 - self.min_improvement) * best_width:
                if width > best_width and best_settings is not None:
                    apparatus.write(best_settings)
                break
            settings = apparatus.read()
            best_width, best_settings = width, {knob: settings[knob] for knob in moved}


@dataclass(frozen=True)
class WobbleCenter:
    """The operator's aperture centring: wobble the focus, move the aperture against the
    image shift, until the image stands still.

    A wobble (alignrl.apparatus.measures.measure_wobble, the task's amplitude, two
    acquisitions) measures the shift (dx, dy) px between the frames at defocus +/- d, which an
    off-axis aperture causes in proportion to its offset. The shift per micrometre (a 2 x 2
    gain: stage and image axes need not agree) is calibrated where the aperture starts, by
    moving aperture_x and then aperture_y by `calibration_fraction` of their intervals and
    wobbling after each (the calibration moves are kept: they cost no extra wobble). Then
    each correction moves the aperture by -gain^-1 shift and wobbles again; it stops when
    |shift| <= `target_fraction` x the task's wobble_spec_px (a margin: the verification's
    wobble has its own noise), after `max_corrections`, or when a correction does not reduce
    |shift| (then it returns to the best setting seen). A wobble that fails (the
    frames do not correlate) ends the alignment at the best setting seen.
    """

    calibration_fraction: float = 0.2  # calibration move, share of each knob's interval
    target_fraction: float = 0.5  # stop within this share of the wobble spec
    max_corrections: int = 6
    knobs: tuple[str, ...] = APERTURE
    name: str = "wobble-center"

    def __post_init__(self) -> None:
        if not 0 < self.calibration_fraction < 0.5:
            raise ValueError("wobble-center: calibration_fraction must be in (0, 0.5)")
        if not 0 < self.target_fraction <= 1:
            raise ValueError("wobble-center: target_fraction must be in (0, 1]")
        if self.max_corrections < 1:
            raise ValueError("wobble-center: max_corrections must be at least 1")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, self.knobs, task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        amplitude = task.wobble_amplitude(apparatus.knobs)
        setting = np.array([float(apparatus.read()[knob]) for knob in self.knobs])
        shift = _wobble(apparatus, amplitude)
        if shift is None:
            return
        gain = np.empty((2, 2))
        for column, knob in enumerate(self.knobs):
            _, high, span = knob_interval(apparatus, knob)
            step = self.calibration_fraction * span
            moved = setting.copy()
            moved[column] += step if setting[column] + step <= high else -step
            self._write(apparatus, moved)
            response = _wobble(apparatus, amplitude)
            if response is None:
                self._write(apparatus, setting)
                return
            gain[:, column] = (response - shift) / (moved[column] - setting[column])
            setting, shift = moved, response
        best_setting, best_shift = setting, float(np.hypot(*shift))
        for _ in range(self.max_corrections):
            if best_shift <= self.target_fraction * task.wobble_spec_px:
                break
            try:
                correction = np.linalg.solve(gain, -shift)
            except np.linalg.LinAlgError:
                break  # the aperture does not move the image: nothing to centre on
            setting = np.array(
                [
                    clip_to_knob(apparatus, knob, value)
                    for knob, value in zip(self.knobs, setting + correction, strict=True)
                ]
            )
            self._write(apparatus, setting)
            measured = _wobble(apparatus, amplitude)
            if measured is None or not float(np.hypot(*measured)) < best_shift:
                break
            shift = measured
            best_setting, best_shift = setting, float(np.hypot(*shift))
        self._write(apparatus, best_setting)

    def _write(self, apparatus: Apparatus, setting: np.ndarray) -> None:
        apparatus.write(dict(zip(self.knobs, setting.tolist(), strict=True)))


def _wobble(apparatus: Apparatus, amplitude_v: float) -> np.ndarray | None:
    """The wobble shift (dx, dy) px, or None where it failed (its acquisitions are spent)."""
    try:
        shift = measure_wobble(apparatus, amplitude_v)
    except ApparatusError:
        return None
    return shift if np.all(np.isfinite(shift)) else None


@dataclass(frozen=True)
class ColumnSequence:
    """The operator's sequence for a whole column: focus over the whole defocus interval
    (`focus`, the hyperbola fit, the best focus baseline), centre the aperture (`aperture`,
    wobble-center), stigmate (`stigmation`, stigmator-search, which refocuses between its
    rounds), and touch the focus up within `touch_up_fraction` of the interval.

    The column task lists its knobs aperture first; the sequence focuses first because a
    wobble is read off two images and is only as precise as they are sharp (the image
    shift's error grows with the blur): on `synthetic` (analytic mode, tuning seeds 1 and 2)
    aperture-first aligned 83 and 95 of 100 columns in a median of 44 and 43 acquisitions,
    focus-first 99 and 100 in 41. Centring the aperture only narrows the probe, it does not
    move the focus, so no second full focus is needed.
    """

    focus: BracketSearch = HyperbolaFit()
    aperture: WobbleCenter = WobbleCenter()
    stigmation: StigmatorSearch = StigmatorSearch()
    touch_up_fraction: float = 0.15  # final focus within +/- this share of the interval
    name: str = "column-sequence"

    def __post_init__(self) -> None:
        if not 0 < self.touch_up_fraction < 1:
            raise ValueError("column-sequence: touch_up_fraction must be in (0, 1)")

    def check_task(self, task: Task) -> None:
        check_task_knobs(
            self.name, (FOCUS_KNOB, *self.aperture.knobs, *self.stigmation.knobs), task
        )

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        low, high, span = knob_interval(apparatus, FOCUS_KNOB)
        self.focus.search(apparatus, FOCUS_KNOB, low, high)
        self.aperture.align_task(apparatus, task, budget)
        self.stigmation.align_task(apparatus, task, budget)
        centre = float(apparatus.read()[FOCUS_KNOB])
        bracket = _bracket(apparatus, FOCUS_KNOB, centre, self.touch_up_fraction * span)
        self.focus.search(apparatus, FOCUS_KNOB, *bracket)


# --- the registry ---------------------------------------------------------------------------

BASELINES: dict[str, Callable[[], Controller]] = {
    "golden-section": GoldenSection,
    "hyperbola": HyperbolaFit,
    "hill-climb": HillClimb,
}  # the focus task's, as ever


def _column_solve() -> ColumnSolve:
    """The model-based column, its focus stage the hyperbola fit."""
    return ColumnSolve(focus=HyperbolaFit())


# Each task's classical controllers: the operator's search, then the model-based solve
# (alignrl/evaluation/model_based.py, column_solve.py), the anchors a champion must beat.
TASK_BASELINES: dict[str, dict[str, Callable[[], Controller | TaskController]]] = {
    "focus": dict(BASELINES),
    "stigmation": {"stigmator-search": StigmatorSearch, "stigmator-solve": StigmatorSolve},
    "aperture": {"wobble-center": WobbleCenter, "wobble-solve": WobbleSolve},
    "column": {"column-sequence": ColumnSequence, "column-solve": _column_solve},
}


def _posterior() -> Controller:
    from alignrl.evaluation.posterior import family_posterior  # scipy's Sobol', on demand

    return family_posterior()


def _posterior_scale_free() -> Controller:
    from alignrl.evaluation.posterior import family_posterior

    return family_posterior(scale_free=True)


def _posterior_robust() -> Controller:
    from alignrl.evaluation.posterior import family_posterior

    return family_posterior(robust=True)


# Controllers that know the focus family's model (alignrl/evaluation/posterior.py): run by
# name like the classical ones (`alignrl evaluate --policy posterior`), but not among a
# task's baselines, at seconds of computing per alignment.
MODEL_BASED: dict[str, Callable[[], Controller]] = {
    "posterior": _posterior,
    "posterior-scale-free": _posterior_scale_free,
    "posterior-robust": _posterior_robust,
}

CLASSICAL: dict[str, Callable[[], Controller | TaskController]] = {
    **{name: make for baselines in TASK_BASELINES.values() for name, make in baselines.items()},
    **MODEL_BASED,
}  # every controller that is not trained, by name


def get_baseline(name: str) -> Controller | TaskController:
    """A classical controller with its default parameters, by name."""
    try:
        return CLASSICAL[name]()
    except KeyError:
        raise ValueError(
            f"unknown controller {name!r}; known controllers: {', '.join(sorted(CLASSICAL))}"
        ) from None


def task_baselines(task: str) -> dict[str, Callable[[], Controller | TaskController]]:
    """The classical controllers of a task, by name, in the order they are reported."""
    try:
        return TASK_BASELINES[task]
    except KeyError:
        raise ValueError(
            f"no classical controllers for task {task!r}; tasks with some: "
            f"{', '.join(sorted(TASK_BASELINES))}"
        ) from None

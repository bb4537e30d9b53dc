"""The whole column by its model-based stages, each using what the stages before learned
(issue 62, item 3; "column-solve").

`ColumnSolve` follows the operator's order of `ColumnSequence` (alignrl/evaluation/
baselines.py): focus, aperture, stigmators, and a last look at the focus, but identifies and
solves where the sequence searches, and reads nothing twice:

* Focus: the hyperbola fit over the whole defocus interval, every probe a directional reading
  (one acquisition, as a plain width). Astigmatism flattens the curve's bottom (by tens of
  volts where the stigmators start far off), but the anisotropy D / T (model_based.py)
  changes sign at the round-beam focus, the more clearly the more astigmatism: where its
  zero crossing between two probes lies more than `switch_fraction` of the interval from the
  vertex, it is the focus V0. The fitted curve gives the stigmators' defocus offset
  (StigmatorSolve.offset), where the stigmation task reads two frames for it.
* Aperture: at focus, `WobbleSolve` (model_based.py), with a larger identifying step and a
  looser end than the aperture task's own: the column's verification judges its wobble with
  the rest of the column in spec, and every wobble is two acquisitions.
* Stigmators: `StigmatorSolve.stigmate` at that offset.
* Focus again: `touch_up` probes re-find the focus in a bracket of +/- `touch_up_fraction`
  of the interval around V0 (0: end at V0).

The choices and their figures (seeds 1 and 2) are beside the fields of `ColumnSolve`.
Every defocus is approached from below (lens hysteresis), every write is clipped into its
interval, and only what a driver gives is read (read, write, knobs, measure and the measures
of alignrl.apparatus.measures); any unit, any turned, coupled or mirrored stigmators and any
turned or mirrored aperture.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.apparatus.focus_curve import fit_focus_curve
from alignrl.apparatus.measures import measure_directional
from alignrl.envs.task import Task
from alignrl.evaluation.controllers import (
    approach_from_below,
    check_task_knobs,
    clip_to_knob,
    knob_interval,
)
from alignrl.evaluation.model_based import (
    APERTURE,
    FOCUS_KNOB,
    STIGMATORS,
    Directional,
    StigmatorSolve,
    WobbleSolve,
    directional,
)

__all__ = ["ColumnSolve"]


class _Recording:
    """The apparatus as the focus search sees it: each width it measures is a directional
    reading, kept (the search needs only the width)."""

    def __init__(self, apparatus: Apparatus) -> None:
        self.inner = apparatus
        self.readings: list[Directional] = []

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self.inner.knobs

    def read(self) -> dict[str, float]:
        return self.inner.read()

    def write(self, values: Mapping[str, float]) -> None:
        self.inner.write(values)

    def image(self) -> np.ndarray | None:
        return self.inner.image()

    def measure(self) -> float:
        width, bins = measure_directional(self.inner)  # a failed frame fails the measure
        reading = directional(self.inner, STIGMATORS, width, bins)
        if reading is not None:
            self.readings.append(reading)
        return width


class FocusSearch(Protocol):
    """The focus stage: the hyperbola fit (alignrl/evaluation/baselines.py, `HyperbolaFit`,
    which names this controller among its own and so hands it in: `get_baseline
    ("column-solve")`)."""

    approach_fraction: float
    fit_points: int

    def search(self, apparatus: Apparatus, knob: str, low: float, high: float) -> None: ...


def _column_wobbles() -> WobbleSolve:
    # the identifying step and the end, share of the interval and of the spec (0.2 and 0.5:
    # a median of 20.5 and 22 column acquisitions on seeds 1/2; 0.35 and 0.7: 20 and 20.5,
    # all aligned)
    return WobbleSolve(step_fraction=0.35, target_fraction=0.7, max_corrections=1, end_at_fit=True)


def _column_stigmators() -> StigmatorSolve:
    # three rounds, every one taken (the stigmation task's end once the zero settles: seeds
    # 1/2, analytic, synthetic-b 20/20 either way, at a median of 21-22 against 20-20.5)
    return StigmatorSolve(rounds=3, settled=0.0)


@dataclass(frozen=True)
class ColumnSolve:
    """The whole column: focus, aperture, stigmators and focus, each stage identifying its
    response and solving, with what the stages before learned (module docstring)."""

    focus: FocusSearch  # the hyperbola fit (a field of baselines.HyperbolaFit's kind)
    aperture: WobbleSolve = field(default_factory=_column_wobbles)
    stigmators: StigmatorSolve = field(default_factory=_column_stigmators)
    # Tuned on synthetic-b (and synthetic), analytic and images, seeds 1 and 2 only; "a/b"
    # below are the columns aligned of 20 on seeds 1/2 (synthetic-b), other fields default.
    # D's zero crossing replaces the vertex where they differ by more than this share (before
    # it: analytic 16/15, after 20/20, the rest of the design then as now)
    switch_fraction: float = 0.04
    # refocusing probes at the end, within +/- touch_up_fraction of the interval (0: end at
    # the first focus, 10/20 and 16/20 before the zero crossing; a vertex through two probes
    # and the last stigmator reading: 17/17 against 20/20)
    touch_up: int = 3
    touch_up_fraction: float = 0.05
    name: str = "column-solve"

    def __post_init__(self) -> None:
        for name in ("switch_fraction", "touch_up_fraction"):
            if not 0 < getattr(self, name) < 0.5:
                raise ValueError(f"{self.name}: {name} must be in (0, 0.5)")
        if self.touch_up in (1, 2) or self.touch_up < 0:
            raise ValueError(f"{self.name}: touch_up must be 0 or at least 3")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, (*APERTURE, FOCUS_KNOB, *STIGMATORS), task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        focus, offset = self._focus(apparatus)
        self.aperture.align_task(apparatus, task, budget)
        self.stigmators.stigmate(apparatus, focus, offset)
        self._touch_up(apparatus, focus)

    def _focus(self, apparatus: Apparatus) -> tuple[float, float]:
        """The hyperbola fit, every probe a directional reading, and D's zero crossing where
        it disagrees: (the focus, the defocus offset for the stigmators)."""
        low, high, span = knob_interval(apparatus, FOCUS_KNOB)
        recording = _Recording(apparatus)
        self.focus.search(recording, FOCUS_KNOB, low, high)
        focus = float(apparatus.read()[FOCUS_KNOB])
        readings = recording.readings
        crossing = _crossing(readings, focus)
        if crossing is not None and abs(crossing - focus) > self.switch_fraction * span:
            focus = clip_to_knob(apparatus, FOCUS_KNOB, crossing)
            approach_from_below(apparatus, FOCUS_KNOB, focus, self.focus.approach_fraction * span)
        floor = slope = 0.0  # no curve: the stigmators' fallback offset
        if readings:
            settings = np.array([reading.defocus for reading in readings])
            widths = np.array([reading.width for reading in readings])
            order = np.argsort(widths, kind="stable")[: self.focus.fit_points]
            curve = fit_focus_curve(settings[order], widths[order])
            if curve is not None:
                floor, slope = curve.floor, curve.slope
        return focus, self.stigmators.offset(span, floor, slope)

    def _touch_up(self, apparatus: Apparatus, focus: float) -> None:
        """Re-find the focus in a bracket around the first one (0 probes: end there)."""
        low, high, span = knob_interval(apparatus, FOCUS_KNOB)
        if not self.touch_up:
            approach_from_below(apparatus, FOCUS_KNOB, focus, self.focus.approach_fraction * span)
            return
        fractions = tuple(np.linspace(0.0, 1.0, self.touch_up))
        search = dataclasses.replace(
            self.focus, probe_fractions=fractions, refine_fractions=(), max_refits=0
        )
        half = self.touch_up_fraction * span
        bottom = min(max(focus - half, low), high - 2.0 * half)
        search.search(apparatus, FOCUS_KNOB, bottom, bottom + 2.0 * half)


def _crossing(readings: list[Directional], focus: float) -> float | None:
    """Where D / T, projected on its largest reading's direction, changes sign between two
    readings adjacent in defocus (linearly interpolated), the one nearest `focus`; None
    where it does not. D vanishes at the round-beam focus whatever the astigmatism, and the
    more astigmatism flattens the focus curve's bottom, the more clearly it changes sign."""
    points = sorted((reading.defocus, reading.ratio(focus)[1]) for reading in readings)
    if len(points) < 2:
        return None
    largest = max((ratio for _, ratio in points), key=lambda ratio: float(np.hypot(*ratio)))
    size = float(np.hypot(*largest))
    if not size > 0:
        return None
    projected = [(defocus, float(ratio @ largest) / size) for defocus, ratio in points]
    best = None
    for (low, below), (high, above) in itertools.pairwise(projected):
        if below * above < 0:
            crossing = low + (high - low) * below / (below - above)
            if best is None or abs(crossing - focus) < abs(best - focus):
                best = crossing
    return best

"""Model-based classical controllers for the stigmators: identify how the column responds,
then solve for the setting that aligns it (issue 62, item 3; docs/evaluation.md,
"stigmator-solve").

`StigmatorSolve` ("stigmator-solve") reads what an astigmatic probe shows out of focus. With
the round-beam focus at dV = 0 and the two line foci A/2 on either side of it, a probe
defocused by dV is stretched along the astigmatism's axis phi or across it, and the squared
widths of edges whose normals point along 0, 45, 90 and 135 degrees tell how
(alignrl/apparatus/directional.py, `measure_directional`): with x = g dV and y = g A / 2,

    v = ((w_0^2 - w_90^2) / (w_0^2 + w_90^2), (w_45^2 - w_135^2) / (w_45^2 + w_135^2))
      ~ 2 x y / (sigma0^2 + x^2 + y^2) (cos 2 phi, sin 2 phi),

which grows with the residual astigmatism r = A (cos 2 phi, sin 2 phi) nearly linearly
while the defocus blurs more than the astigmatism (x > y), and falls again beyond. r is
affine in the stigmator settings s whatever their gain, units, rotation against the image,
coupling or mirror (r = a - G s), so there v = b + J s: readings at one defocus offset, at
the start and after a step of each stigmator, give (b, J), and s* = -J^-1 b makes v vanish.
Each further reading goes where the least-squares fit of all of them puts v = 0 (`rounds`),
and the last fit's zero is where the stigmators end; the defocus goes back where it was, from
below.

At focus v vanishes for any astigmatism, so the readings are taken at an offset found on the
column's own focus curve: `probe_fraction` of the defocus interval, doubled until a frame
there reads `target_ratio` x as wide as the focused one. It reads only what a real driver
gives (no optimum), in any unit, and writes only through the apparatus, inside every
interval. In progress: on `synthetic-b` the bins' scatter (about 4 % a reading) leaves the
fitted zero too far out in a quarter to half of the alignments (docs/evaluation.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.apparatus.measures import measure_directional, measure_wobble
from alignrl.envs.task import Task
from alignrl.evaluation.controllers import (
    approach_from_below,
    check_task_knobs,
    clip_to_knob,
    knob_interval,
)

__all__ = ["APERTURE", "FOCUS_KNOB", "STIGMATORS", "StigmatorSolve", "WobbleSolve"]

FOCUS_KNOB = "defocus"  # the knobs the task controllers align (baselines.py's too)
STIGMATORS = ("stigmator_x", "stigmator_y")
APERTURE = ("aperture_x", "aperture_y")
GROWTH = 2.0  # the defocus offset grows this much a try
OFFSET_TRIES = 5
TRUST = 2.0  # a Newton step moves at most this many identifying steps


@dataclass(frozen=True)
class Reading:
    """One directional reading at stigmator setting `setting`: its mean width (px) and its
    anisotropy v (module docstring, unit-free)."""

    setting: np.ndarray
    width: float
    anisotropy: np.ndarray


@dataclass(frozen=True)
class StigmatorSolve:
    """Stigmation by identifying the stigmators' response and solving for the setting where
    the astigmatism vanishes (module docstring)."""

    probe_fraction: float = 0.02  # the first defocus offset, share of the defocus interval
    # the offset that widens the focused frame this much (1.1 to 1.3 tried on synthetic and
    # synthetic-b, seeds 1 and 2: wider frames read v with more scatter and more levelled off)
    target_ratio: float = 1.2
    # each identifying stigmator move, share of its interval (0.15 to 0.4 tried on synthetic
    # and synthetic-b, seeds 1 and 2: larger steps read J above the bins' scatter)
    step_fraction: float = 0.3
    rounds: int = 5  # readings at the fitted zero, each refitting with every reading (3 tried)
    knobs: tuple[str, ...] = STIGMATORS
    name: str = "stigmator-solve"

    def __post_init__(self) -> None:
        for field_name in ("probe_fraction", "step_fraction"):
            if not 0 < getattr(self, field_name) < 0.5:
                raise ValueError(f"{self.name}: {field_name} must be in (0, 0.5)")
        if not self.target_ratio > 1.0:
            raise ValueError(f"{self.name}: target_ratio must exceed 1")
        if self.rounds < 1:
            raise ValueError(f"{self.name}: rounds must be at least 1")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, self.knobs, task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        if FOCUS_KNOB not in apparatus.knobs:
            raise ValueError(f"{self.name}: needs a {FOCUS_KNOB} knob to read the astigmatism")
        focus = float(apparatus.read()[FOCUS_KNOB])
        start = self._setting(apparatus)
        try:
            best = self._solve(apparatus, focus, start)
        finally:
            low, high = apparatus.knobs[FOCUS_KNOB]
            margin = self.probe_fraction * (float(high) - float(low))
            approach_from_below(apparatus, FOCUS_KNOB, focus, margin)
        _write(apparatus, self.knobs, best)

    # --- the identification and the solve --------------------------------------------------

    def _solve(self, apparatus: Apparatus, focus: float, start: np.ndarray) -> np.ndarray:
        """The stigmator setting to end at (the start where the readings tell nothing)."""
        focused = self._read(apparatus, start)
        if focused is None:
            return start
        first = self._offset(apparatus, focus, focused)
        if first is None:
            return start
        readings = [first]
        spans = [knob_interval(apparatus, knob)[2] for knob in self.knobs]
        steps = self.step_fraction * np.array(spans)
        for axis, knob in enumerate(self.knobs):
            high, step = float(apparatus.knobs[knob][1]), steps[axis]
            moved = start.copy()
            moved[axis] += step if start[axis] + step <= high else -step
            reading = self._read(apparatus, moved)
            if reading is None:
                return start
            readings.append(reading)
        for _ in range(self.rounds):
            target = self._target(apparatus, readings, steps)
            if target is None:
                break
            reading = self._read(apparatus, target)
            if reading is None:
                break
            readings.append(reading)
        target = self._target(apparatus, readings, steps)
        return min(readings, key=_size).setting if target is None else target

    def _target(
        self, apparatus: Apparatus, readings: list[Reading], steps: np.ndarray
    ) -> np.ndarray | None:
        """Where the least-squares affine fit of the readings puts v = 0, at most TRUST
        identifying steps from the reading of the least |v|, inside the intervals."""
        fitted = _affine(readings)
        zero = None if fitted is None else _zero(*fitted)
        if zero is None:
            return None
        best = min(readings, key=_size).setting
        step = zero - best
        length = float(np.hypot(*(step / steps)))  # in identifying steps
        if length > TRUST:
            step *= TRUST / length
        pairs = zip(self.knobs, best + step, strict=True)
        return np.array([clip_to_knob(apparatus, knob, value) for knob, value in pairs])

    def _offset(self, apparatus: Apparatus, focus: float, focused: Reading) -> Reading | None:
        """Move the defocus to the offset the readings are taken at (below the focus where
        the interval allows, else above) and read there; None where no offset gives a
        reading."""
        low, high, _ = knob_interval(apparatus, FOCUS_KNOB)
        offset, reading = self.probe_fraction * (high - low), None
        for attempt in range(OFFSET_TRIES):
            target = focus - offset if focus - offset >= low else min(focus + offset, high)
            apparatus.write({FOCUS_KNOB: target})
            reading = self._read(apparatus, focused.setting)
            if attempt == OFFSET_TRIES - 1:
                break
            if reading is None:
                offset /= GROWTH  # edges lost: nearer focus
                continue
            if reading.width >= self.target_ratio * focused.width:
                break
            offset = min(GROWTH * offset, 0.5 * (high - low))
        return reading

    # --- through the apparatus -------------------------------------------------------------

    def _read(self, apparatus: Apparatus, setting: np.ndarray) -> Reading | None:
        """The directional reading at stigmator `setting`; None where the frame failed."""
        _write(apparatus, self.knobs, setting)
        try:
            width, bins = measure_directional(apparatus)
        except ApparatusError:
            return None
        if not (math.isfinite(width) and np.all(np.isfinite(bins))):
            return None
        squared = np.square(bins)
        anisotropy = np.array(
            [
                (squared[0] - squared[2]) / (squared[0] + squared[2]),
                (squared[1] - squared[3]) / (squared[1] + squared[3]),
            ]
        )
        return Reading(setting.copy(), float(width), anisotropy)

    def _setting(self, apparatus: Apparatus) -> np.ndarray:
        values = apparatus.read()
        return np.array([float(values[knob]) for knob in self.knobs])


@dataclass(frozen=True)
class WobbleSolve:
    """Aperture centring by identifying the wobble's response from two wobbles and solving
    for the axis.

    A wobble's shift is k dV_swing N (o - a): N turns the aperture's axes into the image's
    and may mirror one (SEMConfig.aperture_response), so its columns are one unit vector c
    and +/- c turned by 90 degrees. A wobble where the aperture starts and one after a step
    of aperture_x (`step_fraction` of its interval) give c times the gain; of the two
    responses that leaves (mirrored or not), the unmirrored one is tried first: a wobble at
    its solution ends the alignment where it is within `target_fraction` of the task's
    wobble spec; else the three wobbles give the whole 2 x 2 response by least squares, and
    each further wobble (at most `max_corrections`) is taken at the solution of every wobble
    so far. Ends at the setting of the smallest shift seen. A wobble that fails (frames that
    do not correlate) ends it there too.
    """

    step_fraction: float = 0.2
    target_fraction: float = 0.5
    max_corrections: int = 3
    knobs: tuple[str, ...] = APERTURE
    name: str = "wobble-solve"

    def __post_init__(self) -> None:
        if not 0 < self.step_fraction < 0.5:
            raise ValueError(f"{self.name}: step_fraction must be in (0, 0.5)")
        if not 0 < self.target_fraction <= 1:
            raise ValueError(f"{self.name}: target_fraction must be in (0, 1]")
        if self.max_corrections < 0:
            raise ValueError(f"{self.name}: max_corrections must be at least 0")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, self.knobs, task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        target = self.target_fraction * task.wobble_spec_px
        setting = np.array([float(apparatus.read()[knob]) for knob in self.knobs])
        wobbles: list[tuple[np.ndarray, np.ndarray]] = []
        shift = self._wobble(apparatus, task, setting)
        if shift is None:
            return
        wobbles.append((setting, shift))
        if np.hypot(*shift) > target:
            self._centre(apparatus, task, wobbles, target)
        best = min(wobbles, key=lambda pair: float(np.hypot(*pair[1])))
        _write(apparatus, self.knobs, best[0])

    def _centre(
        self,
        apparatus: Apparatus,
        task: Task,
        wobbles: list[tuple[np.ndarray, np.ndarray]],
        target: float,
    ) -> None:
        start, shift = wobbles[0]
        low, high, _ = knob_interval(apparatus, self.knobs[0])
        step = self.step_fraction * (high - low)
        moved = start + np.array([step if start[0] + step <= high else -step, 0.0])
        response = self._wobble(apparatus, task, moved)
        if response is None:
            return
        wobbles.append((moved, response))
        column = (response - shift) / (moved[0] - start[0])  # d shift / d aperture_x
        unmirrored = np.column_stack([column, [-column[1], column[0]]])
        solved = self._solved(apparatus, unmirrored, moved, response)
        for _ in range(1 + self.max_corrections):
            if solved is None:
                return
            shift = self._wobble(apparatus, task, solved)
            if shift is None:
                return
            wobbles.append((solved, shift))
            if np.hypot(*shift) <= target:
                return
            fitted = _affine_wobbles(wobbles)
            if fitted is None:
                return
            solved = self._solved(apparatus, fitted, solved, shift)

    def _solved(
        self, apparatus: Apparatus, response: np.ndarray, setting: np.ndarray, shift: np.ndarray
    ) -> np.ndarray | None:
        """Where the shift vanishes by `response` from (setting, shift), inside the
        intervals; None where the response does not move the image."""
        try:
            solved = setting - np.linalg.solve(response, shift)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(solved)):
            return None
        pairs = zip(self.knobs, solved, strict=True)
        return np.array([clip_to_knob(apparatus, knob, value) for knob, value in pairs])

    def _wobble(self, apparatus: Apparatus, task: Task, setting: np.ndarray) -> np.ndarray | None:
        """The wobble's shift with the aperture at `setting`; None where it failed."""
        _write(apparatus, self.knobs, setting)
        try:
            shift = measure_wobble(apparatus, task.wobble_amplitude_v)
        except ApparatusError:
            return None
        return shift if np.all(np.isfinite(shift)) else None


def _affine_wobbles(wobbles: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The 2 x 2 response d shift / d setting of the least-squares affine fit of the
    wobbles; None where they do not determine it."""
    design = np.array([[*setting, 1.0] for setting, _ in wobbles])
    values = np.array([shift for _, shift in wobbles])
    coefficients, _, rank, _ = np.linalg.lstsq(design, values, rcond=None)
    return coefficients[:2].T if rank == 3 else None


def _write(apparatus: Apparatus, knobs: tuple[str, ...], setting: np.ndarray) -> None:
    apparatus.write(dict(zip(knobs, (float(value) for value in setting), strict=True)))


def _size(reading: Reading) -> float:
    return float(np.hypot(*reading.anisotropy))


def _affine(readings: list[Reading]) -> tuple[np.ndarray, np.ndarray] | None:
    """The least-squares fit v = J s + b of the readings: (J, b); None where degenerate."""
    design = np.array([[*reading.setting, 1.0] for reading in readings])
    values = np.array([reading.anisotropy for reading in readings])
    coefficients, _, rank, _ = np.linalg.lstsq(design, values, rcond=None)
    if rank < 3:
        return None
    return coefficients[:2].T, coefficients[2]


def _zero(jacobian: np.ndarray, offset: np.ndarray) -> np.ndarray | None:
    try:
        zero = np.linalg.solve(jacobian, -offset)
    except np.linalg.LinAlgError:
        return None
    return zero if np.all(np.isfinite(zero)) else None

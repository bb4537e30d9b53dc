"""Model-based classical controllers for the stigmators and the aperture: identify how the
column responds, then solve for the setting that aligns it (issue 62, item 3;
docs/evaluation.md, "stigmator-solve" and "wobble-solve"). The whole column's
(alignrl/evaluation/column_solve.py) is built of these two.

`StigmatorSolve` ("stigmator-solve") reads what an astigmatic probe shows out of focus. With
a Gaussian probe defocused by dV = V - V0 from the round-beam focus V0, the squared widths of
edges whose normals point along 0, 45, 90 and 135 degrees (alignrl/apparatus/directional.py,
`measure_directional`) give

    D = (w_0^2 - w_90^2, w_45^2 - w_135^2) = -2 k^2 g^2 dV r,

exactly proportional to dV and to the residual astigmatism r, whatever its size (k the
edge width per probe sigma, g the focus gain): no level-off, as the anisotropy normalised by
each reading's own widths has. r is affine in the stigmator settings s whatever their gain,
units, rotation against the image, coupling or mirror (r = p + Q s), and an off-axis aperture
widens every bin alike and leaves D alone. Divided by the sum T of the four squares (a
reading's scatter is relative to its width),

    D / T = (dV / T) (p + Q s),

linear in (p, Q) at any offset: readings at one defocus offset below V0, at the start and
after a step of each stigmator (`step_fraction` of its interval), fix (p, Q) by least
squares, s* = -Q^-1 p; each of at most `rounds` readings there, at `round_offset` of the
offset (the start's astigmatism that set it is mostly gone), refits (a move at most TRUST
identifying steps from the reading of least fitted residual) until a round moves the zero
less than `settled` steps, and the stigmators end at the last fit's zero.

The offset is where the probe reads `offset_ratio` x as wide as at focus (the focus curve
w^2 = floor + slope dV^2, at most `max_offset_fraction` of the interval): the stigmation task
starts in focus, so a reading there and one `probe_fraction` of the interval below give the
floor and the slope (`offset`; the column's focus stage hands its fitted curve instead).
Readings at other defocus do not share one (p, Q) on images (their reading ratio falls with
the width), so only the offset's readings are fitted. 2 + 3 + 1 to `rounds` acquisitions
(8 typically); the defocus goes back where it was, from below.

Both read only what a real driver gives (no optimum), in any unit, and write only through the
apparatus, inside every interval.
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

__all__ = [
    "APERTURE",
    "FOCUS_KNOB",
    "STIGMATORS",
    "Directional",
    "StigmatorSolve",
    "WobbleSolve",
    "directional",
    "fit_response",
    "read_directional",
]

FOCUS_KNOB = "defocus"  # the knobs the task controllers align (baselines.py's too)
STIGMATORS = ("stigmator_x", "stigmator_y")
APERTURE = ("aperture_x", "aperture_y")
TRUST = 2.0  # a stigmator solution moves at most this many identifying steps from the best
LEAST_OFFSET = 0.005  # of the defocus interval: the offset never nearer the focus


@dataclass(frozen=True)
class Directional:
    """One directional reading: the defocus it was taken at (as written), the stigmators,
    the mean width and the four bins' widths (px)."""

    defocus: float
    setting: np.ndarray
    width: float
    bins: np.ndarray

    def ratio(self, focus: float) -> tuple[float, np.ndarray]:
        """((V - V0) / T, D / T) of the module docstring, V0 = `focus`."""
        squared = np.square(self.bins)
        total = float(squared.sum())
        difference = np.array([squared[0] - squared[2], squared[1] - squared[3]])
        return (self.defocus - focus) / total, difference / total


def read_directional(apparatus: Apparatus, stigmators: tuple[str, ...]) -> Directional | None:
    """One directional reading where the column is; None where the frame failed or a bin
    read no positive width."""
    try:
        width, bins = measure_directional(apparatus)
    except ApparatusError:
        return None
    return directional(apparatus, stigmators, width, bins)


def directional(
    apparatus: Apparatus, stigmators: tuple[str, ...], width: float, bins: np.ndarray
) -> Directional | None:
    """A directional reading just taken, with the settings it was taken at; None where a
    bin read no positive finite width."""
    if not (math.isfinite(width) and np.all(np.isfinite(bins)) and np.all(bins > 0)):
        return None
    values = apparatus.read()
    setting = np.array([float(values[knob]) for knob in stigmators])
    return Directional(float(values[FOCUS_KNOB]), setting, float(width), np.asarray(bins, float))


def fit_response(readings: list[Directional], focus: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The least-squares fit D / T = (V - V0) / T (p + Q s) of the readings (module
    docstring), V0 = `focus`: (p, Q), the residual astigmatism r = p + Q s in the bins'
    (cos 2 phi, sin 2 phi) plane per stigmator setting, up to one scale; None where the
    readings do not determine it."""
    if not readings:
        return None
    rows, values = [], []
    for reading in readings:
        scale, ratio = reading.ratio(focus)
        rows.append(scale * np.array([1.0, *reading.setting]))
        values.append(ratio)
    coefficients, _, rank, _ = np.linalg.lstsq(np.array(rows), np.array(values), rcond=None)
    if rank < 3:
        return None
    return coefficients[0], coefficients[1:].T


@dataclass(frozen=True)
class StigmatorSolve:
    """Stigmation by identifying the stigmators' response from directional readings at one
    defocus offset and solving for where the astigmatism vanishes (module docstring)."""

    # Chosen in the column's stages on synthetic-b and synthetic, analytic and images, seeds
    # 1 and 2 (alignrl/evaluation/column_solve.py's figures), then as the stigmation task's
    # own: seeds 1/2, 50 alignments, analytic synthetic-b 47/49 at 8, turned, coupled and
    # mirrored 50/49 at 8; images 26/24 and 29/29 of 30 (the normalised anisotropy before it:
    # 46/44 and 47/43 at 10, images about 60 %).
    offset_ratio: float = 2.5  # the stigmators are read where the probe is this much wider
    # ... at most this share of the defocus interval (images: 19/18 of 20 at 15 %, 17/16 at
    # 10 %, 14/11 at 20 %)
    max_offset_fraction: float = 0.15
    fallback_fraction: float = 0.1  # the offset where the readings give no focus curve
    probe_fraction: float = 0.05  # the reading below focus that gives the curve's slope
    # each identifying stigmator step, share of its interval (images 18/19 of 20 at 0.4, 19/18
    # at 0.3, 17/18 at 0.2)
    step_fraction: float = 0.4
    # at most this many readings at the fitted zero, each refitting (2: images 15/11 of 20),
    # ending once a round moves the zero less than `settled` identifying steps (family:
    # stigmation at its edges, analytic, seeds 1/2, 300 each: 3 rounds 253/252 at 8; 5
    # without the end 263/261 at 10; 5 ending at 0.05 262/262 at 8, at 0.1 260/261 at 7-8;
    # 6 ending at 0.05 264/268 at 8; validation 238/240 at 7 against 237 at 8)
    rounds: int = 6
    settled: float = 0.05
    # The rounds read at this share of the identifying offset: that offset was set by the
    # start's astigmatism, mostly gone by then, and there the last volts read flat (seeds
    # 1/2, images, 30 alignments: synthetic-b 28/25 against 25/22 at the whole offset, turned
    # 28/26 against 28/25, vstig-wide-objective 29/29 against 15/15; 0.25 alike; a fourth
    # round 28/28 on synthetic-b at 9 acquisitions)
    round_offset: float = 0.4
    approach_fraction: float = 0.03  # every defocus approached from this share below
    knobs: tuple[str, ...] = STIGMATORS
    name: str = "stigmator-solve"

    def __post_init__(self) -> None:
        for name in (
            "max_offset_fraction",
            "fallback_fraction",
            "probe_fraction",
            "step_fraction",
            "approach_fraction",
        ):
            if not 0 < getattr(self, name) < 0.5:
                raise ValueError(f"{self.name}: {name} must be in (0, 0.5)")
        if not self.offset_ratio > 1.0:
            raise ValueError(f"{self.name}: offset_ratio must exceed 1")
        if self.rounds < 0:
            raise ValueError(f"{self.name}: rounds must be at least 0")
        if not self.settled >= 0:
            raise ValueError(f"{self.name}: settled must be at least 0")
        if not 0 < self.round_offset <= 1:
            raise ValueError(f"{self.name}: round_offset must be in (0, 1]")

    def check_task(self, task: Task) -> None:
        check_task_knobs(self.name, self.knobs, task)

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        if FOCUS_KNOB not in apparatus.knobs:
            raise ValueError(f"{self.name}: needs a {FOCUS_KNOB} knob to read the astigmatism")
        focus = float(apparatus.read()[FOCUS_KNOB])
        try:
            self.stigmate(apparatus, focus, self._offset(apparatus, focus))
        finally:
            approach_from_below(apparatus, FOCUS_KNOB, focus, self._margin(apparatus))

    # --- the offset -------------------------------------------------------------------------

    def offset(self, span: float, floor: float, slope: float) -> float:
        """The defocus offset where a focus curve w^2 = floor + slope dV^2 reads
        `offset_ratio` x the focused width, within [LEAST_OFFSET, max_offset_fraction] of the
        interval's `span`; `fallback_fraction` of it where the curve is none."""
        if not (floor > 0 and slope > 0 and math.isfinite(floor / slope)):
            return self.fallback_fraction * span
        wanted = math.sqrt(floor * (self.offset_ratio**2 - 1.0) / slope)
        return min(max(wanted, LEAST_OFFSET * span), self.max_offset_fraction * span)

    def _offset(self, apparatus: Apparatus, focus: float) -> float:
        """The offset from a reading at the focus and one `probe_fraction` below it."""
        span = knob_interval(apparatus, FOCUS_KNOB)[2]
        focused = read_directional(apparatus, self.knobs)
        probe = self.probe_fraction * span
        self._defocus(apparatus, focus, probe)
        below = read_directional(apparatus, self.knobs)
        if focused is None or below is None:
            return self.fallback_fraction * span
        floor = focused.width**2
        return self.offset(span, floor, (below.width**2 - floor) / probe**2)

    # --- the identification and the solve --------------------------------------------------

    def stigmate(self, apparatus: Apparatus, focus: float, offset: float) -> None:
        """Identify the stigmators' response at `offset` from the focus and solve (module
        docstring): they end at the last fit's zero, or where they started where the
        readings tell nothing; the defocus is left at the offset."""
        start = _setting(apparatus, self.knobs)
        steps = self.step_fraction * np.array(
            [knob_interval(apparatus, knob)[2] for knob in self.knobs]
        )
        # the start and a step of each stigmator (back from a bound), and where a frame
        # fails (no edges) a step the other way instead, until three have read
        settings, spare = [start], []
        for axis, knob in enumerate(self.knobs):
            top, step = knob_interval(apparatus, knob)[1], steps[axis]
            moved, other = start.copy(), start.copy()
            sign = 1.0 if start[axis] + step <= top else -1.0
            moved[axis] += sign * step
            other[axis] = clip_to_knob(apparatus, knob, start[axis] - sign * step)
            settings.append(moved)
            spare.append(other)
        readings: list[Directional] = []
        for setting in [*settings, *spare]:
            if len(readings) == len(settings):
                break
            reading = self._read(apparatus, focus, offset, setting)
            if reading is not None:
                readings.append(reading)
        target = self._zero(apparatus, readings, focus, steps)
        span = knob_interval(apparatus, FOCUS_KNOB)[2]
        nearer = max(self.round_offset * offset, LEAST_OFFSET * span)
        for _ in range(self.rounds):
            if target is None:
                break
            reading = self._read(apparatus, focus, nearer, target)
            if reading is None:
                break
            readings.append(reading)
            moved_from, target = target, self._zero(apparatus, readings, focus, steps)
            if target is not None and np.hypot(*((target - moved_from) / steps)) < self.settled:
                break
        _write(apparatus, self.knobs, start if target is None else target)

    def _zero(
        self, apparatus: Apparatus, readings: list[Directional], focus: float, steps: np.ndarray
    ) -> np.ndarray | None:
        """Where the least-squares fit D / T = (V - V0) / T (p + Q s) of the readings puts
        p + Q s = 0, at most TRUST identifying steps from the reading of the smallest
        residual the fit sees, inside the intervals; None where the readings do not
        determine it."""
        fitted = fit_response(readings, focus)
        if fitted is None:
            return None
        offset, response = fitted
        try:
            zero = np.linalg.solve(response, -offset)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(zero)):
            return None
        settings = np.array([reading.setting for reading in readings])
        residual = np.hypot(*(offset[:, None] + response @ settings.T))
        best = settings[int(np.argmin(residual))]
        step = zero - best
        length = float(np.hypot(*(step / steps)))
        if length > TRUST:
            step *= TRUST / length
        pairs = zip(self.knobs, best + step, strict=True)
        return np.array([clip_to_knob(apparatus, knob, value) for knob, value in pairs])

    # --- through the apparatus -------------------------------------------------------------

    def _margin(self, apparatus: Apparatus) -> float:
        return self.approach_fraction * knob_interval(apparatus, FOCUS_KNOB)[2]

    def _defocus(self, apparatus: Apparatus, focus: float, offset: float) -> None:
        """The defocus `offset` below the focus where the interval allows, else above,
        approached from below."""
        low, high, _ = knob_interval(apparatus, FOCUS_KNOB)
        at = focus - offset if focus - offset >= low else min(focus + offset, high)
        approach_from_below(apparatus, FOCUS_KNOB, at, self._margin(apparatus))

    def _read(
        self, apparatus: Apparatus, focus: float, offset: float, setting: np.ndarray
    ) -> Directional | None:
        """The directional reading with the stigmators at `setting`, the defocus at the
        offset (approached from below each time: a stigmator write may not move the lens,
        but a reading must not depend on it)."""
        _write(apparatus, self.knobs, setting)
        self._defocus(apparatus, focus, offset)
        return read_directional(apparatus, self.knobs)


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
    so far. Where a bound clips the unmirrored solution into line with the first two
    wobbles, a step of aperture_y is wobbled instead (a wobble there would leave the second
    column unread). Ends at the setting of the smallest shift seen. A wobble that fails
    (frames that do not correlate) ends it there too.
    """

    step_fraction: float = 0.2
    target_fraction: float = 0.5
    max_corrections: int = 3
    # End at the last fit's solution, unwobbled, where the corrections run out short of the
    # target, instead of at the smallest shift seen (the column's: with one correction, a
    # mirrored image on synthetic-b, seed 2, 19/20 columns aligned against 11/20)
    end_at_fit: bool = False
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
        last = self._centre(apparatus, task, wobbles, target) if np.hypot(*shift) > target else None
        if last is not None and self.end_at_fit:
            _write(apparatus, self.knobs, last)
            return
        best = min(wobbles, key=lambda pair: float(np.hypot(*pair[1])))
        _write(apparatus, self.knobs, best[0])

    def _centre(
        self,
        apparatus: Apparatus,
        task: Task,
        wobbles: list[tuple[np.ndarray, np.ndarray]],
        target: float,
    ) -> np.ndarray | None:
        """Identify and solve; the last fit's solution where the corrections ran out short
        of the target (None where it ended otherwise)."""
        start, shift = wobbles[0]
        low, high, _ = knob_interval(apparatus, self.knobs[0])
        step = self.step_fraction * (high - low)
        moved = start + np.array([step if start[0] + step <= high else -step, 0.0])
        response = self._wobble(apparatus, task, moved)
        if response is None:
            return None
        wobbles.append((moved, response))
        column = (response - shift) / (moved[0] - start[0])  # d shift / d aperture_x
        unmirrored = np.column_stack([column, [-column[1], column[0]]])
        solved = self._solved(apparatus, unmirrored, moved, response)
        wanted = _solution(unmirrored, moved, response)
        if solved is not None and wanted is not None and np.any(solved != wanted):
            if abs(solved[1] - start[1]) < 0.25 * step:
                # A bound clipped the solution into line with the first two wobbles: one
                # there would leave the response's second column unread; step aperture_y.
                _, top, _ = knob_interval(apparatus, self.knobs[1])
                beside = moved + np.array([0.0, step if moved[1] + step <= top else -step])
                shift = self._wobble(apparatus, task, beside)
                if shift is None:
                    return None
                wobbles.append((beside, shift))
                fitted = _affine_wobbles(wobbles)
                solved = None if fitted is None else self._solved(apparatus, fitted, beside, shift)
        for _ in range(1 + self.max_corrections):
            if solved is None:
                return None
            shift = self._wobble(apparatus, task, solved)
            if shift is None:
                return None
            wobbles.append((solved, shift))
            if np.hypot(*shift) <= target:
                return None
            fitted = _affine_wobbles(wobbles)
            if fitted is None:
                return None
            solved = self._solved(apparatus, fitted, solved, shift)
        return solved

    def _solved(
        self, apparatus: Apparatus, response: np.ndarray, setting: np.ndarray, shift: np.ndarray
    ) -> np.ndarray | None:
        """Where the shift vanishes by `response` from (setting, shift), inside the
        intervals; None where the response does not move the image."""
        solved = _solution(response, setting, shift)
        if solved is None:
            return None
        pairs = zip(self.knobs, solved, strict=True)
        return np.array([clip_to_knob(apparatus, knob, value) for knob, value in pairs])

    def _wobble(self, apparatus: Apparatus, task: Task, setting: np.ndarray) -> np.ndarray | None:
        """The wobble's shift with the aperture at `setting`; None where it failed."""
        _write(apparatus, self.knobs, setting)
        try:
            shift = measure_wobble(apparatus, task.wobble_amplitude(apparatus.knobs))
        except ApparatusError:
            return None
        return shift if np.all(np.isfinite(shift)) else None


def _solution(response: np.ndarray, setting: np.ndarray, shift: np.ndarray) -> np.ndarray | None:
    """Where the shift vanishes by `response` from (setting, shift), unclipped; None where
    the response does not move the image."""
    try:
        solved = setting - np.linalg.solve(response, shift)
    except np.linalg.LinAlgError:
        return None
    return solved if np.all(np.isfinite(solved)) else None


def _affine_wobbles(wobbles: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The 2 x 2 response d shift / d setting of the least-squares affine fit of the
    wobbles; None where they do not determine it."""
    design = np.array([[*setting, 1.0] for setting, _ in wobbles])
    values = np.array([shift for _, shift in wobbles])
    coefficients, _, rank, _ = np.linalg.lstsq(design, values, rcond=None)
    return coefficients[:2].T if rank == 3 else None


def _write(apparatus: Apparatus, knobs: tuple[str, ...], setting: np.ndarray) -> None:
    apparatus.write(dict(zip(knobs, (float(value) for value in setting), strict=True)))


def _setting(apparatus: Apparatus, knobs: tuple[str, ...]) -> np.ndarray:
    values = apparatus.read()
    return np.array([float(values[knob]) for knob in knobs])

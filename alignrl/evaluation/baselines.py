"""Classical autofocus: what a microscopist would run instead of a trained agent.

Three controllers (see alignrl.evaluation.controllers for the protocol), each a small frozen
dataclass whose defaults were measured on `synthetic` and on `csv:default` (split "train");
docs/evaluation.md gives their figures. Each works on any apparatus with one knob to focus,
counts on nothing but edge widths (px, smaller is sharper) and stops by its own rule:

* `GoldenSection`: shrinks a bracket around the sharpest setting by the golden ratio per
  acquisition, starting from the whole interval; stops when the bracket is narrow enough.
* `HyperbolaFit`: a Gaussian probe gives the focus curve  w^2 = a (V - b)^2 + c  (a
  hyperbola in w). Three probes spread over the interval, a least-squares fit, a jump to the
  vertex b, probes around it, refits on the sharpest points; stops when b settles. Every
  setting is approached from below, so lens hysteresis shifts all of them alike.
* `HillClimb`: fixed steps in the direction that sharpens the image, until a step blurs it;
  then one step back.

A failed measurement (no edges, a driver fault) reads as +inf: "blurred beyond measure".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.evaluation.controllers import (
    Controller,
    approach_from_below,
    clip_to_knob,
    measure_width,
    probe,
)

__all__ = [
    "BASELINES",
    "GoldenSection",
    "HillClimb",
    "HyperbolaFit",
    "fit_focus_curve",
    "get_baseline",
]

GOLDEN_RATIO_CONJUGATE = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618: bracket shrink per acquisition


def _interval(apparatus: Apparatus, knob: str) -> tuple[float, float, float]:
    low, high = (float(value) for value in apparatus.knobs[knob])
    return low, high, high - low


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

    tolerance_fraction: float = 0.03  # final bracket width, share of the knob interval
    name: str = "golden-section"

    def __post_init__(self) -> None:
        if not 0 < self.tolerance_fraction < 1:
            raise ValueError(
                f"golden-section: tolerance_fraction must be in (0, 1), got "
                f"{self.tolerance_fraction}"
            )

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        lower, upper, span = _interval(apparatus, knob)
        tolerance = self.tolerance_fraction * span
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


def fit_focus_curve(
    settings: np.ndarray, widths_px: np.ndarray
) -> tuple[float, float, float] | None:
    """Least-squares fit of  w^2 = a (V - b)^2 + c ; returns (a, b, c), or None.

    Residuals are relative (each squared width weighted by 1 / w^4): a reading's noise
    grows with its width, and a far-blurred reading must not outweigh the sharp ones. None
    where fewer than three finite points or three distinct settings remain, or where the fit
    has no minimum (a <= 0) or no positive width at it (c <= 0).
    """
    settings = np.asarray(settings, dtype=np.float64)
    widths_px = np.asarray(widths_px, dtype=np.float64)
    usable = np.isfinite(widths_px) & (widths_px > 0)
    settings, squared = settings[usable], widths_px[usable] ** 2
    if np.unique(settings).size < 3:
        return None
    centre = float(settings.mean())  # centred and scaled, so the normal matrix is well posed
    scale = float(np.ptp(settings))
    x = (settings - centre) / scale
    design = np.stack([x**2, x, np.ones_like(x)], axis=1) / squared[:, None]
    solution, *_ = np.linalg.lstsq(design, np.ones_like(x), rcond=None)
    quadratic, linear, constant = solution  # w^2 = q x^2 + l x + k
    if not quadratic > 0:
        return None
    vertex_x = -linear / (2.0 * quadratic)
    minimum = constant - quadratic * vertex_x**2
    if not minimum > 0:
        return None
    return float(quadratic / scale**2), float(centre + vertex_x * scale), float(minimum)


@dataclass(frozen=True)
class HyperbolaFit:
    """Fit the focus curve w^2 = a (V - b)^2 + c and jump to its vertex b.

    Three probes at `probe_fractions` of the interval and a least-squares fit
    (fit_focus_curve) give a first vertex; probes at that vertex + `refine_fractions` of the
    interval sample the curve where its model holds (far from focus the edge width
    saturates). Then refits on the `fit_points` sharpest points: the alignment stops as soon
    as a refit moves the vertex by less than `tolerance_fraction` of the interval, else the
    new vertex is probed and refitted. Where no fit is possible (too few measurable points, no
    minimum) the next target halves the gap between the sharpest point and its sharper
    neighbour. Every setting, the final one included, is approached from `approach_fraction`
    of the interval below, so a lagging lens field (hysteresis) shifts them all alike.
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
        low, high, span = _interval(apparatus, knob)
        margin = self.approach_fraction * span
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
        fit = fit_focus_curve(np.array(settings)[order], np.array(widths)[order])
        if fit is not None:
            return float(min(max(fit[1], low), high))
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
        step = self.step_fraction * _interval(apparatus, knob)[2]
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


BASELINES: dict[str, Callable[[], Controller]] = {
    "golden-section": GoldenSection,
    "hyperbola": HyperbolaFit,
    "hill-climb": HillClimb,
}


def get_baseline(name: str) -> Controller:
    """A classical controller with its default parameters, by name."""
    try:
        return BASELINES[name]()
    except KeyError:
        raise ValueError(
            f"unknown controller {name!r}; known controllers: {', '.join(sorted(BASELINES))}"
        ) from None

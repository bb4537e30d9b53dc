"""The focus curve near focus, fitted to readings: the one least-squares fit that the
classical hyperbola fit (alignrl/evaluation/baselines.py), the fit features and the ending
at a fit (alignrl/envs/fit_features.py) and the hindsight curve of the critics
(alignrl/posterior/hindsight.py) all call.

Near focus the edge width follows the probe, a hyperbola in the setting x:

    w^2 = c^2 + a (x - x0)^2

so w^2 is a parabola in x. `fit_focus_curve` fits that parabola to the readings by weighted
least squares, each reading weighted by 1 / w^2 (a relative error per reading: a reading's
noise grows with its width, and the narrow readings near focus count most), the settings
centred and scaled first (they may sit within a hair of each other). Settings and widths
in any units: the optimum comes in the settings', the floor in the widths' squared.
numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FocusCurve", "fit_focus_curve"]


@dataclass(frozen=True)
class FocusCurve:
    """A parabola w^2 = floor + slope (x - optimum)^2 that opens upwards."""

    slope: float  # a > 0, in (width unit / setting unit)^2
    optimum: float  # x0, where the parabola is lowest
    floor: float  # c^2, w^2 at the optimum: <= 0 where the fit finds no positive width there
    settings: np.ndarray  # the settings of the readings that took part

    @property
    def brackets(self) -> bool:
        """Readings on both sides of the optimum took part: an interpolation, never an
        extrapolation beyond them."""
        return bool(self.settings.min() < self.optimum < self.settings.max())


def fit_focus_curve(
    settings: np.ndarray,
    widths: np.ndarray,
    window: float = math.inf,
    resolution: float = 0.0,
) -> FocusCurve | None:
    """The weighted least-squares parabola in w^2 through the readings within `window` x
    the narrowest one (readings not finite or not positive left out).

    None where fewer than three distinct settings take part, or where the parabola does
    not open upwards. Settings closer than `resolution` x their spread count as one (0:
    only equal ones do)."""
    x = np.asarray(settings, np.float64)
    width = np.asarray(widths, np.float64)
    keep = np.isfinite(x) & np.isfinite(width) & (width > 0)
    x, width = x[keep], width[keep]
    if x.size < 3:
        return None
    local = width <= width.min() * window
    x, width = x[local], width[local]
    centre, scale = x.mean(), float(np.ptp(x))
    if x.size < 3 or not scale > 0:
        return None
    u = (x - centre) / scale  # conditioned: the settings may sit within a hair of each other
    distinct = np.round(u / resolution) if resolution > 0 else x
    if np.unique(distinct).size < 3:
        return None
    w2 = width * width
    weights = 1.0 / w2  # a relative error per reading
    design = np.stack([u * u, u, np.ones_like(u)], axis=1) * weights[:, None]
    try:
        (a, b, c), *_ = np.linalg.lstsq(design, w2 * weights, rcond=None)
    except np.linalg.LinAlgError:
        return None
    if not (np.isfinite([a, b, c]).all() and a > 0):
        return None
    return FocusCurve(
        slope=float(a / scale**2),
        optimum=float(centre - scale * b / (2.0 * a)),
        floor=float(c - b * b / (4.0 * a)),
        settings=x,
    )

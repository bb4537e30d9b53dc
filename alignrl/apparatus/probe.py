"""The synthetic SEM's probe optics: edge widths (px) of a Gaussian probe of covariance C.

A straight edge of unit normal n blurred by the probe has the 10-90 % width
TEN_NINETY_PER_SIGMA * sqrt(n^T C n) pixels; round particles show every orientation, so their
mean width is a mean over orientations, and an orientation bin's is the mean over its
+/- 22.5 degrees. Pure numpy functions, shared by the SEM's analytic mode
(alignrl/apparatus/synthetic.py) and the calibration benchmarks; and the instrument family's
focus curve and levelled reading (alignrl/apparatus/family.py), shared with the Bayesian
autofocus that models it (alignrl/evaluation/posterior.py).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from alignrl.apparatus.directional import ORIENTATION_BINS_DEG
from alignrl.apparatus.edge_profiles import TEN_NINETY_PER_SIGMA

__all__ = [
    "directional_edge_widths_px",
    "edge_widths_px",
    "focus_sigma_px",
    "levelled_px",
    "logistic",
    "mean_edge_width_px",
    "probe_covariance",
]

# Edge-normal orientations of the analytic mean width: the particles are round, so their rims
# show every orientation equally. The integrand is smooth and periodic, so the midpoint rule
# on 32 points is exact to rounding.
_ORIENTATIONS = (np.arange(32) + 0.5) * np.pi / 32
# Sub-orientations of one directional bin (+/- 22.5 deg): a bin's width averages them.
_BIN_OFFSETS = (np.arange(8) + 0.5) * (np.pi / 4) / 8 - np.pi / 8


def probe_covariance(sigma_u: float, sigma_v: float, axis: float) -> np.ndarray:
    """Covariance (px^2) in (x, y) = (column, row) of a Gaussian with standard deviations
    sigma_u along the unit vector (cos axis, sin axis) and sigma_v across it: R diag R^T."""
    cos, sin = np.cos(axis), np.sin(axis)
    cov_xx = sigma_u**2 * cos**2 + sigma_v**2 * sin**2
    cov_yy = sigma_u**2 * sin**2 + sigma_v**2 * cos**2
    cov_xy = (sigma_u**2 - sigma_v**2) * sin * cos
    return np.array([[cov_xx, cov_xy], [cov_xy, cov_yy]])


def logistic(value: float, middle: float, spread: float) -> float:
    """1 / (1 + exp(-(value - middle) / spread)), without overflow far from the middle."""
    return 0.5 * (1.0 + math.tanh(0.5 * (value - middle) / spread))


def edge_widths_px(covariance: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """10-90 % widths (px) of straight edges with unit normals at `angles` (rad, atan2(ny, nx))
    blurred by a Gaussian probe of this covariance: 2.563 sqrt(n^T C n)."""
    cos, sin = np.cos(angles), np.sin(angles)
    variance = (
        covariance[0, 0] * cos**2 + 2.0 * covariance[0, 1] * cos * sin + covariance[1, 1] * sin**2
    )
    return TEN_NINETY_PER_SIGMA * np.sqrt(variance)


def mean_edge_width_px(covariance: np.ndarray, power: float = 1.0) -> float:
    """Mean 10-90 % width (px) over uniformly distributed edge orientations, the rims of round
    particles, for a Gaussian probe of this covariance: the power mean (mean w^p)^(1/p), the
    arithmetic mean for p = 1, the geometric mean for p = 0."""
    widths = edge_widths_px(covariance, _ORIENTATIONS)
    if power == 0:
        return float(np.exp(np.log(widths).mean()))
    return float(np.mean(widths**power) ** (1.0 / power))


def directional_edge_widths_px(covariance: np.ndarray) -> np.ndarray:
    """True widths (px) of the four orientation bins of ORIENTATION_BINS_DEG: the edge
    width 2.563 sqrt(n^T C n) averaged over each bin's +/- 22.5 degrees of normal orientation,
    as the rims of round particles fill a bin."""
    centres = np.deg2rad(np.asarray(ORIENTATION_BINS_DEG, dtype=np.float64))
    return edge_widths_px(covariance, centres[:, None] + _BIN_OFFSETS[None, :]).mean(axis=1)


def focus_sigma_px(
    error: Any, gain: Any, floor_sigma_px: Any, curve_power: Any, flat: Any, asymmetry: Any
) -> np.ndarray:
    """A family column's probe sigma(e) (px; alignrl/apparatus/family.py, its module
    docstring), elementwise over arguments that broadcast: the focus error `error` and the
    flat bottom's half-width `flat` in one unit (the knob's, or fractions of the interval),
    `gain` px per that unit."""
    error = np.asarray(error, dtype=np.float64)
    asymmetry = np.asarray(asymmetry, dtype=np.float64)
    above = error > 0
    # each side's gain, broadcast beforehand: np.where broadcasts small operands slowly
    steeper, gentler, _ = np.broadcast_arrays(
        gain * np.sqrt(asymmetry), gain * (1.0 / np.sqrt(asymmetry)), above
    )
    blur = np.where(above, steeper, gentler) * np.maximum(0.0, np.abs(error) - flat)
    return (floor_sigma_px**curve_power + blur**curve_power) ** (1.0 / curve_power)


def levelled_px(width_px: Any, saturation_px: Any) -> np.ndarray:
    """An analytic reading's noise-free width: the true width levelled off at the
    specimen's feature size, w_sat tanh(w / w_sat) (alignrl/apparatus/family.py)."""
    return saturation_px * np.tanh(np.asarray(width_px, dtype=np.float64) / saturation_px)

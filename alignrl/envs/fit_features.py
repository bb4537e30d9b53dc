"""What a local focus-curve fit says of an episode so far: observation features for a
single-knob aligner (`Task.fit_features`), computed from its history window alone.

The width near focus grows as a hyperbola of the focus error, w^2 = w0^2 + g^2 (x - x0)^2,
so w^2 is a parabola in the setting x. From the measured rows of the window whose widths
are within `window` x the narrowest (Task.fit_window, 3 unless set; far readings level off
as the features blur into each other, docs/physics.md, and would bend the parabola), a
least-squares parabola in w^2 is fitted, each row weighted by 1/w^2 (a relative error per
reading: the narrow readings near focus count most; alignrl/apparatus/focus_curve.py, the
fit every focus-curve fit of alignrl calls). Where it opens upwards, it places the optimum
x0 and the floor w0.

Three features, appended to the newest row of the history:

    fit_valid   1 where the fit places an optimum (3 or more rows at distinct settings, a
                parabola that opens upwards), else 0 and the two below are 0;
    fit_step    (x0 - setting) in maximum steps: the action that would reach x0, clipped
                to [-FIT_STEP_LIMIT, FIT_STEP_LIMIT];
    fit_floor   log(w0 / the newest width), clipped to [FIT_FLOOR_MIN, 0]: how much
                narrower the fit says the column can get; FIT_FLOOR_MIN where w0^2 <= 0.

The same fit ends an episode where the task says so (finish_at_fit,
`bracketed_optimum`): over all of the episode's readings within FINISH_WINDOW x the narrowest,
its optimum where readings lie on both sides of it.

Settings come from the history's knob column (a fraction of the interval) and widths from
its quality column (a log ratio to the episode's reference), so the features carry no unit:
two columns that differ only in units and pixel scale give the same features. The fit knows
nothing of hysteresis or drift; the network that reads it learns how far to trust it.
"""

from __future__ import annotations

import numpy as np

from alignrl.apparatus.focus_curve import fit_focus_curve

__all__ = ["FINISH_WINDOW", "FIT_FEATURES", "bracketed_optimum", "fit_features"]

FIT_FEATURES = 3
LOCAL_RATIO = 3.0  # rows within this x the narrowest reading take part in the fit
# The end of an episode (finish_at_fit) fits every reading within this x the narrowest:
# of 2, 3, 5, 10, 20 and every reading, the best on the validation instruments
# (docs/benchmarks.md, "Ending at a fit of the readings").
FINISH_WINDOW = 10.0
FIT_STEP_LIMIT = 2.0
FIT_FLOOR_MIN = -3.0
_MIN_SPREAD = 1e-6  # settings closer than this share of the fitted ones' spread are one


def fit_features(
    knobs: np.ndarray,
    quality: np.ndarray,
    measured: np.ndarray,
    step_in_knob_units: np.ndarray,
    window: float = LOCAL_RATIO,
) -> np.ndarray:
    """(N, 3) fit features of N history windows.

    `knobs`, `quality`, `measured`: (N, H) columns of the windows (the knob as 2 x fraction
    - 1, log(width / reference), 1 where a row is valid and measured); `step_in_knob_units`:
    (N,) one maximum step in the knob column's units (2 x max step / interval). The newest
    row is the last, and measured where a fit is to be read from it."""
    n = knobs.shape[0]
    out = np.zeros((n, FIT_FEATURES), np.float32)
    for row in range(n):
        out[row] = _one(
            knobs[row], quality[row], measured[row] > 0.5, step_in_knob_units[row], window
        )
    return out


def _one(
    x: np.ndarray, q: np.ndarray, measured: np.ndarray, step: float, window: float
) -> np.ndarray:
    features = np.zeros(FIT_FEATURES, np.float32)
    if not measured[-1] or measured.sum() < 3 or not step > 0:
        return features
    setting, newest = float(x[-1]), float(q[-1])
    widths = np.exp(q[measured].astype(np.float64))
    curve = fit_focus_curve(x[measured], widths, window, resolution=_MIN_SPREAD)
    if curve is None:
        return features
    floor_sq = curve.floor  # in (width / the reference)^2
    features[0] = 1.0
    features[1] = np.clip((curve.optimum - setting) / step, -FIT_STEP_LIMIT, FIT_STEP_LIMIT)
    if floor_sq > 0:
        features[2] = np.clip(0.5 * np.log(floor_sq) - newest, FIT_FLOOR_MIN, 0.0)
    else:
        features[2] = FIT_FLOOR_MIN
    return features


def bracketed_optimum(
    settings: np.ndarray, widths: np.ndarray, window: float = FINISH_WINDOW
) -> float | None:
    """Where the focus-curve fit of an episode's readings puts the optimum, if readings on
    both sides of it took part (an interpolation, never an extrapolation beyond them); else
    None. What finish_at_fit ends at (alignrl/envs/core.py)."""
    curve = fit_focus_curve(settings, widths, window, resolution=_MIN_SPREAD)
    return curve.optimum if curve is not None and curve.brackets else None

"""The hindsight posterior for critics: where a column's optimum lay in an episode, told
after it ended, from its readings and the column's focus curve pooled over earlier episodes
(one knob). alignrl/envs/hindsight.py (`HindsightSecrets`) gives the critics' secrets of a
real column with it.

Settings are fractions of the knob's interval, readings edge widths in pixels. numpy only.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from alignrl.apparatus.focus_curve import fit_focus_curve

__all__ = ["PooledCurve"]


class PooledCurve:
    """Where a column's optimum lies, in hindsight, from an episode's readings (one knob).

    Near focus a reading of the edge width follows the probe: w^2 = c^2 + a (x - x0)^2, with
    x the setting (a fraction of the interval), x0 the optimum, c the column's best width and
    a its focus curve's steepness. Both c and a belong to the column, not to the episode:
    they are pooled over the last `POOL` finished episodes (the medians of each episode's own
    parabola in x through its readings w^2 within `FIT_SPAN` x its sharpest: the one
    focus-curve fit, alignrl/apparatus/focus_curve.py), and the reading
    noise from pairs of readings at one setting (a stop and its verification image). An episode's
    optimum is then drawn from its posterior on a grid of the interval, so that a stop on a
    reading at the spec's edge is told "about this far from the optimum, on this side with
    these odds", where the sharpest reading alone would tell it "at the optimum".

    Far from focus the image path compresses the reading (a blurred edge reads narrower than
    the probe), so readings beyond `FAR` x c count with `FAR_LOOSENESS` x the noise. The pool
    lives in memory: a resumed run pools afresh from the episodes after the resume.
    """

    POOL = 256
    MIN_EPISODES = 32
    REFIT_EVERY = 16
    FIT_SPAN = 1.5
    DEFAULT_NOISE = 0.04
    FAR = 2.0
    FAR_LOOSENESS = 8.0
    GRID = np.linspace(0.0, 1.0, 2001)

    def __init__(self, seed: int = 0) -> None:
        self._episodes: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.POOL)
        self._rng = np.random.default_rng(seed)
        self._since_fit = 0
        self.curve: tuple[float, float, float] | None = None  # (a, c, relative noise)

    def add(self, positions: np.ndarray, widths: np.ndarray) -> None:
        """One finished episode: its settings (n,) and readings (n,), failed ones NaN."""
        ok = np.isfinite(widths) & (widths > 0)
        if ok.any():
            self._episodes.append((positions[ok], widths[ok]))
            self._since_fit += 1
        if len(self._episodes) >= self.MIN_EPISODES and (
            self.curve is None or self._since_fit >= self.REFIT_EVERY
        ):
            self.curve = self._fit()
            self._since_fit = 0

    def _fit(self) -> tuple[float, float, float] | None:
        slopes, floors, log_ratios = [], [], []
        for x, w in self._episodes:
            curve = fit_focus_curve(x, w, self.FIT_SPAN)
            if curve is not None and curve.floor > 0:  # a positive best width
                slopes.append(curve.slope)
                floors.append(curve.floor)
            same = np.flatnonzero(np.diff(x) == 0)
            log_ratios.extend(np.log(w[same + 1] / w[same]))
        if len(slopes) < self.MIN_EPISODES // 4:
            return None
        noise = self.DEFAULT_NOISE
        if len(log_ratios) >= 16:  # two readings at one setting differ by sqrt(2) x the noise
            noise = float(np.clip(1.4826 * np.median(np.abs(log_ratios)) / np.sqrt(2), 0.005, 0.2))
        return float(np.median(slopes)), float(np.sqrt(np.median(floors))), noise

    def sample(self, positions: np.ndarray, widths: np.ndarray) -> float | None:
        """A draw of the episode's optimum (a fraction of the interval); None until the
        column's curve is known or where the episode has no reading."""
        ok = np.isfinite(widths) & (widths > 0)
        if self.curve is None or not ok.any():
            return None
        slope, best, noise = self.curve
        x, w = positions[ok], widths[ok]
        model = np.sqrt(best**2 + slope * (x[None, :] - self.GRID[:, None]) ** 2)
        scale = noise * model * np.where(model > self.FAR * best, self.FAR_LOOSENESS, 1.0)
        log_likelihood = -np.sum(0.5 * ((w[None, :] - model) / scale) ** 2 + np.log(scale), 1)
        posterior = np.exp(log_likelihood - log_likelihood.max())
        return float(self._rng.choice(self.GRID, p=posterior / posterior.sum()))

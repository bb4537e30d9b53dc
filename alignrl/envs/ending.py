"""Where alignment episodes end (alignrl/envs/core.py): the task options `stop_at_best`,
`backlash_overshoot`, `finish_at_fit` and `finish_window` of alignrl/envs/task.py.

An episode that ends (stop, or the step limit) may leave its knobs where its last step took
them (the seed), or go back:

* to where its narrowest reading was taken (`stop_at_best`), as a classical autofocus ends;
* or, with `finish_at_fit`, to the optimum a focus-curve fit of all its readings places
  between them (alignrl/envs/fit_features.py, `bracketed_optimum`), where the readings
  bracket it, else to the narrowest reading.

The way back arrives at every knob from the side the narrowest reading was approached from:
where it would come from the other side it first goes past the target by
`backlash_overshoot` x the interval (kept inside it), so that backlash and lens hysteresis,
which put the focus elsewhere for the other side, leave it as that reading had it. No
acquisition is taken on the way back.

`EpisodeEnds` keeps, per episode, what that needs: every measured reading and its setting,
the narrowest one with the side it was approached from, and the side of the last change
written to each knob (from the writes themselves: `wrote`).
"""

from __future__ import annotations

import numpy as np

from alignrl.envs.fit_features import bracketed_optimum
from alignrl.envs.task import Task

__all__ = ["EpisodeEnds"]


class EpisodeEnds:
    """The end of N episodes over k knobs (module docstring)."""

    def __init__(self, n: int, k: int, task: Task) -> None:
        self.task = task
        self.narrowest = np.full(n, np.inf)  # the episode's narrowest reading so far, px
        self.narrowest_setting = np.zeros((n, k))  # where it was taken
        self.narrowest_approach = np.zeros((n, k))  # the side it was approached from
        # Per knob, the sign of the last change written (0: none seen this episode) and where
        # the knob was written last (NaN: not yet).
        self.approach = np.zeros((n, k))
        self.written = np.full((n, k), np.nan)
        self.readings: list[list[tuple[np.ndarray, float]]] = [[] for _ in range(n)]

    def restart(self, indices: np.ndarray, found: np.ndarray | None = None) -> None:
        """New episodes on `indices`: no side known; the knobs as `found` where the episode
        adopts the column as it is (nothing written yet), else unknown."""
        self.approach[indices] = 0.0
        self.written[indices] = np.nan if found is None else found

    def wrote(self, index: int, applied: np.ndarray) -> None:
        """Apparatus `index` now holds `applied` (its units): the side of each knob's change."""
        with np.errstate(invalid="ignore"):
            change = np.sign(applied - self.written[index])  # NaN before the first write
        moved = np.isfinite(change) & (change != 0)
        self.approach[index, moved] = change[moved]
        self.written[index] = applied

    def note(
        self,
        indices: np.ndarray,
        settings: np.ndarray,
        widths: np.ndarray,
        measured: np.ndarray,
        first: np.ndarray,
    ) -> None:
        """Readings of `indices` taken at `settings`; `first`: the episode's first row (its
        record starts afresh)."""
        self.narrowest[indices[first]] = np.inf
        for position, index in enumerate(indices):
            if first[position]:
                self.readings[index] = []
            if measured[position]:
                self.readings[index].append((settings[position].copy(), float(widths[position])))
        narrower = measured & (np.where(measured, widths, np.inf) < self.narrowest[indices])
        self.narrowest[indices[narrower]] = widths[narrower]
        self.narrowest_setting[indices[narrower]] = settings[narrower]
        self.narrowest_approach[indices[narrower]] = self.approach[indices[narrower]]

    def target(self, index: int, low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, bool]:
        """Where episode `index` ends, and whether at a fit: the fitted optimum
        (Task.finish_at_fit, where readings bracket it; inside [low, high]), else its
        narrowest reading's setting."""
        readings = self.readings[index]
        if self.task.finish_at_fit and len(readings) >= 3:
            settings = np.array([setting[0] for setting, _ in readings])
            widths = np.array([width for _, width in readings])
            optimum = bracketed_optimum(settings, widths, self.task.finish_window)
            if optimum is not None:
                return np.clip([optimum], low, high), True
        return self.narrowest_setting[index], False

    def way_back(
        self, index: int, setting: np.ndarray, target: np.ndarray, low: np.ndarray,
        high: np.ndarray,
    ) -> list[np.ndarray]:  # fmt: skip
        """The writes that take episode `index` from `setting` to `target`, every knob
        arriving from the side the narrowest reading was approached from (module docstring):
        one write where each already does (or without an overshoot), else two."""
        side = self.narrowest_approach[index]
        reverse = (side != 0) & (np.sign(target - setting) == -side)
        overshoot = self.task.backlash_overshoot * (high - low)
        if not np.any(reverse & (overshoot > 0)):
            return [target]
        beyond = np.clip(np.where(reverse, target - side * overshoot, target), low, high)
        return [beyond, target]

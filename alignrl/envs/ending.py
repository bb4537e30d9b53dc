"""Where alignment episodes end (alignrl/envs/core.py): the task options `stop_at_best`,
`backlash_overshoot`, `finish_at_fit`, `finish_at_posterior`, `stop_when_sure` and
`finish_window` of alignrl/envs/task.py.

An episode that ends (stop, or the step limit) may leave its knobs where its last step took
them (the seed), or go back:

* to where its narrowest reading was taken (`stop_at_best`), as a classical autofocus ends;
* or, with `finish_at_fit`, to the optimum a focus-curve fit of all its readings places
  between them (alignrl/envs/fit_features.py, `bracketed_optimum`), where the readings
  bracket it, else to the narrowest reading.

With `final_move` the stopping action's own move ends the episode instead; with
`finish_at_fit` too, that move starts from the fit's optimum where the readings bracket one
(`estimated`): the policy says how far from the fit, not how far from where it stands.

With `finish_at_posterior` the fit's place is taken by the setting that a posterior over the
focus training box (alignrl/posterior/inference.py, one per episode, fed every
measured reading) holds most likely to pass; with `stop_when_sure` too, an episode also ends
once that setting passes with the chance asked (`sure`); with `probe_until_sure` a stop it
is unsure of becomes a reading where it would probe next, and with `posterior_walk_after`
every reading from the N-th on is placed there (`probes`), with `posterior_walk_unmeasured`
every reading while none has been measured.

The way back arrives at every knob from the side the narrowest reading was approached from
(at the posterior's setting, from below: the side that setting is placed for):
where it would come from the other side it first goes past the target by
`backlash_overshoot` x the interval (kept inside it), so that backlash and lens hysteresis,
which put the focus elsewhere for the other side, leave it as that reading had it (the
classical controllers take up backlash alike, always from below:
alignrl/evaluation/controllers.py, `approach_from_below`; the engine's writes go through
its own `_write`, which records where the shield left each knob). No acquisition is taken
on the way back.

With `approach_from_below` every reading's setting is reached the same way, from below
(`writes_to`), so that every reading, and the way back, lie on one branch of the backlash.

`EpisodeEnds` keeps, per episode, what that needs: every measured reading with its setting
and the side each knob came from (the narrowest reading is the least of them), and the side
of the last change written to each knob (from the writes themselves: `wrote`).
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from alignrl.envs.fit_features import bracketed_optimum
from alignrl.envs.task import Task

if TYPE_CHECKING:  # made on first use: scipy's Sobol' and the box
    from alignrl.posterior.inference import FamilyPosterior

__all__ = ["STATES_PER_COLUMN", "EndPlan", "EpisodeEnds", "Noted", "resample_for"]

# The states an episode's posterior scores a probe on and judges a stop on, per column it
# draws (Task.posterior_draws), up to the posterior's own SCORED_STATES and STOP_STATES:
# both reached at 250 columns, so the default 256 and the champion's 1,024 judge as many
# states as ever, and a posterior of fewer columns costs less in proportion.
STATES_PER_COLUMN = (8, 80)


def resample_for(draws: int) -> tuple[int, int]:
    """The states (probe, stop) a posterior of `draws` columns judges (STATES_PER_COLUMN;
    FamilyPosterior.resample)."""
    from alignrl.posterior.inference import SCORED_STATES, STOP_STATES

    probe, stop = STATES_PER_COLUMN
    return min(SCORED_STATES, probe * draws), min(STOP_STATES, stop * draws)


class Noted(NamedTuple):
    """One measured reading of an episode, as its end needs it."""

    setting: np.ndarray  # (k,) the knobs' settings, their units
    width: float  # px
    side: np.ndarray  # (k,) the sign of the last change written to each knob (0: unknown)


class EndPlan(NamedTuple):
    """How an episode goes back: the writes in order, whether to a fit, and the narrowest
    reading, which stands as the final one unless the task verifies."""

    writes: list[np.ndarray]
    fitted: bool
    width: float


class EpisodeEnds:
    """The end of N episodes over k knobs (module docstring)."""

    def __init__(self, n: int, k: int, task: Task) -> None:
        self.task = task
        # Per knob, the sign of the last change written (0: none seen this episode) and where
        # the knob was written last (NaN: not yet).
        self.approach = np.zeros((n, k))
        self.written = np.full((n, k), np.nan)
        self.readings: list[list[Noted]] = [[] for _ in range(n)]
        # finish_at_posterior: per episode a FamilyPosterior fed every measured reading (made
        # on first use), and its final() until the next reading
        self._posteriors: list[FamilyPosterior | None] = [None] * n
        self._best: list[tuple[float, float] | None] = [None] * n

    def restart(self, indices: np.ndarray, found: np.ndarray | None = None) -> None:
        """New episodes on `indices`: no side known; the knobs as `found` where the episode
        adopts the column as it is (nothing written yet), else unknown."""
        self.approach[indices] = 0.0
        self.written[indices] = np.nan if found is None else found

    def wrote(self, index: int, applied: np.ndarray) -> None:
        """Apparatus `index` now holds `applied` (its units): the side of each knob's change.
        Kept only where the task goes back or approaches from below (Task.stop_at_best,
        approach_from_below)."""
        if not (self.task.stop_at_best or self.task.approach_from_below):
            return
        with np.errstate(invalid="ignore"):
            change = np.sign(applied - self.written[index])  # NaN before the first write
        moved = np.isfinite(change) & (change != 0)
        self.approach[index, moved] = change[moved]
        self.written[index] = applied

    def writes_to(
        self, index: int, target: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> list[np.ndarray]:
        """The writes that take episode `index`'s knobs to `target` inside [low, high]: with
        Task.approach_from_below, a knob that would come down first goes past the target by
        the overshoot (kept inside the interval), then up to it; else one write."""
        if not self.task.approach_from_below:
            return [target]
        target = np.array(target, float)  # a copy: the caller's row changes as they land
        below = np.ones_like(target)
        return self._arrive(target, self.written[index], below, low, high)

    def note(
        self,
        indices: np.ndarray,
        settings: np.ndarray,
        widths: np.ndarray,
        measured: np.ndarray,
        opening: np.ndarray,
        positions: np.ndarray,
    ) -> None:
        """Readings of `indices` taken at `settings` (`positions`: as fractions of the
        intervals); `opening`: the episode's first row (its record starts afresh)."""
        posterior = self.task.finish_at_posterior
        for position, index in enumerate(indices):
            if opening[position]:
                self.readings[index] = []
                if posterior:
                    self._posterior(index).begin()
            if measured[position]:
                self.readings[index].append(
                    Noted(settings[position].copy(), float(widths[position]),
                          self.approach[index].copy())
                )  # fmt: skip
            if posterior and self._posterior_reads(index, bool(measured[position])):
                self._posterior(index).observe(
                    float(positions[position, 0]),
                    float(widths[position]) if measured[position] else math.nan,
                    self._side(index),
                )
            self._best[index] = None

    def _posterior_reads(self, index: int, measured: bool) -> bool:
        """Whether episode `index`'s posterior reads its latest reading: a measured one, or
        with Task.posterior_no_edges one without edges; with Task.posterior_from_below only
        one whose side is known, not the column as found (one written from above, at the
        interval's lower end where nothing lies below, is read on its branch: `_side`)."""
        if self.task.posterior_from_below and self.approach[index, 0] == 0:
            return False
        return measured or self.task.posterior_no_edges

    def _side(self, index: int) -> float:
        """The side episode `index`'s latest reading came from, as its posterior reads it:
        on its branch with a calibrated column (Task.posterior_column; 0: unknown, the column
        as found), posterior_from_below or posterior_on_sides, else as from below."""
        task = self.task
        if task.posterior_column or task.posterior_from_below or task.posterior_on_sides:
            return float(self.approach[index, 0])
        return 1.0

    def narrowest(self, index: int) -> Noted | None:
        """Episode `index`'s narrowest reading (the first of equals); None where none was
        measured."""
        readings = self.readings[index]
        return min(readings, key=lambda reading: reading.width) if readings else None

    def estimated(self, index: int, low: np.ndarray, high: np.ndarray) -> np.ndarray | None:
        """(1,), its units: where episode `index` ends, estimated from its readings
        (Task.ends_at_estimate): a focus-curve fit's optimum between them (finish_at_fit,
        `finish_window`; None where they bracket none), or the setting the posterior over
        the training box holds most likely to pass (finish_at_posterior; None before a
        reading). `low`, `high`: the knob's interval."""
        readings = self.readings[index]
        if not readings:
            return None
        if self.task.finish_at_posterior:
            return np.array([low[0] + self.best(index)[0] * (high[0] - low[0])])
        settings = np.array([reading.setting[0] for reading in readings])
        widths = np.array([reading.width for reading in readings])
        optimum = bracketed_optimum(settings, widths, self.task.finish_window)
        return None if optimum is None else np.array([optimum])

    def best(self, index: int) -> tuple[float, float]:
        """finish_at_posterior: the setting (a fraction of the interval) the posterior of
        episode `index` holds most likely to pass, and that chance."""
        if self._best[index] is None:
            self._best[index] = self._posteriors[index].final()
        return self._best[index]

    def sure(self, index: int) -> bool:
        """Whether episode `index`'s posterior best setting passes with Task.stop_when_sure."""
        return bool(self.readings[index]) and self.best(index)[1] >= self.task.stop_when_sure

    def probes(
        self, indices: np.ndarray, stop: np.ndarray, steps: np.ndarray, low: np.ndarray,
        high: np.ndarray,
    ) -> dict[int, float]:  # fmt: skip
        """Of the episodes `indices` (`stop`: whose actions stop; `steps`: the steps each has
        taken, so steps + 1 readings), those whose next reading the posterior places, each
        with where it would read next (the knob's units; `low`, `high`: every episode's
        interval): with Task.probe_until_sure, a stopping episode whose posterior is not yet
        that sure of its best setting (the reading is taken in place of the stop); with
        Task.posterior_walk_after, a moving episode that has taken that many readings; with
        Task.posterior_walk_unmeasured, a moving episode none of whose readings was measured.
        None without any (the step of every other task asks nothing more)."""
        task = self.task
        unmeasured = task.posterior_walk_unmeasured
        if not (task.probe_until_sure or task.posterior_walk_after or unmeasured):
            return {}
        chosen = [
            index for index, stopping, step in zip(indices, stop, steps, strict=True)
            if (stopping and task.probe_until_sure and self.readings[index]
                and self.best(index)[1] < task.probe_until_sure)
            or (not stopping and 0 < task.posterior_walk_after <= step + 1)
            or (not stopping and unmeasured and not self.readings[index])
        ]  # fmt: skip
        return {
            int(i): float(low[i, 0] + self._posteriors[i].probe() * (high[i, 0] - low[i, 0]))
            for i in chosen
        }

    def _posterior(self, index: int) -> FamilyPosterior:
        """Episode `index`'s FamilyPosterior: the scale-free posterior over the focus training
        box, made once (scipy's Sobol' and the box) and copied for every other slot (`begin`
        gives each copy its own state)."""
        if self._posteriors[index] is None:
            made = next((each for each in self._posteriors if each is not None), None)
            if made is None and self.task.posterior_column:
                made = self._calibrated()
            if made is None:
                from alignrl.posterior.inference import SCALE_FREE, FamilyPosterior
                from alignrl.posterior.models import focus_box

                made = FamilyPosterior(
                    focus_box(saturation_px=self.task.posterior_saturation_px or None),
                    spec_relative=self.task.success.relative,
                    draws=self.task.posterior_draws,
                    resample=resample_for(self.task.posterior_draws),
                    far_noise=self.task.posterior_far_noise,
                    probe_rule=self.task.posterior_probe_rule,
                    **SCALE_FREE,
                )
            self._posteriors[index] = copy.copy(made)
        return self._posteriors[index]

    def _calibrated(self) -> FamilyPosterior:
        """The posterior over the column calibrated on the microscope (Task.posterior_column,
        alignrl/posterior/calibration.py), in its own pixels, far readings trusted as the
        task says (Task.posterior_far_noise: `alignrl calibrate` writes the far noise the
        column was fitted with)."""
        from alignrl.posterior.calibration import (
            COLUMN_FIELDS,
            calibrated_posterior,
        )

        column = dict(zip(COLUMN_FIELDS, self.task.posterior_column, strict=True))
        return calibrated_posterior(
            column, self.task.success.relative, far_noise=self.task.posterior_far_noise
        )

    def plan(
        self, index: int, setting: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> EndPlan | None:
        """How episode `index`, its knobs at `setting` inside [low, high], goes back; None
        where nothing was measured or it is already there (module docstring)."""
        narrowest = self.narrowest(index)
        if narrowest is None:
            return None
        target, fitted = narrowest.setting, False
        optimum = self.estimated(index, low, high) if self.task.ends_at_estimate else None
        if optimum is not None:
            target, fitted = np.clip(optimum, low, high), True
        if np.array_equal(target, setting):
            return None
        # From the narrowest reading's side; the posterior's setting is placed for an
        # approach from below (FamilyPosterior.final), whatever side that reading came from.
        from_below = fitted and self.task.finish_at_posterior
        side = np.ones_like(narrowest.side) if from_below else narrowest.side
        writes = self._arrive(target, setting, side, low, high)
        return EndPlan(writes, fitted, narrowest.width)

    def _arrive(
        self, target: np.ndarray, start: np.ndarray, side: np.ndarray, low: np.ndarray,
        high: np.ndarray,
    ) -> list[np.ndarray]:  # fmt: skip
        """The writes that take the knobs from `start` (NaN: unknown) to `target`, each
        arriving from its `side` (+1 from below, -1 from above, 0 either): a knob that would
        come from the other side first goes past the target by backlash_overshoot x the
        interval, kept inside [low, high]."""
        overshoot = self.task.backlash_overshoot * (high - low)
        with np.errstate(invalid="ignore"):
            reverse = (side != 0) & (np.sign(target - start) == -side) & (overshoot > 0)
        if not np.any(reverse):
            return [target]
        return [np.clip(np.where(reverse, target - side * overshoot, target), low, high), target]

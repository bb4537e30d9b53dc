"""Where alignment episodes end (alignrl/envs/core.py), as the task's one `Ending` record
says (`Task.ending`, alignrl/envs/endings.py; its flat option names in backquotes below).

The protocol: the env step (AlignmentEpisodes.step) visits `EpisodeEnds` at two fixed
points, and tells it what its writes and readings were:

1. `before(indices, stop, steps, low, high) -> Before(stop, probes)`, once before the
   moves: which episodes stop (a stop the posterior is unsure of is a reading instead) and,
   per episode, where the posterior places its next reading in place of the policy's move;
2. `after(indices, done, stop, moves, setting, low, high, max_step) -> After(done, stop,
   plans)`, once after the readings: which episodes are done and stopped (a sure posterior
   ends one), and how each finished one ends, as an `EndPlan` of writes (a last move, or the
   way back to its narrowest reading or estimate, whose width then stands), which the step
   makes through its own `_write` (`_end`);
3. what it is told: `restart` (new episodes), `note` (each step's readings), `wrote` (where
   every write left the knobs), and `writes_to`, which says how a reading's setting is
   reached (from below with `approach_from_below`). `origins` is where a last move starts.

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

from alignrl.apparatus.backlash import arrival
from alignrl.envs.fit_features import bracketed_optimum
from alignrl.envs.task import Task, knob_change

if TYPE_CHECKING:  # made on first use: scipy's Sobol' and the box
    from alignrl.posterior.inference import FamilyPosterior

__all__ = [
    "STATES_PER_COLUMN",
    "After",
    "Before",
    "EndPlan",
    "EpisodeEnds",
    "Noted",
    "resample_for",
]

# The states an episode's posterior scores a probe on and judges a stop on, per column it
# draws (posterior_draws), up to the posterior's own SCORED_STATES and STOP_STATES:
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
    """How one finished episode ends: the writes in order; whether to an estimate; the
    narrowest reading's width, which stands as the final one unless the task verifies (NaN
    for a last move: the last reading stands); whether a last move was clipped at a bound."""

    index: int
    writes: list[np.ndarray]
    fitted: bool
    width: float
    hit_bound: bool = False


class Before(NamedTuple):
    """What the ending says before a step's moves: which of its episodes stop (a stop the
    posterior is unsure of is a reading instead), and where the posterior places a reading
    (episode -> setting, the knob's units) in place of the policy's move."""

    stop: np.ndarray
    probes: dict[int, float]


class After(NamedTuple):
    """What the ending says after a step's readings: which episodes are done and which of
    them stopped (a sure posterior ends one as a stop whose last move is 0), and how each
    finished episode ends, as plans of writes (none where it stays)."""

    done: np.ndarray
    stop: np.ndarray
    plans: list[EndPlan]


class EpisodeEnds:
    """The end of N episodes over k knobs (module docstring)."""

    def __init__(self, n: int, k: int, task: Task) -> None:
        self.task = task
        self.ending = task.ending  # alignrl/envs/endings.py
        self.settings = task.ending.settings  # its posterior's (at "posterior")
        # Per knob, the sign of the last change written (0: none seen this episode) and where
        # the knob was written last (NaN: not yet).
        self.approach = np.zeros((n, k))
        self.written = np.full((n, k), np.nan)
        self.readings: list[list[Noted]] = [[] for _ in range(n)]
        # finish_at_posterior: per episode a FamilyPosterior fed every measured reading (made
        # on first use), and its final() until the next reading
        self._posteriors: list[FamilyPosterior | None] = [None] * n
        self._best: list[tuple[float, float] | None] = [None] * n

    # --- the protocol: what the env step asks (module docstring) ---------------------

    def before(
        self,
        indices: np.ndarray,
        stop: np.ndarray,
        steps: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> Before:
        """Before the moves of episodes `indices` (`stop`: whose actions stop; `steps`: the
        steps each has taken; `low`, `high`: every episode's interval): which stop, and where
        the posterior places a reading instead of the policy (`probes`)."""
        probes = self.probes(indices, stop, steps, low, high)
        return Before(stop & ~np.isin(indices, list(probes)), probes)

    def after(
        self,
        indices: np.ndarray,
        done: np.ndarray,
        stop: np.ndarray,
        moves: np.ndarray,
        setting: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        max_step: np.ndarray,
    ) -> After:
        """After the readings of episodes `indices` (`done`, `stop`: as the step has them;
        `moves`: their actions' knob components; `setting`, `low`, `high`, `max_step`: every
        episode's, its units): which are done and stopped, and how each finished one ends:
        the stopping ones' last moves (final_move), or every finished one's way back to its
        narrowest reading or estimate (stop_at_best)."""
        ending = self.ending
        if self.settings.stop_when_sure:  # the posterior is sure: a stop whose last move is 0
            sure = ~done & np.array([self.sure(index) for index in indices], bool)
            done, stop = done | sure, stop | sure
            moves = np.where(sure[:, None], 0.0, moves)
        plans: list[EndPlan] = []
        if ending.final_move and np.any(stop):
            plans = self._last_moves(indices[stop], moves[stop], setting, low, high, max_step)
        elif ending.stop_at_best:
            for index in indices[done]:
                plan = self.plan(index, setting[index], low[index], high[index])
                if plan is not None:  # nothing measured, or already there: it stays
                    plans.append(plan)
        return After(done, stop, plans)

    def origins(
        self, indices: np.ndarray, setting: np.ndarray, low: np.ndarray, high: np.ndarray
    ) -> np.ndarray:
        """(len(indices), k), units: where a stopping action's move starts (final_move): at
        "fit" the fitted optimum where the readings bracket one, at "posterior" the
        posterior's best setting; else the present setting."""
        origins = setting[indices].copy()
        if not self.ending.at_estimate:
            return origins
        for position, index in enumerate(indices):
            estimate = self.estimated(index, low[index], high[index])
            if estimate is not None:
                origins[position] = np.clip(estimate, low[index], high[index])
        return origins

    def _last_moves(
        self,
        indices: np.ndarray,
        moves: np.ndarray,
        setting: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        max_step: np.ndarray,
    ) -> list[EndPlan]:
        """final_move: the stopping actions' moves of `indices`, one last time from
        `origins` (final_move_reach x max_step; no floor), clipped at the interval's bounds,
        each reached as any reading's setting (`writes_to`)."""
        reach = max_step[indices] * self.ending.final_move_reach
        target = self.origins(indices, setting, low, high)
        target = target + knob_change(moves, reach, self.task.action_power)
        clipped = np.clip(target, low[indices], high[indices])
        hit = np.any(clipped != target, axis=1)
        return [
            EndPlan(
                int(index),
                self.writes_to(index, clipped[position], low[index], high[index]),
                False,
                math.nan,
                bool(hit[position]),
            )
            for position, index in enumerate(indices)
        ]

    # --- what the episodes' writes and readings tell it ------------------------------

    def restart(self, indices: np.ndarray, found: np.ndarray | None = None) -> None:
        """New episodes on `indices`: no side known; the knobs as `found` where the episode
        adopts the column as it is (nothing written yet), else unknown."""
        self.approach[indices] = 0.0
        self.written[indices] = np.nan if found is None else found

    def wrote(self, index: int, applied: np.ndarray) -> None:
        """Apparatus `index` now holds `applied` (its units): the side of each knob's change.
        Kept only where the task goes back or approaches from below (stop_at_best,
        approach_from_below)."""
        if not self.ending.tracks_sides:
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
        approach_from_below, a knob that would come down first goes past the target by
        the overshoot (kept inside the interval), then up to it; else one write."""
        if not self.ending.approach_from_below:
            return [target]
        target = np.array(target, float)  # a copy: the caller's row changes as they land
        below = np.ones_like(target)
        return self._arrive(index, target, self.written[index], below, low, high)

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
        posterior = self.ending.at == "posterior"
        for position, index in enumerate(indices):
            if opening[position]:
                self.readings[index] = []
                if posterior:
                    self._posterior(index).begin()
            if measured[position]:
                noted = Noted(
                    settings[position].copy(), float(widths[position]), self.approach[index].copy()
                )
                self.readings[index].append(noted)
            if posterior and self._posterior_reads(index, bool(measured[position])):
                self._posterior(index).observe(
                    float(positions[position, 0]),
                    float(widths[position]) if measured[position] else math.nan,
                    self._side(index),
                )
            self._best[index] = None

    def _posterior_reads(self, index: int, measured: bool) -> bool:
        """Whether episode `index`'s posterior reads its latest reading: a measured one, or
        with posterior_no_edges one without edges."""
        return measured or self.settings.no_edges

    def _side(self, index: int) -> float:
        """The side episode `index`'s latest reading came from, as its posterior reads it:
        on its branch with a calibrated column (posterior_column; 0: unknown, the column
        as found), else as from below."""
        return float(self.approach[index, 0]) if self.settings.column else 1.0

    def narrowest(self, index: int) -> Noted | None:
        """Episode `index`'s narrowest reading (the first of equals); None where none was
        measured."""
        readings = self.readings[index]
        return min(readings, key=lambda reading: reading.width) if readings else None

    def estimated(self, index: int, low: np.ndarray, high: np.ndarray) -> np.ndarray | None:
        """(1,), its units: where episode `index` ends, estimated from its readings
        (Ending.at_estimate): a focus-curve fit's optimum between them (finish_at_fit,
        `finish_window`; None where they bracket none), or the setting the posterior over
        the training box holds most likely to pass (finish_at_posterior; None before a
        reading). `low`, `high`: the knob's interval."""
        readings = self.readings[index]
        if not readings:
            return None
        if self.ending.at == "posterior":
            return np.array([low[0] + self.best(index)[0] * (high[0] - low[0])])
        settings = np.array([reading.setting[0] for reading in readings])
        widths = np.array([reading.width for reading in readings])
        optimum = bracketed_optimum(settings, widths, self.ending.finish_window)
        return None if optimum is None else np.array([optimum])

    def best(self, index: int) -> tuple[float, float]:
        """finish_at_posterior: the setting (a fraction of the interval) the posterior of
        episode `index` holds most likely to pass, and that chance."""
        if self._best[index] is None:
            self._best[index] = self._posteriors[index].final()
        return self._best[index]

    def sure(self, index: int) -> bool:
        """Whether episode `index`'s posterior best setting passes with stop_when_sure."""
        return bool(self.readings[index]) and self.best(index)[1] >= self.settings.stop_when_sure

    def probes(
        self,
        indices: np.ndarray,
        stop: np.ndarray,
        steps: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> dict[int, float]:
        """Of the episodes `indices` (`stop`: whose actions stop; `steps`: the steps each has
        taken, so steps + 1 readings), those whose next reading the posterior places, each
        with where it would read next (the knob's units; `low`, `high`: every episode's
        interval): with probe_until_sure, a stopping episode whose posterior is not yet
        that sure of its best setting (the reading is taken in place of the stop); with
        posterior_walk_after, a moving episode that has taken that many readings; with
        posterior_walk_unmeasured, a moving episode none of whose readings was measured.
        None without any (the step of every other task asks nothing more)."""
        settings = self.settings
        sure, after, unmeasured = (
            settings.probe_until_sure,
            settings.walk_after,
            settings.walk_unmeasured,
        )
        if not (sure or after or unmeasured):
            return {}
        chosen = [
            index
            for index, stopping, step in zip(indices, stop, steps, strict=True)
            if (stopping and sure and self.readings[index] and self.best(index)[1] < sure)
            or (not stopping and 0 < after <= step + 1)
            or (not stopping and unmeasured and not self.readings[index])
        ]
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
            if made is None and self.settings.column:
                made = self._calibrated()
            if made is None:
                from alignrl.posterior.inference import SCALE_FREE, FamilyPosterior
                from alignrl.posterior.models import focus_box

                made = FamilyPosterior(
                    focus_box(saturation_px=self.settings.saturation_px or None),
                    spec_relative=self.task.success.relative,
                    draws=self.settings.draws,
                    resample=resample_for(self.settings.draws),
                    far_noise=self.settings.far_noise,
                    probe_rule=self.settings.probe_rule,
                    **SCALE_FREE,
                )
            self._posteriors[index] = copy.copy(made)
        return self._posteriors[index]

    def _calibrated(self) -> FamilyPosterior:
        """The posterior over the column calibrated on the microscope (posterior_column,
        alignrl/posterior/calibration.py), in its own pixels, far readings trusted as the
        task says (posterior_far_noise: `alignrl calibrate` writes the far noise the
        column was fitted with)."""
        from alignrl.posterior.calibration import (
            COLUMN_FIELDS,
            calibrated_posterior,
        )

        column = dict(zip(COLUMN_FIELDS, self.settings.column, strict=True))
        return calibrated_posterior(
            column, self.task.success.relative, far_noise=self.settings.far_noise
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
        optimum = self.estimated(index, low, high) if self.ending.at_estimate else None
        if optimum is not None:
            target, fitted = np.clip(optimum, low, high), True
        if np.array_equal(target, setting):
            return None
        # From the narrowest reading's side; the posterior's setting is placed for an
        # approach from below (FamilyPosterior.final), whatever side that reading came from.
        from_below = fitted and self.ending.at == "posterior"
        side = np.ones_like(narrowest.side) if from_below else narrowest.side
        writes = self._arrive(index, target, setting, side, low, high)
        return EndPlan(index, writes, fitted, narrowest.width)

    def _arrive(
        self,
        index: int,
        target: np.ndarray,
        start: np.ndarray,
        side: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
    ) -> list[np.ndarray]:
        """The writes that take episode `index`'s knobs from `start` to `target`, each
        arriving from its `side`, past the target by backlash_overshoot x the interval first
        where needed (alignrl/apparatus/backlash.py, `arrival`)."""
        overshoot = self.ending.backlash_overshoot * (high - low)
        return arrival(target, start, side, overshoot, low, high, self.approach[index])

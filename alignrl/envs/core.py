"""Alignment episodes over N apparatus at once: the engine behind AlignmentEnv, DuelEnv and
VectorAlignmentEnv (one code path, so the three agree step for step).

An episode (seed section 4.3):
1. `begin`: the apparatus is reset (new scenario) and the success threshold fixed;
2. `misalign`: an action in (-1, 1)^k places each knob within the complexity window around
   the aligned setting, and the first image is acquired (acquisition 1);
3. `step`: each aligner action in (-1, 1)^(k+1) is k knob changes (scaled by the task's
   maximum step) and a stop component (stop when > 0). A change that would leave the
   interval is clipped at the bound and penalised. Each non-stop step acquires one image.
   The episode ends on stop or after `episode_steps` steps; the final reward
   scale x (edge width before - edge width after) is paid then. With the task's
   `verify_final`, "after" is one more image acquired at the final setting (as an
   evaluation's verification), not the last reading the aligner stopped at. With its
   ending at its narrowest reading (`Task.ending`, alignrl/envs/endings.py), the final
   setting is where the episode's narrowest reading was taken (written back without an
   acquisition, arriving from the side the reading was approached from:
   `backlash_overshoot`), as a classical autofocus ends (alignrl/envs/ending.py).

Observations are histories of H steps, oldest first, zero-padded at the front; each row is
FEATURES: [valid, knob settings (k, in [-1, 1]), log(width / ref), measured, last action
(k + 1), steps left (fraction), extras]. The reference width is the task's quality_ref_px,
or, with `quality_reference: first`, the episode's first measured width: then no feature
carries a unit (knobs and steps are fractions of the interval, readings ratios), and the same
network runs on any interval and any pixel scale. The extras are the task's further measures
(alignrl/envs/task.py): log(directional width / width) per orientation bin (4, clipped to
[-1, 1]) and tanh(wobble shift / ref) for x and y (2); a focus task has none, so its rows are
as they always were, unless its `fit_features` adds the three of a local focus-curve fit
(alignrl/envs/fit_features.py). The secret (optimum - setting, as a fraction of the
interval) goes to info["secret"], never into an observation.

What the engine asks of an apparatus beyond the protocol, it asks through the capabilities
of alignrl/apparatus/base.py: the optimum and the best width where it knows them
(`knows_optimum`, `knows_best_quality`), one batched query for a group that answers one
(`answers_batched`), and where a write really left the column (`reports_applied`).

Rewards are paid on the task's cost in px: the edge width, plus `wobble_weight` x the wobble
shift where the task wobbles. Knobs the task does not control are set to their optimum at the
start of an episode where the apparatus knows it (a stigmation episode starts in focus).

A measurement that fails (no edges, a driver fault) is a defined outcome: the row is marked
unmeasured, its width counts as the task's `no_edges_px`, and the episode goes on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    MeasurementError,
    answers_batched,
    knows_best_quality,
    knows_optimum,
    reports_applied,
)
from alignrl.apparatus.measures import measure_directional, measure_wobble
from alignrl.envs import rewards
from alignrl.envs.context import align_others
from alignrl.envs.ending import EndPlan, EpisodeEnds
from alignrl.envs.fit_features import FIT_FEATURES, fit_features
from alignrl.envs.task import Task

__all__ = ["AlignmentEpisodes", "EpisodeInfo", "align_others", "feature_layout", "known_optimum"]

QUALITY_LOG_RANGE = (-2.0, 4.0)  # log(width / ref) is clipped here: 0.35x to 55x the reference


def feature_layout(n_knobs: int, extras: int = 0) -> dict[str, slice]:
    """Column slices of one history row (`extras`: the task's extra_features)."""
    k = n_knobs
    layout = {
        "valid": slice(0, 1),
        "knobs": slice(1, 1 + k),
        "quality": slice(1 + k, 2 + k),
        "measured": slice(2 + k, 3 + k),
        "action": slice(3 + k, 4 + 2 * k),
        "steps_left": slice(4 + 2 * k, 5 + 2 * k),
    }
    if extras:
        layout["extras"] = slice(5 + 2 * k, 5 + 2 * k + extras)
    return layout


def observation_bounds(n_knobs: int, extras: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature (low, high) of a history row."""
    layout = feature_layout(n_knobs, extras)
    width = 5 + 2 * n_knobs + extras
    low, high = np.full(width, -1.0, np.float32), np.ones(width, np.float32)
    for name in ("valid", "measured", "steps_left"):
        low[layout[name]] = 0.0
    low[layout["quality"]], high[layout["quality"]] = QUALITY_LOG_RANGE
    return low, high


def known_optimum(unit: Apparatus, knobs: Sequence[str]) -> np.ndarray | None:
    """The optimum of `knobs` where `unit` can tell it (a simulator); None for a real column."""
    if not knows_optimum(unit):
        return None
    best = unit.optimum()
    return np.array([best[k] for k in knobs], float)


@dataclass
class EpisodeInfo:
    """What happened in one episode so far (per apparatus)."""

    acquisitions: int = 0
    steps: int = 0
    width_before_px: float = float("nan")
    width_px: float = float("nan")
    threshold_px: float = float("nan")
    out_of_bounds: int = 0
    failed_measurements: int = 0
    last_error: str = ""
    ended_at_fit: bool = False  # Ending.at_estimate: the way back went to the estimate


class AlignmentEpisodes:
    """N alignment episodes over N apparatus, stepped together (numpy over the batch)."""

    def __init__(self, apparatus: Sequence[Apparatus], task: Task, history: int = 8) -> None:
        if not apparatus:
            raise ValueError("AlignmentEpisodes needs at least one apparatus")
        if history < 1:
            raise ValueError(f"history length must be at least 1, got {history}")
        for unit in apparatus:
            task.check_apparatus(unit.knobs)
        self.apparatus = list(apparatus)
        self.task = task
        self.n = len(self.apparatus)
        self.k = len(task.knobs)
        self.history_length = history
        self.n_extra = task.extra_features
        self.layout = feature_layout(self.k, self.n_extra)
        self.n_features = 5 + 2 * self.k + self.n_extra
        self.low = np.zeros((self.n, self.k))  # (N, k): each knob's interval, its units
        self.high = np.ones((self.n, self.k))
        self.span = self.high - self.low
        self.max_step = np.zeros((self.n, self.k))  # largest change per action, its units
        self._knobs_read: list[object] = [None] * self.n  # the knobs mapping each row came from
        self._read_intervals(np.arange(self.n))
        # Per knob, the farthest a start may be from the optimum (Task.start_reach; inf: any).
        self.start_reach = np.array([task.start_reach.get(k, np.inf) for k in task.knobs])
        # Scenario simulators sharing one recording answer a whole batch in one numpy query
        # (BatchedQueries); its settings columns are the task's knobs, so they must be the
        # apparatus's, in order (and one write per reading: not approach_from_below).
        same_knobs = all(tuple(u.knobs) == tuple(task.knobs) for u in self.apparatus)
        self._batched = answers_batched(self.apparatus) and same_knobs
        self._batched &= not task.ending.approach_from_below
        self.history = np.zeros((self.n, history, self.n_features), np.float32)
        # The reading quality observations are relative to (Task.quality_reference): the
        # fixed quality_ref_px, or each episode's first measured width (unit-free).
        self.quality_ref = np.full(self.n, task.quality_ref_px)
        self.setting = np.zeros((self.n, self.k))  # knob values the env wrote, units
        self.aligned = np.zeros((self.n, self.k))
        self._optima = np.full((self.n, self.k), np.nan)  # replayed recordings' (fixed) optima
        self.width_before = np.full(self.n, np.nan)
        self.width = np.full(self.n, np.nan)
        self.directional = np.full((self.n, 4 * task.directional), np.nan)  # px per bin
        self.wobble = np.full((self.n, 2 * task.wobble), np.nan)  # shift (dx, dy) px
        self.cost_before = np.full(self.n, np.nan)  # px; what rewards are paid on
        self.cost = np.full(self.n, np.nan)
        self.threshold = np.full(self.n, np.nan)
        self.directional_threshold = np.full(self.n, np.nan)  # px, every bin
        self.bonus_threshold = np.full(self.n, np.nan)  # px; the success bonus is paid within
        self.best_width = np.full(self.n, np.nan)  # px at the optimum; NaN where unknown
        # Where the episodes end: the narrowest reading, the sides knobs were written from
        # (Task.ending: alignrl/envs/endings.py; visited as alignrl/envs/ending.py says).
        self.ends = EpisodeEnds(self.n, self.k, task)
        self.steps = np.zeros(self.n, np.int64)
        self.acquisitions = np.zeros(self.n, np.int64)
        self.active = np.zeros(self.n, bool)
        self.info = [EpisodeInfo() for _ in range(self.n)]
        self.complexity = 1.0

    def _read_intervals(self, indices: np.ndarray) -> None:
        """Each knob's interval and largest step of `indices`, read from the apparatus: an
        instrument family draws a column, with its own interval, at every reset (and a new
        knobs mapping with it: a mapping read before is not read again)."""
        for index in indices:
            knobs = self.apparatus[index].knobs
            if knobs is self._knobs_read[index]:
                continue
            self._knobs_read[index] = knobs
            self.low[index] = [float(knobs[k][0]) for k in self.task.knobs]
            self.high[index] = [float(knobs[k][1]) for k in self.task.knobs]
            self.max_step[index] = self.task.step_sizes(knobs)
        self.span[indices] = self.high[indices] - self.low[indices]

    def set_complexity(self, level: float) -> None:
        """Width of the misalignment window as a fraction of the interval, in (0, 1]."""
        if not 0.0 < level <= 1.0:
            raise ValueError(f"complexity level must be in (0, 1], got {level}")
        self.complexity = float(level)

    # --- episode start ------------------------------------------------------------------

    def begin(self, indices: np.ndarray, seeds: Sequence[int | None]) -> None:
        """Reset the apparatus of `indices` to new scenarios; remember their aligned settings
        and fix their success thresholds."""
        indices = np.asarray(indices, dtype=np.int64)
        for index, seed in zip(indices, seeds, strict=True):
            self.apparatus[index].reset(seed)
            align_others(self.apparatus[index], self.task.knobs, self.task.context, seed)
        self._settle(indices)

    def design(self, indices: np.ndarray, fractions: np.ndarray) -> None:
        """Make each apparatus of `indices` the column its row of `fractions` designs (one
        fraction of the family's box per designed parameter: alignrl.envs.design), then read
        its intervals, optimum, best width and thresholds again: between `begin` and
        `misalign`, where a designing misaligner moves."""
        indices = np.asarray(indices, dtype=np.int64)
        for index, row in zip(indices, np.asarray(fractions, float), strict=True):
            self.apparatus[index].design(row)  # type: ignore[attr-defined]
        self._settle(indices)

    def _settle(self, indices: np.ndarray) -> None:
        """What `begin` learns of the columns of `indices` as they now are: intervals, the
        aligned settings, the success thresholds; the episodes are cleared."""
        self._read_intervals(indices)
        self._reset_quality_ref(indices)
        best = np.full(len(indices), np.nan)
        for position, index in enumerate(indices):
            unit = self.apparatus[index]
            optimum = known_optimum(unit, self.task.knobs)
            self._optima[index] = np.nan if optimum is None else optimum
            if optimum is None:  # a real column has no secret: its setting as found counts
                found = unit.read()
                optimum = np.array([found[k] for k in self.task.knobs], float)
            self.aligned[index] = optimum
            if knows_best_quality(unit):
                best[position] = float(unit.best_quality())
        rule = self.task.success
        self.best_width[indices] = best
        self.threshold[indices] = [
            rule.threshold_px(None if np.isnan(value) else float(value)) for value in best
        ]
        self.directional_threshold[indices] = [
            self.task.directional_threshold_px(float(limit), float(value))
            for limit, value in zip(self.threshold[indices], best, strict=True)
        ]
        tighter = self.task.bonus_relative
        if tighter is None:
            self.bonus_threshold[indices] = self.threshold[indices]
        else:
            # Where the best width is unknown (a real column, an absolute spec), the margin
            # keeps its ratio to the spec: 1.10 / 1.15 of it for the focus task's defaults.
            margin = self.threshold[indices] * min(1.0, tighter / rule.relative)
            self.bonus_threshold[indices] = np.where(
                np.isfinite(best), np.fmin(self.threshold[indices], tighter * best), margin
            )
        self.history[indices] = 0.0
        self.steps[indices] = 0
        self.acquisitions[indices] = 0
        self.ends.restart(indices)
        for index in indices:
            self.info[index] = EpisodeInfo(threshold_px=float(self.threshold[index]))
        self.active[indices] = False

    def adopt(self, indices: np.ndarray) -> None:
        """Start episodes from the apparatus as it is now (no reset, no misalignment): how a
        trained aligner meets a column in an evaluation session or on a user's instrument.
        The first image is acquired here; success thresholds are left to the caller."""
        indices = np.asarray(indices, dtype=np.int64)
        self._read_intervals(indices)
        self._reset_quality_ref(indices)
        for index in indices:
            unit = self.apparatus[index]
            settings = unit.read()
            self.setting[index] = [settings[k] for k in self.task.knobs]
            self.aligned[index] = self.setting[index]
            optimum = known_optimum(unit, self.task.knobs)
            self._optima[index] = np.nan if optimum is None else optimum
            self.info[index] = EpisodeInfo()
        self.threshold[indices] = np.nan
        self.directional_threshold[indices] = np.nan
        self.bonus_threshold[indices] = np.nan
        self.best_width[indices] = np.nan
        self.history[indices] = 0.0
        self.steps[indices] = 0
        self.acquisitions[indices] = 0
        self.ends.restart(indices, found=self.setting[indices])
        widths = self._measure(indices)
        self.width_before[indices] = self.width[indices] = widths
        self.cost_before[indices] = self.cost[indices]
        self._record(indices, widths, np.zeros((len(indices), self.k + 1)))
        self.active[indices] = True

    def misaligner_observation(self, index: int) -> np.ndarray:
        """What a misaligner may know: aligned settings (in [-1, 1]) and the complexity."""
        aligned = 2.0 * (self.aligned[index] - self.low[index]) / self.span[index] - 1.0
        return np.append(np.clip(aligned, -1, 1), self.complexity).astype(np.float32)

    def misalign(self, indices: np.ndarray, actions: np.ndarray) -> None:
        """Place the knobs within the complexity window and acquire the first images."""
        indices = np.asarray(indices, dtype=np.int64)
        actions = np.clip(np.asarray(actions, float).reshape(len(indices), self.k), -1.0, 1.0)
        reach = np.minimum(self.complexity * self.span[indices], self.start_reach)
        window_low = np.maximum(self.low[indices], self.aligned[indices] - reach)
        window_high = np.minimum(self.high[indices], self.aligned[indices] + reach)
        start = window_low + 0.5 * (actions + 1.0) * (window_high - window_low)
        self.setting[indices] = np.clip(start, self.low[indices], self.high[indices])
        widths = self._measure(indices)
        self.width_before[indices] = self.width[indices] = widths
        self.cost_before[indices] = self.cost[indices]
        for position, index in enumerate(indices):
            info = self.info[index]
            info.width_before_px = info.width_px = float(widths[position])
            info.acquisitions = int(self.acquisitions[index])
        self._record(indices, widths, np.zeros((len(indices), self.k + 1)))
        self.active[indices] = True

    def misalignment_scores(self, indices: np.ndarray) -> np.ndarray:
        """What each start of `indices` is worth to the misaligner before the aligner acts
        (see `rewards.misalignment_score`); the aligner is charged the same."""
        indices = np.asarray(indices, dtype=np.int64)
        return rewards.misalignment_score(
            self.cost_before[indices],
            self.best_width[indices],
            self.task.final_reward_scale,
            self.task.final_reward_form,
        )

    # --- stepping -----------------------------------------------------------------------

    def step(self, indices: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply aligner actions to the active episodes `indices`; returns (reward, done)."""
        task = self.task
        actions = np.clip(np.asarray(actions, float).reshape(len(indices), self.k + 1), -1, 1)
        if not np.all(self.active[indices]):
            raise RuntimeError("step called on an episode that has ended: reset it first")
        # The ending, before the moves: which stop, where the posterior reads instead
        stop, probes = self.ends.before(
            indices, actions[:, self.k] > 0, self.steps[indices], self.low, self.high
        )
        reward = np.zeros(len(indices))
        moving = indices[~stop]
        if moving.size:
            change = task.knob_change(
                actions[~stop, : self.k], self.max_step[moving], self.span[moving]
            )
            target = self.setting[moving] + change
            for position in np.flatnonzero(np.isin(moving, list(probes))):
                target[position] = probes[int(moving[position])]
            clipped = np.clip(target, self.low[moving], self.high[moving])
            hit_bound = np.any(clipped != target, axis=1)
            reward[~stop] += rewards.bound_penalty(hit_bound, task.out_of_bounds_penalty)
            reward[~stop] -= task.acquisition_cost
            self.setting[moving] = clipped
            widths = self._measure(moving)
            self.width[moving] = widths
            self.steps[moving] += 1
            self._record(moving, widths, actions[~stop])
            for position, index in enumerate(moving):
                self.info[index].out_of_bounds += int(hit_bound[position])
        done = stop | (self.steps[indices] >= task.episode_steps)
        # The ending, after the readings: which are done, and how each finished one ends
        done, stop, plans = self.ends.after(
            indices, done, stop, actions[:, : self.k], *self._limits
        )
        finished = indices[done]
        self._end(plans)
        if task.ending.final_move and np.any(stop):  # the last moves, as planned
            hit_bound = np.array([plan.hit_bound for plan in plans])
            reward[stop] += rewards.bound_penalty(hit_bound, task.out_of_bounds_penalty)
        if task.ending.stop_at_best and finished.size:  # the way back: its reading stands
            self.cost[finished] = self._costs(finished)
        if task.verify_final and finished.size:
            # One more image where the aligner left the column: the verification an
            # evaluation takes. Rewards and success are judged on it, not on the reading the
            # aligner chose to stop at; the history is over, so it records no row.
            self._measure(finished)
        reward[done] += rewards.final_reward(
            self.cost_before[finished],
            self.cost[finished],
            task.final_reward_scale,
            task.final_reward_form,
        )
        if task.success_bonus:
            within = self._within(finished, self.bonus_threshold[finished])
            reward[done] += rewards.success_bonus(within, task.success_bonus)
        self.active[finished] = False
        for index in indices:
            info = self.info[index]
            info.steps = int(self.steps[index])
            info.acquisitions = int(self.acquisitions[index])
            info.width_px = float(self.width[index])
        return reward, done

    @property
    def _limits(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every episode's setting, interval and largest step (its units), as the ending
        plans with them."""
        return self.setting, self.low, self.high, self.max_step

    def stop_origins(self, indices: np.ndarray) -> np.ndarray:
        """(len(indices), k), units: where a stopping action's move starts (Task.ending's
        final_move: EpisodeEnds.origins)."""
        return self.ends.origins(indices, self.setting, self.low, self.high)

    def _end(self, plans: list[EndPlan]) -> None:
        """Make the writes each finished episode ends with (EpisodeEnds.after), no
        acquisition: a last move, or the way back to the narrowest reading or an estimate,
        whose reading then stands as the final one unless the task verifies. A write the
        apparatus refuses leaves the knobs where they got to (the setting shows where), the
        last reading standing, and the error in the info."""
        for plan in plans:
            index = plan.index
            try:
                for setting in plan.writes:
                    self.setting[index] = self._write(index, setting)
            except ApparatusError as error:
                self.info[index].last_error = str(error)
            else:
                if not np.isnan(plan.width):  # the way back: that reading stands
                    self.width[index] = plan.width
                    self.info[index].ended_at_fit = plan.fitted
            self.info[index].out_of_bounds += int(plan.hit_bound)

    def _costs(self, indices: np.ndarray) -> np.ndarray:
        """The task's cost (px) of the latest measurement of `indices`: the width, plus the
        weighted wobble shift; a failed measurement counts as the task's no-edges width."""
        cost = self.width[indices].copy()
        if self.task.wobble:
            cost += self.task.wobble_weight * np.hypot(*self.wobble[indices].T)
        return np.where(np.isfinite(cost), cost, self.task.no_edges_px)

    def _within(self, indices: np.ndarray, width_threshold: np.ndarray) -> np.ndarray:
        """Whether every measured quality of `indices` is within spec, the width within
        `width_threshold` (Task.within_spec)."""
        return self.task.within_spec(
            self.width[indices],
            width_threshold,
            self.directional[indices],
            self.directional_threshold[indices],
            self.wobble[indices],
        )

    def successes(self) -> np.ndarray:
        """Whether each slot's latest measurement meets every spec of the task."""
        return self._within(np.arange(self.n), self.threshold)

    def secrets(self) -> np.ndarray:
        """`secret` of every slot, (N, k): each apparatus's own optimum (a varied replay
        moves it off the recorded one). Replayed recordings keep their optimum through an
        episode: theirs is read once, at its start."""
        if self._batched:
            return ((self._optima - self.setting) / self.span).astype(np.float32)
        return np.stack([self.secret(index) for index in range(self.n)])

    def secrets_known(self) -> np.ndarray:
        """(N,) bool: whether each slot's apparatus can tell its optimum, so that `secret` is
        the true one (a real column cannot: its secret is zeros)."""
        return np.array([knows_optimum(unit) for unit in self.apparatus])

    def positions(self) -> np.ndarray:
        """(N, k): each knob's setting as a fraction of its interval (0 low, 1 high)."""
        return (self.setting - self.low) / self.span

    def success(self, index: int) -> bool:
        return bool(self.successes()[index])

    def secret(self, index: int) -> np.ndarray:
        """(optimum - setting) / interval width per knob: for critics, never for policies."""
        target = known_optimum(self.apparatus[index], self.task.knobs)
        if target is None:
            return np.zeros(self.k, np.float32)
        return ((target - self.setting[index]) / self.span[index]).astype(np.float32)

    def observation(self, index: int) -> np.ndarray:
        return self.history[index].copy()

    # --- measurement and history --------------------------------------------------------

    def _measure(self, indices: np.ndarray) -> np.ndarray:
        """Write the settings of `indices` and take the task's measures: one image each (two
        more for a wobble). Returns the widths, NaN where a measure failed; the directional
        widths, wobble shifts and costs of `indices` are updated alongside."""
        self.acquisitions[indices] += self.task.acquisitions_per_step
        if self._batched:
            units = [self.apparatus[i] for i in indices]
            widths = units[0].measure_batch(units, self.setting[indices])  # type: ignore[attr-defined]
            for index in indices[~np.isfinite(widths)]:
                self.info[index].failed_measurements += 1
                self.info[index].last_error = "no edges"
            self.width[indices] = widths
            self.cost[indices] = self._costs(indices)
            return widths
        widths = np.full(len(indices), np.nan)
        self.directional[indices] = np.nan
        self.wobble[indices] = np.nan
        for position, index in enumerate(indices):
            unit = self.apparatus[index]
            try:
                limits = self.low[index], self.high[index]
                for setting in self.ends.writes_to(index, self.setting[index], *limits):
                    self.setting[index] = self._write(index, setting)
                width, directional, shift = self._take_measures(unit)
            except (MeasurementError, ApparatusError) as error:
                # A defined outcome on real hardware: no edges far from focus, or a driver
                # fault. The episode goes on with an unmeasured row.
                self.info[index].failed_measurements += 1
                self.info[index].last_error = str(error)
                continue
            widths[position] = width
            self.directional[index] = directional
            self.wobble[index] = shift
        self.width[indices] = widths
        self.cost[indices] = self._costs(indices)
        return widths

    def _write(self, index: int, target: np.ndarray) -> np.ndarray:
        """Write the task's knobs of apparatus `index` to `target` (its units) and return
        where they really are: a safety shield may have clamped the write, or (dry run) not
        sent it, and the history must show where the column is."""
        unit = self.apparatus[index]
        target = np.asarray(target, float)
        unit.write(dict(zip(self.task.knobs, target.tolist(), strict=True)))
        if reports_applied(unit):
            applied = unit.applied_setting()
            target = np.array([applied[k] for k in self.task.knobs], float)
        self.ends.wrote(index, target)
        return target

    def _take_measures(self, unit: Apparatus) -> tuple[float, np.ndarray, np.ndarray]:
        """(width px, directional widths px, wobble shift px) of one apparatus; the arrays
        are empty where the task does not take that measure."""
        task = self.task
        if task.directional:
            width, directional = measure_directional(unit)
        else:
            width, directional = float(unit.measure()), np.empty(0)
        shift = (
            measure_wobble(unit, task.wobble_amplitude(unit.knobs)) if task.wobble else np.empty(0)
        )
        return width, directional, shift

    def _reset_quality_ref(self, indices: np.ndarray) -> None:
        """A new episode's reference width: fixed, or (unit-free) none until its first
        measured width."""
        relative = self.task.quality_reference == "first"
        self.quality_ref[indices] = np.nan if relative else self.task.quality_ref_px

    def _record(self, indices: np.ndarray, widths: np.ndarray, actions: np.ndarray) -> None:
        layout = self.layout
        rows = np.zeros((len(indices), self.n_features), np.float32)
        rows[:, layout["valid"]] = 1.0
        positions = (self.setting[indices] - self.low[indices]) / self.span[indices]
        rows[:, layout["knobs"]] = np.clip(2.0 * positions - 1.0, -1.0, 1.0)
        measured = np.isfinite(widths)
        if self.task.ending.notes_readings:
            opening = self.steps[indices] == 0
            self.ends.note(indices, self.setting[indices], widths, measured, opening, positions)
        reference = self.quality_ref[indices]
        first = measured & ~np.isfinite(reference)  # the episode's first measured width
        reference[first] = widths[first]
        self.quality_ref[indices] = reference
        with np.errstate(invalid="ignore", divide="ignore"):
            quality = np.log(np.where(measured, widths, np.nan) / reference)
        # Unmeasured rows read as the worst quality, flagged by measured = 0.
        quality = np.where(measured, quality, QUALITY_LOG_RANGE[1])
        rows[:, layout["quality"]] = np.clip(quality, *QUALITY_LOG_RANGE)[:, None]
        rows[:, layout["measured"]] = measured[:, None]
        rows[:, layout["action"]] = actions
        left = 1.0 - self.steps[indices] / self.task.episode_steps
        rows[:, layout["steps_left"]] = left[:, None]
        measures = self.task.measure_features
        if measures:
            extras = layout["extras"]
            rows[:, extras.start : extras.start + measures] = self._extra_features(
                indices, measured
            )
        # Oldest first: shift the window left by one and append the new row.
        self.history[indices, :-1] = self.history[indices, 1:]
        self.history[indices, -1] = rows
        if self.task.fit_features:
            # Read from the window with its new row (alignrl/envs/fit_features.py).
            window = self.history[indices]
            step = 2.0 * self.max_step[indices, 0] / self.span[indices, 0]
            self.history[indices, -1, layout["extras"].stop - FIT_FEATURES :] = fit_features(
                window[:, :, layout["knobs"].start],
                window[:, :, layout["quality"].start],
                window[:, :, layout["valid"].start] * window[:, :, layout["measured"].start],
                step,
                self.task.fit_window,
            )

    def _extra_features(self, indices: np.ndarray, measured: np.ndarray) -> np.ndarray:
        """Directional widths as log(w_bin / w) in [-1, 1], wobble shifts as tanh(shift /
        ref); zeros in an unmeasured row."""
        parts = []
        with np.errstate(invalid="ignore", divide="ignore"):
            if self.task.directional:
                ratio = np.log(self.directional[indices] / self.width[indices, None])
                parts.append(np.clip(ratio, -1.0, 1.0))
            if self.task.wobble:
                parts.append(np.tanh(self.wobble[indices] / self.task.wobble_ref_px))
        extras = np.concatenate(parts, axis=1)
        return np.where(measured[:, None] & np.isfinite(extras), extras, 0.0)

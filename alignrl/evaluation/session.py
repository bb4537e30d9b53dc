"""Evaluation sessions (seed sections 6.2-6.3): a controller aligns N misaligned scenarios,
and an image acquired after each alignment is compared with the spec threshold.

Scenario i of a session with seed S:
1. the apparatus is reset with `scenario_seed(S, i)` (a new specimen area, a new optimum;
   a scenario simulator takes row i of its split, so the scenarios are distinct recordings);
2. the knobs the task does not control are set to their optimum where the apparatus knows
   it (as in training episodes, alignrl/envs/core.py: a stigmation session starts in focus);
3. every task knob starts anywhere in its interval, uniformly, drawn from a generator of the
   same scenario seed (its own stream): identical for every controller evaluated with seed S;
4. the controller aligns through a `CountingApparatus` (its acquisitions are counted, every
   image: a wobble is two; at most `budget` of them);
5. the verification: the task's measures are taken where the controller left the column, on
   the apparatus itself (not counted in the controller's acquisitions): the edge width, and
   where the task takes them the directional widths (same image) and the wobble shift. Every
   measure must be within its spec (`Task.within_spec`): the width within a relative
   threshold, `task.success.relative` x the best edge width the apparatus can reach
   (`best_quality()`, simulated apparatus), or the absolute `spec_px`; every directional
   width within `task.directional_threshold_px`; the wobble shift within
   `task.wobble_spec_px`. A measure that fails (no edges, no correlation) is a failure.

Pure logic: no printing, no files; `on_scenario` lets a caller show progress.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    knows_best_quality,
    knows_optimum,
    offers_wobble,
)
from alignrl.apparatus.measures import WOBBLE_KNOB, measure_directional, measure_wobble
from alignrl.apparatus.recorder import scenario_seed
from alignrl.envs.context import align_others
from alignrl.envs.task import DIRECTIONAL_BINS, SuccessRule, Task
from alignrl.evaluation.controllers import (
    Acquisition,
    BudgetExhausted,
    Controller,
    CountingApparatus,
    TaskController,
    check_controller,
    run_controller,
)

__all__ = [
    "DEFAULT_BUDGET",
    "TEST_SEED",
    "VALIDATION_SEED",
    "ScenarioResult",
    "SessionResult",
    "check_session_apparatus",
    "default_budget",
    "reset_scenario",
    "run_session",
    "start_setting",
    "verify_task",
]

DEFAULT_BUDGET = 50  # acquisitions per alignment; an operator gives up long before
START_STREAM = 1  # second entropy word of the start-setting generator (see start_setting)
# The session seeds of training runs and leagues, far from the training envs' (seed * 1000 +
# starts): validation sessions (VALIDATION_SEED) choose best checkpoints and champions; the test
# session (TEST_SEED) reports what they chose and chooses nothing (issue 23).
VALIDATION_SEED = 1_000_000
TEST_SEED = 2_000_000


@dataclass(frozen=True)
class ScenarioResult:
    """One alignment of a session. Settings in the knobs' units (volts, percent,
    micrometres), widths and shifts in px; mappings are keyed by the task's knobs, in order.

    A one-knob record also answers `start`, `final_setting`, `optimum`, `optimum_error` and
    `trajectory` for that knob, as focus records always have.
    """

    index: int
    seed: int  # the apparatus reset seed
    starts: Mapping[str, float]
    final_settings: Mapping[str, float]
    acquisitions: int  # the controller's, without the verification
    budget_exhausted: bool
    final_width_px: float | None  # the verification image; None: it had no edges
    threshold_px: float
    success: bool
    # Where the column's optimum was when the controller stopped (simulated only).
    optima: Mapping[str, float] | None
    shots: tuple[Acquisition, ...]  # every acquisition of the controller, in order
    # The verification's other measures, where the task takes them: the four directional
    # widths (None: not taken, or failed) and their common threshold; the wobble shift.
    final_directional_px: tuple[float, ...] | None = None
    directional_threshold_px: float | None = None
    final_wobble_px: tuple[float, float] | None = None

    @property
    def knobs(self) -> tuple[str, ...]:
        return tuple(self.starts)

    def _knob(self) -> str:
        if len(self.starts) != 1:
            raise ValueError(
                f"this alignment moved {len(self.starts)} knobs ({', '.join(self.starts)}): "
                "use starts, final_settings and optima"
            )
        return next(iter(self.starts))

    @property
    def start(self) -> float:
        return self.starts[self._knob()]

    @property
    def final_setting(self) -> float:
        return self.final_settings[self._knob()]

    @property
    def optimum(self) -> float | None:
        return None if self.optima is None else self.optima[self._knob()]

    @property
    def optimum_error(self) -> float | None:
        """final setting - optimum, where the apparatus knows its optimum."""
        return None if self.optimum is None else self.final_setting - self.optimum

    def optimum_errors(self) -> dict[str, float] | None:
        """final setting - optimum of every knob, where the apparatus knows its optimum."""
        if self.optima is None:
            return None
        return {knob: self.final_settings[knob] - self.optima[knob] for knob in self.starts}

    @property
    def trajectory(self) -> tuple[tuple[float, float | None], ...]:
        """(setting, width or None) of the one knob, per acquisition."""
        knob = self._knob()
        return tuple((float(shot.settings[knob]), shot.width_px) for shot in self.shots)

    @property
    def final_wobble_shift_px(self) -> float | None:
        """|wobble shift| of the verification; None where not measured."""
        return None if self.final_wobble_px is None else math.hypot(*self.final_wobble_px)


class AcquisitionStatistics:
    """The median and 90th percentile of `acquisitions()` (one value per alignment): a
    session's, or a set's pooled over its instruments."""

    def acquisitions(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def median_acquisitions(self) -> float:
        return float(np.median(self.acquisitions()))

    @property
    def p90_acquisitions(self) -> float:
        return float(np.percentile(self.acquisitions(), 90))


@dataclass(frozen=True)
class SessionResult(AcquisitionStatistics):
    """All alignments of a session and their summary statistics."""

    controller: str
    task: Task
    seed: int
    budget: int
    records: tuple[ScenarioResult, ...]
    seconds: float  # wall time of the whole session

    @property
    def knobs(self) -> tuple[str, ...]:
        return self.task.knobs

    @property
    def knob(self) -> str:
        """The aligned knob of a one-knob session."""
        if len(self.task.knobs) != 1:
            raise ValueError(f"task {self.task.name!r} aligns {len(self.task.knobs)} knobs")
        return self.task.knobs[0]

    @property
    def scenarios(self) -> int:
        return len(self.records)

    @property
    def alignments(self) -> int:
        """Alignments run: the scenarios (a set result's `alignments` pools its instruments)."""
        return len(self.records)

    @property
    def successes(self) -> int:
        return sum(record.success for record in self.records)

    def acquisitions(self) -> np.ndarray:
        return np.array([record.acquisitions for record in self.records], dtype=np.float64)

    @property
    def budget_exhausted(self) -> int:
        return sum(record.budget_exhausted for record in self.records)

    @property
    def unmeasured(self) -> int:
        """Verifications that found no edges."""
        return sum(record.final_width_px is None for record in self.records)

    def final_widths(self) -> np.ndarray:
        """Edge widths (px) of the verification images that had edges."""
        widths = [r.final_width_px for r in self.records if r.final_width_px is not None]
        return np.array(widths, dtype=np.float64)

    def final_width_stats(self) -> dict[str, float | None]:
        """median, p90 and max of the measured final edge widths (px); None if none."""
        return _stats(self.final_widths())

    @property
    def median_threshold_px(self) -> float:
        return float(np.median([record.threshold_px for record in self.records]))

    def optimum_error_stats(self) -> dict[str, float | None] | None:
        """median, p90 and max of |final setting - optimum| of a one-knob session; None
        where unknown, and for several knobs (see optimum_errors_stats)."""
        if len(self.task.knobs) != 1:
            return None
        return self.optimum_errors_stats().get(self.knob)

    def optimum_errors_stats(self) -> dict[str, dict[str, float | None]]:
        """Per knob: median, p90 and max of |final setting - optimum|, in the knob's units;
        empty where the apparatus does not know its optimum."""
        errors = [e for r in self.records if (e := r.optimum_errors()) is not None]
        if not errors:
            return {}
        return {
            knob: _stats(np.abs(np.array([e[knob] for e in errors], dtype=np.float64)))
            for knob in self.task.knobs
        }

    def final_wobble_stats(self) -> dict[str, float | None] | None:
        """median, p90 and max of the verifications' |wobble shift| (px), over those that
        measured one; None where the task does not wobble."""
        if not self.task.wobble:
            return None
        shifts = [r.final_wobble_shift_px for r in self.records]
        return _stats(np.array([s for s in shifts if s is not None], dtype=np.float64))

    def final_directional_stats(self) -> dict[str, float | None] | None:
        """median, p90 and max of each verification's widest directional width (px), over
        those measured; None where the task does not measure directional widths."""
        if not self.task.directional:
            return None
        widest = [max(r.final_directional_px) for r in self.records if r.final_directional_px]
        return _stats(np.array(widest, dtype=np.float64))

    @property
    def unmeasured_wobbles(self) -> int:
        """Verifications whose wobble failed (the task wobbles)."""
        return self.task.wobble * sum(r.final_wobble_px is None for r in self.records)

    @property
    def unmeasured_directional(self) -> int:
        """Verifications without directional widths (the task measures them)."""
        return self.task.directional * sum(not r.final_directional_px for r in self.records)

    @property
    def median_directional_threshold_px(self) -> float | None:
        limits = [r.directional_threshold_px for r in self.records]
        if not self.task.directional or any(limit is None for limit in limits):
            return None
        return float(np.median(limits))


def _stats(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {"median": None, "p90": None, "max": None}
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "max": float(values.max()),
    }


def default_budget(task: Task) -> int:
    """The acquisition budget of a session of `task` unless one is given: DEFAULT_BUDGET, or
    the most acquisitions one of the task's episodes can take where that is more (a column
    episode: 21 measurements of 3 images), so that no trained aligner is stopped before its
    own step limit. Focus, stigmation and aperture sessions keep 50."""
    return max(DEFAULT_BUDGET, task.acquisitions_per_step * (task.episode_steps + 1))


def start_setting(seed: int, scenario: int, intervals: Sequence[tuple[float, float]]) -> np.ndarray:
    """The misaligned start of scenario `scenario`: each knob uniform over its interval.

    Its generator is seeded with (scenario seed, START_STREAM), not the scenario seed alone:
    an apparatus that draws its optimum as the first uniform of default_rng(reset seed)
    (SyntheticSEM does) would otherwise see its start tied to its optimum. The knobs take the
    generator's uniforms in order, so the first knob's start is the one a one-knob session
    always drew (focus results stay as they were).
    """
    generator = np.random.default_rng([scenario_seed(seed, scenario), START_STREAM])
    bounds = np.asarray(intervals, dtype=np.float64).reshape(-1, 2)
    return generator.uniform(bounds[:, 0], bounds[:, 1])


def reset_scenario(apparatus: Apparatus, seed: int, index: int) -> int:
    """Reset for scenario `index` of a session; returns the reset seed.

    A scenario simulator walks the rows of its split in order (wrapping around), so a
    session of 100 on the 200 held-out rows aligns 100 different recordings; any other
    apparatus is reset with the scenario seed.
    """
    reset_seed = scenario_seed(seed, index)
    rows = getattr(apparatus, "indices", None)
    reset_to = getattr(apparatus, "reset_to", None)
    if callable(reset_to) and rows is not None and len(rows):
        reset_to(int(rows[index % len(rows)]), reset_seed)
    else:
        apparatus.reset(reset_seed)
    return reset_seed


def _best_quality(apparatus: Apparatus) -> Callable[[], float] | None:
    return apparatus.best_quality if knows_best_quality(apparatus) else None


def check_session_apparatus(apparatus: Apparatus, task: Task, spec_px: float | None = None) -> None:
    """ValueError where a session of `task` cannot run on `apparatus`: a task knob it lacks, a
    wobble it cannot take, or no spec (`spec_px` or the task's absolute one) on an apparatus
    that cannot say its best edge width. A session checks this before its first alignment; a
    training run, before it starts (alignrl/training.py)."""
    task.check_apparatus(apparatus.knobs)
    if task.wobble and not (WOBBLE_KNOB in apparatus.knobs or offers_wobble(apparatus)):
        raise ValueError(
            f"task {task.name!r} measures the wobble, which swings {WOBBLE_KNOB!r}: this "
            "apparatus has neither that knob nor a measure_wobble() of its own"
        )
    if spec_px is None and task.success.absolute_px is None and _best_quality(apparatus) is None:
        raise ValueError(
            "this apparatus cannot tell the best edge width it can reach (it has no "
            "best_quality()), so a relative success threshold is impossible: give an "
            "absolute spec with --spec-px (edge width in px, e.g. from the datasheet)"
        )


def _check_spec_reachable(apparatus: Apparatus, seed: int, scenarios: int, spec_px: float) -> None:
    """Refuse an absolute spec sharper than the apparatus can focus in some scenario.

    Only a simulated apparatus knows its best edge width; each scenario is reset once here
    (cheap) and again when it runs, with the same seed, so the session is unchanged.
    """
    best_quality = _best_quality(apparatus)
    if best_quality is None:
        return
    best = []
    for index in range(scenarios):
        reset_scenario(apparatus, seed, index)
        best.append(float(best_quality()))
    unreachable = sum(value > spec_px for value in best)
    if unreachable:
        low, high = f"{min(best):.3g}", f"{max(best):.3g}"
        reach = f"{low} px" if low == high else f"{low} to {high} px"
        raise ValueError(
            f"--spec-px {spec_px:g} px is sharper than this apparatus can focus in "
            f"{unreachable} of {scenarios} scenarios (best edge width {reach}): no controller "
            f"could meet it; give at least {high} px, or leave --spec-px out for the "
            "relative threshold"
        )


def run_session(
    controller: Controller | TaskController,
    apparatus: Apparatus,
    task: Task,
    scenarios: int = 100,
    seed: int = 0,
    spec_px: float | None = None,
    budget: int | None = None,
    on_scenario: Callable[[ScenarioResult], None] | None = None,
) -> SessionResult:
    """Run `scenarios` alignments of `controller` on `apparatus` (see the module docstring),
    each with at most `budget` acquisitions (default: `default_budget(task)`).

    ValueError, before any alignment, for: a task knob the apparatus lacks, a wobble the
    apparatus cannot take, a controller that cannot align the task (a one-knob controller on
    a task of several), scenarios or budget below 1, spec_px not positive or sharper than the
    apparatus can focus, and no spec_px on an apparatus that cannot say its best edge width.
    """
    check_session_apparatus(apparatus, task, spec_px)
    check_controller(controller, task)
    if scenarios < 1:
        raise ValueError(f"an evaluation session needs at least 1 scenario, got {scenarios}")
    budget = default_budget(task) if budget is None else budget
    if budget < 1:
        raise ValueError(f"the acquisition budget must be at least 1, got {budget}")
    rule = task.success
    if spec_px is not None:
        if not (math.isfinite(spec_px) and spec_px > 0):
            raise ValueError(f"--spec-px must be a positive edge width in px, got {spec_px}")
        rule = dataclasses.replace(rule, absolute_px=float(spec_px))
        _check_spec_reachable(apparatus, seed, scenarios, float(spec_px))
    started = time.perf_counter()
    records = []
    for index in range(scenarios):
        record = _run_scenario(controller, apparatus, task, rule, seed, index, budget)
        records.append(record)
        if on_scenario is not None:
            on_scenario(record)
    return SessionResult(
        controller=controller.name,
        task=task,
        seed=seed,
        budget=budget,
        records=tuple(records),
        seconds=time.perf_counter() - started,
    )


def _run_scenario(
    controller: Controller | TaskController,
    apparatus: Apparatus,
    task: Task,
    rule: SuccessRule,
    seed: int,
    index: int,
    budget: int,
) -> ScenarioResult:
    """Scenario `index`: reset, knobs outside the task aligned, start, align, verify, judge."""
    reset_seed = reset_scenario(apparatus, seed, index)
    # Sessions start the way training episodes do (a stage's context drawn from the scenario).
    align_others(apparatus, task.knobs, task.context, reset_seed)
    best_quality = _best_quality(apparatus)
    best_px = float(best_quality()) if best_quality is not None else None
    threshold = rule.threshold_px(best_px)  # an absolute spec ignores best_px
    known = apparatus.optimum() if knows_optimum(apparatus) and task.start_reach else None
    start = start_setting(seed, index, task.start_intervals(apparatus.knobs, known))
    starts = dict(zip(task.knobs, start.tolist(), strict=True))
    apparatus.write(starts)
    counting = CountingApparatus(apparatus, budget)
    exhausted = False
    try:
        run_controller(controller, counting, task, budget)
    except BudgetExhausted:
        exhausted = True  # the alignment ends where the knobs are
    settings = apparatus.read()
    final_settings = {knob: float(settings[knob]) for knob in task.knobs}
    optima = (
        {knob: float(value) for knob, value in apparatus.optimum().items() if knob in task.knobs}
        if knows_optimum(apparatus)
        else None
    )
    width, directional, shift = verify_task(apparatus, task)
    directional_threshold = (
        task.directional_threshold_px(threshold, best_px) if task.directional else None
    )
    success = task.within_spec(
        np.array([np.nan if width is None else width]),
        np.array([threshold]),
        np.full((1, DIRECTIONAL_BINS), np.nan) if directional is None else directional[None],
        np.array([np.nan if directional_threshold is None else directional_threshold]),
        np.full((1, 2), np.nan) if shift is None else shift[None],
    )[0]
    return ScenarioResult(
        index=index,
        seed=reset_seed,
        starts=starts,
        final_settings=final_settings,
        acquisitions=counting.acquisitions,
        budget_exhausted=exhausted,
        final_width_px=width,
        threshold_px=float(threshold),
        success=bool(success),
        optima=optima,
        shots=tuple(counting.trajectory),
        final_directional_px=None if directional is None else tuple(directional.tolist()),
        directional_threshold_px=directional_threshold,
        final_wobble_px=None if shift is None else (float(shift[0]), float(shift[1])),
    )


def verify_task(
    apparatus: Apparatus, task: Task
) -> tuple[float | None, np.ndarray | None, np.ndarray | None]:
    """The task's measures where the controller left the column, on the apparatus itself
    (not counted): (width px, directional widths px, wobble shift px), each None where the
    task does not take it or it failed. Unlike an episode's measurement (envs/core.py), a
    failed measure here spoils only itself, so that the record shows which one failed."""
    try:
        if task.directional:
            width, directional = measure_directional(apparatus)
        else:
            width, directional = float(apparatus.measure()), None
    except ApparatusError:
        width, directional = None, None  # no edges where it stopped: not aligned
    shift = None
    if task.wobble:
        try:
            shift = measure_wobble(apparatus, task.wobble_amplitude(apparatus.knobs))
        except ApparatusError:
            shift = None
    return width, directional, shift

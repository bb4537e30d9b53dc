"""Evaluation sessions (seed sections 6.2-6.3): a controller aligns N misaligned scenarios,
and an image acquired after each alignment is compared with the spec threshold.

Scenario i of a session with seed S:
1. the apparatus is reset with `scenario_seed(S, i)` (a new specimen area, a new optimum;
   a scenario simulator takes row i of its split, so the scenarios are distinct recordings);
2. the knob starts anywhere in its interval, uniformly, drawn from a generator of the same
   scenario seed (its own stream): identical for every controller evaluated with seed S;
3. the controller aligns through a `CountingApparatus` (its acquisitions are counted, at most
   `budget` of them);
4. one more image, the verification, is acquired where the controller left the knob and
   its edge width (px) compared with the threshold: a relative one, `task.success.relative`
   x the best edge width the apparatus can reach (`best_quality()`, simulated apparatus), or
   the absolute `spec_px`. A verification without edges is a failure. It is not counted in
   the controller's acquisitions.

Pure logic: no printing, no files; `on_scenario` lets a caller show progress.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.apparatus.recorder import scenario_seed
from alignrl.envs.task import SuccessRule, Task
from alignrl.evaluation.controllers import BudgetExhausted, Controller, CountingApparatus

__all__ = ["DEFAULT_BUDGET", "ScenarioResult", "SessionResult", "run_session", "start_setting"]

DEFAULT_BUDGET = 50  # acquisitions per alignment; an operator gives up long before
START_STREAM = 1  # second entropy word of the start-setting generator (see start_setting)


@dataclass(frozen=True)
class ScenarioResult:
    """One alignment of a session. Settings in the knob's units (volts), widths in px."""

    index: int
    seed: int  # the apparatus reset seed
    start: float
    final_setting: float
    acquisitions: int  # the controller's, without the verification image
    budget_exhausted: bool
    final_width_px: float | None  # the verification image; None: it had no edges
    threshold_px: float
    success: bool
    optimum: float | None  # where the focus was when the controller stopped (simulated only)
    trajectory: tuple[tuple[float, float | None], ...]  # (setting, width or None) per image

    @property
    def optimum_error(self) -> float | None:
        """final setting - optimum, where the apparatus knows its optimum."""
        return None if self.optimum is None else self.final_setting - self.optimum


@dataclass(frozen=True)
class SessionResult:
    """All alignments of a session and their summary statistics."""

    controller: str
    knob: str
    seed: int
    budget: int
    records: tuple[ScenarioResult, ...]
    seconds: float  # wall time of the whole session

    @property
    def scenarios(self) -> int:
        return len(self.records)

    @property
    def successes(self) -> int:
        return sum(record.success for record in self.records)

    def acquisitions(self) -> np.ndarray:
        return np.array([record.acquisitions for record in self.records], dtype=np.float64)

    @property
    def median_acquisitions(self) -> float:
        return float(np.median(self.acquisitions()))

    @property
    def p90_acquisitions(self) -> float:
        return float(np.percentile(self.acquisitions(), 90))

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
        """median, p90 and max of |final setting - optimum|; None where unknown."""
        errors = [r.optimum_error for r in self.records if r.optimum_error is not None]
        if not errors:
            return None
        return _stats(np.abs(np.array(errors, dtype=np.float64)))


def _stats(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {"median": None, "p90": None, "max": None}
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "max": float(values.max()),
    }


def start_setting(seed: int, scenario: int, interval: tuple[float, float]) -> float:
    """The misaligned start of scenario `scenario`: uniform over the knob's interval.

    Its generator is seeded with (scenario seed, START_STREAM), not the scenario seed alone:
    an apparatus that draws its optimum as the first uniform of default_rng(reset seed)
    (SyntheticSEM does) would otherwise see its start tied to its optimum.
    """
    generator = np.random.default_rng([scenario_seed(seed, scenario), START_STREAM])
    low, high = interval
    return float(generator.uniform(low, high))


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
    best = getattr(apparatus, "best_quality", None)
    return best if callable(best) else None


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
    controller: Controller,
    apparatus: Apparatus,
    task: Task,
    scenarios: int = 100,
    seed: int = 0,
    spec_px: float | None = None,
    budget: int = DEFAULT_BUDGET,
    on_scenario: Callable[[ScenarioResult], None] | None = None,
) -> SessionResult:
    """Run `scenarios` alignments of `controller` on `apparatus` (see the module docstring).

    ValueError, before any alignment, for: a task knob the apparatus lacks, a task with more
    than one knob, scenarios or budget below 1, spec_px not positive or sharper than the
    apparatus can focus, and no spec_px on an apparatus that cannot say its best edge width.
    """
    task.check_apparatus(apparatus.knobs)
    if len(task.knobs) != 1:
        raise ValueError(
            f"task {task.name!r} has {len(task.knobs)} knobs; evaluation sessions align one"
        )
    if scenarios < 1:
        raise ValueError(f"an evaluation session needs at least 1 scenario, got {scenarios}")
    if budget < 1:
        raise ValueError(f"the acquisition budget must be at least 1, got {budget}")
    knob = task.knobs[0]
    rule = task.success
    if spec_px is not None:
        if not (math.isfinite(spec_px) and spec_px > 0):
            raise ValueError(f"--spec-px must be a positive edge width in px, got {spec_px}")
        rule = dataclasses.replace(rule, absolute_px=float(spec_px))
        _check_spec_reachable(apparatus, seed, scenarios, float(spec_px))
    elif rule.absolute_px is None and _best_quality(apparatus) is None:
        raise ValueError(
            "this apparatus cannot tell the best edge width it can reach (it has no "
            "best_quality()), so a relative success threshold is impossible: give an "
            "absolute spec with --spec-px (edge width in px, e.g. from the datasheet)"
        )
    started = time.perf_counter()
    records = []
    for index in range(scenarios):
        record = _run_scenario(controller, apparatus, knob, rule, seed, index, budget)
        records.append(record)
        if on_scenario is not None:
            on_scenario(record)
    return SessionResult(
        controller=controller.name,
        knob=knob,
        seed=seed,
        budget=budget,
        records=tuple(records),
        seconds=time.perf_counter() - started,
    )


def _run_scenario(
    controller: Controller,
    apparatus: Apparatus,
    knob: str,
    rule: SuccessRule,
    seed: int,
    index: int,
    budget: int,
) -> ScenarioResult:
    reset_seed = reset_scenario(apparatus, seed, index)
    best_quality = _best_quality(apparatus)
    best_px = float(best_quality()) if best_quality is not None else None
    threshold = rule.threshold_px(best_px)  # an absolute spec ignores best_px
    start = start_setting(seed, index, apparatus.knobs[knob])
    apparatus.write({knob: start})
    counting = CountingApparatus(apparatus, budget)
    exhausted = False
    try:
        controller.align(counting, knob, budget)
    except BudgetExhausted:
        exhausted = True  # the alignment ends where the knob is
    final_setting = float(apparatus.read()[knob])
    optimum = getattr(apparatus, "optimum", None)
    optimum_v = float(optimum()[knob]) if callable(optimum) else None
    try:
        final_width: float | None = float(apparatus.measure())
    except ApparatusError:
        final_width = None  # no edges where it stopped: not aligned
    success = final_width is not None and math.isfinite(final_width) and final_width <= threshold
    return ScenarioResult(
        index=index,
        seed=reset_seed,
        start=start,
        final_setting=final_setting,
        acquisitions=counting.acquisitions,
        budget_exhausted=exhausted,
        final_width_px=final_width,
        threshold_px=float(threshold),
        success=bool(success),
        optimum=optimum_v,
        trajectory=tuple(
            (float(shot.settings[knob]), shot.width_px) for shot in counting.trajectory
        ),
    )

"""Alignment tasks: which knobs an aligner controls, how far one action moves them, how long
an episode may last, and what counts as aligned (seed sections 4.3 and 6.2).

A task is a frozen record; `TASKS` maps names to the built-in ones, so a new task is one
entry. Knob changes are in the apparatus's units (volts for lenses).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

__all__ = ["TASKS", "SuccessRule", "Task", "get_task"]


@dataclass(frozen=True)
class SuccessRule:
    """An alignment succeeds when the final edge width is at most the threshold.

    `relative`: threshold = relative x the best edge width the apparatus can reach now
    (needs a simulated apparatus). `absolute_px`: a fixed spec in pixels (a real instrument's
    datasheet value); it takes precedence when set.
    """

    relative: float = 1.15
    absolute_px: float | None = None

    def __post_init__(self) -> None:
        if not self.relative > 1.0:
            raise ValueError(f"relative success threshold must exceed 1, got {self.relative}")
        if self.absolute_px is not None and not self.absolute_px > 0:
            raise ValueError(f"absolute_px must be positive, got {self.absolute_px}")

    def threshold_px(self, best_px: float | None) -> float:
        """The edge width an alignment must reach."""
        if self.absolute_px is not None:
            return self.absolute_px
        if best_px is None or not math.isfinite(best_px):
            raise ValueError(
                "a relative success threshold needs the best achievable edge width, which only "
                "a simulated apparatus knows: give an absolute spec (--spec-px) for this one"
            )
        return self.relative * best_px


@dataclass(frozen=True)
class Task:
    """What an aligner controls and how an episode runs."""

    name: str
    knobs: tuple[str, ...]
    max_step: Mapping[str, float] = field(default_factory=dict)  # per knob, units per action
    max_step_fraction: float = 0.25  # default max change per step: this share of the interval
    episode_steps: int = 10  # acquisitions after the first one, at most
    success: SuccessRule = field(default_factory=SuccessRule)
    out_of_bounds_penalty: float = 1.0  # reward -penalty for a step that hits an interval bound
    final_reward_scale: float = 1.0  # x (quality before - quality after), quality in px
    acquisition_cost: float = 0.0  # reward -cost per acquisition (the seed: none)
    success_bonus: float = 0.0  # optional shaping, off by default: + this when the spec is met
    # Pay the bonus only within this x the best width (tighter than the spec: a margin against
    # measurement noise); None: wherever the spec is met. Success itself keeps the spec.
    bonus_relative: float | None = None
    quality_ref_px: float = 2.5  # quality observations are log(width / this)
    no_edges_px: float = 25.0  # a frame without edges counts as this wide in rewards

    def __post_init__(self) -> None:
        if not self.knobs:
            raise ValueError(f"task {self.name!r} names no knob")
        if self.episode_steps < 1:
            raise ValueError(f"task {self.name!r}: episode_steps must be at least 1")
        if not 0 < self.max_step_fraction <= 2:
            raise ValueError(f"task {self.name!r}: max_step_fraction must be in (0, 2]")
        for knob, step in self.max_step.items():
            if knob not in self.knobs:
                raise ValueError(f"task {self.name!r}: max_step names {knob!r}, not a task knob")
            if not step > 0:
                raise ValueError(f"task {self.name!r}: max_step of {knob!r} must be positive")
        if self.out_of_bounds_penalty < 0 or self.acquisition_cost < 0 or self.success_bonus < 0:
            raise ValueError(f"task {self.name!r}: penalties and costs are magnitudes (>= 0)")
        if self.bonus_relative is not None and not self.bonus_relative > 1:
            raise ValueError(f"task {self.name!r}: bonus_relative must be above 1 (x best width)")
        if not self.quality_ref_px > 0 or not self.no_edges_px > 0:
            raise ValueError(f"task {self.name!r}: quality_ref_px and no_edges_px must be > 0")

    def check_apparatus(self, knobs: Mapping[str, tuple[float, float]]) -> None:
        """Refuse an apparatus that lacks one of the task's knobs."""
        missing = [knob for knob in self.knobs if knob not in knobs]
        if missing:
            have = ", ".join(sorted(knobs)) or "none"
            raise ValueError(
                f"task {self.name!r} needs knob(s) {', '.join(missing)}; the apparatus has {have}"
            )

    def step_sizes(self, knobs: Mapping[str, tuple[float, float]]) -> tuple[float, ...]:
        """Largest change per action of each task knob, in the apparatus's units."""
        self.check_apparatus(knobs)
        return tuple(
            float(self.max_step.get(k, self.max_step_fraction * (knobs[k][1] - knobs[k][0])))
            for k in self.knobs
        )


TASKS: dict[str, Task] = {
    "focus": Task(name="focus", knobs=("defocus",)),
}


def get_task(name: str) -> Task:
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(
            f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}"
        ) from None

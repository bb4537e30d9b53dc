"""The references a regret payoff is measured against (alignrl.envs.design): a classical
controller aligning a twin of the column from the aligner's start, by its own rule, within a
session's acquisition budget, and verified with one more image, as an evaluation session
verifies (alignrl.evaluation.session)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.envs.task import Task
from alignrl.evaluation.baselines import get_baseline
from alignrl.evaluation.controllers import (
    BudgetExhausted,
    Controller,
    CountingApparatus,
    TaskController,
    check_controller,
    run_controller,
)
from alignrl.evaluation.session import default_budget, verify_task

__all__ = ["REFERENCES", "ControllerReference", "make_reference"]

REFERENCES = ("hyperbola", "golden-section")  # the `reference:` values a league takes


@dataclass
class ControllerReference:
    """A classical controller as a regret's reference (alignrl.envs.design.Reference)."""

    controller: Controller | TaskController
    budget: int | None = None  # acquisitions; None: the task's session budget
    name: str = field(init=False)

    def __post_init__(self) -> None:
        self.name = self.controller.name

    def align(self, twin: Apparatus, task: Task) -> tuple[float, int]:
        """Align `twin` from where it stands: (its cost at the final setting, px, NaN where
        that image failed; images acquired before it)."""
        counting = CountingApparatus(twin, self.budget or default_budget(task))
        try:
            run_controller(self.controller, counting, task, counting.budget)
        except BudgetExhausted:
            pass  # the alignment ends where the knobs are
        width, _, shift = verify_task(twin, task)
        if width is None:
            return float("nan"), counting.acquisitions
        cost = width
        if task.wobble and shift is not None:
            cost += task.wobble_weight * float(np.hypot(*shift))
        return float(cost), counting.acquisitions


def make_reference(name: str, task: Task) -> ControllerReference:
    """The reference `name` (REFERENCES) for `task`; ValueError where it cannot align it."""
    if name not in REFERENCES:
        raise ValueError(f"unknown reference {name!r}; known: {', '.join(REFERENCES)}")
    controller = get_baseline(name)
    check_controller(controller, task)
    return ControllerReference(controller)

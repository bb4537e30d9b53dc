"""What an alignment controller is, and the acquisition counter every session runs it through.

A controller aligns an apparatus by itself: it writes settings, acquires images (`measure`,
edge width in px, smaller is sharper; on the multi-knob tasks also directional widths and
wobbles, alignrl/apparatus/measures.py) and stops by its own rule, leaving the knobs where it
believes the column is aligned. Two kinds:

* `Controller`: aligns one knob (`align(apparatus, knob, budget)`), the classical autofocus
  routines. A session hands it the knob of a one-knob task.
* `TaskController`: aligns a whole task (`align_task(apparatus, task, budget)`), any number of
  knobs: the stigmator, aperture and column baselines, and trained policies
  (`PolicyController`), whose observations depend on the task's measures.

`CountingApparatus` counts their acquisitions (every image: a wobble is two), records the
trajectory, and stops them with `BudgetExhausted` when the budget is spent.

A measurement that fails (no edges far out of focus, a driver fault) still costs an
acquisition; controllers read it as an infinitely blurred image (`measure_width`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from alignrl.apparatus.backlash import arrival
from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.envs.task import Task

__all__ = [
    "Acquisition",
    "BudgetExhausted",
    "Controller",
    "CountingApparatus",
    "PolicyController",
    "SequenceController",
    "TaskController",
    "check_controller",
    "clip_to_knob",
    "measure_width",
    "probe",
    "run_controller",
]


class BudgetExhausted(Exception):
    """A controller asked for an acquisition beyond its budget; the alignment ends here.

    Deliberately not an ApparatusError: controllers treat those as blurred images and go on,
    while this one must reach the session.
    """


@runtime_checkable
class Controller(Protocol):
    """Aligns one knob of an apparatus, stopping by its own rule."""

    name: str

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        """Move `knob` to where the controller believes the focus is.

        Work only through `apparatus.write` / `apparatus.measure`, stay inside
        `apparatus.knobs[knob]`, and acquire at most `budget` images.
        """
        ...


@runtime_checkable
class TaskController(Protocol):
    """Aligns every knob of a task, stopping by its own rule."""

    name: str

    def check_task(self, task: Task) -> None:
        """ValueError where this controller cannot align `task` (called before a session
        starts, so that a mismatch is refused before any alignment)."""
        ...

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        """Move the task's knobs to where the controller believes the column is aligned.

        Work only through the apparatus (write, measure, and the measures of
        alignrl.apparatus.measures), stay inside the knobs' intervals, and acquire at most
        `budget` images. Knobs outside the task may be touched the way an operator would
        (refocusing while stigmating); the session verifies wherever they are left.
        """
        ...


def check_controller(controller: Controller | TaskController, task: Task) -> None:
    """Refuse a controller that cannot align `task`: a one-knob controller on a task of
    several knobs, or what a task controller's own `check_task` refuses."""
    if isinstance(controller, TaskController):
        controller.check_task(task)
    elif len(task.knobs) != 1:
        raise ValueError(
            f"controller {controller.name!r} aligns one knob; task {task.name!r} has "
            f"{len(task.knobs)} ({', '.join(task.knobs)})"
        )


def run_controller(
    controller: Controller | TaskController, apparatus: Apparatus, task: Task, budget: int
) -> None:
    """Let `controller` align `task` on `apparatus` (checked by `check_controller`)."""
    if isinstance(controller, TaskController):
        controller.align_task(apparatus, task, budget)
    else:
        controller.align(apparatus, task.knobs[0], budget)


@dataclass(frozen=True)
class Acquisition:
    """One image a controller acquired: the knob settings and its edge width (None: failed,
    or a wobble frame, whose width a native wobble does not report)."""

    settings: Mapping[str, float]
    width_px: float | None
    kind: Literal["image", "wobble"] = "image"


class CountingApparatus:
    """An Apparatus that passes everything through, counting and recording acquisitions.

    The `budget`-th acquisition is the last one allowed: a measurement that would need more
    raises `BudgetExhausted` without acquiring. Failed measurements count and are re-raised.

    Where the wrapped apparatus measures directional widths or wobbles natively
    (`measure_directional()`, `measure_wobble(amplitude_v)`), so does the counter, counting
    one and two acquisitions. Where it does not, neither does the counter: the functions of
    alignrl.apparatus.measures then fall back to `measure` and `image` through it, and every
    frame is counted there. (Always offering them would hide that fallback.)
    """

    NATIVE_MEASURES = ("measure_directional", "measure_wobble")

    def __init__(self, apparatus: Apparatus, budget: int) -> None:
        if budget < 1:
            raise ValueError(f"the acquisition budget must be at least 1, got {budget}")
        self.inner = apparatus
        self.budget = budget
        self.trajectory: list[Acquisition] = []

    @property
    def acquisitions(self) -> int:
        return len(self.trajectory)

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self.inner.knobs

    def reset(self, seed: int | None = None) -> None:
        raise RuntimeError("a controller must not reset the apparatus: the session owns it")

    def read(self) -> dict[str, float]:
        return self.inner.read()

    def write(self, values: Mapping[str, float]) -> None:
        self.inner.write(values)

    def _spend(self, images: int) -> dict[str, float]:
        """Check that `images` more acquisitions fit the budget; the settings they see."""
        if self.acquisitions + images > self.budget:
            spent = "all" if self.acquisitions >= self.budget else f"{self.acquisitions} of"
            raise BudgetExhausted(
                f"{spent} {self.budget} acquisitions of the budget are spent; {images} more needed"
            )
        return dict(self.inner.read())

    def measure(self) -> float:
        settings = self._spend(1)
        try:
            width = float(self.inner.measure())
        except ApparatusError:
            self.trajectory.append(Acquisition(settings, None))
            raise
        self.trajectory.append(Acquisition(settings, width))
        return width

    def image(self) -> np.ndarray | None:
        return self.inner.image()

    def __getattr__(self, name: str) -> Callable[..., object]:
        # Only reached for attributes the class lacks: the native measures, offered exactly
        # where the wrapped apparatus has them.
        if name in CountingApparatus.NATIVE_MEASURES and "inner" in self.__dict__:
            if callable(getattr(self.inner, name, None)):
                return getattr(self, f"_counted_{name}")
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _counted_measure_directional(self) -> tuple[float, np.ndarray]:
        """One acquisition: (mean edge width px, the four directional widths px)."""
        settings = self._spend(1)
        try:
            width, widths = self.inner.measure_directional()  # type: ignore[attr-defined]
        except ApparatusError:
            self.trajectory.append(Acquisition(settings, None))
            raise
        self.trajectory.append(Acquisition(settings, float(width)))
        return float(width), np.asarray(widths, dtype=np.float64)

    def _counted_measure_wobble(self, amplitude_v: float) -> np.ndarray:
        """Two acquisitions, counted also when the pair does not correlate: the shift px."""
        settings = self._spend(2)
        wobble = self.inner.measure_wobble  # type: ignore[attr-defined]
        try:
            return np.asarray(wobble(amplitude_v), dtype=np.float64)
        finally:
            self.trajectory += [Acquisition(settings, None, "wobble")] * 2


# --- helpers shared by controllers --------------------------------------------------------


def knob_interval(apparatus: Apparatus, knob: str) -> tuple[float, float, float]:
    """`knob`'s interval on `apparatus`: (low, high, its width)."""
    low, high = (float(value) for value in apparatus.knobs[knob])
    return low, high, high - low


def check_task_knobs(name: str, knobs: tuple[str, ...], task: Task) -> None:
    """Refuse a task controller `name` of `knobs` for a task without every one of them."""
    missing = [knob for knob in knobs if knob not in task.knobs]
    if missing:
        raise ValueError(
            f"controller {name!r} aligns {', '.join(knobs)}; task {task.name!r} has "
            f"{', '.join(task.knobs)}, not {', '.join(missing)}"
        )


def clip_to_knob(apparatus: Apparatus, knob: str, value: float) -> float:
    """`value` clipped into the knob's allowed interval."""
    low, high = apparatus.knobs[knob]
    return float(min(max(value, low), high))


def measure_width(apparatus: Apparatus) -> float:
    """Acquire one image: its edge width in px, or +inf where the measurement failed.

    No edges (far out of focus) and driver faults both mean "no sharp image here"; the
    acquisition is spent either way. BudgetExhausted passes through.
    """
    try:
        width = float(apparatus.measure())
    except ApparatusError:
        return math.inf
    return width if math.isfinite(width) else math.inf


def probe(
    apparatus: Apparatus, knob: str, value: float, from_below_v: float | None = None
) -> float:
    """Set `knob` to `value` (clipped) and acquire: the edge width there (+inf if failed).

    With `from_below_v`, a setting below the current one is approached from
    `from_below_v` volts underneath, so that every probe ends on an upward move: a lens
    field that lags the voltage (hysteresis) then lags by the same amount at every probe.
    """
    target = clip_to_knob(apparatus, knob, value)
    if from_below_v is not None:
        approach_from_below(apparatus, knob, target, from_below_v)
    else:
        apparatus.write({knob: target})
    return measure_width(apparatus)


def approach_from_below(apparatus: Apparatus, knob: str, target: float, margin_v: float) -> None:
    """Write `target`, passing `margin_v` underneath first if the knob is above or at it
    (alignrl/apparatus/backlash.py, `arrival`: how a knob at the target got there is not
    known to a controller, which takes the worse case, from above)."""
    low, high = apparatus.knobs[knob]
    start = float(apparatus.read()[knob])
    for write in arrival(target, start, 1.0, margin_v, low, high, arrived=-1.0):
        apparatus.write({knob: float(write)})


@dataclass
class PolicyController:
    """A trained aligner as a controller: it sees the history the environments give it and
    acts until it stops or reaches its task's step limit (alignrl/envs/core.py).

    The episode engine is built from the policy's own task, not the session's: the policy's
    observations (which measures, how many extra features) are what it was trained on. The
    session's task must have the same knobs; it judges the result with its own measures.
    """

    name: str
    act: Callable[[np.ndarray], np.ndarray]  # history (H, F) -> action (k + 1,)
    task: Task
    history: int

    def check_task(self, task: Task) -> None:
        if task.knobs != self.task.knobs:
            raise ValueError(
                f"policy {self.name!r} aligns {', '.join(self.task.knobs)} (task "
                f"{self.task.name!r}); task {task.name!r} has {', '.join(task.knobs)}"
            )

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        from alignrl.envs.core import AlignmentEpisodes

        self.check_task(task)
        episodes = AlignmentEpisodes([apparatus], self.task.for_acting(), self.history)
        slot = np.array([0])
        episodes.adopt(slot)
        while episodes.active[0]:
            action = np.asarray(self.act(episodes.observation(0)), dtype=np.float64)
            episodes.step(slot, action[None])


@dataclass
class SequenceController:
    """Task controllers run one after the other, each on its own task, judged together on the
    session's: a full column alignment as an operator does it (aperture, focus, stigmators,
    focus again), by task champions. Each stage moves only its own task's knobs and starts
    from the column as the stage before left it; all share the session's acquisition budget.
    """

    stages: tuple[PolicyController, ...]
    label: str | None = None  # the sequence's name in reports; None: its stages', joined

    def __post_init__(self) -> None:
        if not self.stages:
            raise ValueError("a sequence of aligners needs at least one stage")

    @property
    def name(self) -> str:
        return self.label or " > ".join(stage.name for stage in self.stages)

    def check_task(self, task: Task) -> None:
        moved = {knob for stage in self.stages for knob in stage.task.knobs}
        missing = [knob for knob in task.knobs if knob not in moved]
        if missing:
            raise ValueError(
                f"no stage of {self.name!r} moves {', '.join(missing)} of task {task.name!r}"
            )
        foreign = sorted(moved.difference(task.knobs))
        if foreign:
            raise ValueError(
                f"{self.name!r} moves {', '.join(foreign)}, outside task {task.name!r}"
            )

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        self.check_task(task)
        for stage in self.stages:
            stage.align_task(apparatus, stage.task, budget)

"""What an alignment controller is, and the acquisition counter every session runs it through.

A controller aligns one knob of an apparatus by itself: it writes settings, acquires images
(`measure`, edge width in px, smaller is sharper) and stops by its own rule, leaving the knob
where it believes the focus is. Classical autofocus (alignrl.evaluation.baselines) and,
later, trained policies are controllers. `CountingApparatus` counts their acquisitions,
records the trajectory, and stops them with `BudgetExhausted` when the budget is spent.

A measurement that fails (no edges far out of focus, a driver fault) still costs an
acquisition; controllers read it as an infinitely blurred image (`measure_width`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.envs.task import Task

__all__ = [
    "Acquisition",
    "BudgetExhausted",
    "Controller",
    "CountingApparatus",
    "PolicyController",
    "clip_to_knob",
    "measure_width",
    "probe",
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


@dataclass(frozen=True)
class Acquisition:
    """One image a controller acquired: the knob settings and its edge width (None: failed)."""

    settings: Mapping[str, float]
    width_px: float | None


class CountingApparatus:
    """An Apparatus that passes everything through, counting and recording acquisitions.

    The `budget`-th acquisition is the last one allowed: the next `measure` raises
    `BudgetExhausted` without acquiring. Failed measurements count and are re-raised.
    """

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

    def measure(self) -> float:
        if self.acquisitions >= self.budget:
            raise BudgetExhausted(f"all {self.budget} acquisitions of the budget are spent")
        settings = dict(self.inner.read())
        try:
            width = float(self.inner.measure())
        except ApparatusError:
            self.trajectory.append(Acquisition(settings, None))
            raise
        self.trajectory.append(Acquisition(settings, width))
        return width

    def image(self) -> np.ndarray | None:
        return self.inner.image()


# --- helpers shared by controllers --------------------------------------------------------


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
    """Write `target`, passing `margin_v` underneath first if the knob is above or at it."""
    low, _ = apparatus.knobs[knob]
    if float(apparatus.read()[knob]) >= target and target > low:
        apparatus.write({knob: max(low, target - margin_v)})
    apparatus.write({knob: target})


@dataclass
class PolicyController:
    """A trained aligner as a controller: it sees the history the environments give it and
    acts until it stops or reaches its task's step limit (alignrl/envs/core.py)."""

    name: str
    act: Callable[[np.ndarray], np.ndarray]  # history (H, F) -> action (k + 1,)
    task: Task
    history: int

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        from alignrl.envs.core import AlignmentEpisodes

        if self.task.knobs != (knob,):
            raise ValueError(f"policy {self.name!r} aligns {self.task.knobs}, not {knob!r}")
        episodes = AlignmentEpisodes([apparatus], self.task, self.history)
        slot = np.array([0])
        episodes.adopt(slot)
        while episodes.active[0]:
            action = np.asarray(self.act(episodes.observation(0)), dtype=np.float64)
            episodes.step(slot, action[None])

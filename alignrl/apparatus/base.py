"""The Apparatus protocol: what an agent may do to a charged-particle beam instrument.

An apparatus exposes named knobs (lens voltages in volts, later stigmator and aperture
settings), each with an allowed interval in instrument units. An agent reads and writes knob
settings and acquires images whose quality is the average edge width in pixels (smaller is
sharper). A real microscope driver implements the same protocol and is loaded by import path
(see docs/apparatus.md); simulated apparatus also reveal the optimum, the secret that critics
may see at training time.

Hardware fails: a measurement on a far-defocused image may find no edges, a driver may time
out. Those are exceptions of this module, so that callers can treat them as defined outcomes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "Apparatus",
    "ApparatusError",
    "MeasurementError",
    "NoEdgesError",
    "SimulatedApparatus",
    "check_write",
]


class ApparatusError(RuntimeError):
    """The instrument or its driver failed (communication error, timeout, interlock)."""


class MeasurementError(ApparatusError):
    """An acquisition produced no quality value."""


class NoEdgesError(MeasurementError, ValueError):
    """The image has no edges to measure (far out of focus, blank, or only noise)."""


@runtime_checkable
class Apparatus(Protocol):
    """An instrument an agent can align. Units are the instrument's (volts for lenses)."""

    knobs: Mapping[str, tuple[float, float]]  # name -> allowed (low, high)

    def reset(self, seed: int | None = None) -> None:
        """Start a new scenario: a new specimen area, a new misalignment of the column."""
        ...

    def read(self) -> dict[str, float]:
        """The current knob settings."""
        ...

    def write(self, values: Mapping[str, float]) -> None:
        """Set knobs. ValueError for an unknown knob or a value outside its interval; nothing
        changes then."""
        ...

    def measure(self) -> float:
        """Acquire an image and return its average edge width in pixels."""
        ...

    def image(self) -> np.ndarray | None:
        """The last acquired image, if the apparatus has one."""
        ...


@runtime_checkable
class SimulatedApparatus(Apparatus, Protocol):
    """An apparatus that knows its own best settings (a simulator)."""

    def optimum(self) -> dict[str, float]:
        """The secret: the best knob settings now."""
        ...

    def best_quality(self) -> float:
        """The edge width (px) the apparatus reaches at its optimum now: the reference of
        relative success thresholds."""
        ...


APPARATUS_METHODS = ("reset", "read", "write", "measure", "image")


def check_write(knobs: Mapping[str, tuple[float, float]], values: Mapping[str, float]) -> None:
    """Refuse a write that names an unknown knob or leaves a knob's allowed interval.

    Every apparatus calls this before touching anything, so a refused write changes nothing.
    """
    for name, value in values.items():
        if name not in knobs:
            known = ", ".join(sorted(knobs)) or "none"
            raise ValueError(f"unknown knob {name!r}: this apparatus has {known}")
        low, high = knobs[name]
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"knob {name!r}: {value!r} is not a number") from None
        if not math.isfinite(number):
            raise ValueError(f"knob {name!r}: {value!r} is not a finite number")
        if not low <= number <= high:
            raise ValueError(
                f"knob {name!r}: {number:g} is outside its allowed interval [{low:g}, {high:g}]"
            )

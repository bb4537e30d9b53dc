"""The Apparatus protocol: what an agent may do to a charged-particle beam instrument.

An apparatus exposes named knobs (lens voltages in volts, later stigmator and aperture
settings), each with an allowed interval in instrument units. An agent reads and writes knob
settings and acquires images whose quality is the average edge width in pixels (smaller is
sharper). A real microscope driver implements the same protocol and is loaded by import path
(see docs/apparatus.md); simulated apparatus also reveal the optimum, the secret that critics
may see at training time.

Beyond the protocol, an apparatus may offer capabilities, each a small protocol of its own:
`KnowsOptimum` (the secret), `KnowsBestQuality` (the edge width at the optimum),
`BatchedQueries` (a group answers write-and-measure in one numpy query), `ReportsApplied`
(a write that reports what it applied: the shield), and `MeasuresDirectional` /
`MeasuresWobble` (the multi-knob tasks' measures computed by the apparatus itself). The env
engine and alignrl/apparatus/measures.py ask for them through the helpers here
(`knows_optimum`, ..., `answers_batched`), never by the class of the apparatus.

Hardware fails: a measurement on a far-defocused image may find no edges, a driver may time
out. Those are exceptions of this module, so that callers can treat them as defined outcomes.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from typing import Protocol, TypeGuard, runtime_checkable

import numpy as np

__all__ = [
    "Apparatus",
    "ApparatusError",
    "BatchedQueries",
    "KnowsBestQuality",
    "KnowsOptimum",
    "MeasurementError",
    "MeasuresDirectional",
    "MeasuresWobble",
    "NoEdgesError",
    "ReportsApplied",
    "SimulatedApparatus",
    "answers_batched",
    "check_write",
    "draws_column_at_reset",
    "knows_best_quality",
    "knows_optimum",
    "offers_directional",
    "offers_wobble",
    "reports_applied",
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


# --- capabilities -------------------------------------------------------------------------
#
# A capability is there where its method is there and callable: a driver switches one off by
# setting it to None (`optimum = None`: a column that cannot tell its optimum), which
# `isinstance` against the protocol does not always see (an instance attribute of None, a
# proxy's __getattr__ on Python 3.12+). Ask through the helpers, which see both.


@runtime_checkable
class KnowsOptimum(Protocol):
    """An apparatus that can tell its best settings (a simulator; never a real column)."""

    def optimum(self) -> dict[str, float]:
        """The secret: the best knob settings now."""
        ...


@runtime_checkable
class KnowsBestQuality(Protocol):
    """An apparatus that can tell the edge width (px) it reaches at its optimum now: the
    reference of relative success thresholds."""

    def best_quality(self) -> float:
        """The edge width (px) at the optimum now."""
        ...


@runtime_checkable
class SimulatedApparatus(Apparatus, KnowsOptimum, KnowsBestQuality, Protocol):
    """An apparatus that knows its own best settings and best edge width (a simulator)."""


@runtime_checkable
class BatchedQueries(Protocol):
    """An apparatus whose group, all of one `batch_key`, answers a write and a measurement
    on each unit in one numpy query (scenario simulators replaying one recording).

    A shield never offers this: a batched query would reach the units around its checks.
    """

    def batch_key(self) -> Hashable:
        """Units with equal keys can be measured together by `measure_batch`."""
        ...

    def measure_batch(self, units: Sequence[BatchedQueries], settings: np.ndarray) -> np.ndarray:
        """Write `settings[i]` (one column per knob, in the order of `knobs`) to `units[i]`
        and measure each: the widths (px) that write + measure on each in turn would give
        (the same values, the same noise draws), NaN where a unit finds no edges."""
        ...


@runtime_checkable
class ReportsApplied(Protocol):
    """An apparatus whose writes may not land as asked (the shield clamps them, or in a dry
    run does not send them) and that says where the column really is after each."""

    def applied_setting(self) -> dict[str, float]:
        """The knob settings after the last write, as they were applied."""
        ...


@runtime_checkable
class MeasuresDirectional(Protocol):
    """An apparatus that measures directional edge widths itself (the synthetic SEM, also
    without images); any other gets them from its last image (alignrl/apparatus/measures.py)."""

    def measure_directional(self) -> tuple[float, np.ndarray]:
        """One acquisition: (mean edge width px, widths of the four orientation bins px)."""
        ...


@runtime_checkable
class MeasuresWobble(Protocol):
    """An apparatus that measures a wobble itself; any other gets one from two frames."""

    def measure_wobble(self, amplitude_v: float) -> np.ndarray:
        """Two acquisitions: the shift (dx, dy) px between defocus + and - amplitude_v."""
        ...


def knows_optimum(unit: object) -> TypeGuard[KnowsOptimum]:
    """Whether `unit` can tell its optimum (KnowsOptimum)."""
    return callable(getattr(unit, "optimum", None))


def knows_best_quality(unit: object) -> TypeGuard[KnowsBestQuality]:
    """Whether `unit` can tell its best edge width (KnowsBestQuality)."""
    return callable(getattr(unit, "best_quality", None))


def reports_applied(unit: object) -> TypeGuard[ReportsApplied]:
    """Whether `unit`'s writes report what they applied (ReportsApplied)."""
    return callable(getattr(unit, "applied_setting", None))


def offers_directional(unit: object) -> TypeGuard[MeasuresDirectional]:
    """Whether `unit` measures directional edge widths itself (MeasuresDirectional)."""
    return callable(getattr(unit, "measure_directional", None))


def offers_wobble(unit: object) -> TypeGuard[MeasuresWobble]:
    """Whether `unit` measures a wobble itself (MeasuresWobble)."""
    return callable(getattr(unit, "measure_wobble", None))


def draws_column_at_reset(unit: object) -> bool:
    """Whether `unit` is an instrument family: a new column, with intervals of its own, at
    every reset. It says so with a class attribute `draws_column_at_reset = True`; for any
    other apparatus a change of its intervals is a fault (alignrl/apparatus/shield.py)."""
    return getattr(unit, "draws_column_at_reset", False) is True


def answers_batched(units: Sequence[object]) -> TypeGuard[Sequence[BatchedQueries]]:
    """Whether `units` can be measured together in one batched query: every one offers
    BatchedQueries, and all share one batch key."""
    if not units or not all(isinstance(unit, BatchedQueries) for unit in units):
        return False
    return len({unit.batch_key() for unit in units}) == 1  # type: ignore[attr-defined]


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

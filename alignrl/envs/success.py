"""What counts as aligned (alignrl/envs/task.py): the success rule a task's final width is
held to, and one judged measure of a batch of measurements against its spec, as `align`
prints it and sessions count it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Criterion", "SuccessRule"]


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
class Criterion:
    """One judged measure of a batch of measurements against its spec (px): the final width,
    the widest directional width, or the wobble shift's magnitude. `measured` False: the
    measure could not be taken at all (`value_px` NaN); a NaN value is never `met`."""

    measure: str  # one of MEASURES
    value_px: np.ndarray  # (n,)
    spec_px: np.ndarray  # (n,)
    met: np.ndarray  # (n,) bool
    measured: bool = True

    def words(self, index: int = 0) -> str:
        """Measurement `index` in words, as `alignrl align` reports it."""
        if not self.measured:
            return _UNMEASURED[self.measure]
        value, spec = float(self.value_px[index]), float(self.spec_px[index])
        relation = "<=" if self.met[index] else ">"
        return f"{_LABELS[self.measure]} {value:.3g} px {relation} spec {spec:.3g} px"


_LABELS = {
    "width": "final edge width",
    "directional": "widest directional width",
    "wobble": "wobble shift",
}
_UNMEASURED = {
    "width": "the final image had no edges",
    "directional": "the directional widths could not be measured",
    "wobble": "the wobble could not be measured",
}

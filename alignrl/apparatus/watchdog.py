"""The shield's watchdog: an alignment ends after a time limit or a number of acquisitions.

Times are seconds of an injectable clock (time.monotonic by default), so tests run it on a
clock of their own.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from alignrl.apparatus.limits import ShieldConfigError

__all__ = ["Watchdog"]


@dataclass
class Watchdog:
    """Ends an alignment after `timeout_s` seconds of `clock` or `max_acquisitions` images
    (None: no limit). Checked before every write and measurement."""

    timeout_s: float | None = None
    max_acquisitions: int | None = None
    clock: Callable[[], float] = time.monotonic
    started: float | None = None

    def __post_init__(self) -> None:
        if self.timeout_s is not None and not (
            math.isfinite(self.timeout_s) and self.timeout_s > 0
        ):
            raise ShieldConfigError(f"--timeout must be positive seconds, got {self.timeout_s}")
        if self.max_acquisitions is not None and self.max_acquisitions < 1:
            raise ShieldConfigError(
                f"--max-acquisitions must be at least 1, got {self.max_acquisitions}"
            )

    def start(self) -> None:
        self.started = self.clock()

    def elapsed_s(self) -> float:
        return 0.0 if self.started is None else self.clock() - self.started

    def remaining_s(self) -> float | None:
        """Seconds left before the time limit (None: no limit, or not started)."""
        if self.timeout_s is None or self.started is None:
            return None
        return max(0.0, self.timeout_s - self.elapsed_s())

    def expiry(self, acquisitions: int | None) -> str | None:
        """Why the alignment must end now, or None. `acquisitions`: images acquired so far,
        or None where they do not count (the final verification image)."""
        if self.timeout_s is not None and self.elapsed_s() >= self.timeout_s:
            return f"watchdog: the time limit of {self.timeout_s:g} s passed"
        if (
            self.max_acquisitions is not None
            and acquisitions is not None
            and acquisitions >= self.max_acquisitions
        ):
            return f"watchdog: all {self.max_acquisitions} acquisitions are spent"
        return None

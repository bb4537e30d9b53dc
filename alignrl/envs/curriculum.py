"""The trainer's curriculum (seed section 4.3): the misalignment complexity grows as the
aligner masters it.

The level is the width of the misalignment window as a fraction of the knob interval. After
every episode the curriculum records success or failure; when a full window of recent
episodes succeeds at least `raise_at` of the time, the level rises by `step` (up to 1); when
it collapses below `lower_at`, the level falls back by `step` (down to `minimum`). The window
restarts after each change, so a level is judged on its own episodes. Its state is a plain
dict, saved and restored with a run. `Curriculum.from_config` builds it from a run config's
`curriculum:` section, for the trainer and the league alike.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Protocol

__all__ = ["Curriculum", "CurriculumSettings"]


class CurriculumSettings(Protocol):
    """A config's `curriculum:` section (alignrl.config.run.CurriculumConfig)."""

    enabled: bool
    level: float
    step: float
    window: int
    raise_at: float
    lower_at: float


@dataclass
class Curriculum:
    level: float = 0.1
    minimum: float = 0.05
    maximum: float = 1.0
    step: float = 0.1
    window: int = 100
    raise_at: float = 0.8
    lower_at: float = 0.3
    _recent: deque = field(default_factory=deque, repr=False)

    def __post_init__(self) -> None:
        if not 0 < self.minimum <= self.level <= self.maximum <= 1:
            raise ValueError(
                f"curriculum needs 0 < minimum <= level <= maximum <= 1, got "
                f"{self.minimum}, {self.level}, {self.maximum}"
            )
        if not 0 < self.step <= 1:
            raise ValueError(f"curriculum step must be in (0, 1], got {self.step}")
        if self.window < 1:
            raise ValueError(f"curriculum window must be at least 1, got {self.window}")
        if not 0 <= self.lower_at < self.raise_at <= 1:
            raise ValueError(
                f"curriculum needs 0 <= lower_at < raise_at <= 1, got {self.lower_at}, "
                f"{self.raise_at}"
            )
        self._recent = deque(self._recent, maxlen=self.window)

    @classmethod
    def from_config(cls, settings: CurriculumSettings) -> Curriculum | None:
        """The curriculum a config's section describes, None where it is disabled. Its level
        may fall back as far as the smaller of its start and one step."""
        if not settings.enabled:
            return None
        return cls(
            level=settings.level,
            minimum=min(settings.level, settings.step),
            step=settings.step,
            window=settings.window,
            raise_at=settings.raise_at,
            lower_at=settings.lower_at,
        )

    @property
    def success_rate(self) -> float | None:
        """Success rate over the current window, None until it is full."""
        if len(self._recent) < self.window:
            return None
        return sum(self._recent) / len(self._recent)

    def record(self, success: bool) -> float:
        """Count one episode; returns the (possibly new) level."""
        self._recent.append(bool(success))
        rate = self.success_rate
        if rate is None:
            return self.level
        if rate >= self.raise_at and self.level < self.maximum:
            self.level = min(self.maximum, round(self.level + self.step, 10))
            self._recent.clear()
        elif rate < self.lower_at and self.level > self.minimum:
            self.level = max(self.minimum, round(self.level - self.step, 10))
            self._recent.clear()
        return self.level

    def state_dict(self) -> dict[str, Any]:
        return {"level": self.level, "recent": [int(s) for s in self._recent]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        level = float(state["level"])
        if not self.minimum <= level <= self.maximum:
            raise ValueError(f"saved curriculum level {level} lies outside this curriculum")
        self.level = level
        self._recent = deque((bool(s) for s in state["recent"]), maxlen=self.window)

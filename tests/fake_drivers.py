"""Drivers written the way a user writes one, loaded by import path (`fake_drivers:Class`).

They have no images: their edge width follows the Gaussian-probe focus curve
w = 2.563 * sqrt(sigma0^2 + (gain * (V - V_opt))^2), so tests know every number exactly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numpy as np

from alignrl.apparatus import ApparatusError, NoEdgesError, check_write

TEN_NINETY = 2.563


class ParabolicLens:
    """A noiseless lens whose optimum moves with the reset seed (uniform in 30..70 V)."""

    def __init__(
        self,
        gain_px_per_v: float = 0.2,
        sigma0_px: float = 1.0,
        blind_beyond_v: float | None = None,
        fault_every: int = 0,
        interrupt_at_reset: int | None = None,
        delay_s: float = 0.0,
        faulty_within_v: float | None = None,
    ) -> None:
        self.knobs: Mapping[str, tuple[float, float]] = {"defocus": (0.0, 100.0)}
        self.gain, self.sigma0 = gain_px_per_v, sigma0_px
        self.blind_beyond_v = blind_beyond_v  # |V - V_opt| beyond which no edges are found
        self.fault_every = fault_every  # every n-th acquisition raises a driver fault
        self.interrupt_at_reset = interrupt_at_reset  # operator presses Ctrl-C at this reset
        self.delay_s = delay_s
        self.faulty_within_v = faulty_within_v  # the driver times out this close to focus
        self.resets = 0
        self.calls = 0
        self.writes: list[dict[str, float]] = []
        self.reset(0)

    def reset(self, seed: int | None = None) -> None:
        if self.interrupt_at_reset is not None and self.resets == self.interrupt_at_reset:
            raise KeyboardInterrupt
        self.resets += 1
        self.optimum_v = 30.0 + 40.0 * np.random.default_rng(seed).random()
        self.voltage = 50.0

    def read(self) -> dict[str, float]:
        return {"defocus": self.voltage}

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        self.writes.append(dict(values))
        self.voltage = float(values.get("defocus", self.voltage))

    def measure(self) -> float:
        self.calls += 1
        if self.delay_s:
            time.sleep(self.delay_s)
        if self.fault_every and self.calls % self.fault_every == 0:
            raise ApparatusError("driver timeout")
        error = self.voltage - self.optimum_v
        if self.faulty_within_v is not None and abs(error) < self.faulty_within_v:
            raise ApparatusError("driver timeout near focus")
        if self.blind_beyond_v is not None and abs(error) > self.blind_beyond_v:
            raise NoEdgesError("far out of focus")
        return TEN_NINETY * math.hypot(self.sigma0, self.gain * error)

    def image(self) -> np.ndarray | None:
        return None

    def optimum(self) -> dict[str, float]:
        return {"defocus": self.optimum_v}


class NotAnApparatus:
    """Has knobs but cannot measure: must be refused by make_apparatus."""

    def __init__(self) -> None:
        self.knobs = {"defocus": (0.0, 1.0)}

    def reset(self, seed: int | None = None) -> None: ...


class EmptyInterval(ParabolicLens):
    """Declares a knob whose interval is empty: must be refused by make_apparatus."""

    def __init__(self) -> None:
        super().__init__()
        self.knobs = {"defocus": (5.0, 5.0)}

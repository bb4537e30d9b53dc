"""Drivers written the way a user writes one, loaded by import path (`fake_drivers:Class`).

They have no images: their edge width follows the Gaussian-probe focus curve
w = 2.563 * sqrt(sigma0^2 + (gain * (V - V_opt))^2), so tests know every number exactly.
"""

from __future__ import annotations

import builtins
import math
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

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


class BlindLens(ParabolicLens):
    """The same lens, but it cannot tell its optimum, as a real column cannot."""

    optimum = None  # type: ignore[assignment]


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


class FiveKnobColumn:
    """A cheap, noise-free five-knob column without images, with native directional and
    wobble measures (the synthetic SEM's physics in closed form), so that the multi-knob
    tasks' numbers are exact.

    Probe sigma^2 along the axes of the astigmatism residual r (V; stigmators at
    `stigmator_v_per_pct` V per percent): s0^2 + (gain (dV -/+ |r|/2))^2 + (blur |d|)^2, with
    d the aperture residual (um). A wobble of amplitude A shifts the image by
    shift_gain 2 A R(rotation_deg) d: image and aperture axes may be rotated against each
    other, as on a real column. `images` counts every acquisition.
    """

    knobs: Mapping[str, tuple[float, float]] = {
        "defocus": (0.0, 100.0),
        "stigmator_x": (-100.0, 100.0),
        "stigmator_y": (-100.0, 100.0),
        "aperture_x": (-50.0, 50.0),
        "aperture_y": (-50.0, 50.0),
    }
    gain, stigmator_v_per_pct, blur, shift_gain, sigma0 = 0.2, 0.2, 0.05, 0.02, 1.0

    def __init__(self, rotation_deg: float = 0.0) -> None:
        angle = math.radians(rotation_deg)
        self.rotation = np.array(
            [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
        )
        self.images = 0
        self.reset(0)

    def reset(self, seed: int | None = None) -> None:
        rng = np.random.default_rng(seed)
        self.best = {
            "defocus": float(rng.uniform(30, 70)),
            "stigmator_x": float(rng.uniform(-50, 50)),
            "stigmator_y": float(rng.uniform(-50, 50)),
            "aperture_x": float(rng.uniform(-30, 30)),
            "aperture_y": float(rng.uniform(-30, 30)),
        }
        # As the synthetic SEM: the defocus at its nominal value, the rest misaligned.
        self.setting = {"defocus": 50.0, "stigmator_x": 0.0, "stigmator_y": 0.0}
        self.setting |= {"aperture_x": 0.0, "aperture_y": 0.0}

    def read(self) -> dict[str, float]:
        return dict(self.setting)

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        self.setting.update({name: float(value) for name, value in values.items()})

    def residual(self, group: str) -> np.ndarray:
        return np.array([self.setting[f"{group}_{a}"] - self.best[f"{group}_{a}"] for a in "xy"])

    def measure_directional(self) -> tuple[float, np.ndarray]:
        self.images += 1
        focus = self.setting["defocus"] - self.best["defocus"]
        stig = self.stigmator_v_per_pct * self.residual("stigmator")
        half = 0.5 * float(np.hypot(*stig))
        base = self.sigma0**2 + (self.blur * float(np.hypot(*self.residual("aperture")))) ** 2
        axis = 0.5 * math.atan2(stig[1], stig[0])
        turn = np.array([[math.cos(axis), -math.sin(axis)], [math.sin(axis), math.cos(axis)]])
        variances = [
            base + (self.gain * (focus - half)) ** 2,
            base + (self.gain * (focus + half)) ** 2,
        ]
        covariance = turn @ np.diag(variances) @ turn.T
        angles = np.radians([0.0, 45.0, 90.0, 135.0])
        normals = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        widths = TEN_NINETY * np.sqrt(np.einsum("bi,ij,bj->b", normals, covariance, normals))
        return float(widths.mean()), widths

    def measure(self) -> float:
        return self.measure_directional()[0]

    def measure_wobble(self, amplitude_v: float) -> np.ndarray:
        self.images += 2
        return self.shift_gain * 2.0 * amplitude_v * self.rotation @ self.residual("aperture")

    def image(self) -> np.ndarray | None:
        return None

    def optimum(self) -> dict[str, float]:
        return dict(self.best)

    def best_quality(self) -> float:
        return TEN_NINETY * self.sigma0


def _bound(value: float | str) -> float:
    return float(value)  # "inf", "-inf" and "nan" from JSON arguments too


class HostileLens(ParabolicLens):
    """A ParabolicLens that lies, fails or hangs as told, and records every write it
    receives before checking it (`HostileLens.received`, across the instances a command
    builds; `HostileLens.received_in`: each with the interval the driver declared as it came),
    so a test can see what got through the shield.

    read_value: what read() says the defocus is; width: what measure() returns (a number,
    or "nan"); write_error / measure_error / read_error / reset_error / knobs_error /
    image_error: the name of an exception class ("RuntimeError", "ApparatusError",
    "SystemExit", ...) that call raises (knobs: the getter, after the constructor); hang:
    "read", "write", "measure", "reset", "knobs" or "init" (the constructor): that call blocks
    for `hang_s` seconds (None: forever), first creating the file `hang_marker` if given;
    hang_after: calls of that kind that return normally first.
    narrow_after / narrow_to: after this many writes received, the knobs getter declares
    `narrow_to` instead (a column that changed its allowed range); interval_at_reset: from
    the second reset on, the knobs getter declares this interval ("inf" allowed);
    integer_knob: the knob is named 1, not "defocus"; optimum_value: what optimum() says;
    best_width: what best_quality() says (None: it has no best_quality); image_shape:
    image() returns zeros of this shape; interval: the defocus interval (default 0..100 V).
    """

    received: ClassVar[list[dict[str, float]]] = []
    received_in: ClassVar[list[tuple[dict[str, float], dict[Any, tuple[float, float]]]]] = []
    instances: ClassVar[list[HostileLens]] = []

    def __init__(
        self,
        read_value: float | None = None,
        width: float | str | None = None,
        write_error: str | None = None,
        measure_error: str | None = None,
        read_error: str | None = None,
        reset_error: str | None = None,
        knobs_error: str | None = None,
        image_error: str | None = None,
        hang: str | None = None,
        hang_s: float | None = None,
        hang_after: int = 0,
        hang_marker: str | None = None,
        narrow_after: int | None = None,
        narrow_to: tuple[float, float] = (45.0, 55.0),
        interval_at_reset: tuple[float | str, float | str] | None = None,
        integer_knob: bool = False,
        optimum_value: dict[str, float] | None = None,
        best_width: float | str | None = None,
        image_shape: tuple[int, ...] | None = None,
        interval: tuple[float, float] | None = None,
        **options: Any,
    ) -> None:
        self.read_value, self.width = read_value, width
        self.errors = {"write": write_error, "measure": measure_error, "read": read_error}
        self.errors |= {"reset": reset_error, "knobs": knobs_error, "image": image_error}
        self.hang, self.hang_s, self.hang_after = hang, hang_s, hang_after
        self.hang_marker = hang_marker
        self.narrow_after, self.narrow_to = narrow_after, tuple(narrow_to)
        self.interval_at_reset = interval_at_reset
        self.integer_knob = integer_knob
        self.optimum_value, self.best_width = optimum_value, best_width
        self.image_shape = image_shape
        if best_width is None:  # a lens that cannot tell its best width, as before
            self.best_quality = None  # type: ignore[method-assign,assignment]
        self.counts: dict[str, int] = {}
        self.mine: list[dict[str, float]] = []  # the writes this instance received
        self.hung = threading.Event()  # set while a call hangs
        self.opened = False
        self._misbehave("init")
        super().__init__(**options)
        if interval is not None:
            self._knobs = {"defocus": (float(interval[0]), float(interval[1]))}
        self.opened = True
        HostileLens.instances.append(self)

    @property
    def knobs(self) -> Mapping[Any, tuple[float, float]]:  # type: ignore[override]
        if self.opened:
            self._misbehave("knobs")
        return self.declared()

    @knobs.setter
    def knobs(self, value: Mapping[str, tuple[float, float]]) -> None:
        self._knobs = dict(value)

    def declared(self) -> dict[Any, tuple[float, float]]:
        """The intervals the driver declares now (without misbehaving)."""
        interval = self._knobs["defocus"]
        if self.narrow_after is not None and len(self.mine) >= self.narrow_after:
            interval = (float(self.narrow_to[0]), float(self.narrow_to[1]))
        if self.interval_at_reset is not None and self.resets > 1:
            interval = (_bound(self.interval_at_reset[0]), _bound(self.interval_at_reset[1]))
        return {1 if self.integer_knob else "defocus": interval}

    def _misbehave(self, call: str) -> None:
        self.counts[call] = self.counts.get(call, 0) + 1
        if call == self.hang and self.counts[call] > self.hang_after:
            self.hung.set()
            if self.hang_marker is not None:
                Path(self.hang_marker).touch()
            threading.Event().wait(self.hang_s)  # None: never returns
        name = self.errors.get(call)
        if name is not None and (call != "reset" or self.opened):
            error = ApparatusError if name == "ApparatusError" else getattr(builtins, name)
            raise error(f"vendor SDK: {call} failed (E_{call.upper()}_42)")

    def reset(self, seed: int | None = None) -> None:
        if hasattr(self, "counts"):  # ParabolicLens.__init__ resets before ours is done
            self._misbehave("reset")
        super().reset(seed)
        if hasattr(self, "_knobs"):  # the column as found: the middle of its interval
            self.voltage = 0.5 * sum(self._knobs["defocus"])

    def read(self) -> dict[Any, float]:
        self._misbehave("read")
        name = 1 if self.integer_knob else "defocus"
        if self.read_value is not None:
            return {name: self.read_value}
        return {name: self.voltage}

    def write(self, values: Mapping[str, float]) -> None:
        declared = self.declared()
        HostileLens.received.append({name: float(value) for name, value in values.items()})
        HostileLens.received_in.append((HostileLens.received[-1], declared))
        self.mine.append(HostileLens.received[-1])
        self._misbehave("write")
        check_write(declared, values)
        self.writes.append(dict(values))
        self.voltage = float(next(iter(values.values())))

    def measure(self) -> float:
        self._misbehave("measure")
        true_width = super().measure()
        if self.width is None:
            return true_width
        return self.width if isinstance(self.width, int) else float(self.width)

    def image(self) -> np.ndarray | None:
        self._misbehave("image")
        return None if self.image_shape is None else np.zeros(self.image_shape)

    def optimum(self) -> dict[str, float]:
        return super().optimum() if self.optimum_value is None else dict(self.optimum_value)

    def best_quality(self) -> float:
        return float(self.best_width)  # type: ignore[arg-type]


class HostileFamily(HostileLens):
    """The hostile lens as an instrument family: it may bring other intervals with a new
    column at reset (and only then)."""

    draws_column_at_reset = True

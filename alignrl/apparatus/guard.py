"""What guards every call alignrl makes to a driver: the exceptions that end work on an
instrument, calls bounded in time, and checks of what a driver answers.

`BoundedDriver` runs a driver's calls on one worker thread of its own; the caller waits at
most a limit (DEFAULT_CALL_TIMEOUT_S, or what is left of a watchdog's time), and a call that
does not return is abandoned where it hangs. `checked_reading` and `checked_width` judge a
reading and an edge width (px) before anything believes them. The shield
(alignrl/apparatus/shield.py) puts these around every driver.
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from alignrl.apparatus.base import ApparatusError, MeasurementError

__all__ = [
    "DEFAULT_CALL_TIMEOUT_S",
    "MAX_EDGE_WIDTH_PX",
    "Aborted",
    "BoundedDriver",
    "DriverFailure",
    "DriverTimeout",
    "RefusedWrite",
    "ShieldStop",
    "StartOutsideLimits",
    "WatchdogExpired",
    "checked_reading",
    "checked_width",
    "construct_within",
]

# The longest one driver call (a read, a write, an acquisition) may take before it is
# abandoned: a slow-scan SEM frame at high resolution takes tens of seconds, a stuck driver
# forever. `--call-timeout` sets it per command.
DEFAULT_CALL_TIMEOUT_S = 60.0


# --- exceptions ---------------------------------------------------------------------------


class ShieldStop(Exception):
    """The shield ends the alignment. Deliberately not an ApparatusError: the alignment loop
    treats those as unmeasured images and goes on, while this must end it."""


class WatchdogExpired(ShieldStop):
    """The time limit passed or the acquisitions are spent."""


class Aborted(ShieldStop):
    """A call after the alignment was aborted: nothing reaches the driver any more."""


class RefusedWrite(ShieldStop):
    """A write the shield will not clamp into shape: a non-finite value or an unknown knob."""


class StartOutsideLimits(ShieldStop):
    """The column sits outside the site limits before the alignment started."""


class DriverFailure(ShieldStop):
    """The driver failed on a read or a write, raised an exception of its own, or answered
    what cannot be: the column's state is not known."""


class DriverTimeout(DriverFailure):
    """A driver call did not return within its limit: it is abandoned on its worker thread
    and nothing more is sent to that driver."""


# --- what a driver may answer --------------------------------------------------------------

MAX_EDGE_WIDTH_PX = 1e6  # wider than any image: a driver that says so is not measuring
READBACK_TOLERANCE = 1e-6  # of a knob's interval: a readback's rounding, not a lie


def _real(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        return None
    number = float(value)
    return number if math.isfinite(number) else None


def checked_reading(
    answer: Any, knobs: Mapping[str, tuple[float, float]]
) -> tuple[dict[str, float], str | None]:
    """A driver's `read()` as {knob: value}, and what is wrong with it (None: nothing).

    Every knob must be there, a finite number inside its interval (to a readback's
    rounding); a knob the apparatus does not have is wrong too. A driver that reads where it
    cannot be is not the apparatus it says it is, and nothing it says can be trusted."""
    if not isinstance(answer, Mapping):
        return {}, f"the driver's read() returned {type(answer).__name__}, not {{knob: value}}"
    values: dict[str, float] = {}
    for name, interval in knobs.items():
        if name not in answer:
            return {}, f"the driver's read() has no value for knob {name!r}"
        number = _real(answer[name])
        if number is None:
            return {}, f"the driver reads {name} = {answer[name]!r}: not a finite number"
        low, high = float(interval[0]), float(interval[1])
        slack = READBACK_TOLERANCE * (high - low)
        if not low - slack <= number <= high + slack:
            return {}, (
                f"the driver reads {name} = {number:g}, outside its own interval "
                f"[{low:g}, {high:g}]: it is not the apparatus it says it is"
            )
        values[name] = min(max(number, low), high)
    unknown = sorted(str(name) for name in answer if name not in knobs)
    if unknown:
        return {}, f"the driver's read() names knobs it does not have: {', '.join(unknown)}"
    return values, None


def checked_width(value: Any) -> float:
    """A driver's edge width in px; MeasurementError (an unmeasured image) for anything but a
    positive finite width below MAX_EDGE_WIDTH_PX."""
    width = _real(value)
    if width is None or not 0 < width < MAX_EDGE_WIDTH_PX:
        raise MeasurementError(
            f"the driver's measure() returned {value!r}, not a positive finite edge width "
            "in px: the image counts as unmeasured"
        )
    return width


# --- bounded driver calls -----------------------------------------------------------------


@dataclass
class _Call:
    function: Callable[..., Any]
    arguments: tuple[Any, ...]
    done: threading.Event = field(default_factory=threading.Event)
    value: Any = None
    error: BaseException | None = None

    def run(self) -> None:
        try:
            self.value = self.function(*self.arguments)
        except BaseException as error:  # handed to the caller, KeyboardInterrupt too
            self.error = error
        self.done.set()


def construct_within(
    what: str, construct: Callable[[], Any], timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S
) -> Any:
    """`construct()` (a driver's constructor: it may connect to a microscope) on a thread of
    its own, waited for at most `timeout_s`: DriverTimeout if it does not return, and a
    DriverFailure for an exception of its own that is not an ApparatusError, ValueError,
    TypeError or OSError (those say what is wrong with the arguments or the connection)."""
    pending = _Call(construct, ())
    thread = threading.Thread(target=pending.run, name="alignrl-driver-open", daemon=True)
    thread.start()
    if not pending.done.wait(timeout_s):
        raise DriverTimeout(
            f"{what} did not return within {timeout_s:g} s (--call-timeout); abandoned"
        )
    error = pending.error
    if error is None:
        return pending.value
    if isinstance(error, ApparatusError | ValueError | TypeError | OSError) or not isinstance(
        error, Exception
    ):
        raise error
    raise DriverFailure(f"{what} raised {type(error).__name__}: {error}") from None


class BoundedDriver:
    """A driver whose calls each return within a time limit, or are abandoned.

    Every method call runs on one worker thread (a driver sees its calls in order and from
    one thread, as from a plain loop); the caller waits at most `limit()` seconds for it.
    On a timeout the call is abandoned where it hangs, `on_fault` is told, and DriverTimeout
    (or `expired()`'s WatchdogExpired, where the watchdog's time ran out first) is raised;
    every later call is refused. An exception of the driver's own that is not an
    ApparatusError (and not a ValueError from `write`, which the shield judges) becomes a
    DriverFailure naming the call. Attributes that are not methods pass through.
    """

    def __init__(
        self,
        driver: Any,
        limit: Callable[[], tuple[float | None, str | None]],
        on_fault: Callable[[str, str], None],
    ) -> None:
        self._driver = driver
        self._limit = limit  # -> (seconds to wait or None, the watchdog's reason if it binds)
        self._on_fault = on_fault
        self._requests: queue.SimpleQueue[_Call] = queue.SimpleQueue()
        self._worker: threading.Thread | None = None
        self.abandoned: str | None = None  # the call that never returned

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self._driver.knobs

    def __getattr__(self, name: str) -> Any:
        attribute = getattr(self.__dict__["_driver"], name)
        if not callable(attribute):
            return attribute
        return lambda *arguments: self.call(name, attribute, *arguments)

    def _serve(self) -> None:
        while True:
            self._requests.get().run()

    def call(self, name: str, function: Callable[..., Any], *arguments: Any) -> Any:
        if self.abandoned is not None:
            raise DriverTimeout(
                f"{name}() not sent: the driver's {self.abandoned}() never returned"
            )
        if self._worker is None:
            self._worker = threading.Thread(
                target=self._serve, name="alignrl-driver-calls", daemon=True
            )
            self._worker.start()
        pending = _Call(function, arguments)
        timeout_s, watchdog_reason = self._limit()
        self._requests.put(pending)
        if not pending.done.wait(timeout_s):
            self.abandoned = name
            if watchdog_reason is not None:
                reason = f"{watchdog_reason} during the driver's {name}() call, abandoned"
                self._on_fault(name, reason)
                raise WatchdogExpired(reason)
            reason = (
                f"the driver's {name}() did not return within {timeout_s:g} s "
                "(--call-timeout); the call is abandoned"
            )
            self._on_fault(name, reason)
            raise DriverTimeout(reason)
        error = pending.error
        if error is None:
            return pending.value
        if isinstance(error, ApparatusError | ShieldStop | KeyboardInterrupt):
            raise error
        if name == "write" and isinstance(error, ValueError):
            raise error  # the shield judges a refused write
        if not isinstance(error, Exception):
            raise error  # SystemExit and the like are not the driver's to turn into results
        reason = f"the driver's {name}() raised {type(error).__name__}: {error}"
        self._on_fault(name, reason)
        raise DriverFailure(reason) from None

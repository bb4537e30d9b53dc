"""What guards every call alignrl makes to a driver: the exceptions that end work on an
instrument, calls bounded in time, and checks of what a driver answers.

`BoundedDriver` runs a driver's calls on one worker thread of its own, its getters (`knobs`,
any attribute) included; the caller waits at most a limit (DEFAULT_CALL_TIMEOUT_S, or what is
left of a watchdog's time), and a call that does not return is abandoned where it hangs.
`within` does the same for what comes before a driver exists (its module's import, its
constructor). `checked_intervals`, `checked_reading`, `checked_width`, `checked_optimum` and
`checked_best_quality` judge what a driver answers before anything believes it. The shield
(alignrl/apparatus/shield.py) puts these around every driver.

Whatever a driver raises that is not an ApparatusError (a vendor SDK's RuntimeError, a
`SystemExit` or any other BaseException) is a DriverFailure naming the call: only the
operator's own Ctrl-C (KeyboardInterrupt) passes as it is.
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
    "checked_best_quality",
    "checked_intervals",
    "checked_optimum",
    "checked_reading",
    "checked_width",
    "construct_within",
    "declared_intervals",
    "within",
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
# Narrower than any edge a detector can resolve (a tenth of a pixel): a driver that says so is
# not measuring either, and such a width would set a success threshold no column can meet.
MIN_EDGE_WIDTH_PX = 0.1
READBACK_TOLERANCE = 1e-6  # of a knob's interval: a readback's rounding, not a lie
# The largest knob bound a driver may declare, in its units: beyond any lens voltage,
# stigmator or aperture setting (and far from where a focus fit's squares overflow).
MAX_KNOB_MAGNITUDE = 1e9
# The narrowest interval, relative to its bounds: one a float can still tell points apart in.
MIN_RELATIVE_WIDTH = 1e-9


def _real(value: Any) -> float | None:
    """`value` as a finite float; None for anything else (an integer too large for a float
    included)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _short(value: Any) -> str:
    """A driver's answer in a message: its repr, cut to 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def checked_intervals(answer: Any) -> tuple[dict[str, tuple[float, float]], str | None]:
    """A driver's `knobs` as {knob: (low, high)}, and what is wrong with it (None: nothing).

    A non-empty mapping whose names are non-empty strings and whose intervals are two finite
    numbers within +-MAX_KNOB_MAGNITUDE, low below high by at least MIN_RELATIVE_WIDTH of the
    larger bound (bounds of +-1e308 are no interval, nor is [1, 1 + 1e-15])."""
    if not isinstance(answer, Mapping) or not answer:
        return {}, f"knobs must be a non-empty mapping name -> (low, high), got {_short(answer)}"
    intervals: dict[str, tuple[float, float]] = {}
    for name, interval in answer.items():
        if not isinstance(name, str) or not name:
            return {}, f"knob names must be non-empty strings, got {_short(name)}"
        try:
            low, high = (_real(bound) for bound in interval)
        except (TypeError, ValueError):
            return {}, f"knob {name!r} needs (low, high), got {_short(interval)}"
        if (
            low is None
            or high is None
            or max(abs(low), abs(high)) > MAX_KNOB_MAGNITUDE
            or not high - low >= MIN_RELATIVE_WIDTH * max(1.0, abs(low), abs(high))
        ):
            return {}, (
                f"knob {name!r} has an empty or infinite interval {_short(interval)}: it "
                f"needs two finite numbers low < high within +-{MAX_KNOB_MAGNITUDE:g}, apart "
                f"by at least {MIN_RELATIVE_WIDTH:g} of the larger"
            )
        intervals[name] = (low, high)
    return intervals, None


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
    finite width from MIN_EDGE_WIDTH_PX up to (not including) MAX_EDGE_WIDTH_PX."""
    width = _real(value)
    if width is None or not MIN_EDGE_WIDTH_PX <= width < MAX_EDGE_WIDTH_PX:
        raise MeasurementError(
            f"the driver's measure() returned {_short(value)}, not an edge width in px "
            f"(finite, {MIN_EDGE_WIDTH_PX:g} to {MAX_EDGE_WIDTH_PX:g}): the image counts as "
            "unmeasured"
        )
    return width


def checked_optimum(
    answer: Any, knobs: Mapping[str, tuple[float, float]]
) -> tuple[dict[str, float], str | None]:
    """A simulated apparatus's `optimum()` (the secret critics and starts are built from) as
    {knob: value}, and what is wrong with it: a value for every knob, finite and inside the
    knob's interval, as a reading must be."""
    values, wrong = checked_reading(answer, knobs)
    if wrong is not None:
        wrong = wrong.replace("read()", "optimum()").replace(" reads ", " says the optimum of ")
    return values, wrong


def checked_best_quality(value: Any) -> tuple[float, str | None]:
    """A simulated apparatus's `best_quality()` (success thresholds are built from it), and
    what is wrong with it: it must be an edge width as `checked_width` takes one."""
    try:
        return checked_width(value), None
    except MeasurementError:
        return math.nan, (
            f"the driver's best_quality() returned {_short(value)}, not an edge width in px "
            f"(finite, {MIN_EDGE_WIDTH_PX:g} to {MAX_EDGE_WIDTH_PX:g})"
        )


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


def _driver_raised(what: str, error: BaseException) -> DriverFailure:
    """A driver's own exception as the DriverFailure that names it (SystemExit's code too)."""
    detail = str(error) if not isinstance(error, SystemExit) else f"exit code {error.code!r}"
    return DriverFailure(f"{what} raised {type(error).__name__}: {detail}"[:2000])


def within(
    what: str,
    work: Callable[[], Any],
    timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S,
    passes: tuple[type[BaseException], ...] = (ApparatusError,),
) -> Any:
    """`work()` (a driver's import, constructor or getter, before any shield exists) on a
    thread of its own, waited for at most `timeout_s`: DriverTimeout if it does not return.
    An exception in `passes` (and the operator's KeyboardInterrupt) is raised as it came;
    any other, BaseExceptions such as SystemExit included, is a DriverFailure naming `what`."""
    pending = _Call(work, ())
    thread = threading.Thread(target=pending.run, name="alignrl-driver-open", daemon=True)
    thread.start()
    if not pending.done.wait(timeout_s):
        raise DriverTimeout(
            f"{what} did not return within {timeout_s:g} s (--call-timeout); abandoned"
        )
    error = pending.error
    if error is None:
        return pending.value
    if isinstance(error, (*passes, KeyboardInterrupt)):
        raise error
    raise _driver_raised(what, error) from None


def construct_within(
    what: str, construct: Callable[[], Any], timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S
) -> Any:
    """`construct()` (a driver's constructor: it may connect to a microscope) `within` the
    time limit; an ApparatusError, ValueError, TypeError or OSError (what is wrong with the
    arguments or the connection) passes as it came, anything else is a DriverFailure."""
    return within(what, construct, timeout_s, (ApparatusError, ValueError, TypeError, OSError))


_MISSING = object()
# Calls whose failure spoils no work: a driver that cannot give its last image (for a --gif)
# has still measured it. Their exceptions are a MeasurementError, not a driver fault; a hang
# or a BaseException still is one.
BEST_EFFORT_CALLS = frozenset({"image"})
# How long a call interrupted by the operator is given to return (s) before it is left where
# it is: an abort ends within a second, a quick call still lets a restore follow it.
INTERRUPT_GRACE_S = 0.1


def declared_intervals(
    apparatus: Any, what: str, timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S
) -> dict[str, tuple[float, float]]:
    """The intervals `apparatus` declares now, read `within` the time limit and checked
    (`checked_intervals`); a DriverFailure naming `what` for an answer that is none."""
    answer = within(f"{what}: the knobs getter", lambda: apparatus.knobs, timeout_s)
    knobs, wrong = checked_intervals(answer)
    if wrong is not None:
        raise DriverFailure(f"{what}: {wrong}")
    return knobs


class BoundedDriver:
    """A driver whose calls each return within a time limit, or are abandoned.

    Every method call and every attribute read (`knobs`, a capability) runs on one worker
    thread (a driver sees its calls in order and from one thread, as from a plain loop); the
    caller waits at most `limit()` seconds for it. On a timeout the call is abandoned where
    it hangs, `on_fault` is told, and DriverTimeout (or WatchdogExpired, where the watchdog's
    time ran out first) is raised; every later call is refused. The operator's Ctrl-C while
    a call is pending leaves that call pending too (`abandoned`): nothing more is sent to a
    driver whose call has not returned. An exception of the driver's own that is not an
    ApparatusError (and not a ValueError from `write`, which the shield judges), BaseExceptions
    such as SystemExit included, becomes a DriverFailure naming the call.
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
        self._methods: dict[str, Callable[..., Any]] = {}
        self.abandoned: str | None = None  # the call that never returned

    @property
    def knobs(self) -> Any:
        """The intervals the driver declares now, as it answers them (unchecked)."""
        return self.call("knobs", getattr, self._driver, "knobs")

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        methods = self.__dict__["_methods"]
        if name in methods:
            return methods[name]
        attribute = self.call(name, getattr, self.__dict__["_driver"], name, _MISSING)
        if attribute is _MISSING:
            raise AttributeError(name)
        if not callable(attribute):
            return attribute

        def bounded(*arguments: Any) -> Any:
            return self.call(name, attribute, *arguments)

        methods[name] = bounded
        return bounded

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
        try:
            returned = pending.done.wait(timeout_s)
        except KeyboardInterrupt:
            # The operator's Ctrl-C (or SIGTERM) while the driver works: a call about to
            # return is waited for a moment; one that does not is left to it, and the driver
            # gets nothing more (not even a restore).
            try:
                finished = pending.done.wait(INTERRUPT_GRACE_S)
            except KeyboardInterrupt:
                finished = False
            if not finished:
                self.abandoned = name
            raise
        if not returned:
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
        if name in BEST_EFFORT_CALLS and isinstance(error, Exception):
            raise MeasurementError(f"the driver's {name}() raised {type(error).__name__}: {error}")
        failure = _driver_raised(f"the driver's {name}()", error)
        self._on_fault(name, str(failure))
        raise failure from None

"""The safety shield: every call alignrl makes to an instrument passes through it.

`ShieldedApparatus` wraps an apparatus and implements the Apparatus protocol itself, so the
alignment loop of the environments (alignrl/envs/core.py) runs over it unchanged and the
policy sees exactly the history features it was trained on. `TrainingShield`
(alignrl/apparatus/training_shield.py) is the same shield for work of many episodes: training
and adaptation, evaluation sessions, baselines and recordings. `make_apparatus`
(alignrl/apparatus/registry.py) wraps every driver loaded by import path in one, so no command
can reach a real instrument around it. Its rules, in order,
before any write reaches the driver:

1. after an abort nothing is written (the one exception: `restore()`, at most once, and never
   after a driver call was abandoned, interrupted or failed);
2. the watchdog: past the time limit, or with all acquisitions spent, the alignment ends;
3. a non-finite value or an unknown knob is refused;
4. each knob is clamped into the tighter of the apparatus's interval and the site limits,
   then its change from the current setting to at most the knob's maximum step;
5. a write that changes nothing is not sent; in a dry run, no write is sent;
6. before a write is sent, the driver's intervals are read again (a bounded call): where they
   are not those the limits were resolved against, the driver changed its mind inside the
   alignment (a real column changes its allowed range with its mode, its high voltage, a
   lens' current limit), and that is a driver fault: audited, nothing more written. Only a
   driver that declares itself a family (`draws_column_at_reset`, alignrl/apparatus/base.py)
   may bring other intervals, and only with a new scenario (`TrainingShield.reset`).

Every driver call is bounded in time (`BoundedDriver`): it runs on one worker thread of the
shield's, and the caller waits at most the call limit (default DEFAULT_CALL_TIMEOUT_S) or
what is left of the watchdog's time, whichever is less. A call that does not return is
abandoned, the abort is audited, and nothing more is sent to that driver. A driver that lies
is caught where it answers: a reading outside the knob's interval or not finite, an optimum
outside it or a best width that is no edge width is a driver failure; an edge width outside
[MIN_EDGE_WIDTH_PX, MAX_EDGE_WIDTH_PX) is an unmeasured image. Any exception a driver raises
other than ApparatusError (a vendor SDK's RuntimeError, a SystemExit) is a driver failure
naming the call.

Every call to the driver, and every decision, is one record in the audit log (`AuditSink`),
with the wall time (ISO 8601, UTC) and the monotonic clock of the watchdog, in seconds. Values
are in instrument units (volts for lenses), edge widths in px.

Pure logic but for the worker thread: the only I/O is through the wrapped apparatus and the
audit sink (`JsonLinesAudit` writes a file). The rules themselves are plain functions of
alignrl/apparatus/limits.py (limits, clamping, the options a command shields with), the
watchdog is alignrl/apparatus/watchdog.py, the bounded calls and driver checks
alignrl/apparatus/guard.py; their names are importable from here as well.

Capabilities (alignrl/apparatus/base.py): every shield reports where a write left the column
(ReportsApplied, `applied_setting`). A TrainingShield also passes on what a simulated
instrument can tell, and only that: KnowsOptimum and KnowsBestQuality where its apparatus has
them, and a scenario simulator's `indices`. It never offers BatchedQueries: a batched query
would reach the instrument around every rule above.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Mapping
from datetime import UTC, datetime
from typing import Any, NoReturn

import numpy as np

from alignrl.apparatus.audit import AuditFailure, AuditSink, JsonLinesAudit, MemoryAudit
from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    MeasurementError,
    knows_best_quality,
)
from alignrl.apparatus.guard import (
    DEFAULT_CALL_TIMEOUT_S,
    Aborted,
    BoundedDriver,
    DriverFailure,
    DriverTimeout,
    RefusedWrite,
    ShieldStop,
    StartOutsideLimits,
    WatchdogExpired,
    checked_best_quality,
    checked_intervals,
    checked_reading,
    checked_width,
)
from alignrl.apparatus.limits import (
    KnobLimits,
    ShieldConfigError,
    ShieldOptions,
    WriteDecision,
    clamp_write,
    resolve_limits,
)
from alignrl.apparatus.measures import WOBBLE_KNOB, measure_directional, measure_wobble
from alignrl.apparatus.watchdog import Watchdog

__all__ = [
    "DEFAULT_CALL_TIMEOUT_S",
    "Aborted",
    "AuditSink",
    "BoundedDriver",
    "DriverFailure",
    "DriverTimeout",
    "JsonLinesAudit",
    "KnobLimits",
    "MemoryAudit",
    "RefusedWrite",
    "ShieldConfigError",
    "ShieldOptions",
    "ShieldStop",
    "ShieldedApparatus",
    "StartOutsideLimits",
    "Watchdog",
    "WatchdogExpired",
    "WriteDecision",
    "clamp_write",
    "resolve_limits",
]

OPERATOR_ABORT = "operator abort (Ctrl-C or SIGTERM)"


class ShieldedApparatus:
    """An apparatus seen through the shield (see the module docstring).

    `knobs` are the wrapped apparatus's own intervals, so that history features and step
    sizes are those the policy was trained with; the site limits act on the writes. Call
    `begin()` first: it reads the starting setting and starts the watchdog.

    With `dry_run`, writes are decided and logged but never sent: the column stays where it
    was, and reads and measurements show it there.
    """

    def __init__(
        self,
        apparatus: Apparatus,
        limits: Mapping[str, KnobLimits],
        audit: AuditSink,
        watchdog: Watchdog | None = None,
        dry_run: bool = False,
        call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S,
    ) -> None:
        if call_timeout_s is not None and not (
            math.isfinite(call_timeout_s) and call_timeout_s > 0
        ):
            raise ShieldConfigError(
                f"--call-timeout must be positive seconds, got {call_timeout_s}"
            )
        self.driver = apparatus  # the driver itself: only ever called through `inner`
        self.call_timeout_s = call_timeout_s
        self.audit = audit
        self.watchdog = watchdog or Watchdog()
        self.dry_run = dry_run
        self.abort_reason: str | None = None
        self.failed = False  # a driver call failed or was abandoned: no restore either
        self.setting: dict[str, float] | None = None  # the column as the shield last left it
        self.inner: Any = BoundedDriver(apparatus, self._call_limit, self._driver_fault)
        self.knobs: Mapping[str, tuple[float, float]] = self._declared_intervals()
        self.limits = dict(limits)
        self._limits_inside()
        self.start: dict[str, float] | None = None
        self.acquisitions = 0  # alignment images that reached the driver
        self.writes = 0  # writes that reached the driver
        self.clamped = 0  # writes clamped (in a dry run: that would have been)
        self.refused = 0  # writes not made, other than in a dry run
        self.restored = False  # the start was written back after an abort
        self._restore_tried = False
        self._final = False  # inside final_measures()

    def _call_limit(self) -> tuple[float | None, str | None]:
        """How long the next driver call may take: the call limit, or what is left of the
        watchdog's time where that is less (then also the watchdog's reason)."""
        remaining = self.watchdog.remaining_s()
        if remaining is not None and (
            self.call_timeout_s is None or remaining < self.call_timeout_s
        ):
            return remaining, f"watchdog: the time limit of {self.watchdog.timeout_s:g} s passed"
        return self.call_timeout_s, None

    def _driver_fault(self, call: str, reason: str) -> None:
        """A driver call was abandoned or raised what no driver may: audited, and the end."""
        self.failed = True
        self.log("driver-fault", call=call, sent=True, error=reason)
        self.abort(reason)

    def _fault(self, call: str, reason: str) -> NoReturn:
        """The driver answered what cannot be: audited, the end, nothing more written."""
        self._driver_fault(call, reason)
        raise DriverFailure(reason)

    def _declared_intervals(self) -> dict[str, tuple[float, float]]:
        """The intervals the driver declares now (a bounded call), checked."""
        knobs, wrong = checked_intervals(self.inner.knobs)
        if wrong is not None:
            self._fault("knobs", f"the driver's knobs: {wrong}")
        return knobs

    def _limits_inside(self) -> None:
        """Every limit lies inside its knob's interval (they were resolved from a reading of
        the intervals a moment before: a driver that moved them since is at fault)."""
        for name, knob in self.limits.items():
            low, high = self.knobs.get(name, (math.nan, math.nan))
            if not low <= knob.low < knob.high <= high:
                self._fault(
                    "knobs",
                    f"the driver's interval of {name} is [{low:g}, {high:g}] now, which does "
                    f"not hold the limits [{knob.low:g}, {knob.high:g}] resolved from it",
                )

    def _intervals_hold(self) -> None:
        """Rule 6, before a write is sent: the driver declares the intervals it declared when
        the limits were resolved; otherwise a driver fault (nothing more is written)."""
        now = self._declared_intervals()
        if now == self.knobs:
            return
        changes = [
            f"{name} {list(self.knobs.get(name, ()))} -> {list(now.get(name, ()))}"
            for name in sorted(set(now) | set(self.knobs))
            if now.get(name) != self.knobs.get(name)
        ]
        self._fault(
            "knobs",
            f"the driver's intervals changed during the alignment ({'; '.join(changes)}): "
            "it is not the column the limits were set for",
        )

    @property
    def aborted(self) -> bool:
        return self.abort_reason is not None

    # --- records ------------------------------------------------------------------------

    def log(self, event: str, **fields: Any) -> None:
        """One audit record: the event, when (UTC and the watchdog's clock), and `fields`."""
        entry = {
            "event": event,
            "time": datetime.now(UTC).isoformat(timespec="microseconds"),
            "monotonic_s": self.watchdog.clock(),
            "elapsed_s": self.watchdog.elapsed_s(),
            **fields,
        }
        try:
            self.audit.record(entry)
        except AuditFailure as error:
            # Nothing is sent that is not on record: the end, without a restore either.
            self.failed = True
            if self.abort_reason is None:
                self.abort_reason = str(error)
            raise

    def _stop_if_due(self, event: str, acquisitions: int | None, **fields: Any) -> None:
        """Rules 1 and 2: after an abort, or when the watchdog fires, the call is logged as
        aborted and never reaches the driver."""
        if self.abort_reason is not None:
            self.log(event, decision="aborted", sent=False, reason=self.abort_reason, **fields)
            if event == "write":
                self.refused += 1
            raise Aborted(f"{event} after the alignment was aborted ({self.abort_reason})")
        expired = self.watchdog.expiry(acquisitions)
        if expired is not None:
            self.log(event, decision="aborted", sent=False, reason=expired, **fields)
            if event == "write":
                self.refused += 1
            raise WatchdogExpired(expired)

    # --- the protocol -------------------------------------------------------------------

    def begin(self) -> dict[str, float]:
        """Read the starting setting, start the watchdog, and refuse (StartOutsideLimits) a
        column that sits outside the limits: the shield never jumps into them."""
        self.watchdog.start()
        start = self.read()
        self.start, self.setting = dict(start), dict(start)
        outside = [
            f"{name} = {value:g} (limits [{self.limits[name].low:g}, {self.limits[name].high:g}])"
            for name, value in start.items()
            if name in self.limits and not self.limits[name].low <= value <= self.limits[name].high
        ]
        if outside:
            reason = (
                f"the column starts outside the limits: {'; '.join(outside)}; move it inside "
                "by hand or widen --limits"
            )
            self.log("refused-start", reason=reason)
            raise StartOutsideLimits(reason)
        return dict(start)

    def reset(self, seed: int | None = None) -> None:
        raise RuntimeError("align never resets the apparatus: it starts from the column as it is")

    def read(self) -> dict[str, float]:
        self._stop_if_due("read", None)
        try:
            answer = self.inner.read()
        except KeyboardInterrupt:
            self.log("read", sent=True, error="interrupted by the operator")
            raise
        except ApparatusError as error:
            self.log("read", sent=True, error=str(error))
            raise DriverFailure(f"the driver failed to read the knobs: {error}") from None
        values, lie = checked_reading(answer, self.knobs)
        if lie is not None:
            self.log("read", sent=True, error=lie)
            self.failed = True
            self.abort(lie)
            raise DriverFailure(lie)
        self.log("read", sent=True, values=values)
        return values

    def write(self, values: Mapping[str, float]) -> None:
        requested = {name: float(value) for name, value in values.items()}
        self._stop_if_due("write", self.acquisitions, requested=requested)
        assert self.setting is not None, "call begin() before the first write"
        try:
            decision = clamp_write(self.limits, self.setting, requested)
        except RefusedWrite as error:
            self.refused += 1
            self.log(
                "write", requested=requested, decision="refused", sent=False, reason=str(error)
            )
            raise
        self.clamped += bool(decision.clamps)
        verdict = "clamped" if decision.clamps else "allowed"
        record = {"requested": requested, "value": decision.values, "clamps": list(decision.clamps)}
        if all(self.setting.get(name) == value for name, value in decision.values.items()):
            # Nothing would change (the loop's first write repeats the setting it just read,
            # or a clamp held the knob where it is): no command goes to the instrument.
            self.log("write", decision=verdict, sent=False, unchanged=True, **record)
            return
        if self.dry_run:
            self.log("write", decision="dry-run", would_be=verdict, sent=False, **record)
            return
        self._intervals_hold()
        # Logged before it is sent: a crash during the driver call leaves it on record.
        self.log("write", decision=verdict, sent=True, **record)
        self.writes += 1
        try:
            self.inner.write(decision.values)
        except KeyboardInterrupt:
            self.setting = None  # the driver may or may not have set it
            self.log("write-error", error="interrupted by the operator", value=decision.values)
            raise
        except (ApparatusError, ValueError) as error:
            # ValueError: the driver refused a value inside its own interval, so it is not
            # the apparatus it says it is; either way its state is unknown now.
            self.setting = None
            self.log("write-error", error=str(error), value=decision.values)
            raise DriverFailure(f"the driver failed to write {decision.values}: {error}") from None
        self.setting.update(decision.values)

    def measure(self) -> float:
        """An alignment image (counted by the watchdog). Measurement failures are logged and
        raised as they came, so the alignment records an unmeasured row and goes on."""
        purpose = self._count("measure", 1)
        return self._acquire(purpose)

    @contextlib.contextmanager
    def final_measures(self) -> Iterator[None]:
        """Measurements inside are the final ones, judged against the spec: not counted
        against the acquisitions, but after an abort or past the time limit not taken."""
        self._final = True
        try:
            yield
        finally:
            self._final = False

    def verify(self) -> float | None:
        """The final image (see `final_measures`). None: it had no edges."""
        with self.final_measures():
            try:
                return self.measure()
            except ApparatusError:
                return None

    def _count(self, event: str, images: int, count: bool = True, **fields: Any) -> str:
        """Rules 1 and 2 for a measurement of `images` acquisitions; counts them (with
        `count`) unless they are final. Returns the purpose the audit log names."""
        if self._final:
            self._stop_if_due(event, None, purpose="final", **fields)
            return "final"
        self._stop_if_due(event, self.acquisitions + images - 1, purpose="alignment", **fields)
        self.acquisitions += images if count else 0
        return "alignment"

    def _acquire(self, purpose: str) -> float:
        try:
            width = checked_width(self.inner.measure())
        except KeyboardInterrupt:
            self.log("measure", purpose=purpose, sent=True, error="interrupted by the operator")
            raise
        except ApparatusError as error:  # MeasurementError and NoEdgesError included
            self.log("measure", purpose=purpose, sent=True, error=str(error))
            raise
        self.log("measure", purpose=purpose, sent=True, width_px=width)
        return width

    def measure_directional(self) -> tuple[float, np.ndarray]:
        """An alignment image measured in four edge orientations (one acquisition)."""
        purpose = self._count("measure", 1)
        try:
            width, widths = measure_directional(self.inner)
        except KeyboardInterrupt:
            self.log("measure", purpose=purpose, sent=True, error="interrupted by the operator")
            raise
        except ApparatusError as error:
            self.log("measure", purpose=purpose, sent=True, error=str(error))
            raise
        self.log(
            "measure",
            purpose=purpose,
            sent=True,
            width_px=width,
            directional_px=[float(w) for w in widths],
        )
        return width, widths

    def measure_wobble(self, amplitude_v: float) -> np.ndarray:
        """A wobble (two acquisitions): the defocus swings +/- amplitude around its setting
        and comes back. The swing is a measurement, not a move, so the maximum step does not
        apply, but it never leaves the limits: the amplitude shrinks to fit them (logged). In
        a dry run nothing is written, so there is no wobble: MeasurementError."""
        purpose = self._count("wobble", 2, count=False, amplitude_v=amplitude_v)
        if self.dry_run:
            self.log("wobble", decision="dry-run", sent=False, amplitude_v=amplitude_v)
            raise MeasurementError("dry run: a wobble swings the defocus, so none is made")
        if self.setting is None:
            raise DriverFailure("the column's setting is unknown after a failed write")
        centre = self.setting.get(WOBBLE_KNOB)
        if centre is None or WOBBLE_KNOB not in self.limits:
            raise MeasurementError(f"a wobble swings {WOBBLE_KNOB!r}, which is not shielded here")
        limits = self.limits[WOBBLE_KNOB]
        safe = max(0.0, min(float(amplitude_v), centre - limits.low, limits.high - centre))
        if safe <= 0:
            self.log(
                "wobble",
                decision="refused",
                sent=False,
                amplitude_v=amplitude_v,
                reason="the defocus sits on a limit: no room to swing",
            )
            raise MeasurementError("wobble refused: the defocus sits on a limit")
        decision = "clamped" if safe < amplitude_v else "allowed"
        self._intervals_hold()
        self.log(
            "wobble",
            decision=decision,
            sent=True,
            amplitude_v=safe,
            swing=[centre - safe, centre + safe],
        )
        self.acquisitions += 2 if purpose == "alignment" else 0
        try:
            shift = measure_wobble(_IntervalsHeld(self), safe)
        except KeyboardInterrupt:
            self.log("wobble-error", error="interrupted by the operator")
            raise
        except ApparatusError as error:
            self.log("wobble-error", error=str(error))
            raise
        self.log("measure", purpose=purpose, sent=True, shift_px=[float(v) for v in shift])
        return shift

    def image(self) -> np.ndarray | None:
        return self.inner.image()

    def best_width(self) -> float | None:
        """The apparatus's best edge width in px (a simulator's `best_quality()`), checked:
        a width that is none is a driver fault. None where it cannot tell (a real column)."""
        if not knows_best_quality(self.inner):
            return None
        width, wrong = checked_best_quality(self.inner.best_quality())
        if wrong is not None:
            self._fault("best_quality", wrong)
        return width

    def applied_setting(self) -> dict[str, float]:
        """Where the column is after the last write: the clamped value, or (dry run, or a
        write that was not sent) where it was. AlignmentEpisodes records this in the history,
        so the policy sees the real setting, as it saw a setting clipped at a bound in
        training."""
        if self.setting is None:
            raise DriverFailure("the column's setting is unknown after a failed write")
        return dict(self.setting)

    # --- ending -------------------------------------------------------------------------

    def abort(self, reason: str) -> None:
        """From now on nothing reaches the driver, except one `restore()`."""
        if self.abort_reason is None:
            self.abort_reason = reason
            self.log("abort", reason=reason, setting=self.setting)

    def restore(self) -> bool:
        """Write the starting setting back, once, after an abort; True if it was written.

        Not written in a dry run or where the column is known to be at its start. The write
        is exempt from the maximum step (it returns to a setting the column just held) but
        not from the limits, which the start lies inside.
        """
        if self._restore_tried or self.start is None:
            return False
        self._restore_tried = True
        if self.failed or self.inner.abandoned is not None:
            why = (
                f"the driver's {self.inner.abandoned}() had not returned"
                if self.inner.abandoned is not None
                else "a driver call failed or hung"
            )
            self.log("restore", sent=False, reason=why, value=self.start)
            return False
        if self.dry_run or self.setting == self.start:
            why = "dry run: nothing was written" if self.dry_run else "the column is at its start"
            self.log("restore", sent=False, reason=why, value=self.start)
            return False
        try:
            self._intervals_hold()
        except DriverFailure:
            self.log("restore", sent=False, reason="the driver's intervals changed")
            raise
        self.log("restore", sent=True, value=self.start)
        self.writes += 1
        try:
            self.inner.write(self.start)
        except KeyboardInterrupt:
            self.log("write-error", error="interrupted by the operator", value=self.start)
            raise
        except (ApparatusError, ValueError) as error:
            self.log("write-error", error=str(error), value=self.start)
            raise DriverFailure(f"restoring the start {self.start} failed: {error}") from None
        self.setting = dict(self.start)
        self.restored = True
        return True


class _IntervalsHeld:
    """The shield's bounded driver for a wobble made of frames (alignrl/apparatus/measures.py):
    before each of its writes (the swing out, the swing back, the return) the driver must still
    declare the intervals the limits were resolved against (rule 6)."""

    def __init__(self, shield: ShieldedApparatus) -> None:
        self._shield = shield

    def __getattr__(self, name: str) -> Any:
        return getattr(self._shield.inner, name)

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self._shield.knobs

    def write(self, values: Mapping[str, float]) -> None:
        self._shield._intervals_hold()
        self._shield.inner.write(values)

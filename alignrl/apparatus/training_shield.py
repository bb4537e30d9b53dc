"""The safety shield for work of many episodes on an instrument (`TrainingShield`): training
and adaptation, evaluation sessions, baselines, recordings; and `shield_apparatus`, which puts
one around an apparatus with a command's options. The rules are those of one alignment
(alignrl/apparatus/shield.py), applied scenario after scenario; what differs is the start of
a scenario (a reset, a jump to the scenario's start) and the intervals of a family, which may
change with it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from alignrl.apparatus.audit import MEMORY_AUDIT_RECORDS, AuditSink, MemoryAudit
from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    draws_column_at_reset,
    knows_best_quality,
    knows_optimum,
)
from alignrl.apparatus.guard import (
    DEFAULT_CALL_TIMEOUT_S,
    DriverFailure,
    checked_optimum,
    declared_intervals,
)
from alignrl.apparatus.limits import (
    KnobLimits,
    ShieldConfigError,
    ShieldOptions,
    resolve_limits,
)
from alignrl.apparatus.shield import ShieldedApparatus

__all__ = ["TrainingShield", "shield_apparatus"]


class TrainingShield(ShieldedApparatus):
    """The shield for work of many episodes on an instrument: training and adaptation,
    evaluation sessions, baselines, recordings.

    `reset(seed)` starts a new scenario on the instrument (a new specimen area, a new state
    of the column) and reads where the column is. The writes after it, up to the episode's
    first acquisition, set up the scenario's start (the misalignment, the knobs a stage does
    not align): clamped into the limits like every write, but exempt from the maximum step,
    as a scenario's start is a jump by design. Every later write is the aligner's and obeys
    every rule. No watchdog: the episode's step limit and the run's budget end the work; each
    driver call is still bounded by the call limit.
    """

    def __init__(
        self,
        apparatus: Apparatus,
        limits: Mapping[str, KnobLimits],
        audit: AuditSink,
        unit: str = "0",
        call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S,
        options: ShieldOptions | None = None,
    ) -> None:
        self.unit = unit  # which apparatus of the run: every record names it (from the first)
        super().__init__(apparatus, limits, audit, call_timeout_s=call_timeout_s)
        # The site limits and maximum steps the limits were resolved from: a new scenario
        # may bring a new interval (an instrument family draws a column per reset), and the
        # limits are then resolved again against it.
        self._options = options or ShieldOptions()
        self._start_limits = self._without_max_step(self.limits)
        self._starting = False
        self._draws_columns = draws_column_at_reset(self.inner)  # may change intervals at reset
        # A simulated instrument's secret (the optimum, the best edge width) passes through,
        # bounded and checked like every answer, for the critics and for relative success
        # thresholds; so do a scenario simulator's rows (`indices`), which evaluation sessions
        # walk in order with `reset_to`. A real column has none of them, nor has its shield.
        if knows_optimum(self.inner):
            self.optimum: Callable[[], dict[str, float]] = self._optimum
        if knows_best_quality(self.inner):
            self.best_quality: Callable[[], float | None] = self.best_width
        if getattr(self.inner, "indices", None) is not None:
            self.indices = self.inner.indices

    def _optimum(self) -> dict[str, float]:
        values, wrong = checked_optimum(self.inner.optimum(), self.knobs)
        if wrong is not None:
            self._fault("optimum", wrong)
        return values

    def log(self, event: str, **fields: Any) -> None:
        super().log(event, unit=self.unit, **fields)

    def reset(self, seed: int | None = None) -> None:
        self._new_scenario(lambda: self.inner.reset(seed), seed=seed)

    def reset_to(self, row: int, seed: int | None = None) -> None:
        """A scenario simulator's recorded scenario `row` (evaluation sessions)."""
        self._new_scenario(lambda: self.inner.reset_to(row, seed), seed=seed, row=row)  # type: ignore[attr-defined]

    @staticmethod
    def _without_max_step(limits: Mapping[str, KnobLimits]) -> dict[str, KnobLimits]:
        """The limits a scenario's start obeys: the same intervals, no maximum step."""
        return {
            name: KnobLimits(knob.low, knob.high, knob.low_rule, knob.high_rule, None)
            for name, knob in limits.items()
        }

    def _new_scenario(self, start: Callable[[], None], **fields: Any) -> None:
        self._stop_if_due("reset", None, **fields)
        try:
            start()
        except ApparatusError as error:
            self.log("reset", sent=True, error=str(error), **fields)
            raise DriverFailure(f"the driver failed to start a new scenario: {error}") from None
        self.log("reset", sent=True, **fields)
        self._follow_intervals()
        self.watchdog.start()
        self.start = self.read()
        self.setting = dict(self.start)
        self._starting = True

    def _follow_intervals(self) -> None:
        """After a reset: where a family (`draws_column_at_reset`) now gives other intervals
        (its new column), resolve the limits again against them, site limits and maximum
        steps as given; a site limit the new interval does not hold stops the work
        (ShieldConfigError), before anything is written to the new column. Any other
        apparatus whose intervals change is at fault (rule 6)."""
        knobs = self._declared_intervals()
        if knobs == dict(self.knobs):
            return
        if not self._draws_columns:
            self._intervals_hold()  # the fault, naming the change
        try:
            limits = resolve_limits(knobs, self._options.site_limits, self._options.max_step)
        except ShieldConfigError as error:
            self.log("limits", sent=False, error=str(error))
            self.abort_reason = f"the new scenario's intervals do not fit the limits: {error}"
            raise ShieldConfigError(self.abort_reason) from None
        self.knobs, self.limits = knobs, limits
        self._start_limits = self._without_max_step(limits)
        self.log("limits", intervals={name: list(bounds) for name, bounds in knobs.items()})

    def write(self, values: Mapping[str, float]) -> None:
        if self.setting is None and not self.aborted:
            # Written to before any reset (a driver used as it stands): start from its reading.
            self.start = self.read()
            self.setting = dict(self.start)
        if not self._starting:
            super().write(values)
            return
        aligner_limits, self.limits = self.limits, self._start_limits
        try:
            super().write(values)
        finally:
            self.limits = aligner_limits

    def _count(self, event: str, images: int, count: bool = True, **fields: Any) -> str:
        self._starting = False  # the episode's first acquisition: its start is set
        return super()._count(event, images, count, **fields)


def shield_apparatus(apparatus: Apparatus, options: ShieldOptions | None = None) -> Apparatus:
    """`apparatus` behind a TrainingShield with `options`' limits: ShieldConfigError for
    limits that do not fit it, before anything is sent."""
    options = options or ShieldOptions()
    knobs = declared_intervals(apparatus, "the apparatus", options.call_timeout_s)
    limits = resolve_limits(knobs, options.site_limits, options.max_step)
    audit = options.audit if options.audit is not None else MemoryAudit(MEMORY_AUDIT_RECORDS)
    return TrainingShield(  # type: ignore[return-value]
        apparatus,
        limits,
        audit,
        unit=options.unit,
        call_timeout_s=options.call_timeout_s,
        options=options,
    )

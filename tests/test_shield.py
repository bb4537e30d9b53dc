"""The safety shield of `alignrl align`: every rule is checked where it matters, at the driver.

`RecordingDriver` wraps the CSV scenario simulator and records every call; it fails the test
(AssertionError, also kept in `violations`) the moment a write reaches it that the shield
should have stopped: outside the apparatus interval or the site limits, a step larger than
the maximum step, or any write after an abort other than the one restore. It is also a user
driver by import path (`test_shield:RecordingDriver`) for the command-line tests.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import pytest

from alignrl.apparatus import ApparatusError, NoEdgesError
from alignrl.apparatus.guard import Aborted
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.shield import (
    KnobLimits,
    MemoryAudit,
    RefusedWrite,
    ShieldConfigError,
    ShieldedApparatus,
    StartOutsideLimits,
    Watchdog,
    clamp_write,
    resolve_limits,
)
from alignrl.deploy.align import align
from alignrl.deploy.policy import DeployablePolicy
from alignrl.envs.core import feature_layout
from alignrl.envs.task import get_task

TASK = get_task("focus")  # 10 steps, at most 25 V per action on a 0..100 V interval
HISTORY = 4
KNOBS = {"defocus": (0.0, 100.0)}
EPSILON = 1e-9


class RecordingDriver:
    """A simulator behind a driver that checks what reaches it (see the module docstring).

    low/high: the site limits the shield must keep; max_step: the largest change it may let
    through; interrupt_at / sigterm_at: the operator presses Ctrl-C / a SIGTERM arrives
    during that measurement (1-based); no_edges_at / fault_at: those measurements fail;
    fail_write_at: that write (1-based) fails in the driver; seconds_per_measure: how far
    each measurement moves `clock` (the watchdog's, injected by the test).
    """

    last: ClassVar[RecordingDriver | None] = None

    def __init__(
        self,
        spec: str = "csv:default",
        seed: int = 3,
        start_v: float | None = None,
        low: float | None = None,
        high: float | None = None,
        max_step: float | None = None,
        interrupt_at: int | None = None,
        sigterm_at: int | None = None,
        no_edges_at: Sequence[int] = (),
        fault_at: Sequence[int] = (),
        fail_write_at: int | None = None,
        seconds_per_measure: float = 0.0,
        best_quality: bool = True,
    ) -> None:
        self.inner = make_apparatus(spec, seed=seed)
        self.knobs: Mapping[str, tuple[float, float]] = dict(self.inner.knobs)
        if start_v is not None:
            self.inner.write({"defocus": start_v})
        self.low, self.high, self.max_step = low, high, max_step
        self.interrupt_at, self.sigterm_at = interrupt_at, sigterm_at
        self.no_edges_at, self.fault_at = set(no_edges_at), set(fault_at)
        self.fail_write_at = fail_write_at
        self.seconds_per_measure = seconds_per_measure
        self.now = 0.0
        self.calls: list[tuple[str, Any]] = []
        self.violations: list[str] = []
        self.start: dict[str, float] | None = None
        self.aborted_at: int | None = None  # len(calls) when the abort was raised
        self.restores = 0
        if not best_quality:
            self.best_quality = None  # type: ignore[assignment]
        RecordingDriver.last = self

    def clock(self) -> float:
        return self.now

    def count(self, kind: str) -> int:
        return sum(1 for call in self.calls if call[0] == kind)

    def writes(self) -> list[float]:
        return [call[1]["defocus"] for call in self.calls if call[0] == "write"]

    def _violation(self, message: str) -> None:
        self.violations.append(message)
        raise AssertionError(f"the shield let through: {message}")

    def reset(self, seed: int | None = None) -> None:
        self._violation("a reset (align must start from the column as it is)")

    def read(self) -> dict[str, float]:
        values = self.inner.read()
        self.calls.append(("read", dict(values)))
        if self.start is None:
            self.start = dict(values)
        return values

    def write(self, values: Mapping[str, float]) -> None:
        values = dict(values)
        self.calls.append(("write", values))
        if self.fail_write_at is not None and self.count("write") == self.fail_write_at:
            raise ApparatusError("the lens supply does not answer")
        value = values["defocus"]
        current = self.inner.read()["defocus"]
        if self.aborted_at is not None:
            if values == self.start and self.restores == 0:
                self.restores += 1  # the one restore, exempt from the maximum step
                self.inner.write(values)
                return
            self._violation(f"a write {values} after the abort")
        low, high = self.knobs["defocus"]
        if not (math.isfinite(value) and low <= value <= high):
            self._violation(f"{value} outside the apparatus interval [{low}, {high}]")
        if self.low is not None and value < self.low - EPSILON:
            self._violation(f"{value} below the site limit {self.low}")
        if self.high is not None and value > self.high + EPSILON:
            self._violation(f"{value} above the site limit {self.high}")
        if self.max_step is not None and abs(value - current) > self.max_step + EPSILON:
            self._violation(f"a step {current} -> {value} larger than {self.max_step}")
        self.inner.write(values)

    def measure(self) -> float:
        self.calls.append(("measure", None))
        if self.aborted_at is not None:
            self._violation("a measurement after the abort")
        number = self.count("measure")
        self.now += self.seconds_per_measure
        if number == self.interrupt_at:
            self.aborted_at = len(self.calls)
            raise KeyboardInterrupt
        if number == self.sigterm_at:
            import os
            import signal

            self.aborted_at = len(self.calls)
            os.kill(os.getpid(), signal.SIGTERM)  # the handler raises on the next bytecode
        if number in self.no_edges_at:
            raise NoEdgesError("no edges in this frame")
        if number in self.fault_at:
            raise ApparatusError("frame grabber timeout")
        return float(self.inner.measure())

    def best_quality(self) -> float:
        self.calls.append(("best_quality", None))
        return float(self.inner.best_quality())  # type: ignore[attr-defined]

    def image(self) -> np.ndarray | None:
        return None

    def optimum_v(self) -> float:
        """For the scripted policies of the tests only (alignrl never sees it)."""
        return float(self.inner.optimum()["defocus"])  # type: ignore[attr-defined]


# --- scripted policies --------------------------------------------------------------------


def setting_seen(history: np.ndarray) -> float:
    """The defocus (V) the newest history row says the column is at."""
    normalized = float(history[-1, feature_layout(1)["knobs"]][0])
    return KNOBS["defocus"][0] + (normalized + 1.0) / 2.0 * 100.0


def scripted(
    act: Callable[[np.ndarray], Sequence[float]], name: str = "scripted"
) -> DeployablePolicy:
    return DeployablePolicy(
        name, lambda history: np.asarray(act(history), float), TASK, HISTORY, "a test script"
    )


def constant(*action: float) -> DeployablePolicy:
    return scripted(lambda history: action, f"constant{action}")


def by_row(*actions: Sequence[float]) -> DeployablePolicy:
    """actions[i] once the history holds i + 1 measured rows (the last one from then on);
    an empty history (the shape check before the alignment) gets actions[0]."""

    def act(history: np.ndarray) -> Sequence[float]:
        rows = int(history[:, feature_layout(1)["valid"]].sum())
        return actions[min(max(rows - 1, 0), len(actions) - 1)]

    return scripted(act, "by-row")


def seeker(driver: RecordingDriver, tolerance_v: float = 0.3) -> DeployablePolicy:
    """Moves toward the optimum from where the history says the column is; stops there."""

    def act(history: np.ndarray) -> list[float]:
        error_v = driver.optimum_v() - setting_seen(history)
        if abs(error_v) < tolerance_v:
            return [0.0, 1.0]
        return [float(np.clip(error_v / 25.0, -1.0, 1.0)), -1.0]

    return scripted(act, "seeker")


def run(
    policy: DeployablePolicy,
    driver: RecordingDriver,
    site: Mapping[str, Any] | None = None,
    max_step: Mapping[str, Any] | None = None,
    **options: Any,
) -> tuple[Any, MemoryAudit]:
    audit = MemoryAudit()
    limits = resolve_limits(driver.knobs, site, max_step)
    result = align(policy, driver, limits, audit, clock=driver.clock, **options)
    assert not driver.violations
    return result, audit


def records(audit: MemoryAudit, event: str, **match: Any) -> list[dict[str, Any]]:
    return [
        entry
        for entry in audit.entries
        if entry["event"] == event and all(entry.get(k) == v for k, v in match.items())
    ]


# --- limits: pure rules -------------------------------------------------------------------


def test_site_limits_tighten_the_interval_and_name_their_rule() -> None:
    limits = resolve_limits(KNOBS, {"defocus": [40, 100]}, {"defocus": 2})
    assert limits["defocus"] == KnobLimits(40.0, 100.0, "site limit", "apparatus interval", 2.0)
    assert resolve_limits(KNOBS)["defocus"] == KnobLimits(
        0.0, 100.0, "apparatus interval", "apparatus interval", None
    )


@pytest.mark.parametrize(
    ("site", "max_step", "message"),
    [
        ({"defocus": [-5, 60]}, None, "not inside the apparatus's interval"),
        ({"defocus": [40, 101]}, None, "not inside the apparatus's interval"),
        ({"defocus": [120, 130]}, None, "not inside the apparatus's interval"),  # disjoint
        ({"defocus": [60, 40]}, None, "must be below high"),
        ({"defocus": [50, 50]}, None, "must be below high"),
        ({"defocus": [40, float("nan")]}, None, "not a finite number"),
        ({"defocus": [40, "60"]}, None, "is not a number"),
        ({"defocus": 40}, None, "needs [low, high]"),
        ({"stigmator_x": [0, 1]}, None, "unknown knob 'stigmator_x'"),
        (None, {"defocus": 0}, "must be a positive change"),
        (None, {"defocus": -1.0}, "must be a positive change"),
        (None, {"defocus": float("inf")}, "not a finite number"),
        (None, {"aperture_x": 1.0}, "--max-step: unknown knob"),
    ],
)
def test_bad_limits_are_refused_with_a_reason(
    site: dict[str, Any] | None, max_step: dict[str, Any] | None, message: str
) -> None:
    with pytest.raises(ShieldConfigError, match=message.replace("[", r"\[").replace("(", r"\(")):
        resolve_limits(KNOBS, site, max_step)


def test_clamp_write_applies_interval_site_limit_and_max_step_in_order() -> None:
    limits = resolve_limits(KNOBS, {"defocus": [40, 60]}, {"defocus": 2.0})
    current = {"defocus": 59.0}
    inside = clamp_write(limits, current, {"defocus": 60.0})
    assert inside.values == {"defocus": 60.0} and inside.clamps == ()
    site = clamp_write(limits, current, {"defocus": 75.0})
    assert site.values == {"defocus": 60.0}
    assert site.clamps[0]["rule"] == "site limit high 60"
    step = clamp_write(limits, current, {"defocus": 41.0})
    assert step.values == {"defocus": 57.0} and step.clamps[0]["rule"] == "max step 2"
    both = clamp_write(limits, {"defocus": 45.0}, {"defocus": 10.0})
    assert both.values == {"defocus": 43.0}
    assert both.clamps[0] == {
        "knob": "defocus",
        "from": 10.0,
        "to": 43.0,
        "rule": "site limit low 40, max step 2",
    }
    interval = clamp_write(resolve_limits(KNOBS), {"defocus": 90.0}, {"defocus": 130.0})
    assert interval.values == {"defocus": 100.0}
    assert interval.clamps[0]["rule"] == "apparatus interval high 100"
    for bad in (float("nan"), float("inf")):
        with pytest.raises(RefusedWrite, match="not a finite value"):
            clamp_write(limits, current, {"defocus": bad})
    with pytest.raises(RefusedWrite, match="unknown knob"):
        clamp_write(limits, current, {"stigmator_x": 0.0})


def test_watchdog_fires_on_time_and_on_acquisitions() -> None:
    now = [100.0]
    watchdog = Watchdog(timeout_s=5.0, max_acquisitions=3, clock=lambda: now[0])
    watchdog.start()
    assert watchdog.expiry(2) is None
    assert "3 acquisitions" in (watchdog.expiry(3) or "")
    assert watchdog.expiry(None) is None  # the final image is not counted
    now[0] = 105.0
    assert "5 s" in (watchdog.expiry(0) or "")
    with pytest.raises(ShieldConfigError):
        Watchdog(timeout_s=0.0)
    with pytest.raises(ShieldConfigError):
        Watchdog(max_acquisitions=0)


# --- the shielded apparatus on its own ----------------------------------------------------


def test_shielded_writes_are_clamped_before_the_driver_sees_them() -> None:
    driver = RecordingDriver(low=40, high=60, max_step=2.0)
    audit = MemoryAudit()
    shield = ShieldedApparatus(
        driver, resolve_limits(driver.knobs, {"defocus": [40, 60]}, {"defocus": 2}), audit
    )
    assert shield.begin() == {"defocus": 50.0}
    shield.write({"defocus": 95.0})  # site limit then max step: 52
    shield.write({"defocus": 52.5})
    shield.write({"defocus": 52.5})  # unchanged: not sent
    assert driver.writes() == [52.0, 52.5]
    assert (shield.writes, shield.clamped, shield.refused) == (2, 1, 0)
    writes = records(audit, "write")
    assert [w["decision"] for w in writes] == ["clamped", "allowed", "allowed"]
    assert writes[0]["clamps"][0]["rule"] == "site limit high 60, max step 2"
    assert writes[2]["sent"] is False and writes[2]["unchanged"] is True
    with pytest.raises(RefusedWrite):
        shield.write({"defocus": float("nan")})
    assert driver.writes() == [52.0, 52.5] and shield.refused == 1


def test_shield_refuses_to_start_outside_the_site_limits() -> None:
    driver = RecordingDriver(start_v=30.0)
    audit = MemoryAudit()
    shield = ShieldedApparatus(driver, resolve_limits(driver.knobs, {"defocus": [40, 60]}), audit)
    with pytest.raises(StartOutsideLimits, match="defocus = 30"):
        shield.begin()
    assert driver.count("write") == 0


def test_shield_after_abort_lets_nothing_through_but_one_restore() -> None:
    driver = RecordingDriver()
    shield = ShieldedApparatus(driver, resolve_limits(driver.knobs), MemoryAudit())
    shield.begin()
    shield.write({"defocus": 60.0})
    driver.aborted_at = len(driver.calls)  # from here the driver accepts only the restore
    shield.abort("operator abort")
    for call in (lambda: shield.write({"defocus": 61.0}), shield.measure, shield.read):
        with pytest.raises(Exception, match="aborted"):
            call()
    assert shield.restore() is True
    assert shield.restore() is False  # once only
    assert driver.writes() == [60.0, 50.0] and driver.restores == 1


# --- the shield around the alignment loop ---------------------------------------------------


def test_interval_rule_keeps_every_write_inside_the_apparatus() -> None:
    driver = RecordingDriver()
    result, _ = run(constant(1.0, -1.0), driver)  # full speed up, never stops
    assert max(driver.writes()) == 100.0  # 75, 100, then held at the bound
    assert driver.writes() == [75.0, 100.0]
    assert result.outcome == "not-aligned" and result.final_setting == {"defocus": 100.0}


def test_site_limits_tighter_than_the_interval_hold_the_knob() -> None:
    driver = RecordingDriver(low=40, high=60)
    result, audit = run(constant(1.0, -1.0), driver, site={"defocus": [40, 60]})
    assert driver.writes() == [60.0]
    assert result.clamped == 10 and result.writes == 1
    clamp = records(audit, "write", decision="clamped")[0]["clamps"][0]
    assert clamp == {"knob": "defocus", "from": 75.0, "to": 60.0, "rule": "site limit high 60"}


def test_max_step_limits_every_change_and_the_policy_sees_the_real_setting() -> None:
    driver = RecordingDriver(max_step=5.0)  # seed 3: focus at 69.8 V, start 50 V
    seen: list[float] = []
    policy = seeker(driver)
    recording = scripted(lambda h: (seen.append(setting_seen(h)), policy.act(h))[1], "seeker")
    result, _ = run(recording, driver, max_step={"defocus": 5.0}, spec_px=3.5)
    steps = np.diff([50.0, *driver.writes()])
    assert np.all(np.abs(steps) <= 5.0 + EPSILON) and len(steps) >= 4
    # The history shows where the column is, not where the policy asked it to go: the
    # seeker, which trusts the history, still reaches the focus in 5 V steps.
    assert seen[2:6] == pytest.approx([55.0, 60.0, 65.0, 69.8], abs=0.3)  # [0]: shape check
    assert result.outcome == "aligned" and result.clamped >= 3


def test_non_finite_action_stops_before_any_write() -> None:
    driver = RecordingDriver()
    result, audit = run(constant(float("nan"), -1.0), driver)
    assert driver.count("write") == 0
    assert result.outcome == "aborted" and "non-finite" in result.reason
    assert result.exit_code == 3 and records(audit, "action", decision="refused")


def test_non_finite_action_later_stops_with_the_writes_before_it() -> None:
    driver = RecordingDriver()
    result, _ = run(by_row([0.2, -1.0], [math.inf, -1.0], [0.2, -1.0]), driver)
    assert driver.writes() == [55.0]
    assert result.aborted and result.final_setting == {"defocus": 55.0}


def test_watchdog_by_acquisitions_stops_before_the_next_write() -> None:
    driver = RecordingDriver()
    result, audit = run(constant(0.1, -1.0), driver, max_acquisitions=3)
    assert driver.count("measure") == 3 and driver.calls[-1][0] == "measure"
    assert driver.writes() == [52.5, 55.0]  # the third step's write never reached it
    assert result.outcome == "aborted" and "3 acquisitions" in result.reason
    assert records(audit, "write", decision="aborted")


def test_watchdog_by_time_uses_the_injected_clock() -> None:
    driver = RecordingDriver(seconds_per_measure=1.0)  # each image takes 1 s
    result, audit = run(constant(0.1, -1.0), driver, timeout_s=3.5)
    # images end at 1, 2, 3, 4 s; the write due at 4 s is refused, and nothing follows
    assert driver.count("measure") == 4 and driver.calls[-1][0] == "measure"
    assert result.exit_code == 3 and "3.5 s" in result.reason
    assert records(audit, "abort")[0]["monotonic_s"] == 4.0


@pytest.mark.parametrize("restore", [False, True])
def test_ctrl_c_inside_the_driver_stops_at_once(restore: bool) -> None:
    driver = RecordingDriver(interrupt_at=4)
    result, audit = run(constant(0.2, -1.0), driver, restore_on_abort=restore)
    aborted = driver.calls[driver.aborted_at :]
    if restore:
        assert aborted == [("write", {"defocus": 50.0})]  # exactly one restore, to the start
        assert result.restored and result.final_setting == {"defocus": 50.0}
    else:
        assert aborted == []  # the last safe setting stays
        assert result.final_setting == {"defocus": 65.0}
    assert result.outcome == "aborted" and result.reason.startswith("operator abort")
    assert records(audit, "abort")


def test_sigterm_is_an_operator_abort() -> None:
    import signal

    from alignrl.deploy.align import operator_signals

    before = signal.getsignal(signal.SIGTERM)
    driver = RecordingDriver(sigterm_at=2)
    with operator_signals():
        result, _ = run(constant(0.2, -1.0), driver, restore_on_abort=True)
    assert signal.getsignal(signal.SIGTERM) is before
    assert result.aborted and result.restored
    assert driver.calls[driver.aborted_at :] == [("write", {"defocus": 50.0})]


def test_dry_run_writes_nothing_and_logs_every_write_it_would_make() -> None:
    driver = RecordingDriver()
    result, audit = run(constant(0.2, -1.0), driver, dry_run=True, max_step={"defocus": 2.0})
    assert driver.count("write") == 0 and result.writes == 0
    would = records(audit, "write", decision="dry-run")
    assert len(would) == TASK.episode_steps
    # The column never moves, so every decision starts from 50 V: 50 + 5 asked, 52 allowed.
    assert all(w["requested"] == {"defocus": 55.0} for w in would)
    assert all(w["value"] == {"defocus": 52.0} and w["would_be"] == "clamped" for w in would)
    assert driver.count("measure") == TASK.episode_steps + 2  # it still measures
    assert result.final_setting == result.start_setting == {"defocus": 50.0}


def test_audit_log_has_a_line_for_every_driver_call() -> None:
    driver = RecordingDriver(max_step=3.0, no_edges_at=[3])
    result, audit = run(seeker(driver), driver, max_step={"defocus": 3.0})
    sent = [entry for entry in audit.entries if entry.get("sent")]
    by_event = {
        event: sum(1 for e in sent if e["event"] == event) for event in {e["event"] for e in sent}
    }
    assert by_event == {
        "read": driver.count("read"),
        "write": driver.count("write"),
        "measure": driver.count("measure"),
        "reference": driver.count("best_quality"),
    }
    assert audit.entries[0]["event"] == "start" and audit.entries[-1]["event"] == "end"
    for entry in audit.entries:
        assert entry["time"].endswith("+00:00") and isinstance(entry["monotonic_s"], float)
    assert audit.entries[-1]["result"]["outcome"] == result.outcome


def test_measurement_failures_are_logged_and_the_alignment_goes_on() -> None:
    driver = RecordingDriver(no_edges_at=[2], fault_at=[3])
    histories: list[np.ndarray] = []
    result, audit = run(
        scripted(lambda h: (histories.append(h.copy()), [0.1, -1.0])[1]), driver, spec_px=3.0
    )
    failed = [e for e in records(audit, "measure") if "error" in e]
    assert [e["error"] for e in failed] == ["no edges in this frame", "frame grabber timeout"]
    measured = feature_layout(1)["measured"]
    assert histories[3][-3:, measured].ravel().tolist() == [1.0, 0.0, 0.0]  # [0]: shape check
    assert result.acquisitions == TASK.episode_steps + 1 and result.outcome == "not-aligned"


def test_final_image_without_edges_is_not_aligned() -> None:
    driver = RecordingDriver(no_edges_at=[2])
    result, _ = run(constant(0.0, 1.0), driver, spec_px=50.0)  # stops at once
    assert result.final_width_px is None and result.exit_code == 1


def test_driver_failure_on_write_stops_with_exit_4() -> None:
    driver = RecordingDriver(fail_write_at=2)
    result, audit = run(constant(0.2, -1.0), driver, restore_on_abort=True)
    assert driver.writes() == [55.0, 60.0]  # the failed one, then nothing: not even a restore
    assert result.outcome == "driver-failure" and result.exit_code == 4
    assert result.final_setting is None and "lens supply" in result.reason
    assert records(audit, "write-error")


def test_a_bug_in_the_policy_surfaces_but_the_log_ends_and_nothing_follows() -> None:
    driver = RecordingDriver()

    def act(history: np.ndarray) -> list[float]:
        if history[:, 0].sum() >= 2:
            raise RuntimeError("CUDA error: an illegal memory access")
        return [0.2, -1.0]

    audit = MemoryAudit()
    with pytest.raises(RuntimeError, match="illegal memory access"):
        align(scripted(act), driver, resolve_limits(driver.knobs), audit, restore_on_abort=True)
    assert driver.writes() == [55.0]  # and no restore: a bug is not an operator's abort
    assert [e["event"] for e in audit.entries[-2:]] == ["abort", "end"]
    assert "RuntimeError" in audit.entries[-1]["error"]


# --- the measures of the multi-knob tasks -------------------------------------------------


def _column_shield(**kwargs: Any) -> tuple[ShieldedApparatus, MemoryAudit, Any]:
    from fake_drivers import FiveKnobColumn

    column = FiveKnobColumn()
    column.write({"defocus": 50.0, "aperture_x": 10.0})
    audit = MemoryAudit()
    site = kwargs.pop("site", None)
    shield = ShieldedApparatus(column, resolve_limits(column.knobs, site), audit, **kwargs)
    shield.begin()
    return shield, audit, column


def test_a_wobble_stays_inside_the_limits_and_is_on_record() -> None:
    shield, audit, column = _column_shield(site={"defocus": [47.0, 70.0]})
    expected = column.measure_wobble(3.0)  # the swing the limits leave: 50 - 47 = 3 V
    shift = shield.measure_wobble(5.0)
    assert shift == pytest.approx(expected)
    assert shield.acquisitions == 2
    wobble = [entry for entry in audit.entries if entry["event"] == "wobble"]
    assert wobble[0]["decision"] == "clamped" and wobble[0]["swing"] == [47.0, 53.0]
    assert column.read()["defocus"] == 50.0  # back where it was


def test_a_dry_run_makes_no_wobble_and_a_limit_leaves_no_room() -> None:
    from alignrl.apparatus import MeasurementError

    shield, _, column = _column_shield(dry_run=True)
    before = column.images
    with pytest.raises(MeasurementError, match="dry run"):
        shield.measure_wobble(5.0)
    assert column.images == before
    shield, _, _ = _column_shield(site={"defocus": [50.0, 60.0]})
    with pytest.raises(MeasurementError, match="sits on a limit"):
        shield.measure_wobble(5.0)


def test_directional_measures_count_and_log() -> None:
    shield, audit, column = _column_shield()
    width, widths = shield.measure_directional()
    assert (width, list(widths)) == (column.measure_directional()[0], list(widths))
    assert shield.acquisitions == 1
    assert audit.entries[-1]["directional_px"] == pytest.approx(list(widths))


def test_a_family_column_brings_its_own_interval_at_every_reset_and_the_shield_follows() -> None:
    """An instrument family draws a column, with its own interval, at every reset: the
    training shield resolves its limits again against each one (an adaptation across the
    family wrote into the first column's interval before, and died at the first new one),
    and still refuses every write outside the interval of the column now in place."""
    from alignrl.apparatus.limits import ShieldOptions
    from alignrl.apparatus.training_shield import shield_apparatus

    column = make_apparatus("family:focus", {"analytic": True})
    shielded = shield_apparatus(column, ShieldOptions(simulators=True, max_step={"defocus": 5.0}))
    seen = set()
    for seed in range(6):
        shielded.reset(seed)
        low, high = column.knobs["defocus"]
        assert shielded.knobs["defocus"] == (low, high)
        seen.add((low, high))
        assert shielded.limits["defocus"].low == low and shielded.limits["defocus"].high == high
        assert shielded.limits["defocus"].max_step == 5.0  # the options hold on every column
        shielded.write({"defocus": high + 0.25 * (high - low)})  # the start: clamped, no step
        assert column.read()["defocus"] == high
        with contextlib.suppress(NoEdgesError):  # far from focus a frame may have none
            shielded.measure()
        shielded.write({"defocus": low})  # the aligner's: clamped to the maximum step
        assert column.read()["defocus"] == pytest.approx(high - 5.0)
    assert len(seen) == 6


def test_site_limits_that_a_new_column_does_not_hold_stop_before_any_write() -> None:
    from alignrl.apparatus.limits import ShieldOptions
    from alignrl.apparatus.training_shield import shield_apparatus

    column = make_apparatus("family:focus", {"analytic": True})
    column.reset(0)
    low, high = column.knobs["defocus"]
    limits = {"defocus": [low + 0.1 * (high - low), high - 0.1 * (high - low)]}
    shielded = shield_apparatus(column, ShieldOptions(simulators=True, site_limits=limits))
    seed = next(s for s in range(1, 50) if column.reset(s) or column.knobs["defocus"][0] > low)
    with pytest.raises(ShieldConfigError, match="do not fit the limits"):
        shielded.reset(seed)
    assert shielded.aborted and shielded.writes == 0
    with pytest.raises(Aborted):
        shielded.write({"defocus": sum(column.knobs["defocus"]) / 2})
    assert shielded.writes == 0

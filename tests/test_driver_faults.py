"""A driver that changes its mind, exits, hangs where no call is made, or answers what cannot
be: every verb that touches it ends with the driver code, having written nothing outside the
interval the driver declared at that moment, and says so in its audit log.

The driver is `fake_drivers:HostileLens` (tests/fake_drivers.py), run through each verb as
tests/test_shielded_paths.py runs it. `make test` runs a sample of the verb matrix (each
behaviour on a few verbs, each verb under a few behaviours); `make test-all` runs all of it.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_drivers import HostileLens
from hostile import Outcome, assert_refused, run_cli
from test_shielded_paths import VERBS, _command, _moving_policy, member_file  # noqa: F401

from alignrl.apparatus.audit import MemoryAudit
from alignrl.apparatus.guard import DriverFailure
from alignrl.apparatus.limits import ShieldOptions
from alignrl.apparatus.registry import make_apparatus

EXIT_DRIVER_FAILURE, EXIT_INTERRUPTED = 4, 130
ROOT = Path(__file__).parent.parent
NAMED_FAULTS = {"end", "abort", "driver-fault"}


@pytest.fixture(autouse=True)
def fresh_driver_records() -> None:
    HostileLens.received.clear()
    HostileLens.received_in.clear()
    HostileLens.instances.clear()


def _with_log(verb: str, command: list[str], root: Path) -> tuple[list[str], Path | None]:
    """The command with an audit log where the verb takes one; where it keeps it."""
    if verb in ("adapt", "train"):
        return command, None  # the run's own audit.jsonl
    if verb == "league":
        return command, None  # audited in memory
    log = root / "audit.jsonl"
    return [*command, "--log", str(log)], log


def _audit(verb: str, log: Path | None, root: Path) -> list[dict[str, Any]] | None:
    if log is None:
        found = sorted(root.glob("runs/*/audit.jsonl"))
        if not found:
            return None
        log = found[-1]
    if not log.exists():  # the driver failed as it was opened: nothing was ever sent
        assert HostileLens.received == []
        return None
    return [json.loads(line) for line in log.read_text().splitlines()]


def _nothing_outside_what_was_declared() -> None:
    """Every write the driver received was finite and inside the interval it declared as
    the write came."""
    for values, declared in HostileLens.received_in:
        for name, value in values.items():
            low, high = declared[name]
            assert math.isfinite(value) and low <= value <= high, (values, declared)


def _ends_on_record(records: list[dict[str, Any]] | None) -> None:
    """The audit log's last record is the end, or the fault that ended the work."""
    if records is None:
        return
    assert records, "an empty audit log"
    assert records[-1]["event"] in NAMED_FAULTS, records[-3:]


# --- the matrix: each behaviour through each verb ----------------------------------------

BEHAVIOURS: dict[str, tuple[dict[str, Any], str]] = {
    "narrows": ({"narrow_after": 2, "narrow_to": [45.0, 55.0]}, "intervals changed"),
    "exit-in-write": ({"write_error": "SystemExit"}, "write() raised SystemExit"),
    "exit-in-measure": ({"measure_error": "SystemExit"}, "measure() raised SystemExit"),
    "exit-in-read": ({"read_error": "SystemExit"}, "read() raised SystemExit"),
    "exit-in-knobs": ({"knobs_error": "SystemExit"}, "raised SystemExit"),
    "getter-raises": ({"knobs_error": "RuntimeError"}, "raised RuntimeError"),
    "hang-in-knobs": ({"hang": "knobs", "hang_after": 3}, "did not return within 1 s"),
    "reads-huge-integer": ({"read_value": 10**400}, "not a finite number"),
}
# The sample `make test` runs: every behaviour on two verbs, every verb at least twice.
SAMPLE = {
    ("narrows", "align"),
    ("narrows", "evaluate-classical"),
    ("narrows", "train"),
    ("exit-in-write", "record"),
    ("exit-in-write", "evaluate-policy"),
    ("exit-in-measure", "baselines"),
    ("exit-in-measure", "league"),
    ("exit-in-read", "align"),
    ("exit-in-read", "adapt"),
    ("exit-in-knobs", "evaluate-posterior"),
    ("exit-in-knobs", "record"),
    ("getter-raises", "baselines"),
    ("getter-raises", "league"),
    ("hang-in-knobs", "evaluate-classical"),
    ("hang-in-knobs", "adapt"),
    ("reads-huge-integer", "evaluate-posterior"),
    ("reads-huge-integer", "train"),
    ("narrows", "evaluate-policy"),
}
# train and league take no --call-timeout: their driver calls have the default limit (60 s),
# which a test of a hang would wait out; the other verbs show the limit on the getter.
TIMED = [verb for verb in VERBS if verb not in ("train", "league")]
MATRIX = [
    pytest.param(behaviour, verb, marks=() if (behaviour, verb) in SAMPLE else pytest.mark.long)
    for behaviour in BEHAVIOURS
    for verb in (TIMED if behaviour.startswith("hang") else VERBS)
]


@pytest.mark.parametrize(("behaviour", "verb"), MATRIX)
def test_a_driver_fault_ends_every_verb_with_the_driver_code_and_nothing_outside(
    behaviour: str,
    verb: str,
    tmp_path: Path,
    member_file: Path,  # noqa: F811
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.9, -1.0)
    driver, named = BEHAVIOURS[behaviour]
    command, log = _with_log(verb, _command(verb, tmp_path, member_file, driver), tmp_path)
    outcome = run_cli([*command, *(["--call-timeout", "1"] if verb in TIMED else [])], capsys)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, named)
    _nothing_outside_what_was_declared()
    _ends_on_record(_audit(verb, log, tmp_path))


def test_an_interval_that_narrows_stops_the_alignment_before_its_next_write(
    tmp_path: Path,
    member_file: Path,  # noqa: F811
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.9, -1.0)
    driver = {"narrow_after": 2, "narrow_to": [45.0, 55.0]}
    command, log = _with_log("align", _command("align", tmp_path, member_file, driver), tmp_path)
    outcome = run_cli([*command, "--json"], capsys)
    assert outcome.code == EXIT_DRIVER_FAILURE, outcome.text
    result = json.loads(outcome.out)
    assert result["outcome"] == "driver-failure" and not result["success"]
    assert "defocus [0.0, 100.0] -> [45.0, 55.0]" in result["reason"]
    assert len(HostileLens.received) == 2  # the two before the change; none after
    records = _audit("align", log, tmp_path)
    assert records is not None
    fault = next(r for r in records if r["event"] == "driver-fault")
    assert fault["call"] == "knobs"
    later = records[records.index(fault) + 1 :]
    assert not any(r.get("sent") for r in later), later
    assert records[-1]["event"] == "end"


def test_a_family_follows_its_new_interval_at_reset_but_not_inside_an_alignment() -> None:
    audit = MemoryAudit()
    family = make_apparatus(
        "fake_drivers:HostileFamily",
        {"interval_at_reset": [10.0, 90.0]},
        shield=ShieldOptions(audit=audit),
    )
    family.reset(1)  # the driver's second reset: a new column, with its own interval
    assert family.knobs == {"defocus": (10.0, 90.0)}
    family.write({"defocus": 95.0})  # a scenario's start, clamped into the new interval
    assert HostileLens.received == [{"defocus": 90.0}]
    lens = make_apparatus(
        "fake_drivers:HostileLens",
        {"interval_at_reset": [10.0, 90.0]},
        shield=ShieldOptions(audit=MemoryAudit()),
    )
    with pytest.raises(DriverFailure, match=r"intervals changed .*defocus \[0.0, 100.0\]"):
        lens.reset(1)  # a driver that is no family may not change its mind at reset either
    narrowing = make_apparatus(
        "fake_drivers:HostileFamily",
        {"narrow_after": 1},
        shield=ShieldOptions(audit=MemoryAudit()),
    )
    narrowing.reset(0)
    narrowing.write({"defocus": 60.0})
    narrowing.measure()
    with pytest.raises(DriverFailure, match="intervals changed"):
        narrowing.write({"defocus": 50.0})  # within the new interval, but mid-alignment
    assert HostileLens.received[-1] == {"defocus": 60.0}


@pytest.mark.parametrize(
    ("driver", "named"),
    [
        ({"interval_at_reset": [-1e308, 1e308]}, "empty or infinite interval"),
        ({"interval_at_reset": ["-inf", "inf"]}, "empty or infinite interval"),
        ({"optimum_value": {}}, "optimum() has no value for knob 'defocus'"),
        ({"optimum_value": {"defocus": 150.0}}, "outside its own interval"),
        ({"best_width": 1e-300}, "best_quality() returned 1e-300"),
        ({"best_width": "nan"}, "best_quality() returned nan"),
    ],
    ids=[
        "family-1e308",
        "family-inf",
        "optimum-missing",
        "optimum-outside",
        "best-1e-300",
        "best-nan",
    ],
)
def test_a_family_or_simulated_driver_whose_secret_cannot_be_is_a_driver_fault(
    driver: dict[str, Any], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    command = ["evaluate", "--policy", "hyperbola", "--scenarios", "2", "--quiet"]
    command += ["--apparatus", "fake_drivers:HostileFamily"]
    command += [] if "best_width" in driver else ["--spec-px", "3"]  # else the best width's
    outcome = run_cli([*command, "--apparatus-args", json.dumps(driver)], capsys)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, named)
    _nothing_outside_what_was_declared()


@pytest.mark.parametrize(
    ("driver", "code", "named"),
    [
        ({"integer_knob": True}, 2, "knob names must be non-empty strings, got 1"),
        ({"interval": [0.0, 1e300]}, 2, "empty or infinite interval (0.0, 1e+300)"),
        ({"width": 10**400}, 0, ""),  # an unmeasured image, every time: nothing aligned
        ({"width": 1e-300}, 0, ""),
    ],
    ids=["knob-named-1", "interval-1e300", "width-huge-integer", "width-1e-300"],
)
def test_impossible_answers_are_refused_or_unmeasured_never_an_internal_error(
    driver: dict[str, Any], code: int, named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    command = ["evaluate", "--policy", "hyperbola", "--scenarios", "2", "--spec-px", "3"]
    command += ["--apparatus", "fake_drivers:HostileLens", "--json", "--quiet"]
    outcome = run_cli([*command, "--apparatus-args", json.dumps(driver)], capsys)
    assert_refused(outcome, code, named)
    if code == 0:
        assert json.loads(outcome.out)["successes"] == 0


# --- before the driver exists: its import and its constructor ---------------------------


@pytest.mark.parametrize(
    ("spec", "environment", "named"),
    [
        ("driver_fails_on_import:Lens", {"HOSTILE_IMPORT": "exit"}, "raised SystemExit"),
        ("driver_fails_on_import:Lens", {"HOSTILE_IMPORT": "raise"}, "raised RuntimeError"),
        ("driver_hangs_on_import:Lens", {}, "importing module 'driver_hangs_on_import' did not"),
        ("fake_drivers:HostileLens", {}, "opening the driver"),
    ],
    ids=["exits", "raises", "hangs", "constructor-hangs"],
)
@pytest.mark.parametrize("verb", ["evaluate", "align"])
def test_an_import_or_constructor_that_exits_raises_or_hangs_is_a_driver_failure(
    spec: str,
    environment: dict[str, str],
    named: str,
    verb: str,
    member_file: Path,  # noqa: F811
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for key, value in environment.items():
        monkeypatch.setenv(key, value)
    driver = {"hang": "init"} if spec.startswith("fake_drivers") else {}
    policy = "hyperbola" if verb == "evaluate" else str(member_file)
    command = [verb, "--policy", policy, "--apparatus", spec, "--spec-px", "3"]
    command += ["--apparatus-args", json.dumps(driver), "--call-timeout", "1"]
    started = time.perf_counter()
    outcome = run_cli(command, capsys)
    assert time.perf_counter() - started < 10
    assert_refused(outcome, EXIT_DRIVER_FAILURE, named)


# --- a --gif never changes the outcome -------------------------------------------------


@pytest.mark.parametrize(
    "driver", [{"image_shape": [2, 2, 8, 8]}, {"image_error": "RuntimeError"}], ids=["4d", "raises"]
)
@pytest.mark.parametrize("verb", ["align", "evaluate-classical"])
def test_a_driver_image_that_is_none_spoils_frames_not_the_result(
    driver: dict[str, Any],
    verb: str,
    tmp_path: Path,
    member_file: Path,  # noqa: F811
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.3, -1.0)
    plain = run_cli([*_command(verb, tmp_path, member_file, {}), "--json"], capsys)
    gif = tmp_path / "film.gif"
    filmed_command = [*_command(verb, tmp_path, member_file, driver), "--json", "--gif", str(gif)]
    filmed = run_cli(filmed_command, capsys)
    assert filmed.code == plain.code, filmed.text
    without, with_gif = json.loads(plain.out), json.loads(filmed.out)
    for key in ("outcome", "successes", "final_width_px", "acquisitions"):
        assert with_gif.get(key) == without.get(key), key


# --- Ctrl-C or SIGTERM while a driver call hangs -----------------------------------------

# A hang far longer than the exit takes (about 0.2 s on 2 idle cores, benchmarks aside): a
# command that waited for the call to return would take all of it.
HUNG_FOR_S = 30.0
RUNNER = """
import sys
import alignrl.deploy.policy as policy_module
from test_shield import constant
policy_module.load_deployable = lambda *args, **kw: constant(0.3, -1.0)
from alignrl.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _terminated_while_hung(command: list[str], marker: Path) -> tuple[Outcome, float]:
    """`alignrl COMMAND` in a process of its own, sent SIGTERM once its driver hangs; its
    outcome and the seconds from the signal to its exit."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(["tests", "docs/examples"])}
    process = subprocess.Popen(
        [sys.executable, "-c", RUNNER, *command],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not marker.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the driver never hung"
        time.sleep(0.05)
    signalled = time.monotonic()
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=60)
    return Outcome(process.returncode, out, err), time.monotonic() - signalled


def test_sigterm_during_a_hung_call_ends_align_at_once_and_restores_nothing(
    tmp_path: Path,
    member_file: Path,  # noqa: F811
) -> None:
    marker, log = tmp_path / "hung", tmp_path / "audit.jsonl"
    driver = {"hang": "measure", "hang_after": 2, "hang_marker": str(marker)}
    driver["hang_s"] = HUNG_FOR_S
    command = _command("align", tmp_path, member_file, driver)
    command += ["--restore-on-abort", "--log", str(log), "--json"]
    outcome, seconds = _terminated_while_hung(command, marker)
    assert outcome.code == 3, outcome.text  # aborted by the operator
    assert seconds < HUNG_FOR_S / 2, f"{seconds:.2f} s from SIGTERM to exit"
    result = json.loads(outcome.out)
    assert result["outcome"] == "aborted" and not result["restored"]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    (restore,) = [r for r in records if r["event"] == "restore"]
    assert restore["sent"] is False and "measure() had not returned" in restore["reason"]
    assert records[-1]["event"] == "end"


@pytest.mark.parametrize("verb", ["evaluate-policy", "baselines"])
def test_sigterm_ends_a_session_as_ctrl_c_does(
    verb: str,
    tmp_path: Path,
    member_file: Path,  # noqa: F811
) -> None:
    marker = tmp_path / "hung"
    driver = {"hang": "measure", "hang_after": 2, "hang_marker": str(marker)}
    driver["hang_s"] = HUNG_FOR_S
    outcome, seconds = _terminated_while_hung(_command(verb, tmp_path, member_file, driver), marker)
    assert outcome.code == EXIT_INTERRUPTED, outcome.text
    assert "interrupted" in outcome.err and "Traceback" not in outcome.err
    assert seconds < HUNG_FOR_S / 2, f"{seconds:.2f} s from SIGTERM to exit"


def test_a_recording_never_writes_a_file_its_own_validation_rejects(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sweep.csv"
    command = ["record", "--apparatus", "fake_drivers:HostileLens", "--scenarios", "1"]
    command += ["--apparatus-args", json.dumps({"interval": [0.0, 1e-7]}), "--out", str(out)]
    outcome = run_cli([*command, "--quiet"], capsys)
    assert_refused(outcome, 2, f"{out}, row 1", "spans only 1e-07")
    assert not out.exists()


@pytest.mark.parametrize("call", ["write", "knobs", "read"])
def test_the_python_api_raises_a_driver_failure_where_a_driver_exits(call: str) -> None:
    from test_shield import constant

    from alignrl import api

    driver = {f"{call}_error": "SystemExit"}
    with pytest.raises(DriverFailure, match="raised SystemExit"):
        api.evaluate("hyperbola", "fake_drivers:HostileLens", driver, scenarios=2, spec_px=3.0)
    moving = constant(0.9, -1.0)
    if call == "knobs":  # the driver fails as it is opened: nothing to align
        with pytest.raises(DriverFailure, match="raised SystemExit"):
            api.align(moving, "fake_drivers:HostileLens", driver, spec_px=3.0)
        return
    result = api.align(moving, "fake_drivers:HostileLens", driver, spec_px=3.0)
    assert result.outcome == "driver-failure" and "SystemExit" in result.reason


CALIBRATE_SAMPLE = {"narrows", "exit-in-measure"}


@pytest.mark.parametrize(
    "behaviour",
    [
        pytest.param(name, marks=() if name in CALIBRATE_SAMPLE else pytest.mark.long)
        for name in BEHAVIOURS
    ],
)
def test_a_driver_fault_ends_a_calibration_with_the_driver_code_and_nothing_outside(
    behaviour: str, light: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    driver, named = BEHAVIOURS[behaviour]
    out, log = tmp_path / "calibrated", tmp_path / "audit.jsonl"
    command = ["calibrate", "--policy", str(light), "--apparatus", "fake_drivers:HostileLens"]
    command += ["--apparatus-args", json.dumps(driver), "--spec-px", "3", "--alignments", "3"]
    command += ["--population", "8", "--rounds", "1", "--quiet", "--out", str(out)]
    outcome = run_cli([*command, "--log", str(log), "--call-timeout", "1"], capsys)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, named)
    assert not out.exists()
    _nothing_outside_what_was_declared()
    _ends_on_record(_audit("calibrate", log, tmp_path))


class NarrowingWobbleLens:
    """A lens with images (a wobble by frames needs them) that narrows its defocus interval
    once it has received its first write."""

    def __init__(self) -> None:
        self.intervals = {"defocus": (0.0, 100.0)}
        self.voltage, self.received = 50.0, []
        self.frame = np.random.default_rng(0).random((32, 32))

    @property
    def knobs(self) -> dict[str, tuple[float, float]]:
        return dict(self.intervals)

    def reset(self, seed: int | None = None) -> None: ...

    def read(self) -> dict[str, float]:
        return {"defocus": self.voltage}

    def write(self, values: dict[str, float]) -> None:
        self.received.append(dict(values))
        self.voltage = values["defocus"]
        self.intervals = {"defocus": (45.0, 55.0)}

    def measure(self) -> float:
        return 3.0

    def image(self) -> np.ndarray:
        return self.frame


def test_each_write_of_a_wobble_is_checked_against_the_interval_declared_then() -> None:
    from alignrl.apparatus.shield import ShieldedApparatus, resolve_limits

    lens = NarrowingWobbleLens()
    shield = ShieldedApparatus(lens, resolve_limits(lens.knobs), MemoryAudit())
    shield.begin()
    with pytest.raises(DriverFailure, match=r"defocus \[0.0, 100.0\] -> \[45.0, 55.0\]"):
        shield.measure_wobble(10.0)
    assert lens.received == [{"defocus": 60.0}]  # the swing out; nothing after the change

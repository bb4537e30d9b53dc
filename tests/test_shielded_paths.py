"""Every path by which alignrl touches an instrument goes through the shield, and no driver
call can hang a command.

The instrument is `fake_drivers:HostileLens`, loaded by import path as a user's driver is: it
records every write it receives before it checks it, and lies, fails or hangs as told. Each
command runs end to end through `alignrl.cli.main` (tests/hostile.py); the shield's own rules
are in tests/test_shield.py.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import one_sac_each, write_experiment, write_league_files
from fake_drivers import HostileLens
from hostile import Outcome, assert_refused, run_cli
from test_align import tiny_member
from test_shield import constant

import alignrl.deploy.policy as policy_module
from alignrl.apparatus.training_shield import TrainingShield
from alignrl.envs.task import get_task
from alignrl.league.ray_backend import MatchWorker

DRIVER = "fake_drivers:HostileLens"
SPEC = ["--spec-px", "3.0"]  # the lens's best edge width is 2.563 px
SITE = {"defocus": [20.0, 80.0]}
EXIT_SHIELD_STOP, EXIT_DRIVER_FAILURE = 3, 4
SMALL = {
    "encoder_kwargs": {"hidden": [16]},
    "hidden": [16, 16],
    "batch_size": 16,
    "learning_starts": 16,
    "random_steps": 32,
}


@pytest.fixture(autouse=True)
def fresh_driver_records() -> None:
    HostileLens.received.clear()
    HostileLens.instances.clear()


@pytest.fixture(scope="module")
def member_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("members") / "tiny.pt"
    tiny_member().save(path)
    return path


def _args(**driver: Any) -> list[str]:
    return ["--apparatus", DRIVER, "--apparatus-args", json.dumps(driver)]


def _train_config(root: Path, driver: dict[str, Any]) -> Path:
    settings = {
        "name": "on-driver",
        "seed": 1,
        "envs": 2,
        "apparatus": DRIVER,
        "apparatus_args": driver,
        "task_options": {"success_absolute_px": 3.0},
        "learner": SMALL,
        "budget": {"env_steps": 48, "eval_every": 48, "eval_scenarios": 2},
    }
    return write_experiment(root, settings)


def _league_config(root: Path, driver: dict[str, Any]) -> Path:
    settings = {
        "name": "league-on-driver",
        "envs": 2,
        "apparatus": DRIVER,
        "apparatus_args": driver,
        "task_options": {"success_absolute_px": 3.0},
        "schedule": {
            "iterations": 2,
            "matches": 2,
            "snapshot_every": 100,
            "evaluate_every": 2,
            "eval_scenarios": 2,
            "checkpoint_every": 2,
        },
    }
    return write_league_files(
        root, **one_sac_each(SMALL), settings=settings, file="league-on-driver.yaml"
    )


def _command(verb: str, root: Path, member: Path, driver: dict[str, Any]) -> list[str]:
    """`verb` on the hostile driver, with site limits and a largest step where it takes
    them (record sweeps the whole interval; train and league have no site limits)."""
    limits = ["--limits", json.dumps(SITE), "--max-step", json.dumps({"defocus": 5.0})]
    session = ["--scenarios", "2", "--quiet", *SPEC, *limits]
    one = ["--scenarios", "1", *session[2:]]
    runs = ["--runs-dir", str(root / "runs")]
    return {
        "evaluate-classical": ["evaluate", "--policy", "hyperbola", *_args(**driver), *session],
        "evaluate-policy": ["evaluate", "--policy", str(member), *_args(**driver), *session],
        # one scenario: the posterior's alignments cost ~1.4 CPU-s each
        "evaluate-posterior": ["evaluate", "--policy", "posterior", *_args(**driver), *one],
        "baselines": ["baselines", *_args(**driver), *session],
        "record": [
            "record",
            *_args(**driver),
            "--scenarios",
            "1",
            "--out",
            str(root / "sweep.csv"),
            "--quiet",
        ],
        "align": ["align", "--policy", str(member), *_args(**driver), *SPEC, *limits],
        "adapt": [
            "adapt",
            "--from",
            str(member),
            *_args(**driver),
            "--steps",
            "40",
            "--eval-every",
            "40",
            "--eval-scenarios",
            "2",
            "--envs",
            "2",
            *SPEC,
            *limits,
            *runs,
            "--quiet",
        ],
        "train": ["train", str(_train_config(root, driver)), *runs, "--quiet"],
        "league": ["league", "run", str(_league_config(root, driver)), *runs, "--quiet"],
    }[verb]


SITE_LIMITED = {"evaluate-classical", "evaluate-policy", "evaluate-posterior", "baselines"}
SITE_LIMITED |= {"align", "adapt"}
VERBS = ["evaluate-classical", "evaluate-policy", "evaluate-posterior", "baselines", "record"]
VERBS += ["align", "adapt"]
VERBS += ["train", "league"]


def _moving_policy(monkeypatch: pytest.MonkeyPatch, *action: float) -> None:
    """`align` and `evaluate` run this policy, whatever --policy says (an untrained member
    may stop at once): it moves by action[0] of the interval's step and never stops."""
    policy = constant(*action)
    monkeypatch.setattr(policy_module, "load_deployable", lambda *_args, **_kw: policy)


def _received_inside(verb: str, some: bool = True) -> None:
    """What reached the driver: finite, inside its interval, inside the site limits where
    the command had them (and with `some`, at least one write)."""
    received = [write["defocus"] for write in HostileLens.received]
    assert received or not some, f"{verb}: nothing was written at all"
    assert all(math.isfinite(value) and 0.0 <= value <= 100.0 for value in received), received
    if verb in SITE_LIMITED:
        assert all(20.0 <= value <= 80.0 for value in received), received


@pytest.mark.parametrize("verb", VERBS)
def test_every_command_writes_to_a_driver_only_through_the_shield(
    verb: str,
    tmp_path: Path,
    member_file: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.9, -1.0)  # big steps: the largest step must cut them
    outcome = run_cli(_command(verb, tmp_path, member_file, {}), capsys)
    assert outcome.code in (0, 1), outcome.text  # align: 1 is "not aligned", a result
    _received_inside(verb)
    if verb == "align":  # one alignment from the column as found: every step within 5 V
        settings = [50.0] + [write["defocus"] for write in HostileLens.received]
        assert np.all(np.abs(np.diff(settings)) <= 5.0 + 1e-9), settings


@pytest.mark.parametrize("verb", VERBS)
@pytest.mark.parametrize(
    ("driver", "named"),
    [
        ({"read_value": 150.0}, "outside its own interval [0, 100]"),
        ({"read_value": float("nan")}, "not a finite number"),
        ({"write_error": "RuntimeError"}, "write() raised RuntimeError"),
        ({"write_error": "ApparatusError"}, "failed to write"),
        ({"measure_error": "OSError"}, "measure() raised OSError"),
    ],
    ids=["reads-150", "reads-nan", "vendor-write-error", "write-fails", "vendor-measure-error"],
)
def test_a_lying_or_failing_driver_ends_each_command_with_the_driver_code(
    verb: str,
    driver: dict[str, Any],
    named: str,
    tmp_path: Path,
    member_file: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.3, -1.0)
    outcome = run_cli(_command(verb, tmp_path, member_file, driver), capsys)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, named)
    if verb in ("train", "league"):  # what a run keeps, and how to go on
        assert "last checkpoint" in outcome.err and "is kept: continue with" in outcome.err
    if verb == "adapt":  # failed in its zero-shot session: the same command starts it again
        assert "run the same command again" in outcome.err
        assert sorted(p.name for p in (tmp_path / "runs").glob("*/*")) == ["audit.jsonl"]
    received = [write["defocus"] for write in HostileLens.received]
    assert all(math.isfinite(value) and 0.0 <= value <= 100.0 for value in received)
    if "write_error" in driver:  # the first failed write was the last one sent
        assert len(received) == 1, received


@pytest.mark.parametrize("verb", ["evaluate-policy", "align", "adapt"])
@pytest.mark.parametrize("width", [-1.0, 0.0, "nan", "inf"])
def test_an_impossible_width_is_an_unmeasured_image_never_a_nan_write(
    verb: str,
    width: float | str,
    tmp_path: Path,
    member_file: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    outcome = run_cli(_command(verb, tmp_path, member_file, {"width": width}), capsys)
    assert outcome.code in (0, 1), outcome.text  # the work ends; nothing succeeded
    _received_inside(verb, some=False)  # a policy with nothing measured may not move


@pytest.mark.parametrize(
    ("verb", "named"),
    [("evaluate-policy", "defocus = nan is not a finite value"), ("align", "non-finite action")],
)
def test_a_policy_that_answers_nan_is_stopped_before_its_write(
    verb: str,
    named: str,
    tmp_path: Path,
    member_file: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, float("nan"), -1.0)
    outcome = run_cli(_command(verb, tmp_path, member_file, {}), capsys)
    assert_refused(outcome, EXIT_SHIELD_STOP, named)
    _received_inside(verb, some=False)


def test_the_ray_workers_open_the_driver_behind_the_shield() -> None:
    worker = MatchWorker(0, DRIVER, {"read_value": 150.0}, 2, get_task("focus"), 8, 1)
    units = worker.episodes.apparatus
    assert all(isinstance(unit, TrainingShield) for unit in units)
    with pytest.raises(Exception, match="outside its own interval"):
        units[0].reset(0)  # a lying driver stops the worker's match; nothing is written
    assert HostileLens.received == []


# --- hangs ----------------------------------------------------------------------------


def _hung(outcome: Outcome, seconds: float, limit_s: float) -> None:
    assert seconds < limit_s + 5.0, f"took {seconds:.1f} s against a limit of {limit_s} s"
    assert any(lens.hung.is_set() for lens in HostileLens.instances), "the driver never hung"


@pytest.mark.parametrize("verb", ["evaluate-policy", "baselines", "adapt", "record"])
def test_a_driver_call_that_never_returns_ends_the_command_at_the_call_limit(
    verb: str, tmp_path: Path, member_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    command = _command(verb, tmp_path, member_file, {"hang": "measure", "hang_after": 3})
    log = tmp_path / "audit.jsonl"
    if verb != "adapt":  # an adaptation keeps its audit in the run
        command += ["--log", str(log)]
    started = time.perf_counter()
    outcome = run_cli([*command, "--call-timeout", "1"], capsys)
    _hung(outcome, time.perf_counter() - started, 1.0)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, "measure() did not return within 1 s")
    if verb == "adapt":
        (log,) = (tmp_path / "runs").glob("*/audit.jsonl")
    records = [json.loads(line) for line in log.read_text().splitlines()]
    events = [record["event"] for record in records]
    assert events[-2:] == ["driver-fault", "abort"], events[-4:]  # the abort is on record


def test_the_watchdog_ends_an_alignment_in_the_middle_of_a_hung_call(
    tmp_path: Path, member_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "audit.jsonl"
    command = _command("align", tmp_path, member_file, {"hang": "measure", "hang_after": 1})
    started = time.perf_counter()
    outcome = run_cli([*command, "--timeout", "2", "--log", str(log), "--json"], capsys)
    _hung(outcome, time.perf_counter() - started, 2.0)
    assert outcome.code == EXIT_SHIELD_STOP, outcome.text
    result = json.loads(outcome.out)
    assert result["outcome"] == "aborted" and "time limit of 2 s" in result["reason"]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    events = [record["event"] for record in records]
    fault = events.index("driver-fault")
    assert "measure() call, abandoned" in records[fault]["error"]
    # The abort is on record, and after the hung call nothing more reached the driver.
    assert "abort" in events[fault:] and "end" in events[fault:]
    assert not any(record.get("sent") for record in records[fault + 1 :])


def test_align_exits_within_its_limit_when_a_measurement_never_returns(
    tmp_path: Path, member_file: Path
) -> None:
    """In a process of its own: a call that never returns must not keep the process alive."""
    command = _command("align", tmp_path, member_file, {"hang": "measure"})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(["tests", "docs/examples"])}
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "alignrl.cli", *command, "--call-timeout", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        cwd=Path(__file__).parent.parent,
    )
    elapsed = time.perf_counter() - started
    assert done.returncode == EXIT_DRIVER_FAILURE, done.stderr
    assert "measure() did not return within 2 s" in done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert elapsed < 60, elapsed  # the import of torch included; a hang would never end


# --- a fuzz over driver misbehaviour ----------------------------------------------------

EXCEPTIONS = ["RuntimeError", "OSError", "KeyError", "TypeError", "ZeroDivisionError"]
EXCEPTIONS += ["ApparatusError", "ValueError", "TimeoutError", "ConnectionError"]


def _random_driver(seed: int) -> dict[str, Any]:
    """One driver's misbehaviour drawn from `seed`: any mix of lying reads, impossible
    widths, exceptions of any type in any call, and a hang."""
    rng = np.random.default_rng(seed)
    driver: dict[str, Any] = {}
    if rng.random() < 0.3:
        driver["read_value"] = float(rng.choice([-5.0, 0.0, 42.0, 100.0, 150.0, np.nan, np.inf]))
    if rng.random() < 0.3:
        driver["width"] = str(rng.choice(["-1", "0", "nan", "inf", "1e300", "2.7"]))
    for call in ("write", "measure", "read"):
        if rng.random() < 0.2:
            driver[f"{call}_error"] = str(rng.choice(EXCEPTIONS))
    if rng.random() < 0.15:
        driver |= {"hang": str(rng.choice(["read", "write", "measure"])), "hang_after": 2}
    return driver


@pytest.mark.parametrize("seed", range(24))
def test_no_driver_misbehaviour_gets_a_bad_write_through_or_a_traceback_out(
    seed: int,
    tmp_path: Path,
    member_file: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.6, -1.0)
    driver = _random_driver(seed)
    verb = ["evaluate-classical", "align", "baselines", "evaluate-policy"][seed % 4]
    command = [*_command(verb, tmp_path, member_file, driver), "--call-timeout", "0.5"]
    outcome = run_cli(command, capsys)  # no traceback, no internal error
    # 2: align refuses a column that reads outside the site limits before it starts
    assert outcome.code in (0, 1, 2, EXIT_SHIELD_STOP, EXIT_DRIVER_FAILURE), (driver, outcome.text)
    _received_inside(verb, some=False)


def test_a_recording_whose_driver_hangs_keeps_the_scenarios_it_finished(
    tmp_path: Path, member_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run_cli(_command("record", tmp_path, member_file, {}), capsys)  # one scenario, to count
    per_scenario = HostileLens.instances[-1].counts["measure"]
    out = tmp_path / "sweep.csv"
    out.unlink()
    driver = {"hang": "measure", "hang_after": per_scenario + 3}  # in the second scenario
    command = _command("record", tmp_path, member_file, driver)
    command[command.index("--scenarios") + 1] = "3"
    outcome = run_cli([*command, "--call-timeout", "0.5"], capsys)
    assert_refused(outcome, EXIT_DRIVER_FAILURE, "measure() did not return within 0.5 s")
    rows = out.read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("0,")  # the header and scenario 0

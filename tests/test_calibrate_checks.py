"""`alignrl calibrate` checks before it touches the column, and writes a calibrated policy only
from readings that support one (issue 60, item 7): every refusal one line, nothing sent to
the driver before a refusal of what could be checked without it, nothing written after one,
Ctrl-C and SIGTERM alike (exit 130), nothing half-written.

Drivers come from tests/fake_drivers.py (HostileLens records every write it receives) and,
for widths that follow no setting, `RandomWidthLens` here (`test_calibrate_checks:...`)."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_drivers import HostileLens, ParabolicLens
from hostile import assert_refused, run_cli
from test_calibration import COLUMN, _sweeps

import alignrl.checkpoints as checkpoints
import alignrl.posterior.calibration as calibration_module
from alignrl.cli.common import EXIT_INTERRUPTED
from alignrl.posterior.calibration import (
    MAX_SEARCH_BYTES,
    SUPPORT_P,
    UncalibratedError,
    calibrate,
    check_support,
    search_memory,
    support_p,
)

EXIT_NOT_CALIBRATED = 1  # documented in docs/cli.md, alignrl calibrate
HOSTILE = "fake_drivers:HostileLens"


class RandomWidthLens(ParabolicLens):
    """A lens whose measure() says a width drawn at random, whatever the setting: a driver
    that reads no image."""

    def __init__(self) -> None:
        super().__init__()
        self.rng = np.random.default_rng(7)

    def measure(self) -> float:
        return float(self.rng.uniform(2.0, 30.0))


def _calibrate(policy: Path, out: Path, *extra: str, apparatus: str = HOSTILE) -> list[str]:
    argv = ["calibrate", "--policy", str(policy), "--apparatus", apparatus, "--spec-px", "3"]
    argv += ["--alignments", "3", "--population", "8", "--rounds", "1", "--quiet"]
    return [*argv, "--out", str(out), *extra]


def _nothing_left(folder: Path, out: Path) -> None:
    """No calibrated policy, and no staging folder of one, under `folder`."""
    assert not out.exists()
    assert not [path.name for path in folder.iterdir() if path.name.startswith(f".{out.name}")]


# --- refused before the first write -------------------------------------------------------


def _learner_disagrees(policy: Path, tmp_path: Path) -> Path:
    folder = shutil.copytree(policy, tmp_path / "policy")
    record = json.loads((folder / "learner.json").read_text())
    record["run"]["task_options"]["posterior_far_noise"] = 0.3  # the card says 0.1
    (folder / "learner.json").write_text(json.dumps(record))
    return folder


BEFORE_ANY_WRITE = {
    # an --out inside a file: today found only when the export is written, after it all
    "out inside a file": (
        lambda policy, tmp: (policy, tmp / "notes.txt" / "calibrated"),
        (),
        ["notes.txt", "is a file"],
    ),
    # a population whose arrays no machine holds: the figure and the cap, stated
    "population beyond memory": (
        lambda policy, tmp: (policy, tmp / "out"),
        ("--population", "10000000"),
        ["10000000", "GiB", "at most"],
    ),
    # the policy's learner state against its card: today read after the alignments
    "learner state unlike its card": (
        lambda policy, tmp: (_learner_disagrees(policy, tmp), tmp / "out"),
        (),
        ["learner.json", "card.json", "task_options.posterior_far_noise", "0.3"],
    ),
}


@pytest.mark.parametrize("case", list(BEFORE_ANY_WRITE))
def test_calibrate_refuses_before_it_writes_to_the_column(
    case: str, light: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    where, extra, names = BEFORE_ANY_WRITE[case]
    (tmp_path / "notes.txt").write_text("not a folder\n")
    policy, out = where(light, tmp_path)
    HostileLens.received.clear()
    outcome = run_cli(_calibrate(policy, out, *extra), capsys)
    assert_refused(outcome, 2, *names)
    assert HostileLens.received == [], "written to the column before a refusal"
    assert len(outcome.err.strip().splitlines()) == 1, outcome.err  # one line, no dump
    assert "{" not in outcome.err
    assert not out.exists()


def test_the_search_is_bounded_by_the_memory_it_states() -> None:
    total, per_column = search_memory(256)
    assert total == 256 * per_column and 0.5e6 < per_column < 2e6  # 3 x 4,007 x 8 B x 10
    most = MAX_SEARCH_BYTES // per_column
    calibration_module.check_search(most, 1)
    with pytest.raises(ValueError, match=rf"give at most {most} columns"):
        calibration_module.check_search(most + 1, 1)


# --- readings that support no calibration ---------------------------------------------------

UNSUPPORTED = {
    # widths drawn at random whatever the setting
    "random widths": (
        ["--apparatus", "test_calibrate_checks:RandomWidthLens"],
        "do not follow a focus curve",
    ),
    # one width everywhere: the knob changes nothing
    "one width everywhere": (
        ["--apparatus-args", '{"width": 5.0}'],
        "do not follow a focus curve",
    ),
    # widths no detector resolves
    "widths of 1e-300 px": (
        ["--apparatus-args", '{"width": 1e-300}'],
        "needs measured readings",
    ),
    # the lens's focus lies at 30-70 V: limits of [0, 20] keep it out of reach
    "limits that exclude focus": (
        ["--limits", '{"defocus": [0, 20]}'],
        "at or beyond the limits [0, 20] of defocus",
    ),
}


@pytest.mark.parametrize("case", list(UNSUPPORTED))
def test_readings_that_support_no_column_write_no_calibrated_policy(
    case: str, light: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    extra, why = UNSUPPORTED[case]
    argv = _calibrate(light, tmp_path / "out")
    if extra[0] == "--apparatus":  # in place of the HostileLens
        argv[argv.index("--apparatus") + 1] = extra[1]
        extra = []
    outcome = run_cli([*argv, *extra], capsys)
    assert_refused(outcome, EXIT_NOT_CALIBRATED, why, "not calibrated")
    assert len(outcome.err.strip().splitlines()) == 1, outcome.err
    _nothing_left(tmp_path, tmp_path / "out")


def test_check_support_tells_a_focus_curve_from_widths_that_ignore_the_setting() -> None:
    sweeps = _sweeps(COLUMN, 6, seed=1, above=2)
    assert support_p(sweeps) == pytest.approx(0.001)  # no shuffle does as well
    found = calibrate(sweeps, population=16, rounds=2)
    check_support(sweeps, found)  # the column's own readings: supported
    rng = np.random.default_rng(0)
    drawn = [[(u, float(rng.uniform(2, 30)), side) for u, _, side in s] for s in sweeps]
    same = [[(u, 5.0, side) for u, _, side in s] for s in sweeps]
    shrinking = [[(u, 30.0 / (1 + 20 * abs(u - 0.5)), side) for u, _, side in s] for s in sweeps]
    for widths in (drawn, same, shrinking):
        assert support_p(widths) > SUPPORT_P
        with pytest.raises(UncalibratedError, match=r"do not follow a focus curve"):
            check_support(widths, found)
    # focus at 0.3-0.7 of the interval: limits at 0-0.2 of it exclude it
    with pytest.raises(UncalibratedError, match=r"limits \[0, 20\] of defocus"):
        check_support(sweeps, found, (0.0, 100.0), (0.0, 20.0))
    # widths no detector resolves are no readings
    blank = [[(u, 1e-300, side) for u, _, side in sweep] for sweep in sweeps]
    with pytest.raises(UncalibratedError, match=r"hold 0 of \d+ \(.*below 0.1 px"):
        calibrate(blank, population=8, rounds=1)


# --- Ctrl-C and SIGTERM: exit 130, nothing half-written ---------------------------------------


def _interrupt_in_the_posterior(monkeypatch: pytest.MonkeyPatch, raise_: Any) -> None:
    """`raise_()` at the search's first weighing of its columns."""
    evidence = calibration_module.column_evidence

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        raise_()
        return evidence(*args, **kwargs)

    monkeypatch.setattr(calibration_module, "column_evidence", interrupted)


def _ctrl_c() -> None:
    raise KeyboardInterrupt


def _sigterm() -> None:
    os.kill(os.getpid(), signal.SIGTERM)


class _Unhandled(Exception):
    """SIGTERM reached a handler calibrate should have replaced."""


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_an_interrupt_inside_the_posterior_ends_cleanly(
    how: str,
    light: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _interrupt_in_the_posterior(monkeypatch, _ctrl_c if how == "ctrl-c" else _sigterm)

    def unhandled(signum: int, frame: object) -> None:
        raise _Unhandled("SIGTERM was not turned into an interrupt")

    before = signal.signal(signal.SIGTERM, unhandled)  # never the test run's own death
    try:
        outcome = run_cli(_calibrate(light, tmp_path / "out"), capsys)
    finally:
        signal.signal(signal.SIGTERM, before)
    assert_refused(outcome, EXIT_INTERRUPTED, "interrupted", "no calibrated policy written")
    assert outcome.err.strip().splitlines() == [
        f"interrupted: no calibrated policy written ({tmp_path / 'out'} left as it was: a "
        "calibration counts only when complete)"
    ]
    _nothing_left(tmp_path, tmp_path / "out")


def test_an_interrupt_while_the_calibration_is_written_leaves_nothing(
    light: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Ctrl-C as calibration.json is written: the policy beside it must not stand without it
    atomic_write = checkpoints.atomic_write

    def interrupted(path: Path, write: Any) -> None:
        if path.name == "calibration.json":
            raise KeyboardInterrupt
        atomic_write(path, write)

    monkeypatch.setattr(checkpoints, "atomic_write", interrupted)
    outcome = run_cli(_calibrate(light, tmp_path / "out"), capsys)
    assert outcome.code == EXIT_INTERRUPTED, outcome.text
    _nothing_left(tmp_path, tmp_path / "out")
    # uninterrupted, the same command (as small a search as the refusals above have, on a
    # lens whose readings follow its curve) calibrates: the refusals are the readings'
    monkeypatch.setattr(checkpoints, "atomic_write", atomic_write)
    outcome = run_cli(_calibrate(light, tmp_path / "out"), capsys)
    assert outcome.code == 0, outcome.text
    assert {"calibration.json", "card.json", "learner.json"} <= {
        path.name for path in (tmp_path / "out").iterdir()
    }

"""One process per run (alignrl/runs/lock.py), and a run whose evaluation apparatus cannot be
used refused before its folder exists.

A second process on a run that another holds (a resume, a `--force` start into it) is refused
at once: exit 2, one line naming the run directory and the holder's PID, nothing in the run
changed. A lock left by a process killed with SIGKILL is taken over by the next one; the lock
goes when its holder ends, normally or by an exception. The holders here are real processes of
their own (flock locks belong to a process's open file)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import SMALL_SAC, narrowed, one_sac_each, write_experiment, write_league_files
from hostile import assert_refused, assert_unchanged, run_cli, tree_state

from alignrl.cli import main
from alignrl.runs.lock import LOCK_FILE, RunLock, RunLockedError

TINY = {
    "name": "tiny",
    "envs": 2,
    "learner": narrowed(SMALL_SAC, 8),
    "budget": {
        "env_steps": 20,
        "eval_every": 20,
        "eval_scenarios": 2,
        "test_scenarios": 0,
        "checkpoint_every": 20,
    },
}
LEAGUE = {
    "name": "duel",
    "envs": 2,
    "schedule": {"iterations": 1, "matches": 2, "eval_scenarios": 1, "checkpoint_every": 1},
}
SMALL = {"encoder_kwargs": {"hidden": [8]}, "hidden": [8], "batch_size": 16}
HOLD = (
    "import sys, time\n"
    "from alignrl.runs.lock import RunLock\n"
    "lock = RunLock(sys.argv[1], create=False).acquire()\n"
    "print('held', flush=True)\n"
    "if sys.argv[2] == 'die':\n"
    "    import os, signal; os.kill(os.getpid(), signal.SIGKILL)\n"
    "time.sleep(120)\n"
)


def _holder(run: Path, then: str = "sleep") -> subprocess.Popen[str]:
    """A process of its own that takes `run`'s lock (and sleeps, or kills itself)."""
    process = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(run), then], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout is not None and process.stdout.readline().strip() == "held"
    return process


@contextmanager
def held_elsewhere(run: Path) -> Iterator[int]:
    """`run` locked by another process while the block runs; its PID."""
    process = _holder(run)
    try:
        yield process.pid
    finally:
        process.kill()
        process.wait(timeout=30)


@pytest.fixture(scope="module")
def module_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("locks")


@pytest.fixture(scope="module")
def training_run(module_folder: Path) -> Path:
    """A finished tiny training run (20 env steps) and its config beside runs/."""
    config = write_experiment(module_folder, TINY)
    assert main(["train", str(config), "--runs-dir", str(module_folder / "runs"), "--quiet"]) == 0
    return module_folder / "runs" / "tiny"


@pytest.fixture(scope="module")
def league_run(module_folder: Path) -> Path:
    """A league run's folder after its start (iteration 0 checkpointed, nothing played)."""
    from conftest import create_league

    path = write_league_files(module_folder, **one_sac_each(SMALL), settings=LEAGUE)
    create_league(path, module_folder / "runs").close()
    return module_folder / "runs" / "duel"


def _copy(run: Path, tmp_path: Path) -> Path:
    """The run copied under tmp_path/runs/, its config file beside runs/ as in the module."""
    for name in ("tiny.yaml", "league.yaml", "aligners.yaml", "misaligners.yaml"):
        if (run.parent.parent / name).exists():
            shutil.copy(run.parent.parent / name, tmp_path / name)
    return Path(shutil.copytree(run, tmp_path / "runs" / run.name))


# --- a second process on a held run --------------------------------------------------------


@pytest.mark.parametrize(
    "verb", ["train --resume", "adapt --resume", "train --force", "league resume", "league run"]
)
def test_a_second_process_on_a_run_is_refused_at_once(
    verb: str,
    training_run: Path,
    league_run: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = _copy(league_run if verb.startswith("league") else training_run, tmp_path)
    runs = ["--runs-dir", tmp_path / "runs"]
    argv = {
        "train --resume": ["train", "--resume", run, "--steps", 40, "--quiet"],
        "adapt --resume": ["adapt", "--resume", run, "--steps", 40, "--quiet"],
        "train --force": ["train", tmp_path / "tiny.yaml", *runs, "--force", "--quiet"],
        "league resume": ["league", "resume", run, "--quiet"],
        "league run": ["league", "run", tmp_path / "league.yaml", *runs, "--force", "--quiet"],
    }[verb]
    with held_elsewhere(run) as pid:
        before = tree_state(run)
        outcome = run_cli(argv, capsys)
        assert_refused(outcome, 2, str(run), f"PID {pid}", "in use by another alignrl process")
        assert len(outcome.err.strip().splitlines()) == 1, outcome.err
        assert_unchanged(before, run)
        assert tree_state(run) == before  # nothing new either: no --force removal, no rows
    # Once the holder is gone, the same command goes ahead (and lets go of the run again).
    if verb in ("train --resume", "league resume"):
        assert run_cli(argv, capsys).code == 0
        assert not (run / LOCK_FILE).exists()


def test_a_lock_left_by_a_killed_process_is_taken_over(
    training_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _copy(training_run, tmp_path)
    killed = _holder(run, then="die")
    assert killed.wait(timeout=30) == -signal.SIGKILL
    left = json.loads((run / LOCK_FILE).read_text())
    assert left["pid"] == killed.pid  # the file stays: only the flock went with the process
    with RunLock(run) as lock:
        assert lock.stale is not None and lock.stale.pid == killed.pid
    killed = _holder(run, then="die")
    killed.wait(timeout=30)
    outcome = run_cli(["train", "--resume", run, "--steps", 40, "--quiet", "--json"], capsys)
    assert outcome.code == 0, outcome.text
    assert json.loads(outcome.out)["env_steps"] == 40
    assert not (run / LOCK_FILE).exists()


def test_the_lock_goes_after_a_normal_end_and_after_an_exception(
    training_run: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from alignrl.training import Trainer

    run = _copy(training_run, tmp_path)
    assert run_cli(["train", "--resume", run, "--quiet"], capsys).code == 0  # finished: no work
    assert not (run / LOCK_FILE).exists()
    with RunLock(run):  # free: this process takes it
        pass

    def broken(self: Trainer, **_: object) -> None:
        assert (self.run_dir / LOCK_FILE).exists()  # held while it trains
        raise ValueError("the trainer broke")

    monkeypatch.setattr(Trainer, "run", broken)
    outcome = run_cli(["train", "--resume", run, "--steps", 40, "--quiet"], capsys)
    assert_refused(outcome, 2, "the trainer broke")
    assert not (run / LOCK_FILE).exists()
    with held_elsewhere(run):  # another process can take it: nothing of ours holds it
        pass

    def interrupted(self: Trainer, **_: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "run", interrupted)
    assert run_cli(["train", "--resume", run, "--steps", 40, "--quiet"], capsys).code == 130
    with held_elsewhere(run):
        pass


def test_the_lock_itself(tmp_path: Path) -> None:
    """In one process: a second open of the lock is refused as another process's would be;
    the folders a lock made for a run that never started go with it; a resume's lock never
    makes a folder."""
    run = tmp_path / "runs" / "new"
    with RunLock(run) as lock:
        assert lock.held and (run / LOCK_FILE).exists() and lock.stale is None
        assert lock.only_the_lock()  # (a --force start has no run to remove here)
        with pytest.raises(RunLockedError, match=f"PID {os.getpid()}") as refused:
            RunLock(run).acquire()
        assert str(run) in str(refused.value)
    assert not (tmp_path / "runs").exists()  # both folders it made, empty, are gone
    with RunLock(tmp_path / "missing", create=False) as lock:
        assert not lock.held
    assert not (tmp_path / "missing").exists()
    run.mkdir(parents=True)
    with RunLock(run) as lock:
        (run / "config.yaml").write_text("name: new\n")
        assert not lock.only_the_lock()
    assert sorted(p.name for p in run.iterdir()) == ["config.yaml"]  # a run's folder stays


# --- an evaluation apparatus that cannot be used ------------------------------------------

BROKEN_EVALUATIONS = {
    "missing file": ({"eval_apparatus": "csv:/nowhere/scenarios.csv"}, "/nowhere/scenarios.csv"),
    "unknown spec": ({"eval_apparatus": "no-such-apparatus"}, "no-such-apparatus"),
    "wrong arguments": ({"eval_apparatus_args": {"dose": 3}}, "dose"),
    "missing knobs": (
        {"task": "stigmation", "apparatus": "synthetic", "apparatus_args": {"analytic": True}},
        "stigmator_x",
    ),
}


@pytest.mark.parametrize("case", list(BROKEN_EVALUATIONS))
@pytest.mark.parametrize("verb", ["train", "league run"])
def test_an_evaluation_apparatus_that_cannot_be_used_is_refused_before_the_run_folder(
    verb: str, case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    changes, named = BROKEN_EVALUATIONS[case]
    runs = tmp_path / "runs"
    if verb == "train":
        argv = ["train", write_experiment(tmp_path, {**TINY, **changes})]
    else:
        path = write_league_files(tmp_path, **one_sac_each(SMALL), settings={**LEAGUE, **changes})
        argv = ["league", "run", path]
    outcome = run_cli([*argv, "--runs-dir", runs, "--quiet"], capsys)
    assert_refused(outcome, 2, "eval_apparatus", named)
    assert not runs.exists() or not any(runs.iterdir())


def test_a_broken_evaluation_apparatus_leaves_the_run_force_would_replace(
    training_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _copy(training_run, tmp_path)
    before = tree_state(run)
    config = write_experiment(tmp_path, {**TINY, "eval_apparatus": "csv:/nowhere/x.csv"})
    argv = ["train", config, "--runs-dir", tmp_path / "runs", "--force", "--quiet"]
    assert_refused(run_cli(argv, capsys), 2, "csv:/nowhere/x.csv")
    assert tree_state(run) == before

"""A kill -9 at any file write loses nothing: the league and the trainer are killed at every
write boundary of a tiny run (each atomic write, CSV append, file or folder deletion), resumed
from disk, and run to the end; what they leave must be what an uninterrupted run leaves.

A kill -9 just before the k-th write leaves the disk as it was then: one uninterrupted run
copies its run directory at each write boundary, before the write (`Writes.leave`), and each
copy is resumed to the end on its own, as `alignrl league|train resume` would after the kill.
Nothing of the run's memory reaches the copy, not even what an exception unwinding the
stack would write (a `finally`, a file closed by the garbage collector), so the copy is what a
SIGKILL leaves, and a run is played once rather than once per kill. TensorBoard is a
recorder that keeps only what was flushed before the kill, and honours `purge_step` as
TensorBoard does when it reads the events back.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import SMALL_PPO, SMALL_SAC, narrowed, read_csv, write_experiment, write_league_files

import alignrl.checkpoints as checkpoints
from alignrl.checkpoints import load_checkpoint
from alignrl.cli import main
from alignrl.config.experiment import parse_experiment
from alignrl.league.config import load_league
from alignrl.league.loop import League, leaderboard
from alignrl.metrics import CsvLog
from alignrl.training import Trainer


@dataclass
class Events:
    """What TensorBoard would show of one run directory: (tag, step, value) in order."""

    durable: list[tuple[str, int, float]] = field(default_factory=list)


class RecordingBoard:
    """A stand-in SummaryWriter: events reach `durable` only on flush (a kill loses the
    rest), and a writer opened with purge_step hides the earlier events from that step on."""

    boards: dict[str, Events] = {}  # noqa: RUF012 (one per test, reset by the fixture)

    def __init__(self, log_dir: str, purge_step: int | None = None) -> None:
        self.events = self.boards.setdefault(log_dir, Events())
        if purge_step is not None:
            self.events.durable = [e for e in self.events.durable if e[1] < purge_step]
        self.pending: list[tuple[str, int, float]] = []

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.pending.append((tag, int(step), float(value)))

    @property
    def file_writer(self) -> RecordingBoard:  # where a run's hyperparameters are written
        return self

    def add_summary(self, summary: Any, global_step: int | None = None) -> None:
        """A run's hyperparameters: not kept (written once per run, which tests/test_training.py
        checks on real event files)."""

    def flush(self) -> None:
        self.events.durable += self.pending
        self.pending = []

    def close(self) -> None:
        self.flush()


class Writes:
    """Counts the run's writes; while `run` is set, copies that run directory, and the
    TensorBoard events flushed so far, just before each write: what a kill there leaves."""

    def __init__(self) -> None:
        self.count = 0
        self.log: list[str] = []
        self.run: Path | None = None
        self.left: dict[int, tuple[Path | None, list[tuple[str, int, float]]]] = {}

    def boundary(self, what: str) -> None:
        self.count += 1
        self.log.append(what)
        if self.run is not None:
            self.left[self.count] = self.leave(self.run, self.count)

    def leave(self, run: Path, k: int) -> tuple[Path | None, list[tuple[str, int, float]]]:
        if not run.exists():
            return None, []
        copy = run.parent.parent / "left" / str(k)
        shutil.copytree(run, copy, copy_function=shutil.copyfile)
        board = RecordingBoard.boards.get(str(run / "tensorboard"), Events())
        return copy, list(board.durable)

    def killed(self, k: int, runs: Path) -> None:
        """`runs` as a kill just before write `k` left it: the run directory (none if it did
        not exist yet) and its flushed TensorBoard events."""
        copy, durable = self.left.pop(k)
        runs.mkdir()
        if copy is not None:
            copy.rename(runs / "crash")
            RecordingBoard.boards[str(runs / "crash" / "tensorboard")] = Events(durable)


@pytest.fixture
def writes(monkeypatch: pytest.MonkeyPatch) -> Writes:
    return instrument(monkeypatch)


def instrument(monkeypatch: pytest.MonkeyPatch) -> Writes:
    """Every write of a run through `Writes`, and TensorBoard through RecordingBoard."""
    counter = Writes()
    atomic_write, write_rows = checkpoints.atomic_write, CsvLog.write
    rmtree, unlink = shutil.rmtree, Path.unlink

    def counted_atomic_write(path: Path, write: Any) -> None:
        counter.boundary(f"write {path}")
        atomic_write(path, write)

    def counted_rows(log: CsvLog, rows: list[dict[str, Any]]) -> None:
        if rows:
            counter.boundary(f"append {log.path}")
        write_rows(log, rows)

    def counted_rmtree(path: Any, *args: Any, **kwargs: Any) -> None:
        counter.boundary(f"rmtree {path}")
        rmtree(path, *args, **kwargs)

    def counted_unlink(path: Path, missing_ok: bool = False) -> None:
        counter.boundary(f"unlink {path}")
        unlink(path, missing_ok=missing_ok)

    monkeypatch.setattr(checkpoints, "atomic_write", counted_atomic_write)
    monkeypatch.setattr(CsvLog, "write", counted_rows)
    monkeypatch.setattr(shutil, "rmtree", counted_rmtree)
    monkeypatch.setattr(Path, "unlink", counted_unlink)
    monkeypatch.setattr(RecordingBoard, "boards", {})
    monkeypatch.setattr("torch.utils.tensorboard.SummaryWriter", RecordingBoard)
    return counter


# --- what a run directory holds -----------------------------------------------------------


@dataclass(eq=False)
class Checkpoint:
    """A .pt file of a run: its bytes, and what `load_checkpoint` reads from them. Two with
    the same bytes are the same checkpoint; others are compared as loaded."""

    data: bytes
    state: dict[str, Any]


def _same(a: Any, b: Any, where: str) -> None:
    if isinstance(a, Checkpoint):
        assert isinstance(b, Checkpoint), where
        if a.data != b.data:
            _same(a.state, b.state, where)
    elif isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for key in a:
            _same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list | tuple):
        assert isinstance(b, list | tuple) and len(a) == len(b), where
        for index, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{index}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def contents(run: Path, like: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every file of a run directory as comparable values: checkpoints loaded, CSVs as rows
    without their wall-clock `seconds`, TensorBoard as the events it would show. A checkpoint
    with the bytes of its namesake in `like` (the contents of a run that loaded) is that one,
    not loaded again: most checkpoints of a resumed run are byte for byte the uninterrupted
    run's, and the same bytes load the same."""
    found: dict[str, Any] = {}
    for path in sorted(run.rglob("*")):
        relative = str(path.relative_to(run))
        if not path.is_file() or relative.startswith("tensorboard"):
            continue
        if path.suffix == ".pt":
            data, known = path.read_bytes(), (like or {}).get(relative)
            if isinstance(known, Checkpoint) and known.data == data:
                found[relative] = known
            else:
                found[relative] = Checkpoint(data, load_checkpoint(path))
        elif path.suffix == ".csv":
            rows = read_csv(path)
            found[relative] = [{k: v for k, v in row.items() if k != "seconds"} for row in rows]
        else:
            found[relative] = path.read_text()
    found["tensorboard"] = RecordingBoard.boards.get(str(run / "tensorboard"), Events()).durable
    return found


def assert_same_run(resumed: dict[str, Any], reference: dict[str, Any], kill: str) -> None:
    assert sorted(resumed) == sorted(reference), kill
    for name in reference:
        _same(resumed[name], reference[name], f"{kill}: {name}")


def assert_rows_once(run: Path, kill: str) -> None:
    """No metrics row twice: iterations 1, 2, ... and per CSV strictly increasing keys."""
    for path in run.rglob("*.csv"):
        rows = read_csv(path)
        if path.name == "iterations.csv":
            assert [int(r["iteration"]) for r in rows] == list(range(1, len(rows) + 1)), kill
        if path.name == "episodes.csv":
            assert [int(r["episode"]) for r in rows] == sorted({int(r["episode"]) for r in rows})
        if path.name == "updates.csv":
            assert [int(r["updates"]) for r in rows] == sorted({int(r["updates"]) for r in rows})
        if path.name == "evaluations.csv" and "member" not in (rows[0] if rows else {}):
            steps = [int(r["env_steps"]) for r in rows]
            assert steps == sorted(set(steps)), f"{kill}: {path.name} {steps}"


# --- the league ---------------------------------------------------------------------------

# Snapshots every 2 iterations with one kept per team, checkpoints every 3: the snapshot of
# iteration 4 pushes out that of 2, which the checkpoint of 3 lists (the window where a
# kill used to lose the run). PBT copies and evaluations at 3 and 6.
LEAGUE_SCHEDULE = {
    "iterations": 6,
    "matches": 4,
    "snapshot_every": 2,
    "pbt_every": 3,
    "evaluate_every": 3,
    "eval_scenarios": 2,
    "checkpoint_every": 3,
    "keep_best": 1,
}


def league_config(tmp_path: Path) -> Path:
    small_sac, small_ppo = narrowed(SMALL_SAC, 8), narrowed(SMALL_PPO, 8)
    aligners, misaligners = (
        [{"id": f"{team}-sac", "learner": small_sac}, {"id": f"{team}-ppo", "learner": small_ppo}]
        for team in ("a", "m")
    )
    settings = {
        "name": "crash",
        "envs": 2,
        "schedule": LEAGUE_SCHEDULE,
        "matchmaking": {"max_snapshots": 1},
        "pbt": {"min_gap": 0.0},
    }
    return write_league_files(tmp_path, aligners, misaligners, settings)


def league_to_the_end(config_path: Path, runs: Path) -> Path:
    """Start the league, or resume it where a kill left it, as `alignrl league run|resume`
    would; then the read-only views (leaderboard, export) must work."""
    run = runs / "crash"
    if (run / "config.yaml").exists():
        league = League.resume(run)
    else:  # killed before the run existed: `alignrl league run` again
        league = League.create(*load_league(config_path), runs)
    league.run(progress=False)
    (run / "leaderboard.json").write_text(json.dumps(leaderboard(league)))
    return run


def league_kills(tmp_path: Path, writes: Writes, select: Any) -> int:
    config = league_config(tmp_path)
    writes.run = tmp_path / "uninterrupted" / "crash"
    reference_run = league_to_the_end(config, tmp_path / "uninterrupted")
    writes.run = None
    total, log = writes.count, list(writes.log)
    reference = contents(reference_run)
    chosen = [k for k in range(1, total + 1) if select(k, log)]
    for kill_at in chosen:
        runs = tmp_path / f"kill-{kill_at}"
        writes.killed(kill_at, runs)
        kill = f"kill before write {kill_at}/{total} ({log[kill_at - 1]})"
        # The views of a killed run read it: its checkpoint and all it refers to exist.
        if (runs / "crash" / "config.yaml").exists():
            viewed = League.resume(runs / "crash", read_only=True)
            assert leaderboard(viewed), kill
            for team in ("aligner", "misaligner"):
                for player in viewed.pool.candidates(team):
                    viewed.player(player)
        run = league_to_the_end(config, runs)
        assert_rows_once(run, kill)
        assert_same_run(contents(run, like=reference), reference, kill)
        shutil.rmtree(runs)
    assert_same_run(contents(reference_run, like=reference), reference, "the reference, untouched")
    return len(chosen)


def _snapshot_window(k: int, log: list[str]) -> bool:
    """Every write from the iteration-4 snapshot (which prunes one the checkpoint of 3
    lists) to the end, the iteration-6 checkpoint and its pruning included; every tenth
    before."""
    first = next(i for i, what in enumerate(log, 1) if "snapshots" in what and "@4.pt" in what)
    return k >= first or k % 10 == 0


def test_a_league_killed_at_any_write_of_the_snapshot_window_resumes_to_the_same_end(
    tmp_path: Path, writes: Writes
) -> None:
    assert league_kills(tmp_path, writes, _snapshot_window) > 20


@pytest.mark.slow
@pytest.mark.long
def test_a_league_killed_at_every_other_write_resumes_to_the_same_end(
    tmp_path: Path, writes: Writes
) -> None:
    """The writes the snapshot window leaves out: with it, every write of the league is a
    kill once (`make crash-check` and `make test-all` run both; `make test` the window
    alone)."""
    assert league_kills(tmp_path, writes, lambda k, log: not _snapshot_window(k, log)) > 0


def test_a_full_disk_at_a_checkpoint_keeps_the_previous_one_and_says_where(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    league = League.create(*load_league(league_config(tmp_path)), tmp_path / "runs")
    league.run(progress=False)
    run = league.run_dir
    before = contents(run)
    fsync = os.fsync

    def full(descriptor: int) -> None:
        if "league.pt" in os.readlink(f"/proc/self/fd/{descriptor}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        fsync(descriptor)

    monkeypatch.setattr(os, "fsync", full)
    league.iteration += 1
    with pytest.raises(OSError, match=r"No space left on device: '.*iteration-000007/league.pt'"):
        league.checkpoint()
    monkeypatch.setattr(os, "fsync", fsync)
    assert not (run / "checkpoints" / "iteration-000007").exists()
    assert_same_run(contents(run), before, "full disk")
    assert League.resume(run).iteration == 6


# --- the trainer --------------------------------------------------------------------------

TINY_TRAIN = {
    "name": "crash",
    "envs": 2,
    "learner": narrowed(SMALL_SAC, 8),
    "budget": {"env_steps": 60, "eval_every": 40, "eval_scenarios": 2, "checkpoint_every": 20},
}


def train_to_the_end(runs: Path) -> Path:
    run = runs / "crash"
    if (run / "config.yaml").exists():
        trainer = Trainer.resume(run)
    else:
        trainer = Trainer.create(parse_experiment(TINY_TRAIN), runs)
    trainer.run(progress=False)
    return run


def _checkpointed_steps(run: Path) -> int | None:
    last = run / "checkpoints" / "last.pt"
    return int(load_checkpoint(last)["env_steps"]) if last.exists() else None


def _near_a_checkpoint(k: int, log: list[str]) -> bool:
    """Writes beside any that is not an episode row (checkpoints, evaluations, headers), and
    every fourth episode row."""
    beside = log[max(k - 2, 0) : k + 1]
    return any("episodes.csv" not in what or "write" in what for what in beside) or k % 4 == 0


def test_a_trainer_killed_at_a_write_resumes_as_from_its_last_checkpoint(
    tmp_path: Path, writes: Writes
) -> None:
    assert trainer_kills(tmp_path, writes, _near_a_checkpoint) > 15


@pytest.mark.slow
@pytest.mark.long
def test_a_trainer_killed_at_every_other_write_resumes_as_from_its_last_checkpoint(
    tmp_path: Path, writes: Writes
) -> None:
    """The writes `_near_a_checkpoint` leaves out: with it, every write of the trainer is a
    kill once."""
    assert trainer_kills(tmp_path, writes, lambda k, log: not _near_a_checkpoint(k, log)) > 0


def trainer_kills(tmp_path: Path, writes: Writes, select: Any) -> int:
    """A resumed trainer starts its episodes over (its env seeds change with each start), so
    a kill anywhere after a checkpoint must end as a kill just after that checkpoint does;
    before the first one, and after the last, as the uninterrupted run."""
    writes.run = tmp_path / "uninterrupted" / "crash"
    reference_run = train_to_the_end(tmp_path / "uninterrupted")
    writes.run = None
    total, log = writes.count, list(writes.log)
    uninterrupted = contents(reference_run)
    references: dict[int | None, dict[str, Any]] = {None: uninterrupted}
    final = int(TINY_TRAIN["budget"]["env_steps"])
    chosen = [k for k in range(1, total + 1) if select(k, log)]
    for kill_at in chosen:
        runs = tmp_path / f"kill-{kill_at}"
        writes.killed(kill_at, runs)
        kill = f"kill before write {kill_at}/{total} ({log[kill_at - 1]})"
        resumed_from = _checkpointed_steps(runs / "crash")
        run = train_to_the_end(runs)
        assert_rows_once(run, kill)
        found = contents(run, like=uninterrupted)
        if resumed_from == final:  # after the last checkpoint: nothing is written again
            assert_same_run(found, uninterrupted, kill)
        elif resumed_from in references:
            assert_same_run(found, references[resumed_from], kill)
        else:  # the first kill after this checkpoint: rows up to it are the uninterrupted
            references[resumed_from] = found
            for name in ("episodes.csv", "updates.csv", "evaluations.csv"):
                kept = [
                    r
                    for r in uninterrupted[f"metrics/{name}"]
                    if int(r["env_steps"]) <= resumed_from
                ]
                assert found[f"metrics/{name}"][: len(kept)] == kept, f"{kill}: {name}"
        shutil.rmtree(runs)
    assert len(references) >= 3  # kills after at least two checkpoints were compared
    return len(chosen)


def test_a_finished_run_resumed_twice_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_experiment(tmp_path, TINY_TRAIN)
    runs = tmp_path / "runs"
    assert main(["train", str(config), "--runs-dir", str(runs), "--quiet", "--json"]) == 0
    finished = json.loads(capsys.readouterr().out)
    run = runs / "crash"
    files = {path: path.stat().st_mtime_ns for path in run.rglob("*") if path.is_file()}
    for _ in range(2):
        assert main(["train", "--resume", str(run), "--quiet", "--json"]) == 0
        out, err = capsys.readouterr()
        assert "is finished at 60 env steps" in err
        again = json.loads(out)
        assert {k: v for k, v in again.items() if k != "seconds"} == {
            k: v for k, v in finished.items() if k != "seconds"
        }
    assert {path: path.stat().st_mtime_ns for path in run.rglob("*") if path.is_file()} == files
    evaluations = read_csv(run / "metrics" / "evaluations.csv")
    assert [row["env_steps"] for row in evaluations] == ["40", "60"]


def test_a_full_disk_in_training_is_one_line_naming_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_experiment(tmp_path, TINY_TRAIN)
    runs = tmp_path / "runs"
    fsync = os.fsync
    checkpoints_written = []

    def full(descriptor: int) -> None:
        if "last.pt" in os.readlink(f"/proc/self/fd/{descriptor}"):
            checkpoints_written.append(descriptor)
            if len(checkpoints_written) > 1:
                raise OSError(errno.ENOSPC, "No space left on device")
        fsync(descriptor)

    monkeypatch.setattr(os, "fsync", full)
    assert main(["train", str(config), "--runs-dir", str(runs), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("alignrl: error: [Errno 28] No space left on device: ")
    assert "checkpoints/last.pt" in err and "Traceback" not in err
    assert _checkpointed_steps(runs / "crash") == 20  # the first checkpoint, intact
    assert not list((runs / "crash" / "checkpoints").glob(".*"))  # no temporary left
    monkeypatch.setattr(os, "fsync", fsync)
    assert main(["train", "--resume", str(runs / "crash"), "--quiet"]) == 0


# --- SIGTERM ------------------------------------------------------------------------------


def test_sigterm_stops_training_as_ctrl_c_does_and_it_resumes(tmp_path: Path) -> None:
    settings = {**TINY_TRAIN, "budget": {**TINY_TRAIN["budget"], "env_steps": 20000}}
    config = write_experiment(tmp_path, settings)
    runs = tmp_path / "runs"
    command = [sys.executable, "-m", "alignrl.cli", "train"]
    process = subprocess.Popen(
        [*command, str(config), "--runs-dir", str(runs), "--quiet"], stderr=subprocess.PIPE
    )
    last = runs / "crash" / "checkpoints" / "last.pt"
    deadline = time.monotonic() + 120
    while not last.exists() and time.monotonic() < deadline:
        assert process.poll() is None, process.stderr.read() if process.stderr else ""
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err.decode()
    assert "the last checkpoint is kept: continue with `alignrl train --resume" in err.decode()
    stopped_at = _checkpointed_steps(runs / "crash")
    assert stopped_at is not None and stopped_at < 20000
    resumed = Trainer.resume(runs / "crash")
    assert resumed.env_steps == stopped_at and resumed.starts >= 1

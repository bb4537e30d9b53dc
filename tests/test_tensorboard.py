"""TensorBoard holds what the CSVs hold, once: a training run and a league killed after their
events reached the disk (and before their next checkpoint) resume to the same curves as a run
never stopped, every step of every tag once, whether read by TensorBoard's Python reader
(EventAccumulator, which honours purge_step) or straight from the files (as its Rust data
server and any script read them); the run's hyperparameters are there once.

The kill is `Killed`, raised in place of the last checkpoint after the events are flushed: the
run resumes from the checkpoint before, with events after it on disk.
"""

from __future__ import annotations

import collections
import socket
import time
from pathlib import Path

import pytest
from conftest import TINY_RUN, create_league, read_csv, write_league

from alignrl.config.experiment import parse_experiment
from alignrl.league.loop import League
from alignrl.runs.state import EVENT_FILES, HPARAMS_TAG, TensorBoardLog, cut_events
from alignrl.training import Trainer

# The tiny run of the training tests, evaluated every 100 steps and saved every 200.
TINY = {
    **TINY_RUN,
    "budget": {"env_steps": 400, "eval_every": 100, "eval_scenarios": 3, "checkpoint_every": 200},
}


class Killed(BaseException):
    """kill -9 just before a checkpoint is written."""


def shown(folder: Path) -> dict[str, list[int]]:
    """Each scalar tag's steps as TensorBoard's Python reader shows them."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    board = EventAccumulator(str(folder)).Reload()
    return {tag: [event.step for event in board.Scalars(tag)] for tag in board.Tags()["scalars"]}


def on_disk(folder: Path) -> dict[str, list[int]]:
    """Each tag's steps as the event files hold them, file after file (hparams included)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    steps = collections.defaultdict(list)
    for path in sorted(folder.glob(EVENT_FILES)):
        for event in EventFileLoader(str(path)).Load():
            for value in event.summary.value:
                steps[value.tag].append(event.step)
    return dict(steps)


def assert_each_step_once(folder: Path) -> dict[str, list[int]]:
    """The tags of `folder`, each step once in order, the same in the reader and the files;
    the hyperparameters written once."""
    steps, files = shown(folder), on_disk(folder)
    assert files.pop(HPARAMS_TAG, None) is not None and len(on_disk(folder)[HPARAMS_TAG]) == 1
    for tag, found in steps.items():
        assert found == sorted(set(found)), f"{folder}: {tag} {found}"
    assert files == steps, folder
    return steps


def test_a_cut_keeps_each_file_up_to_the_step_and_drops_a_torn_record(tmp_path: Path) -> None:
    from torch.utils.tensorboard import SummaryWriter

    folder = tmp_path / "tensorboard"
    writer = SummaryWriter(str(folder))
    for step in range(1, 11):
        writer.add_scalar("a", step, step)
    writer.close()
    (events,) = folder.glob(EVENT_FILES)
    with events.open("ab") as handle:
        handle.write(b"\x30\x00\x00\x00")  # the start of a record a kill cut short
    assert cut_events(folder, 10) == {"a"}  # all kept, the torn record gone
    assert on_disk(folder) == {"a": list(range(1, 11))}
    assert cut_events(folder, 5) == {"a"}
    assert on_disk(folder) == {"a": [1, 2, 3, 4, 5]}
    assert not list(folder.glob(".*"))  # no temporary left
    assert cut_events(folder, 0) == set()  # no summary left: the file goes
    assert list(folder.iterdir()) == []


def test_hyperparameters_are_written_once_and_known_after_a_cut(tmp_path: Path) -> None:
    board = TensorBoardLog(tmp_path / "tensorboard")
    board.add_hparams({"learning_rate": 3e-4, "algorithm": "sac"}, step=0)
    board.add_hparams({"learning_rate": 1.0}, step=0)  # a second call writes nothing
    board.add_scalar("a", 1.0, 5)
    board.close()
    resumed = TensorBoardLog(tmp_path / "tensorboard")
    resumed.resume_after(2)  # the scalar goes, the hyperparameters (step 0) stay
    resumed.add_hparams({"learning_rate": 1.0})
    resumed.close()
    assert on_disk(tmp_path / "tensorboard") == {HPARAMS_TAG: [0]}


def _train(runs: Path) -> Trainer:
    trainer = Trainer.create(parse_experiment(TINY), runs)
    trainer.run(progress=False)
    return trainer


def test_a_training_run_killed_after_its_events_resumes_to_the_same_curves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    reference = assert_each_step_once(_train(tmp_path / "a").run_dir / "tensorboard")
    assert {
        "episode/return",
        "episode/success",
        "episode/acquisitions",
        "learner/q1_loss",
        "validation/successes",
        "validation/success_rate_low",
        "test/successes",
        "test/success_rate_high",
    } <= set(reference)
    assert reference["validation/successes"] == [100, 200, 300, 400]
    assert reference["test/successes"] == [400]

    checkpoint = Trainer.checkpoint

    def killed_at_the_end(trainer: Trainer) -> None:
        if trainer.env_steps == 400:
            trainer.logs.flush()  # what the kill leaves: the events up to now on disk
            raise Killed
        checkpoint(trainer)

    monkeypatch.setattr(Trainer, "checkpoint", killed_at_the_end)
    with pytest.raises(Killed):
        _train(tmp_path / "b")
    monkeypatch.undo()
    folder = tmp_path / "b" / "tiny" / "tensorboard"
    assert max(on_disk(folder)["validation/successes"]) == 400  # events past the checkpoint
    resumed = Trainer.resume(folder.parent)
    assert resumed.env_steps == 200
    resumed.run(progress=False)
    resumed.logs.close()

    steps = assert_each_step_once(folder)
    assert sorted(steps) == sorted(reference)
    rows = read_csv(folder.parent / "metrics" / "episodes.csv")
    episodes = sorted({int(row["env_steps"]) for row in rows})
    for tag, found in steps.items():
        if tag.startswith("episode/"):
            # Episodes in flight at the kill start over: the same up to the checkpoint, and
            # after it at the steps the episodes CSV holds.
            assert [s for s in found if s <= 200] == [s for s in reference[tag] if s <= 200]
            assert found == episodes, tag
        else:
            assert found == reference[tag], tag


def test_a_league_killed_after_its_events_resumes_to_the_same_curves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    schedule = {
        "iterations": 4,
        "matches": 8,
        "snapshot_every": 2,
        "pbt_every": 2,
        "evaluate_every": 2,
        "eval_scenarios": 2,
        "checkpoint_every": 2,
    }

    def league(folder: Path) -> League:
        folder.mkdir()
        return create_league(write_league(folder, schedule=schedule), folder / "runs")

    uninterrupted = league(tmp_path / "a")
    uninterrupted.run(progress=False)
    checkpoint = League.checkpoint

    def killed_at_the_end(self: League) -> Path:
        if self.iteration == 4:
            self.logs.flush()
            raise Killed
        return checkpoint(self)

    monkeypatch.setattr(League, "checkpoint", killed_at_the_end)
    killed = league(tmp_path / "b")
    with pytest.raises(Killed):
        killed.run(progress=False)
    monkeypatch.undo()
    run = killed.run_dir
    resumed = League.resume(run)
    assert resumed.iteration == 2
    resumed.run(progress=False)

    reference = uninterrupted.run_dir / "tensorboard"
    members = sorted(path.name for path in (reference / "members").iterdir())
    assert "a-sac" in members and any("-pbt" in name for name in members)  # PBT copies too
    assert sorted(path.name for path in (run / "tensorboard" / "members").iterdir()) == members
    tags = set()
    for member in members:
        steps = assert_each_step_once(run / "tensorboard" / "members" / member)
        assert steps == assert_each_step_once(reference / "members" / member), member
        tags |= {tag.split("/")[0] for tag in steps}
    assert tags == {"learner", "episode", "validation"}
    league_steps = assert_each_step_once(run / "tensorboard")
    assert "league/success_rate" in league_steps
    assert league_steps == assert_each_step_once(reference)


def test_a_writer_opened_in_the_second_of_an_older_file_sorts_after_it(tmp_path: Path) -> None:
    """TensorBoard reads a folder's event files in name order: a resumed run's file must sort
    after the killed run's, even when both open within one second (in the same process a
    counter of 10 would sort before one of 9; in another, a smaller process id first)."""
    folder = tmp_path / "tensorboard"
    folder.mkdir()
    older = folder / f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.999999.9"
    older.write_bytes(b"")
    log = TensorBoardLog(folder)
    log.add_scalar("x", 1.0, 1)
    log.close()
    names = sorted(path.name for path in folder.glob("*tfevents*"))
    assert len(names) == 2 and names[0] == older.name

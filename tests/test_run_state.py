"""alignrl.runs.state: the random streams a checkpoint restores (and refuses when corrupt), the
lazy TensorBoard writer, the run config readers and the knob record."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from alignrl.config.experiment import dump_experiment, parse_experiment
from alignrl.config_reading import ConfigError
from alignrl.envs.task import get_task
from alignrl.runs import state as run_state
from alignrl.runs.state import (
    KNOBS_FILE,
    TensorBoardLog,
    knob_limits,
    read_training_config,
    record_knobs,
    recorded_knobs,
    restore_rng,
    rng_state,
    run_config_data,
)


def _draws(rng: np.random.Generator) -> tuple[list[float], list[float]]:
    return rng.random(3).tolist(), torch.rand(3).tolist()


def test_a_restored_state_draws_what_the_saved_one_would() -> None:
    rng = np.random.default_rng(7)
    rng.random(5)
    saved = rng_state(rng)
    expected = _draws(rng)
    restore_rng(rng, saved)
    assert _draws(rng) == expected
    restore_rng(np.random.default_rng(0), saved)  # another generator takes the state too


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("numpy_rng", None, "numpy_rng: not a PCG64 generator state"),
        ("numpy_rng", {"bit_generator": "MT19937", "state": {}}, "numpy_rng: not a PCG64"),
        ("numpy_rng", {"bit_generator": "PCG64", "state": {"state": "x"}}, "numpy_rng: not a"),
        ("torch_rng", torch.zeros(3, dtype=torch.uint8), "torch_rng: not the state of torch's"),
        ("torch_rng", [1, 2, 3], "torch_rng: not the state"),
    ],
)
def test_a_corrupt_state_names_its_key_and_changes_neither_stream(
    key: str, value: object, message: str
) -> None:
    rng = np.random.default_rng(3)
    corrupt = {**rng_state(np.random.default_rng(11)), key: value}
    before = rng_state(rng)
    with pytest.raises(ValueError, match=message):
        restore_rng(rng, corrupt)
    assert rng.bit_generator.state == before["numpy_rng"]
    assert torch.equal(torch.get_rng_state(), before["torch_rng"])
    with pytest.raises(ValueError, match="numpy_rng"):
        restore_rng(rng, {"torch_rng": before["torch_rng"]})  # missing


class Recorder:
    """A stand-in SummaryWriter that records how it was opened and what it was given."""

    opened: list[tuple[str, int | None]] = []  # noqa: RUF012 (reset by each test)

    def __init__(self, log_dir: str, purge_step: int | None = None) -> None:
        self.opened.append((log_dir, purge_step))
        self.events: list[tuple[str, float, int]] = []

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.events.append((tag, value, step))

    def flush(self) -> None: ...

    def close(self) -> None: ...


def test_tensorboard_opens_on_first_event_and_purges_after_a_resume(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(Recorder, "opened", [])
    monkeypatch.setattr("torch.utils.tensorboard.SummaryWriter", Recorder)
    fresh = TensorBoardLog(tmp_path / "tensorboard")
    fresh.flush()
    fresh.close()  # nothing logged: never opened
    assert Recorder.opened == []
    resumed = TensorBoardLog(tmp_path / "tensorboard")
    resumed.resume_after(40)
    resumed.add_scalar("a", 1.0, 41)
    resumed.add_scalar("b", 2.0, 42)
    assert Recorder.opened == [(str(tmp_path / "tensorboard"), 41)]
    with pytest.raises(RuntimeError, match="before the first event"):
        resumed.resume_after(50)


def test_the_run_config_readers(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"is not a league run \(no config.yaml\)"):
        run_config_data(tmp_path, "league run")
    config = parse_experiment({"name": "x", "history": 6})
    (tmp_path / "config.yaml").write_text(dump_experiment(config))
    assert read_training_config(tmp_path) == config
    assert run_config_data(tmp_path)["history"] == 6
    (tmp_path / "config.yaml").write_text("- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        read_training_config(tmp_path)


def test_the_knob_record_round_trips_and_refuses_what_does_not_fit(tmp_path: Path) -> None:
    focus = get_task("focus")
    assert recorded_knobs(tmp_path, focus) is None  # a run from before the record
    limits = knob_limits(focus, {"defocus": (10.0, 90.0), "stigmator_x": (-1.0, 1.0)})
    assert limits == [{"name": "defocus", "low": 10.0, "high": 90.0, "max_step": 20.0}]
    record_knobs(tmp_path, "mylab:Column", limits)
    assert recorded_knobs(tmp_path, focus) == limits
    with pytest.raises(ValueError, match=r"knobs.json: lists 1 knob\(s\); task 'stigmation'"):
        recorded_knobs(tmp_path, get_task("stigmation"))
    path = tmp_path / KNOBS_FILE
    record = json.loads(path.read_text())
    record["knobs"][0]["max_step"] = -1.0
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"knobs\[0\] \(defocus\) needs low < high and max_step"):
        recorded_knobs(tmp_path, focus)
    record["knobs"][0]["max_step"] = "20"
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"knobs\[0\].max_step is '20', not a number"):
        recorded_knobs(tmp_path, focus)
    path.write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        recorded_knobs(tmp_path, focus)
    path.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match=run_state.KNOBS_FORMAT):
        recorded_knobs(tmp_path, focus)

"""Knob intervals and steps are recorded in the run when it starts (knobs.json, before
config.yaml), and export reads them from there: a run whose instrument can no longer be opened
still exports, with the intervals it trained on. A run made before the record opens its
training apparatus, and says so in one line."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
from typing import Any

import pytest
from test_league import write_league

import alignrl.checkpoints as checkpoints
from alignrl.apparatus.registry import make_apparatus
from alignrl.config.experiment import parse_experiment
from alignrl.deploy.export import export_policy
from alignrl.league.config import load_league
from alignrl.league.loop import League
from alignrl.runs.sources import ExportError, resolve_source
from alignrl.runs.state import KNOBS_FILE
from alignrl.training import Trainer

DRIVER = "vanishing_lens"
LENS_KNOBS = [{"name": "defocus", "low": 10.0, "high": 90.0, "max_step": 20.0}]  # 0.25 x 80 V


def _write_driver(folder: Path) -> None:
    (folder / f"{DRIVER}.py").write_text(
        "from fake_drivers import ParabolicLens\n\n\n"
        "class Lens(ParabolicLens):\n"
        "    def __init__(self) -> None:\n"
        "        super().__init__()\n"
        '        self.knobs = {"defocus": (10.0, 90.0)}\n'
    )
    importlib.invalidate_caches()


def _remove_driver(folder: Path) -> None:
    (folder / f"{DRIVER}.py").unlink()
    sys.modules.pop(DRIVER, None)
    importlib.invalidate_caches()


def _writes(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the files atomic writes replace, in order."""
    names: list[str] = []
    atomic_write = checkpoints.atomic_write

    def recorded(path: Path, write: Any) -> None:
        names.append(path.name)
        atomic_write(path, write)

    monkeypatch.setattr(checkpoints, "atomic_write", recorded)
    return names


@pytest.fixture
def trained(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """A tiny run trained on a driver loaded by import path (evaluated on `synthetic`)."""
    monkeypatch.syspath_prepend(str(tmp_path))
    _write_driver(tmp_path)
    writes = _writes(monkeypatch)
    settings = {
        "name": "lens",
        "envs": 2,
        "apparatus": f"{DRIVER}:Lens",
        "apparatus_args": {},
        "eval_apparatus": "synthetic",
        "eval_apparatus_args": {},
        "task_options": {"success_absolute_px": 2.95},  # the lens cannot say its best width
        "learner": {
            "algorithm": "ppo",
            "encoder": "mlp",
            "encoder_kwargs": {"hidden": [8]},
            "hidden": [8],
            "rollout_steps": 8,
            "batch_size": 8,
            "epochs": 1,
        },
        "budget": {"env_steps": 16, "eval_every": 16, "eval_scenarios": 1, "checkpoint_every": 16},
    }
    Trainer.create(parse_experiment(settings), tmp_path / "runs").run(progress=False)
    yield tmp_path / "runs" / "lens", writes
    sys.modules.pop(DRIVER, None)


def test_a_run_records_its_knobs_before_its_config(trained: tuple[Path, list[str]]) -> None:
    run, writes = trained
    record = json.loads((run / KNOBS_FILE).read_text())
    assert record["apparatus"] == f"{DRIVER}:Lens" and record["knobs"] == LENS_KNOBS
    assert writes.index(KNOBS_FILE) < writes.index("config.yaml")


def test_export_reads_the_record_when_the_driver_is_gone(
    trained: tuple[Path, list[str]], tmp_path: Path
) -> None:
    run, _ = trained
    _remove_driver(tmp_path)
    with pytest.raises(ValueError, match="cannot import module 'vanishing_lens'"):
        make_apparatus(f"{DRIVER}:Lens", {})
    notes: list[str] = []
    result = export_policy(resolve_source(run), tmp_path / "out", "safetensors", note=notes.append)
    assert result.card["knobs"] == LENS_KNOBS and notes == []
    # A run from before the record: its apparatus is opened, and the export says so.
    (run / KNOBS_FILE).unlink()
    with pytest.raises(ExportError, match=r"cannot read the knob intervals .*vanishing_lens"):
        export_policy(resolve_source(run), tmp_path / "old", "safetensors", note=notes.append)
    assert len(notes) == 1 and f"no {KNOBS_FILE}" in notes[0] and "vanishing_lens:Lens" in notes[0]
    _write_driver(tmp_path)
    result = export_policy(resolve_source(run), tmp_path / "old", "safetensors", note=notes.append)
    assert result.card["knobs"] == LENS_KNOBS and len(notes) == 2


def test_a_record_that_does_not_fit_the_task_is_refused(
    trained: tuple[Path, list[str]], tmp_path: Path
) -> None:
    run, _ = trained
    record = json.loads((run / KNOBS_FILE).read_text())
    record["knobs"][0]["name"] = "stigmator_x"
    (run / KNOBS_FILE).write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"knobs.json: knobs\[0\] is not knob 'defocus'"):
        export_policy(resolve_source(run), tmp_path / "out", "safetensors")
    assert not (tmp_path / "out").exists()


def test_a_league_records_its_knobs_before_its_config(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    writes = _writes(monkeypatch)
    config, aligners, misaligners = load_league(write_league(tmp_path))
    League.create(config, aligners, misaligners, tmp_path / "runs")
    record = json.loads((tmp_path / "runs" / "tiny" / KNOBS_FILE).read_text())
    knobs = make_apparatus(config.apparatus, config.apparatus_args).knobs["defocus"]
    assert record["knobs"] == [
        {"name": "defocus", "low": knobs[0], "high": knobs[1], "max_step": 25.0}
    ]
    assert writes.index(KNOBS_FILE) < writes.index("config.yaml")


def test_an_export_never_carries_an_interval_wider_than_its_run_recorded(
    trained: tuple[Path, list[str]], tmp_path: Path
) -> None:
    """An export of an export whose card was widened, interval and step alike (so that the
    card agrees with itself), is held to the knobs.json of the run its card names."""
    run, _ = trained
    first = export_policy(resolve_source(run), tmp_path / "first", "safetensors").out
    again = export_policy(resolve_source(first), tmp_path / "again", "safetensors")
    assert again.card["knobs"] == LENS_KNOBS  # as recorded: exported again as it is
    card = json.loads((first / "card.json").read_text())
    assert card["source"]["run"] == str(run)
    card["knobs"][0].update(low=-70.0, high=170.0, max_step=60.0)  # 0.25 x 240 V, as the rule
    (first / "card.json").write_text(json.dumps(card))
    source = resolve_source(first)  # the card alone is consistent
    with pytest.raises(ExportError) as refused:
        export_policy(source, tmp_path / "wide", "safetensors")
    message = str(refused.value)
    assert f"{first / 'card.json'}: knobs[0].low (defocus) is -70" in message
    assert f"the 10 its run recorded in {run / KNOBS_FILE}" in message
    assert not (tmp_path / "wide").exists()

"""champion:focus-v2, the aligner trained across the instrument family: it ships what
adaptation needs, adapts straight from the package on a driver that cannot tell its optimum,
and acts alike on two instruments that differ only in their units."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from fake_drivers import BlindLens
from test_family import _scaled

from alignrl.apparatus.family import FamilyColumn
from alignrl.apparatus.family_box import load_family
from alignrl.apparatus.instruments import INSTRUMENT_DIR, VALIDATION_SET
from alignrl.checkpoints import load_checkpoint
from alignrl.cli import main
from alignrl.config.experiment import load_experiment
from alignrl.deploy.policy import load_deployable
from alignrl.envs.endings import ending_options, with_ending
from alignrl.envs.task import get_task
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.session import run_session
from alignrl.runs.sources import champion_folder, resolve_source

CHAMPION = "champion:focus-v2"


def test_the_champion_ships_its_learner_state_and_sees_no_units() -> None:
    folder = champion_folder("focus-v2")
    assert {path.name for path in folder.iterdir()} >= {
        "policy.safetensors",
        "card.json",
        "model_card.md",
        "learner.safetensors",
        "learner.json",
    }
    source = resolve_source(CHAMPION)
    assert source.learner_state and source.kind == "champion"
    assert source.task.quality_reference == "first"  # readings relative to the first one
    card = json.loads((folder / "card.json").read_text())
    assert card["task"]["options"]["quality_reference"] == "first"


def test_the_shipped_champion_acts_as_its_experiment_file_says() -> None:
    """The card in the package carries experiments/focus-v2.yaml's acting_options (the file
    the champion is trained and exported from), so a change to either shows here."""
    experiment = Path(__file__).resolve().parents[1] / "experiments" / "focus-v2.yaml"
    acting = load_experiment(experiment).acting_options.model_dump()
    task = resolve_source(CHAMPION).task
    chosen = {name: value for name, value in acting.items() if value is not None}
    assert chosen["posterior_probe_rule"] == "entropy"
    flat = {**ending_options(task.ending, every=True), "move_floor": task.move_floor}
    for name, value in chosen.items():  # the ending's options as its flat names
        assert flat[name] == (tuple(value) if isinstance(value, list) else value), name


def test_adapt_from_the_champion_on_a_driver_without_an_optimum(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert BlindLens.optimum is None  # as a real column: no secret for the critics
    source = resolve_source(CHAMPION)
    argv = ["adapt", "--from", CHAMPION, "--apparatus", "fake_drivers:BlindLens"]
    argv += ["--spec-px", "3", "--steps", "300", "--envs", "4", "--eval-scenarios", "3"]
    argv += ["--eval-every", "300"]  # evaluated as it starts and ends
    argv += ["--name", "adapted", "--runs-dir", str(tmp_path), "--quiet", "--json"]
    # The champion's own task options but a posterior of 16 columns (the least a task
    # takes), not its 1,024: the same adaptation in less computing (its posterior is asked
    # at every reading).
    argv += ["--set", "task_options.posterior_draws=16"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["env_steps"] >= 300
    run = tmp_path / "adapted"
    adaptation = yaml.safe_load((run / "config.yaml").read_text())["adaptation"]
    assert adaptation["hindsight_secrets"] is True
    assert adaptation["hindsight_optimum"] == "posterior"
    agent = load_checkpoint(run / "checkpoints" / "last.pt")["agent"]
    assert agent["steps_seen"] > source.agent.steps_seen
    assert agent["learner"]["updates"] > source.agent.updates
    size = int(agent["replay"]["size"])
    # The posterior stood in for the optimum the driver cannot tell.
    assert np.abs(np.asarray(agent["replay"]["secret"][:size])).max() > 0.01


def test_the_champion_aligns_alike_in_any_units() -> None:
    policy = load_deployable(CHAMPION)
    # its posterior of 16 columns, not 1,024: units mean as little to it, in less computing
    policy = dataclasses.replace(policy, task=with_ending(policy.task, posterior_draws=16))
    base = load_family(INSTRUMENT_DIR / VALIDATION_SET / "val-mid.yaml")
    other = _scaled(base, volts=9.0, shift=-5000.0, pixels=1.7)
    results = []
    for family in (base, other):
        controller = PolicyController(
            name="focus-v2", act=policy.act, task=policy.task, history=policy.history
        )
        column = FamilyColumn(family, seed=0, analytic=True)
        results.append(run_session(controller, column, get_task("focus"), scenarios=6, seed=3))
    one, two = results
    assert [r.acquisitions for r in one.records] == [r.acquisitions for r in two.records]
    assert [r.success for r in one.records] == [r.success for r in two.records]
    fraction = [
        [(r.final_settings["defocus"] - r.starts["defocus"]) for r in result.records]
        for result in results
    ]
    np.testing.assert_allclose(np.array(fraction[1]), 9.0 * np.array(fraction[0]), rtol=1e-4)

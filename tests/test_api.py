"""alignrl.api, the calls of docs/python.md (which tests/test_docs_python.py runs whole): each
does what its command does, and refuses what its command refuses, before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from alignrl import api
from alignrl.apparatus import make_apparatus
from alignrl.config_reading import ConfigError
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import CLASSICAL
from alignrl.evaluation.session import run_session


def test_an_experiment_is_checked_as_strictly_as_a_file() -> None:
    config = api.experiment("quick", envs=4, budget={"env_steps": 600})
    assert (config.name, config.envs, config.budget.env_steps) == ("quick", 4, 600)
    assert config.budget.eval_every == api.experiment().budget.eval_every  # defaults kept
    with pytest.raises(ConfigError, match=r"experiment 'quick': budget\.env_step: Extra inputs"):
        api.experiment("quick", budget={"env_step": 600})
    with pytest.raises(ConfigError, match=r"learner\.algorithm"):
        api.experiment("quick", learner={"algorithm": "dqn"})


def test_evaluate_runs_the_session_the_command_runs() -> None:
    held_out = {"split": "test", "noise": 0.02}
    session = api.evaluate("hyperbola", "csv:default", held_out, scenarios=5, seed=3)
    same = run_session(
        CLASSICAL["hyperbola"](),
        make_apparatus("csv:default", held_out),
        get_task("focus"),
        scenarios=5,
        seed=3,
    )
    assert session.controller == "hyperbola" and session.scenarios == 5
    assert [r.trajectory for r in session.records] == [r.trajectory for r in same.records]


def test_align_refuses_a_gif_it_cannot_write_before_it_loads_anything(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"gif .*missing/a\.gif: the folder .* does not exist"):
        api.align("champion:no-such-champion", gif=tmp_path / "missing" / "a.gif")


def test_train_refuses_a_folder_that_holds_a_run(tmp_path: Path) -> None:
    (tmp_path / "quick").mkdir()
    (tmp_path / "quick" / "config.yaml").write_text("name: quick\n")
    with pytest.raises(FileExistsError, match="already holds a run"):
        api.train(api.experiment("quick"), runs_dir=tmp_path)

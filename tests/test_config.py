"""Experiment configs load strictly: every mistake names the file, the key and what was wanted."""

from __future__ import annotations

from pathlib import Path

import pytest

from alignrl.config.experiment import dump_experiment, load_experiment, parse_experiment
from alignrl.config_reading import ConfigError

ROOT = Path(__file__).resolve().parents[1]
# Experiments that name rosters (`aligners:`) are leagues (tests/test_league.py); the rest
# train one aligner.
EXPERIMENTS = sorted(
    path
    for path in ROOT.glob("experiments/*.yaml")
    if "aligners" not in __import__("yaml").safe_load(path.read_text())
)


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda path: path.name)
def test_shipped_experiments_load(path: Path) -> None:
    config = load_experiment(path)
    assert config.name
    assert parse_experiment(__import__("yaml").safe_load(dump_experiment(config))) == config


def test_defaults_are_the_seed_setting() -> None:
    config = parse_experiment({})
    assert config.apparatus == "csv:default" and config.task == "focus"
    assert config.learner.algorithm == "sac" and config.learner.secret_critics


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("learner:\n  lerning_rate: 0.1\n", ["learner.lerning_rate", "Extra inputs"]),
        ("budget:\n  env_steps: many\n", ["budget.env_steps", "'many'"]),
        ("learner:\n  learning_rate: 5\n", ["learner.learning_rate", "less than 1"]),
        ("history: 0\n", ["history", "greater than or equal to 1"]),
        ("learner:\n  encoder: lstm\n", ["learner.encoder", "'mlp', 'gru' or 'gtrxl'"]),
        ("name: 'my run/../x'\n", ["name"]),
        ("curriculum:\n  lower_at: 0.9\n  raise_at: 0.5\n", ["lower_at"]),
        ("- 1\n- 2\n", ["mapping"]),
        ("learner: [unclosed\n", ["not valid YAML"]),
    ],
)
def test_bad_configs_name_the_file_and_the_key(
    tmp_path: Path, text: str, fragments: list[str]
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_experiment(path)
    message = str(caught.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message


def test_a_missing_config_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml does not exist"):
        load_experiment(tmp_path / "nope.yaml")


def test_configs_are_frozen() -> None:
    config = parse_experiment({})
    with pytest.raises(ValueError):
        config.seed = 3  # type: ignore[misc]
    renamed = config.model_copy(update={"name": "other"})
    assert renamed.name == "other" and config.name == "experiment"


def test_task_options_change_a_copy_of_the_named_task() -> None:
    from alignrl.envs.task import get_task

    config = parse_experiment(
        {
            "task_options": {
                "acquisition_cost": 0.1,
                "success_absolute_px": 3.0,
                "episode_steps": 6,
                "success_bonus": 2.0,
            }
        }
    )
    task = config.resolved_task()
    assert task.acquisition_cost == 0.1 and task.episode_steps == 6
    assert task.success_bonus == 2.0
    assert task.success.absolute_px == 3.0 and task.success.relative == 1.15
    assert get_task("focus").acquisition_cost == 0.0  # the registry's task is untouched
    with pytest.raises(ConfigError, match=r"task_options\.cost"):
        parse_experiment({"task_options": {"cost": 1}})


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"posterior_draws": 64.0}, "posterior_draws"),
        ({"posterior_walk_after": 2.0}, "posterior_walk_after"),
        ({"episode_steps": 10**6}, "episode_steps"),
    ],
)
def test_counts_of_task_options_are_whole_numbers_within_bounds(options: dict, key: str) -> None:
    # A float for a count is a typo refused as one, never truncated; a count has a bound.
    from alignrl.config.task_options import TaskOptions

    with pytest.raises(ValueError, match=key):
        TaskOptions(**options)

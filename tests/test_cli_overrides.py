"""Command-line habits (issue 23): `--set key.path=value` and `--seed` on train, league run and
adapt, checked by the strict models with the key path in the error; the run's config.yaml
records the overrides, the command line and the git commit; `--force` replaces a run of the
same name and nothing else; `python -m alignrl` is the command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import SMALL_SAC, quiet_schedule, read_csv, write_experiment, write_league

from alignrl.cli import main
from alignrl.config.experiment import load_experiment
from alignrl.config_reading import ConfigError
from alignrl.league.config import load_league
from alignrl.overlays import OverlayError, apply_overrides

TINY = {
    "name": "tiny",
    "apparatus": "synthetic",
    "apparatus_args": {"analytic": True},
    "eval_apparatus": "synthetic",
    "eval_apparatus_args": {"analytic": True},
    "envs": 2,
    "learner": SMALL_SAC,
    "budget": {"env_steps": 40, "eval_every": 40, "eval_scenarios": 2, "checkpoint_every": 40},
}


def test_overrides_set_nested_keys_lists_and_yaml_values_without_changing_the_input() -> None:
    data = {"budget": {"env_steps": 5}, "seed": 0, "ray": {"workers": [{"envs": 2}]}}
    changed = apply_overrides(
        data,
        [
            "budget.env_steps=2000",
            "seed=3",
            "task_options.success_bonus=5.0",
            "ray.workers.0.envs=4",
            "name=focus run",
            "device=null",
            "seed=4",
        ],
    )
    assert changed == {
        "budget": {"env_steps": 2000},
        "seed": 4,  # the later assignment wins
        "ray": {"workers": [{"envs": 4}]},
        "task_options": {"success_bonus": 5.0},
        "name": "focus run",
        "device": None,
    }
    assert data == {"budget": {"env_steps": 5}, "seed": 0, "ray": {"workers": [{"envs": 2}]}}


@pytest.mark.parametrize(
    ("assignment", "message"),
    [
        ("budget", "expected key.path=value"),
        ("budget..env_steps=3", "expected key.path=value"),
        ("seed.low=1", "seed is 0, not a mapping to set low in"),
        ("ray.workers.3.envs=1", "ray.workers is a list of 1; 3 is not one of its indices"),
        ("name=[unclosed", "the value is not YAML"),
    ],
)
def test_a_malformed_override_is_refused_with_what_it_says(assignment: str, message: str) -> None:
    with pytest.raises(OverlayError, match=message):
        apply_overrides({"seed": 0, "ray": {"workers": [{"envs": 2}]}}, [assignment])


def test_the_strict_models_check_an_overridden_experiment_and_name_the_key(
    tmp_path: Path,
) -> None:
    path = write_experiment(tmp_path, TINY)
    config = load_experiment(path, ["budget.env_steps=80", "learner.batch_size=8", "seed=7"])
    assert (config.budget.env_steps, config.learner.batch_size, config.seed) == (80, 8, 7)
    with pytest.raises(
        ConfigError, match=r"with --set budget.env_stepz=3: budget.env_stepz: Extra"
    ):
        load_experiment(path, ["budget.env_stepz=3"])
    with pytest.raises(ConfigError, match=r"budget.env_steps: Input should be greater than or"):
        load_experiment(path, ["budget.env_steps=-3"])
    league = write_league(tmp_path, schedule=quiet_schedule())
    config, _, _ = load_league(league, ["schedule.matches=3", "design=false"])
    assert config.schedule.matches == 3
    with pytest.raises(ConfigError, match=r"schedule.matchez: Extra inputs"):
        load_league(league, ["schedule.matchez=3"])


def test_train_with_set_and_seed_records_them_with_the_command_and_commit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_experiment(tmp_path, TINY)
    runs = tmp_path / "runs"
    argv = [
        "train",
        str(path),
        "--runs-dir",
        str(runs),
        "--quiet",
        "--set",
        "budget.env_steps=60",
        "--set",
        "learner.batch_size=8",
        "--seed",
        "3",
    ]
    assert main(argv) == 0
    recorded = yaml.safe_load((runs / "tiny" / "config.yaml").read_text())
    assert recorded["seed"] == 3 and recorded["budget"]["env_steps"] == 60
    provenance = recorded["provenance"]
    assert provenance["overrides"] == ["budget.env_steps=60", "learner.batch_size=8", "seed=3"]
    assert (
        provenance["command"].startswith("alignrl train ") and "--seed 3" in provenance["command"]
    )
    commit = provenance["git_commit"]
    assert commit is None or len(commit.removesuffix("+dirty")) == 40
    # The same name again is refused; --force replaces it (and says so); --resume takes no
    # overrides.
    assert main(argv) == 2
    assert "--force" in capsys.readouterr().err
    assert main([*argv[:5], "--force"]) == 0
    assert "--force: removed the run in" in capsys.readouterr().err
    assert yaml.safe_load((runs / "tiny" / "config.yaml").read_text())["seed"] == 0
    assert main(["train", "--resume", str(runs / "tiny"), "--seed", "4"]) == 2
    assert "give --set or --seed or --resume" in capsys.readouterr().err


def test_resume_with_steps_gives_a_finished_run_a_new_budget_on_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_experiment(tmp_path, TINY)
    runs, run = tmp_path / "runs", tmp_path / "runs" / "tiny"
    # --steps N on a new run is --set budget.env_steps=N.
    assert main(["train", str(path), "--runs-dir", str(runs), "--quiet", "--steps", "40"]) == 0
    recorded = yaml.safe_load((run / "config.yaml").read_text())
    assert recorded["provenance"]["overrides"] == ["budget.env_steps=40"]
    capsys.readouterr()
    # Finished: --resume alone trains nothing; --resume --steps 80 goes on to 80.
    assert main(["train", "--resume", str(run), "--quiet"]) == 0
    assert "is finished at 40 env steps" in capsys.readouterr().err
    assert main(["train", "--resume", str(run), "--quiet", "--json", "--steps", "80"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["env_steps"] == 80 and summary["test"] is not None
    recorded = yaml.safe_load((run / "config.yaml").read_text())
    assert recorded["budget"]["env_steps"] == 80
    assert recorded["provenance"]["overrides"] == ["budget.env_steps=40", "budget.env_steps=80"]
    sessions = [int(row["env_steps"]) for row in read_csv(run / "metrics" / "evaluations.csv")]
    assert sessions == [40, 80]
    # A budget at or below the steps already taken is refused; config.yaml is left as it was.
    before = (run / "config.yaml").read_text()
    assert main(["train", "--resume", str(run), "--quiet", "--steps", "80"]) == 2
    assert "--steps 80: " in capsys.readouterr().err
    assert (run / "config.yaml").read_text() == before
    assert main(["train", "--resume", str(run), "--steps", "120", "--seed", "3"]) == 2


def test_force_replaces_only_a_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_experiment(tmp_path, TINY)
    keep = tmp_path / "runs" / "tiny"
    keep.mkdir(parents=True)
    (keep / "notes.txt").write_text("not a run")
    assert main(["train", str(path), "--runs-dir", str(tmp_path / "runs"), "--force"]) == 2
    assert "is not one" in capsys.readouterr().err
    assert (keep / "notes.txt").exists()


def test_league_run_takes_set_and_seed(tmp_path: Path) -> None:
    path = write_league(tmp_path, schedule=quiet_schedule(iterations=2))
    runs = tmp_path / "runs"
    argv = [
        "league",
        "run",
        str(path),
        "--runs-dir",
        str(runs),
        "--quiet",
        "--set",
        "schedule.matches=4",
        "--seed",
        "5",
    ]
    assert main(argv) == 0
    recorded = yaml.safe_load((runs / "tiny" / "config.yaml").read_text())
    assert (recorded["seed"], recorded["schedule"]["matches"]) == (5, 4)
    assert recorded["provenance"]["overrides"] == ["schedule.matches=4", "seed=5"]


def test_python_dash_m_alignrl_is_the_command() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "alignrl", "--version"], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0 and done.stdout.startswith("alignrl ")

"""What many test files build: tiny learners, rosters, leagues and training experiments
written as YAML under a test's own folder, and the CSV reader for run metrics.

Test files import these by name (`from conftest import SMALL_SAC, write_league`); the values
are those the tests were written with, so a test that moved here draws the same random numbers
and asserts the same results. Everything is written under the folder a test passes in (its
`tmp_path`): nothing here touches a fixed path, so tests run in parallel (`pytest -n 2`).
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import yaml

if TYPE_CHECKING:
    from alignrl.league.loop import League

# A SAC and a PPO learner small enough to learn something in a few dozen env steps.
SMALL_SAC = {
    "encoder_kwargs": {"hidden": [16]},
    "hidden": [16],
    "batch_size": 16,
    "learning_starts": 16,
    "random_steps": 32,
    "buffer_size": 2000,
}
SMALL_PPO = {
    "algorithm": "ppo",
    "encoder": "mlp",
    "encoder_kwargs": {"hidden": [16]},
    "hidden": [16],
    "batch_size": 16,
    "rollout_steps": 4,
    "epochs": 2,
}


def narrowed(learner: dict[str, Any], width: int) -> dict[str, Any]:
    """`learner` with one hidden layer of `width` units in its encoder and its heads."""
    return {**learner, "encoder_kwargs": {"hidden": [width]}, "hidden": [width]}


def write_yaml(path: Path, data: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def write_experiment(folder: Path, settings: dict[str, Any]) -> Path:
    """A training experiment, `folder/<name>.yaml`."""
    return write_yaml(folder / f"{settings['name']}.yaml", settings)


def write_rosters(
    folder: Path, aligners: list[dict[str, Any]], misaligners: list[dict[str, Any]]
) -> dict[str, str]:
    """`folder/aligners.yaml` and `folder/misaligners.yaml`; the league keys naming them."""
    for team, members in (("aligner", aligners), ("misaligner", misaligners)):
        write_yaml(folder / f"{team}s.yaml", {"team": team, "members": members})
    return {team: str(folder / f"{team}.yaml") for team in ("aligners", "misaligners")}


def one_sac_each(learner: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """Rosters of one member per team, `a-sac` and `m-sac`, both with `learner`."""
    return {
        "aligners": [{"id": "a-sac", "learner": learner}],
        "misaligners": [{"id": "m-sac", "learner": learner}],
    }


def write_league_files(
    folder: Path,
    aligners: list[dict[str, Any]],
    misaligners: list[dict[str, Any]],
    settings: dict[str, Any],
    file: str = "league.yaml",
) -> Path:
    """A league experiment `folder/file` with its two rosters beside it; `settings` may name
    other roster files instead."""
    return write_yaml(folder / file, {**write_rosters(folder, aligners, misaligners), **settings})


# The tiny league's schedule: snapshots at 3 and 6, PBT and evaluations at 4 and 8
TINY_SCHEDULE = {
    "iterations": 8,
    "matches": 8,
    "snapshot_every": 3,
    "pbt_every": 4,
    "evaluate_every": 4,
    "eval_scenarios": 4,
    "checkpoint_every": 2,
}


def write_league(folder: Path, **changes: Any) -> Path:
    """The tiny league of the league tests: a SAC and a PPO member per team (the PPO aligner
    with a GRU), 8 iterations of 8 matches with snapshots, PBT, evaluations and checkpoints
    all happening; `changes` replace top-level keys."""
    gru_ppo = {**SMALL_PPO, "encoder": "gru", "encoder_kwargs": {"hidden": 8}}
    settings = {
        "name": "tiny",
        "envs": 4,
        "schedule": dict(TINY_SCHEDULE),
        "pbt": {"min_gap": 0.0},
        **changes,
    }
    return write_league_files(
        folder,
        aligners=[{"id": "a-sac", "learner": SMALL_SAC}, {"id": "a-ppo", "learner": gru_ppo}],
        misaligners=[{"id": "m-sac", "learner": SMALL_SAC}, {"id": "m-ppo", "learner": SMALL_PPO}],
        settings=settings,
    )


def quiet_schedule(**changes: Any) -> dict[str, Any]:
    """A short schedule without snapshots or evaluations to speak of; `changes` on top."""
    return {
        "iterations": 6,
        "matches": 8,
        "snapshot_every": 100,
        "evaluate_every": 100,
        "eval_scenarios": 2,
        "checkpoint_every": 3,
        **changes,
    }


def create_league(path: Path, runs: Path) -> League:
    """The league of experiment `path`, its run directory made under `runs`."""
    from alignrl.league.config import load_league  # torch: only for the tests that need it
    from alignrl.league.loop import League

    return League.create(*load_league(path), runs)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def kill_league_after(
    command: list[str], run: Path, checkpoint: int, timeout_s: float = 180
) -> int:
    """Start the league `command` (alignrl league run ...), SIGKILL it once its run `run` has
    checkpointed iteration `checkpoint` or later, and return the iteration LATEST names."""
    process = subprocess.Popen(command, stderr=subprocess.PIPE)
    latest = run / "checkpoints" / "LATEST"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if latest.exists() and int(latest.read_text().split("-")[1]) >= checkpoint:
            break
        assert process.poll() is None, process.stderr.read() if process.stderr else ""
        time.sleep(0.02)
    os.kill(process.pid, signal.SIGKILL)
    process.wait(timeout=30)
    return int(latest.read_text().split("-")[1])


def iteration_outcomes(run: Path) -> list[tuple[str, ...]]:
    """A league run's metrics/iterations.csv rows without their wall times: what two runs
    that played alike agree on."""
    rows = read_csv(run / "metrics" / "iterations.csv")
    return [tuple(v for k, v in row.items() if k != "seconds") for row in rows]


# The tiny training run of the training and TensorBoard tests (400 env steps of a small SAC).
TINY_RUN: dict[str, Any] = {
    "name": "tiny",
    "envs": 2,
    "learner": {
        "encoder_kwargs": {"hidden": [16]},
        "hidden": [16],
        "batch_size": 32,
        "learning_starts": 50,
        "random_steps": 100,
        "buffer_size": 1000,
    },
    "budget": {"env_steps": 400, "eval_every": 200, "eval_scenarios": 5, "checkpoint_every": 50},
}


def without_seconds(value: Any) -> Any:
    """A session's --json (or any nesting of it) without its "seconds" keys: what two runs of
    the same session agree on, wall time aside."""
    if isinstance(value, dict):
        return {k: without_seconds(v) for k, v in value.items() if k != "seconds"}
    if isinstance(value, list):
        return [without_seconds(item) for item in value]
    return value


@pytest.fixture(scope="module")
def light(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """As `light_export`, once for a module whose tests only read it."""
    from alignrl.cli import main

    out = tmp_path_factory.mktemp("light") / "light"
    argv = ["export", "champion:focus-v2", "--format", "safetensors", "--with-learner-state"]
    assert main([*argv, "--set", "task_options.posterior_draws=64", "--out", str(out)]) == 0
    return out


@pytest.fixture
def light_export(tmp_path: Path) -> Path:
    """champion:focus-v2 exported with a posterior of 64 columns, not its 1,024 (the same
    network and learner state): its alignments at a sixteenth of the computing."""
    from alignrl.cli import main

    out = tmp_path / "light"
    argv = ["export", "champion:focus-v2", "--format", "safetensors", "--with-learner-state"]
    argv += ["--set", "task_options.posterior_draws=64", "--out", str(out), "--json"]
    assert main(argv) == 0
    return out


class WriteRecorder:
    """An apparatus passed through, every write kept (`writes`): what a controller asked of
    the driver, to check against the intervals."""

    def __init__(self, inner) -> None:
        self.inner, self.writes = inner, []
        self.knobs = inner.knobs

    def write(self, values) -> None:
        self.writes.append(dict(values))
        self.inner.write(values)

    def __getattr__(self, name):
        return getattr(self.inner, name)

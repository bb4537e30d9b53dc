"""A league whose aligners start from trained ones (`init_from` in the roster): the member acts
as its source did, keeps its critics and entropy coefficient, takes the roster's fine-tuning
keys, and a source that does not fit stops the league before any file is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import SMALL_SAC, create_league, quiet_schedule, write_league, write_yaml

from alignrl.cli import main
from alignrl.config_reading import ConfigError
from alignrl.league.config import load_league
from alignrl.league.loop import League


def _source(tmp_path: Path) -> Path:
    """A member file of a tiny league that has played and learned a little."""
    (tmp_path / "source").mkdir()
    path = write_league(
        tmp_path / "source",
        name="source",
        pbt={"enabled": False},
        schedule=quiet_schedule(iterations=4, checkpoint_every=4),
    )
    league = create_league(path, tmp_path / "source" / "runs")
    league.run(progress=False)
    member = league.members["a-sac"]
    assert member.updates > 0  # it learned: its weights are not the fresh ones
    path = tmp_path / "a-sac.pt"
    member.save(path)
    return path


def _warm_league(tmp_path: Path, member: dict, name: str = "warm", **changes: object) -> Path:
    """A league file whose aligner roster is `member` beside a fresh one."""
    folder = tmp_path / name
    folder.mkdir()
    path = write_league(folder, name=name, **changes)
    roster = {"team": "aligner", "members": [member, {"id": "fresh", "learner": SMALL_SAC}]}
    write_yaml(folder / "aligners.yaml", roster)
    return path


def _actions(agent, observations: np.ndarray) -> np.ndarray:
    return np.stack([agent.act(row) for row in observations])


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    return _source(tmp_path_factory.mktemp("warm"))


def test_a_warm_started_aligner_acts_as_its_source_and_fine_tunes_at_its_own_rate(
    tmp_path: Path, source: Path
) -> None:
    from alignrl.agents.agent import Agent

    trained = Agent.load(source)
    entry = {"id": "tuned", "init_from": str(source), "learner": {"learning_rate": 1.0e-4}}
    league = create_league(_warm_league(tmp_path, entry), tmp_path / "runs")
    tuned, fresh = league.members["tuned"], league.members["fresh"]
    observations = (
        np.random.default_rng(3)
        .uniform(-1, 1, (16, *tuned.spec.observation_shape))
        .astype(np.float32)
    )
    np.testing.assert_allclose(_actions(tuned, observations), _actions(trained, observations))
    assert not np.allclose(_actions(fresh, observations), _actions(trained, observations))
    # Its critics and entropy coefficient came along; its random warm-up is behind it.
    for critic in ("q1", "q2", "v", "v_target"):
        mine = getattr(tuned.learner, critic).state_dict()
        theirs = getattr(trained.learner, critic).state_dict()
        for key, value in theirs.items():
            torch.testing.assert_close(mine[key], value)
    assert tuned.learner.log_alpha.item() == pytest.approx(trained.learner.log_alpha.item())
    assert tuned.steps_seen == trained.steps_seen > 0
    # The source's settings, the roster's fine-tuning key on top, in every optimizer.
    assert tuned.spec.hyperparameters["hidden"] == trained.spec.hyperparameters["hidden"]
    assert tuned.spec.hyperparameters["learning_rate"] == 1.0e-4
    assert all(
        group["lr"] == 1.0e-4
        for optimizer in (tuned.learner.actor_optimizer, tuned.learner.critic_optimizer)
        for group in optimizer.param_groups
    )
    # The run records the source; its starting point is the trained one.
    run = tmp_path / "runs" / "warm"
    saved = yaml.safe_load((run / "aligners.yaml").read_text())["members"][0]
    assert saved["init_from"] == str(source) and saved["learner"]["learning_rate"] == 1.0e-4
    initial = Agent.load(run / "initial" / "tuned.pt")
    np.testing.assert_allclose(_actions(initial, observations), _actions(trained, observations))


def test_a_warm_started_league_plays_learns_and_resumes_without_its_source(
    tmp_path: Path, source: Path
) -> None:
    copy = tmp_path / "copy.pt"
    copy.write_bytes(source.read_bytes())
    entry = {"id": "tuned", "init_from": str(copy)}
    # 3 iterations: a snapshot at 2, the evaluation and the checkpoint at the last
    schedule = quiet_schedule(iterations=3, snapshot_every=2, checkpoint_every=3)
    path = _warm_league(tmp_path, entry, pbt={"enabled": False}, schedule=schedule)
    league = create_league(path, tmp_path / "runs")
    before = league.members["tuned"].updates
    league.run(progress=False)
    assert league.members["tuned"].updates > before
    copy.unlink()  # a resumed league reads its own checkpoint, never the source again
    resumed = League.resume(tmp_path / "runs" / "warm")
    assert resumed.iteration == league.iteration
    assert resumed.members["tuned"].updates == league.members["tuned"].updates
    # The report says which aligner started from what.
    assert main(["leaderboard", str(tmp_path / "runs" / "warm")]) == 0
    report = (tmp_path / "runs" / "warm" / "report.md").read_text()
    assert f"tuned from {copy}" in report and "fresh from" not in report


@pytest.mark.parametrize(
    ("member", "message"),
    [
        ({"init_from": "no/such/run"}, "does not exist"),
        ({"learner": {"hidden": [32, 32]}}, "networks were built with hidden"),
        ({"learner": {"algorithm": "ppo"}}, "algorithm='sac'"),
    ],
)
def test_a_source_that_does_not_fit_stops_before_any_file(
    tmp_path: Path, source: Path, member: dict, message: str
) -> None:
    entry = {"id": "tuned", "init_from": str(source), **member}
    config, aligners, misaligners = load_league(_warm_league(tmp_path, entry))
    with pytest.raises(ConfigError, match=message) as error:
        League.create(config, aligners, misaligners, tmp_path / "runs")
    assert "aligner 'tuned'" in str(error.value)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"history": 10}, "reads 8 history rows"),
        (
            {
                "task": "stigmation",
                "apparatus": "synthetic",
                "apparatus_args": {"analytic": True},
                "eval_apparatus": "synthetic",
                "eval_apparatus_args": {"analytic": True},
            },
            "trained on task 'focus'",
        ),
    ],
)
def test_a_source_of_another_task_or_history_is_refused(
    tmp_path: Path, source: Path, changes: dict, message: str
) -> None:
    path = _warm_league(tmp_path, {"id": "tuned", "init_from": str(source)})
    settings = {**yaml.safe_load(path.read_text()), **changes}
    write_yaml(path, settings)
    config, aligners, misaligners = load_league(path)
    with pytest.raises(ConfigError, match=message):
        League.create(config, aligners, misaligners, tmp_path / "runs")
    assert not (tmp_path / "runs").exists()


def test_misaligners_cannot_be_warm_started(tmp_path: Path, source: Path) -> None:
    path = write_league(tmp_path)
    roster = {
        "team": "misaligner",
        "members": [{"id": "m", "init_from": str(source), "learner": SMALL_SAC}],
    }
    write_yaml(tmp_path / "misaligners.yaml", roster)
    with pytest.raises(ConfigError, match="misaligners m start fresh"):
        load_league(path)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_cpu_trained_aligner_warm_starts_a_league_on_cuda(tmp_path: Path, source: Path) -> None:
    from alignrl.agents.agent import Agent

    trained = Agent.load(source)
    path = _warm_league(
        tmp_path,
        {"id": "tuned", "init_from": str(source)},
        device="cuda",
        pbt={"enabled": False},
        schedule=quiet_schedule(
            iterations=8,
            matches=16,
            evaluate_every=2,
            eval_scenarios=4,
            checkpoint_every=2,
            uniform_starts=0.5,
        ),
    )
    league = create_league(path, tmp_path / "runs")
    tuned = league.members["tuned"]
    assert all(p.device.type == "cuda" for p in tuned.learner.actor.parameters())
    observations = (
        np.random.default_rng(3)
        .uniform(-1, 1, (16, *tuned.spec.observation_shape))
        .astype(np.float32)
    )
    np.testing.assert_allclose(
        _actions(tuned, observations), _actions(trained, observations), atol=1e-5
    )
    before = tuned.updates
    league.run(progress=False)
    assert tuned.updates > before
    assert (tmp_path / "runs" / "warm" / "best" / "best.json").exists()


def test_init_replay_brings_the_sources_experience_along(tmp_path: Path, source: Path) -> None:
    # A member file (its replay left out) cannot give one.
    entry = {"id": "tuned", "init_from": str(source), "init_replay": True}
    config, aligners, misaligners = load_league(_warm_league(tmp_path, entry, "empty"))
    with pytest.raises(ConfigError, match="init_replay needs a SAC checkpoint"):
        League.create(config, aligners, misaligners, tmp_path / "runs")
    assert not (tmp_path / "runs").exists()
    # A training run's checkpoints/last.pt holds it, and gives all of it.
    from alignrl.config.experiment import parse_experiment
    from alignrl.training import Trainer

    settings = {
        "name": "trained",
        "envs": 2,
        "learner": {**SMALL_SAC, "buffer_size": 2000},
        "budget": {"env_steps": 80, "eval_every": 80, "eval_scenarios": 2, "checkpoint_every": 40},
    }
    trainer = Trainer.create(parse_experiment(settings), tmp_path / "trained-runs")
    trainer.run(progress=False)
    last = tmp_path / "trained-runs" / "trained" / "checkpoints" / "last.pt"
    entry = {"id": "tuned", "init_from": str(last), "init_replay": True}
    league = create_league(_warm_league(tmp_path, entry, "kept"), tmp_path / "runs")
    tuned, size = league.members["tuned"], trainer.agent.replay.size
    assert size >= 80 and tuned.replay.size == size
    np.testing.assert_array_equal(tuned.replay.action[:size], trainer.agent.replay.action[:size])
    assert league.members["fresh"].replay.size == 0
    # A smaller buffer than the source's cannot hold it.
    entry = {**entry, "learner": {"buffer_size": 1000}}
    config, aligners, misaligners = load_league(_warm_league(tmp_path, entry, "small"))
    with pytest.raises(ConfigError, match="replay of capacity 2000"):
        League.create(config, aligners, misaligners, tmp_path / "runs2")


def test_init_replay_needs_init_from(tmp_path: Path) -> None:
    entry = {"id": "tuned", "init_replay": True}
    with pytest.raises(ConfigError, match="init_replay needs init_from"):
        load_league(_warm_league(tmp_path, entry))

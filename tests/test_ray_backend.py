"""The Ray backend on 2 local workers: frozen members play exactly as in-process, learning
members learn centrally from what the workers played, a worker lost mid-match is restarted
and its matches replayed as they were, a league on two microscopes checkpoints and resumes
with no iteration lost, and config errors name the file and the key. One local Ray serves
the whole module."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("ray", reason="the Ray backend needs the ray extra: pip install 'alignrl[ray]'")

import ray
from test_league import write_league

from alignrl.agents.agent import Agent
from alignrl.config_reading import ConfigError
from alignrl.envs import make_apparatus_copies
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.duel import DuelBatch
from alignrl.league.backends import InProcessBackend
from alignrl.league.config import load_league
from alignrl.league.loop import League
from alignrl.league.matches import (
    WorkerFailedError,
    learn_from_matches,
    record_matches,
)
from alignrl.league.ray_backend import RayBackend, split_matches

# Two microscopes: the shipped recordings, measured with different noise.
TWO_MICROSCOPES = [
    {"apparatus": "csv:default", "apparatus_args": {"noise": 0.02, "split": "train"}, "envs": 4},
    {"apparatus": "csv:default", "apparatus_args": {"noise": 0.05, "split": "train"}, "envs": 4},
]
# Half a CPU each: the module's Ray (2 CPUs) holds a league's 2 workers and 2 more.
RAY = {"workers": [{"envs": 4}, {"envs": 4}], "num_cpus_per_worker": 0.5}


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def league(tmp_path_factory: pytest.TempPathFactory):
    """A league on 2 workers with the experiment's apparatus (csv:default, noise 0.02, train
    split): the same matches as the in-process backend's 4 envs."""
    folder = tmp_path_factory.mktemp("ray-league")
    config, aligners, misaligners = load_league(write_league(folder, backend="ray", ray=RAY))
    league = League.create(config, aligners, misaligners, folder / "runs")
    yield league
    league.close()


def _copy(agent: Agent) -> Agent:
    twin = Agent(agent.spec, agent.envs)
    twin.load_state_dict(agent.state_dict(replay=True))
    return twin


def _sorted_outcomes(result) -> list[tuple[float, bool, int]]:
    # The in-process backend reports matches as they end, the Ray backend in seed order.
    return sorted(zip(result.returns, result.successes, result.acquisitions, strict=True))


def test_shares_follow_the_workers_envs() -> None:
    assert split_matches(8, [4, 4]) == [4, 4]
    assert split_matches(10, [2, 6]) == [3, 7]  # 2.5 and 7.5: the tie goes to the first
    assert split_matches(3, [8, 8, 8, 8]) == [1, 1, 1, 0]
    assert split_matches(32, [8, 8]) == [16, 16]


def test_frozen_members_play_exactly_as_in_process(league: League) -> None:
    config = league.config
    in_process = InProcessBackend(config)
    for aligner_id, misaligner_id in (("a-sac", "m-ppo"), ("a-ppo", "m-sac")):
        aligner, misaligner = league.members[aligner_id], league.members[misaligner_id]
        on_ray = league.backend.play(
            aligner, misaligner, 8, np.random.default_rng(3), set(), deterministic=True
        )
        here = in_process.play(
            aligner, misaligner, 8, np.random.default_rng(3), set(), deterministic=True
        )
        assert on_ray.matches == 8 and _sorted_outcomes(on_ray) == _sorted_outcomes(here)
        assert sorted(on_ray.payoffs) == sorted(here.payoffs)
        assert aligner.steps_seen == misaligner.steps_seen == 0  # frozen: nothing stored


def test_uniform_starts_play_on_the_workers_from_each_matchs_seed(league: League) -> None:
    aligner = league.members["a-sac"]
    first, again = (
        league.backend.play(
            aligner, league.uniform_starts, 8, np.random.default_rng(7), set(), deterministic=True
        )
        for _ in range(2)
    )
    assert first.matches == 8 and _sorted_outcomes(first) == _sorted_outcomes(again)
    assert aligner.steps_seen == 0  # frozen here: nothing stored
    assert len({round(p, 6) for p in first.payoffs}) > 1  # the starts differ match to match


def test_learning_members_learn_centrally_what_the_workers_played(league: League) -> None:
    """The driver learns from the workers' trajectories as if it had recorded the same
    shares itself: the learning members end exactly alike."""
    aligner, misaligner = league.members["a-sac"], league.members["m-ppo"]
    twins = _copy(aligner), _copy(misaligner)
    learning = {aligner.id, misaligner.id}
    torch.manual_seed(0)
    result = league.backend.play(aligner, misaligner, 12, np.random.default_rng(5), learning)

    rng = np.random.default_rng(5)
    seeds = [int(s) for s in rng.integers(0, 2**31 - 1, 12)]
    config = league.config
    played = []
    for first, count in zip((0, 6), split_matches(12, [4, 4]), strict=True):  # 6 each
        units = make_apparatus_copies(config.apparatus, config.apparatus_args, 4)
        episodes = AlignmentEpisodes(units, config.resolved_task(), config.history)
        duel = DuelBatch(episodes)
        played += record_matches(duel, seeds[first : first + count], *twins, (True, True))
    torch.manual_seed(0)
    local = learn_from_matches(played, *twins, learning, rng)

    assert result.returns == local.returns and result.successes == local.successes
    # Zero-sum: the misaligner stored minus the aligner's payoffs; one transition per
    # aligner step and per match, in match order.
    steps = sum(len(match.steps.reward) for match in played)
    assert aligner.replay.size == aligner.steps_seen == twins[0].replay.size == steps
    assert misaligner.steps_seen == misaligner.rollout.size == 12
    stored = misaligner.rollout.reward[:12]
    np.testing.assert_allclose(stored, -np.array(result.payoffs), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(aligner.replay.action[:steps], twins[0].replay.action[:steps])
    assert len(result.updates["a-sac"]) == len(local.updates["a-sac"]) > 0
    for mine, theirs in zip(
        aligner.learner.actor.parameters(), twins[0].learner.actor.parameters(), strict=True
    ):
        assert torch.equal(mine, theirs)


def test_a_worker_lost_mid_match_is_restarted_and_its_matches_replayed(league: League) -> None:
    backend: RayBackend = league.backend  # type: ignore[assignment]
    aligner, misaligner = league.members["a-ppo"], league.members["m-sac"]
    backend.play(aligner, misaligner, 8, np.random.default_rng(9), {"a-ppo"})  # some training
    aligner_state = _copy(aligner)
    backend.fail_after(1, 3)  # worker 1's process exits at its 3rd aligner step
    replays = list(backend.replays)
    after = backend.play(_copy(aligner_state), misaligner, 8, np.random.default_rng(9), set())
    assert backend.replays == [replays[0], replays[1] + 1]
    # Every match is back, and the replayed ones are those of a run without the failure
    # (frozen members: the same weights as the learning run's acting copies had).
    reference = backend.play(_copy(aligner_state), misaligner, 8, np.random.default_rng(9), set())
    assert after.matches == 8
    assert after.returns == reference.returns and after.successes == reference.successes


def test_a_worker_lost_beyond_max_restarts_stops_with_its_name(league: League) -> None:
    config = league.config.model_copy(
        update={
            "ray": league.config.ray.model_copy(
                update={"workers": [league.config.ray.workers[0]], "max_restarts": 0}
            )
        }
    )
    backend = RayBackend(config)
    try:
        backend.fail_after(0, 1)
        aligner, misaligner = league.members["a-sac"], league.members["m-sac"]
        with pytest.raises(
            WorkerFailedError, match=r"worker 0 \(csv:default .*lost mid-batch 1 time "
        ):
            backend.play(aligner, misaligner, 4, np.random.default_rng(0), set())
    finally:
        backend.close()


def _iterations(run: Path) -> list[dict[str, str]]:
    with (run / "metrics" / "iterations.csv").open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_a_league_on_two_microscopes_loses_a_worker_checkpoints_and_resumes(
    tmp_path: Path,
) -> None:
    # 2 iterations, then 2 more on resuming: a snapshot, an evaluation and a checkpoint in
    # each run, and PBT at iteration 3 (never at a run's last) in the resumed one.
    schedule = {
        "iterations": 2,
        "matches": 8,
        "snapshot_every": 2,
        "pbt_every": 3,
        "evaluate_every": 2,
        "eval_scenarios": 2,
        "checkpoint_every": 2,
    }
    ray_settings = {**RAY, "workers": TWO_MICROSCOPES}
    path = write_league(tmp_path, backend="ray", ray=ray_settings, schedule=schedule)
    config, aligners, misaligners = load_league(path)
    first = League.create(config, aligners, misaligners, tmp_path / "runs")
    try:
        first.backend.fail_after(1, 5)  # lost during the first iteration
        first.run(progress=False)
        assert first.backend.replays == [0, 1]
    finally:
        first.close()
    run = tmp_path / "runs" / "tiny"
    assert [int(row["iteration"]) for row in _iterations(run)] == [1, 2]
    assert (run / "checkpoints" / "LATEST").read_text().strip() == "iteration-000002"
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace("iterations: 2", "iterations: 4"))
    resumed = League.resume(run)
    try:
        assert isinstance(resumed.backend, RayBackend) and resumed.iteration == 2
        resumed.run(progress=False)
    finally:
        resumed.close()
    rows = _iterations(run)
    assert [int(row["iteration"]) for row in rows] == [1, 2, 3, 4]  # none lost or doubled
    assert all(int(row["matches"]) == 8 for row in rows)
    assert (run / "checkpoints" / "LATEST").read_text().strip() == "iteration-000004"


@pytest.mark.parametrize(
    ("ray_settings", "message"),
    [
        ({"worker": []}, r"league.yaml: ray.worker: Extra inputs are not permitted"),
        ({"workers": []}, r"league.yaml: ray.workers: List should have at least 1 item"),
        (
            {"workers": [{"apparatus": "microscope-a"}]},
            r"league.yaml: ray.workers.0.apparatus: .*unknown apparatus 'microscope-a'",
        ),
        ({"workers": [{"envs": 0}]}, r"ray.workers.0.envs: Input should be greater than"),
        ({"workers": [{"resource": {"a": 1}}]}, r"ray.workers.0.resource: Extra inputs"),
        ({"max_restarts": -1}, r"ray.max_restarts: Input should be greater than or equal"),
    ],
)
def test_ray_config_errors_name_the_file_and_the_key(
    tmp_path: Path, ray_settings: dict, message: str
) -> None:
    path = write_league(tmp_path, backend="ray", ray=ray_settings)
    with pytest.raises(ConfigError, match=message):
        load_league(path)


def test_designers_play_on_the_workers_exactly_as_in_process(tmp_path: Path) -> None:
    from test_designers import DESIGN_LEAGUE

    path = write_league(tmp_path, backend="ray", ray=RAY, **DESIGN_LEAGUE)
    config, aligners, misaligners = load_league(path)
    league = League.create(config, aligners, misaligners, tmp_path / "runs")
    try:
        aligner, designer = league.members["a-sac"], league.members["m-sac"]
        on_ray, here = (
            backend.play(aligner, designer, 8, np.random.default_rng(3), set(), deterministic=True)
            for backend in (league.backend, InProcessBackend(config))
        )
        assert on_ray.matches == 8
        assert sorted(zip(on_ray.payoffs, on_ray.rated, strict=True)) == sorted(
            zip(here.payoffs, here.rated, strict=True)
        )
        assert sorted(map(tuple, on_ray.designs)) == sorted(map(tuple, here.designs))
        assert len({tuple(d) for d in here.designs}) == 8  # its draws vary the columns
    finally:
        league.close()

"""The league: matches are zero-sum, members learn, PBT copies, a kill -9 loses nothing,
configs fail clearly, and the leaderboard reads a run."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import (
    SMALL_SAC,
    create_league,
    iteration_outcomes,
    kill_league_after,
    quiet_schedule,
    read_csv,
    write_league,
    write_yaml,
)

from alignrl.cli import main
from alignrl.config_reading import ConfigError
from alignrl.league.config import load_league
from alignrl.league.loop import League, leaderboard


def tiny_league(tmp_path: Path, **changes: object) -> League:
    return create_league(write_league(tmp_path, **changes), tmp_path / "runs")


def test_matches_are_zero_sum_and_both_sides_store_their_experience(tmp_path: Path) -> None:
    league = tiny_league(tmp_path)
    aligner, misaligner = league.members["a-sac"], league.members["m-sac"]
    result = league.backend.play(
        aligner, misaligner, 10, np.random.default_rng(0), {"a-sac", "m-sac"}
    )
    assert result.matches == 10 and len(result.returns) == 10
    # Zero-sum: the misaligner's reward for each match is minus the aligner's payoff, which
    # is its return (the seed's rewards it learns from) less what the start was worth.
    stored = misaligner.replay.reward[: misaligner.replay.size]
    payoffs = np.array(result.payoffs)
    np.testing.assert_allclose(np.sort(stored), np.sort(-payoffs), rtol=1e-5, atol=1e-5)
    # An aligner cannot win back more than the misalignment: its payoff is at most the bonus.
    assert np.all(payoffs <= 1e-6) and not np.allclose(payoffs, np.array(result.returns))
    assert misaligner.replay.size == 10 and np.all(misaligner.replay.done[:10] == 1.0)
    # One stored transition per aligner action: at least one per match, at most the limit.
    assert 10 <= aligner.replay.size == aligner.steps_seen <= 10 * 11
    # A member outside `learning` plays and changes nothing.
    frozen = league.members["a-ppo"]
    league.backend.play(frozen, misaligner, 4, np.random.default_rng(1), set())
    assert frozen.steps_seen == 0 and misaligner.replay.size == 10


def test_a_tiny_league_rates_snapshots_copies_and_keeps_the_best(tmp_path: Path) -> None:
    league = tiny_league(tmp_path)
    league.run(progress=False)
    run = tmp_path / "runs" / "tiny"
    rows = read_csv(run / "metrics" / "iterations.csv")
    assert [int(row["iteration"]) for row in rows] == list(range(1, 9))
    # Every player (members and snapshots) is rated, and the ratings moved; the anchor's did
    # not (test_every_rated_match_rates_the_pair_once_and_the_anchor_plays_every_one).
    ratings = [
        league.ratings.rating(p).mu
        for t in ("aligner", "misaligner")
        for p in league.pool.candidates(t)
    ]
    assert len(league.pool.snapshots("aligner")) >= 2
    assert all(np.isfinite(ratings))
    assert np.std(ratings) > 0
    assert tuple(league.ratings.rating("hyperbola")) == (25.0, 0.0)
    lineage = read_csv(run / "metrics" / "lineage.csv")
    assert lineage and all(
        row["member"].startswith(row["parent"].split("-pbt")[0]) for row in lineage
    )
    copies = {row["member"] for row in lineage}
    assert copies & set(league.members)  # the copies play on as members
    # PBT every 4 iterations of 8: a copy at 4, none at the last, where no training follows
    # and a copy would only duplicate its parent in the weakest's place
    assert {int(row["iteration"]) for row in lineage} == {4}
    best = json.loads((run / "best" / "best.json").read_text())
    assert best and all((run / "best" / f"{row['member']}.pt").exists() for row in best)
    assert (run / "checkpoints" / "LATEST").read_text().strip() == "iteration-000008"
    board = leaderboard(league)
    assert {row["team"] for row in board} == {"aligner", "misaligner"}
    assert any(row["snapshot"] for row in board)


def test_every_rated_match_rates_the_pair_once_and_the_anchor_plays_every_one(
    tmp_path: Path,
) -> None:
    league = tiny_league(
        tmp_path,
        pbt={"enabled": False},
        schedule=quiet_schedule(),
    )
    updates: list[tuple[str, str, int]] = []
    update = league.ratings.update

    def counted(a: str, b: str, scores: list[float]) -> object:
        updates.append((a, b, len(scores)))
        return update(a, b, scores)

    league.ratings.update = counted  # type: ignore[method-assign]
    league.run(progress=False)
    aligners = league.pool.candidates("aligner")
    misaligners = league.pool.candidates("misaligner")
    played = sum(league.payoff.matches(a, m) for a in aligners for m in misaligners)
    assert played == 6 * 8
    # One rating update per match against the misaligner and one against the anchor, which
    # aligned the same starts: per aligner, as many anchor matches as rated ones.
    assert sum(n for _, b, n in updates if b != "hyperbola") == played
    assert sum(n for _, b, n in updates if b == "hyperbola") == played
    for aligner in aligners:
        rated = sum(league.payoff.matches(aligner, m) for m in misaligners)
        assert league.anchor_payoff.matches(aligner, "hyperbola") == rated
    assert league.anchor_record["hyperbola"][0] == played and league.unanchored == 0
    assert tuple(league.ratings.rating("hyperbola")) == (25.0, 0.0)


def _league_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "alignrl.cli", "league", *args]


def test_kill_minus_nine_then_resume_loses_no_completed_iteration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`alignrl league run` SIGKILLed once it has checkpointed iteration 4 or later, then
    resumed: every iteration is in iterations.csv once, and status and the leaderboard read
    the run. Only the killed run is a process of its own (a real kill -9); the resume and the
    views read its directory from this one, as they would from a new one."""
    iterations = 9
    config = write_league(
        tmp_path,
        schedule={
            "iterations": iterations,
            "matches": 4,
            "snapshot_every": 3,
            "pbt_every": 4,
            "evaluate_every": 4,
            "eval_scenarios": 2,
            "checkpoint_every": 1,
        },
    )
    runs = tmp_path / "runs"
    run = runs / "tiny"
    killed_at = kill_league_after(
        _league_command("run", str(config), "--runs-dir", str(runs), "--quiet"), run, 4
    )
    assert 4 <= killed_at < iterations
    assert main(["league", "resume", str(run), "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["iterations"] == iterations
    rows = read_csv(run / "metrics" / "iterations.csv")
    assert [int(row["iteration"]) for row in rows] == list(range(1, iterations + 1))  # once each
    assert main(["league", "status", str(run), "--json"]) == 0
    status = json.loads(capsys.readouterr().out)
    assert status["iteration"] == iterations
    assert main(["leaderboard", str(run), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["leaderboard"]
    assert {row["member"] for row in rows} >= set(status["members"]["aligner"])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"schedul": {}}, "schedul: Extra inputs are not permitted"),
        ({"schedule": {"matches": 0}}, "schedule.matches: Input should be greater than or equal"),
        ({"aligners": "nowhere.yaml"}, "roster file nowhere.yaml does not exist"),
        ({"matchmaking": {"pfsp": 0, "uniform": 0, "latest": 0}}, "cannot all be 0"),
    ],
)
def test_league_config_errors_name_the_file_and_the_key(
    tmp_path: Path, change: dict, message: str
) -> None:
    path = write_league(tmp_path, **change)
    with pytest.raises(ConfigError, match=message):
        load_league(path)


LEAGUES = sorted(
    path
    for path in Path(__file__).resolve().parents[1].glob("experiments/*.yaml")
    if "aligners" in yaml.safe_load(path.read_text())
)


@pytest.mark.parametrize("path", LEAGUES, ids=lambda path: path.name)
def test_shipped_leagues_and_rosters_load(path: Path) -> None:
    from alignrl.config.experiment import dump_experiment
    from alignrl.league.config import parse_league

    config, aligners, misaligners = load_league(path)
    assert parse_league(yaml.safe_load(dump_experiment(config))) == config
    assert len(aligners.members) >= 2 and len(misaligners.members) >= 2
    if any(member.init_from for member in aligners.members):
        # A warm-started roster (docs/league.md): its aligners all start from a trained
        # one, and differ in how they fine-tune.
        assert all(member.init_from for member in aligners.members)
        assert len({m.learner.learning_rate for m in aligners.members}) >= 2
    else:
        # Mixed architectures and learners, as the design asks of the default rosters.
        assert len({(m.learner.algorithm, m.learner.encoder) for m in aligners.members}) >= 3


def test_roster_errors_name_the_roster_file(tmp_path: Path) -> None:
    path = write_league(tmp_path)
    roster = tmp_path / "aligners.yaml"
    twice = [{"id": "x", "learner": SMALL_SAC}, {"id": "x", "learner": SMALL_SAC}]
    write_yaml(roster, {"team": "aligner", "members": twice})
    with pytest.raises(ConfigError, match=r"aligners.yaml: .*repeated: x"):
        load_league(path)
    write_yaml(roster, {"team": "misaligner", "members": [{"id": "x"}]})
    with pytest.raises(ConfigError, match="used as the aligner roster"):
        load_league(path)
    write_yaml(roster, {"team": "aligner", "members": [{"id": "x", "learner": {"epochs": 3}}]})
    with pytest.raises(
        ConfigError, match=r"members.0.learner: .*epochs does not apply to algorithm sac"
    ):
        load_league(path)


def test_cli_league_run_prints_the_leaderboard_and_refuses_a_second_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_league(
        tmp_path, schedule={"iterations": 2, "matches": 4, "evaluate_every": 2, "eval_scenarios": 2}
    )
    runs = str(tmp_path / "runs")
    assert main(["league", "run", str(path), "--runs-dir", runs, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "member" in out and "a-sac" in out and "m-ppo" in out
    assert main(["league", "run", str(path), "--runs-dir", runs, "--quiet"]) == 2
    assert "league resume" in capsys.readouterr().err


def test_a_resumed_league_plays_exactly_as_one_never_stopped(tmp_path: Path) -> None:
    schedule = {
        "iterations": 6,
        "matches": 6,
        "snapshot_every": 2,
        "pbt_every": 4,
        "evaluate_every": 100,
        "eval_scenarios": 2,
        "checkpoint_every": 3,
    }
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
    straight = tiny_league(tmp_path / "a", schedule=schedule)
    straight.run(progress=False)
    stopped = tiny_league(tmp_path / "b", schedule={**schedule, "iterations": 3})
    stopped.run(progress=False)
    run = tmp_path / "b" / "runs" / "tiny"
    config = (run / "config.yaml").read_text().replace("iterations: 3", "iterations: 6")
    (run / "config.yaml").write_text(config)
    League.resume(run).run(progress=False)
    assert iteration_outcomes(run) == iteration_outcomes(tmp_path / "a" / "runs" / "tiny")
    # The ratings (mu, sigma and history, anchors included) and the anchors' record as well.
    resumed, never = (
        League.resume(run, read_only=True),
        League.resume(tmp_path / "a" / "runs" / "tiny", read_only=True),
    )
    assert resumed.ratings.state_dict() == never.ratings.state_dict()
    assert resumed.anchor_record == never.anchor_record
    assert resumed.anchor_payoff.state_dict() == never.anchor_payoff.state_dict()


def test_pbt_copies_the_strongest_and_perturbs_its_learning_rate(tmp_path: Path) -> None:
    league = tiny_league(tmp_path, pbt={"min_gap": 5.0, "perturb": [0.5, 2.0]})
    # a-sac beats m-ppo 20 times, a-ppo and m-sac draw 20 times: as sure of each rating, a-ppo
    # and m-ppo are now the weakest, by more than min_gap of the ordinal.
    league.ratings.update("a-sac", "m-ppo", [1.0] * 20)
    league.ratings.update("a-ppo", "m-sac", [0.5] * 20)
    ordinal = {player: rating.ordinal for player, rating in league.ratings.ranking()}
    assert ordinal["a-sac"] - ordinal["a-ppo"] >= 5.0 <= ordinal["m-sac"] - ordinal["m-ppo"]
    changes = league.exploit_and_explore()
    aligner = [c for c in changes if c["parent"] == "a-sac"]
    assert len(aligner) == 1 and aligner[0]["replaced"] == "a-ppo"
    copy = league.members[aligner[0]["member"]]
    parent = league.members["a-sac"]
    assert "a-ppo" not in league.members and copy.spec.parent == "a-sac"
    assert league.ratings.rating(copy.id) == league.ratings.rating("a-sac")
    for a, b in zip(
        copy.learner.actor.parameters(), parent.learner.actor.parameters(), strict=True
    ):
        assert torch.equal(a, b)  # the weights are copied ...
    rate = copy.learner.actor_optimizer.param_groups[0]["lr"]
    assert rate / parent.learner.actor_optimizer.param_groups[0]["lr"] in (0.5, 2.0)
    assert copy.spec.hyperparameters["learning_rate"] == pytest.approx(rate)  # ... and perturbed
    # In the misaligner team m-ppo lost far more: it is replaced by a copy of m-sac.
    assert [(c["parent"], c["replaced"]) for c in changes if c["parent"].startswith("m-")] == [
        ("m-sac", "m-ppo")
    ]
    # The copies share their parents' ratings: no lead of min_gap, so nobody is replaced.
    assert league.exploit_and_explore() == []


def test_backend_ray_without_ray_says_what_to_install_before_writing_anything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, as where it is missing
    monkeypatch.delitem(sys.modules, "alignrl.league.ray_backend", raising=False)
    config, aligners, misaligners = load_league(write_league(tmp_path, backend="ray"))
    with pytest.raises(ConfigError, match=r"backend: ray needs .*pip install 'alignrl\[ray\]'"):
        League.create(config, aligners, misaligners, tmp_path / "runs")
    assert not (tmp_path / "runs").exists()


def test_uniform_starts_cover_the_window_and_teach_only_the_aligner(tmp_path: Path) -> None:
    league = tiny_league(tmp_path)
    aligner = league.members["a-sac"]
    starts: list[np.ndarray] = []
    misalign = league.backend.episodes.misalign

    def spy(slots: np.ndarray, actions: np.ndarray) -> None:
        starts.append(np.array(actions))
        misalign(slots, actions)

    league.backend.episodes.misalign = spy
    league.uniform_starts.rng = np.random.default_rng(0)
    result = league.backend.play(
        aligner, league.uniform_starts, 200, np.random.default_rng(1), {aligner.id}
    )
    drawn = np.concatenate(starts)
    assert result.matches == 200 and drawn.shape == (200, 1)
    # Uniform over the window: mean 0, variance 1/3, both ends reached.
    assert abs(drawn.mean()) < 0.1 and abs(drawn.var() - 1 / 3) < 0.05
    assert drawn.min() < -0.9 and drawn.max() > 0.9
    assert aligner.steps_seen >= 200 and "uniform-starts" not in league.members


def test_a_league_with_uniform_starts_rates_only_the_misaligners_matches(
    tmp_path: Path,
) -> None:
    league = tiny_league(
        tmp_path,
        pbt={"enabled": False},
        schedule=quiet_schedule(uniform_starts=0.5),
    )
    league.run(progress=False)
    run = tmp_path / "runs" / "tiny"
    rows = read_csv(run / "metrics" / "iterations.csv")
    aligner_turns = sum(row["learner"].startswith("a-") for row in rows)
    assert 0 < aligner_turns < len(rows)
    # Every iteration played its 8 matches; the aligner's turns rated 4 of them.
    assert all(int(row["matches"]) == 8 for row in rows)
    played = sum(
        league.payoff.matches(a, m)
        for a in league.pool.candidates("aligner")
        for m in league.pool.candidates("misaligner")
    )
    assert played == 8 * len(rows) - 4 * aligner_turns
    assert "uniform-starts" not in {
        p for t in ("aligner", "misaligner") for p in league.pool.candidates(t)
    }
    # The aligners' episode logs hold every match they learned from, rated or not (with no
    # snapshots, an aligner is an active member and learns in every match it plays).
    episodes = sum(
        len(read_csv(path)) for path in (run / "metrics" / "members").glob("a-*/episodes.csv")
    )
    assert episodes == sum(int(row["matches"]) for row in rows) == 8 * len(rows)


def test_a_members_episodes_are_its_own_matches_not_its_snapshots(tmp_path: Path) -> None:
    """A snapshot loaded from file carries its live member's id; its matches were logged as
    that member's episodes (so a member's learning curve held matches it never played).
    Every episode in a live aligner's episodes.csv comes from an iteration where it, by its
    own id, was the aligner; the tiny league does pick a snapshot aligner."""
    league = tiny_league(tmp_path)
    league.run(progress=False)
    metrics = league.run_dir / "metrics"
    iterations = read_csv(metrics / "iterations.csv")
    matches = league.config.schedule.matches
    assert any("@" in row["aligner"] for row in iterations)  # a snapshot aligned
    for member in ("a-sac", "a-ppo"):
        own = {int(row["iteration"]) for row in iterations if row["aligner"] == member}
        episodes = read_csv(metrics / "members" / member / "episodes.csv")
        played = {(int(row["episode"]) - 1) // matches + 1 for row in episodes}
        assert played <= own, (member, sorted(played - own))

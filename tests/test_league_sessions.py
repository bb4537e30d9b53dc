"""Issue 23 in the league: validation sessions choose and a test session of its own seed
reports the champion, every success figure with its interval; the anchors (classical
controllers of fixed rating) align the same columns from the same starts as the aligners,
leave the matches as they were, and stay out where the apparatus has no twin."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import create_league, quiet_schedule, write_league

import alignrl.training
from alignrl.apparatus.base import knows_optimum
from alignrl.cli import main
from alignrl.config_reading import ConfigError
from alignrl.league.config import VALIDATION_SEED, load_league
from alignrl.league.loop import League, leaderboard
from alignrl.league.matches import learn_from_matches, make_anchors
from alignrl.league.report import write_league_report
from alignrl.league.sessions import read_test
from alignrl.league.standings import anchor_lines, anchor_records

SCHEDULE = {**quiet_schedule(iterations=4, evaluate_every=2, eval_scenarios=3), "keep_best": 2}


def tiny(root: Path, **changes: Any) -> League:
    return create_league(write_league(root, schedule=SCHEDULE, **changes), root / "runs")


def test_the_validation_seed_is_the_evaluation_seed_model_cards_cite() -> None:
    assert alignrl.training.EVALUATION_SEED == VALIDATION_SEED


@pytest.fixture(scope="module")
def judged(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A tiny league run to its end, every session it ran recorded (agent or controller,
    seed, starts), then its test session."""
    root = tmp_path_factory.mktemp("judged")
    league = tiny(root)
    sessions: list[dict[str, Any]] = []
    policy_sessions = alignrl.training.evaluate_policy

    def recorded(*args: Any, **kwargs: Any) -> Any:
        result = policy_sessions(*args, **kwargs)
        starts = [record.start for record in result.records]
        sessions.append({"name": kwargs["name"], "seed": kwargs["seed"], "starts": starts})
        return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(alignrl.training, "evaluate_policy", recorded)
        league.run(progress=False)
        chose = list(sessions)
        test = league.test()
    return {"league": league, "chose": chose, "tested": sessions[len(chose) :], "test": test}


def test_validation_sessions_choose_and_the_test_session_has_scenarios_of_its_own(
    judged: dict[str, Any],
) -> None:
    league, chose, tested, test = (judged[k] for k in ("league", "chose", "tested", "test"))
    sessions = league.config.sessions
    assert chose and {s["seed"] for s in chose} == {sessions.validation_seed}
    assert [s["name"] for s in tested] == ["champion", "untrained"]
    assert {s["seed"] for s in tested} == {sessions.test_seed} != {sessions.validation_seed}
    # Other scenarios, other starts: no start of the test session is one a choice saw.
    seen = {start for session in chose for start in session["starts"]}
    assert not seen & set(tested[0]["starts"])
    assert tested[0]["starts"] == tested[1]["starts"]  # champion and untrained alike
    # The champion is the validation sessions' choice, and says so.
    best = json.loads((league.run_dir / "best" / "best.json").read_text())
    assert test["chosen_by"] == {
        "session": "validation",
        "seed": sessions.validation_seed,
        "member": best[0]["member"],
        "iteration": best[0]["iteration"],
        "successes": best[0]["successes"],
        "scenarios": best[0]["scenarios"],
        "interval": test["chosen_by"]["interval"],
    }
    assert read_test(league.run_dir) == test


def test_the_test_session_puts_the_champion_beside_untrained_and_classical(
    judged: dict[str, Any],
) -> None:
    test = judged["test"]
    labels = [row["label"] for row in test["rows"]]
    assert labels == ["champion", "untrained", "golden-section", "hyperbola", "hill-climb"]
    assert test["session"] == "test" and test["scenarios"] == 3
    for row in test["rows"]:
        low, high = row["interval"]
        assert row["scenarios"] == 3 and 0.0 <= low <= row["successes"] / 3 <= high <= 1.0
    # On the synthetic recordings the hyperbola fit aligns every test scenario (50/50 on make
    # run's), far above what an untrained aligner does: the interval says how sure that is.
    hyperbola = test["rows"][3]
    assert hyperbola["successes"] == 3 and hyperbola["interval"][0] > 0.4


def test_the_report_says_which_session_each_figure_comes_from(judged: dict[str, Any]) -> None:
    league, test = judged["league"], judged["test"]
    write_league_report(league.run_dir, leaderboard(league))
    markdown = (league.run_dir / "report.md").read_text()
    page = (league.run_dir / "report.html").read_text()
    section = markdown[markdown.index("## Test session") : markdown.index("## Lineage")]
    assert f"seed {test['seed']}" in section and f"seed {VALIDATION_SEED}" in section
    assert "chose nothing" in section and "| champion |" in section and "| hyperbola |" in section
    assert "<h2>Test session</h2>" in page
    assert "best validation session (95 % interval)" in markdown
    assert "## Anchors" in markdown and "25.0 (fixed)" in markdown


def test_the_test_seed_must_differ_from_the_validation_seed(tmp_path: Path) -> None:
    path = write_league(tmp_path, sessions={"test_seed": 7, "validation_seed": 7})
    with pytest.raises(ConfigError, match=r"sessions: .*must not replay the scenarios"):
        load_league(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"ratings": {"anchors": {"stigmator-search": 25.0}}}, "ratings.anchors: .*stigmator"),
        (
            {"ratings": {"anchors": {"hyperbola": float("nan")}}},
            r"ratings.anchors.hyperbola: .*finite number",
        ),
        ({"sessions": {"test_classical": ["telepathy"]}}, "sessions.test_classical: .*telepathy"),
    ],
)
def test_anchors_and_test_controllers_that_cannot_align_the_task_are_refused(
    tmp_path: Path, change: dict, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        load_league(write_league(tmp_path, **change))


def test_a_member_named_as_an_anchor_is_refused_before_anything_is_written(
    tmp_path: Path,
) -> None:
    path = write_league(tmp_path)
    roster = (tmp_path / "aligners.yaml").read_text().replace("a-sac", "hyperbola")
    (tmp_path / "aligners.yaml").write_text(roster)
    with pytest.raises(ConfigError, match="hyperbola are the names of anchors"):
        load_league(path)


def test_the_anchors_align_the_same_columns_from_the_same_starts(tmp_path: Path) -> None:
    league = tiny(tmp_path)
    backend = league.backend
    (anchor,) = backend.anchors
    episodes = backend.episodes
    starts: list[tuple[float, float]] = []  # (setting, optimum) each start of the aligner
    twins: list[tuple[float, float]] = []  # what the anchor was given to align
    misalign, align = episodes.misalign, anchor.align

    def placed(slots: np.ndarray, actions: np.ndarray) -> None:
        misalign(slots, actions)
        for slot in slots:
            optimum = episodes.apparatus[slot].optimum()["defocus"]
            starts.append((float(episodes.setting[slot, 0]), optimum))

    def aligned(twin: Any, task: Any) -> tuple[float, int]:
        assert twin not in episodes.apparatus  # a twin, never the league's own apparatus
        twins.append((twin.read()["defocus"], twin.optimum()["defocus"]))
        return align(twin, task)

    episodes.misalign, anchor.align = placed, aligned  # type: ignore[method-assign]
    aligner, misaligner = league.members["a-sac"], league.members["m-sac"]
    with_anchor = backend.play(
        aligner, misaligner, 10, np.random.default_rng(5), set(), deterministic=True, anchored=True
    )
    assert twins == starts and len(twins) == 10
    assert len(with_anchor.anchor_scores["hyperbola"]) == 10
    # The anchor changed nothing of the matches themselves.
    starts.clear()
    alone = backend.play(
        aligner, misaligner, 10, np.random.default_rng(5), set(), deterministic=True
    )
    assert len(twins) == 10 and alone.anchor_scores == {}
    for name in ("successes", "acquisitions", "returns", "payoffs"):
        assert getattr(alone, name) == getattr(with_anchor, name), name


def test_an_apparatus_without_a_twin_plays_no_anchor_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from fake_drivers import ParabolicLens

    class RealLens(ParabolicLens):
        optimum = None  # a real microscope cannot tell its optimum, nor give a twin

    simulated, real = ParabolicLens(), RealLens()
    assert not knows_optimum(real) and make_anchors(["hyperbola"], [simulated, real]) == []
    assert len(make_anchors(["hyperbola"], [simulated])) == 1
    # Nor does a driver behind the shield, even one that can tell its optimum: a copy of it
    # would reach the same instrument around the shield.
    from alignrl.apparatus.limits import ShieldOptions
    from alignrl.apparatus.training_shield import shield_apparatus

    shielded = shield_apparatus(ParabolicLens(), ShieldOptions())
    assert knows_optimum(shielded) and make_anchors(["hyperbola"], [shielded]) == []
    # A league on such an apparatus: every rated match is played, none with the anchor.
    monkeypatch.setattr("alignrl.league.matches.can_twin", lambda unit: False)
    league = tiny(tmp_path, pbt={"enabled": False})
    league.run(progress=False)
    rated = sum(league.payoff.matches(a, m) for a, m in league.payoff.pairs())
    assert rated == 4 * 8 and league.unanchored == rated
    assert tuple(league.ratings.rating("hyperbola")) == (25.0, 0.0)
    records = anchor_records(
        league.ratings, league.anchor_payoff, league.anchor_record, league.unanchored
    )
    assert records["anchors"][0]["matches"] == 0
    assert any("32 rated matches without anchors" in line for line in anchor_lines(records))


def test_a_league_without_anchors_has_none_on_its_leaderboard(tmp_path: Path) -> None:
    league = tiny(tmp_path, ratings={"anchors": {}})
    assert league.backend.anchors == [] and league.ratings.anchors == []
    league.step()
    assert not any(row["anchor"] for row in leaderboard(league))


def test_league_run_prints_and_gives_the_test_session_with_intervals(tmp_path: Path) -> None:
    path = write_league(tmp_path, schedule={**SCHEDULE, "iterations": 2})
    runs = str(tmp_path / "runs")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["league", "run", str(path), "--runs-dir", runs, "--quiet", "--json"]) == 0
    payload = json.loads(out.getvalue())
    test = payload["test"]
    assert test["session"] == "test" and test["seed"] != test["chosen_by"]["seed"]
    assert [row["label"] for row in test["rows"]][:2] == ["champion", "untrained"]
    evaluated = [row for row in payload["leaderboard"] if row["successes"] is not None]
    assert evaluated and all(row["session"] == "validation" for row in evaluated)
    assert all(len(row["interval"]) == 2 for row in evaluated)
    assert payload["anchors"]["anchors"][0]["anchor"] == "hyperbola"
    run = tmp_path / "runs" / "tiny"
    with contextlib.redirect_stdout(out := io.StringIO()):
        assert main(["leaderboard", str(run)]) == 0
    shown = out.getvalue()
    assert "rating μ ± σ" in shown and "validation (95 %)" in shown
    assert "test session: 3 held-out scenarios of seed 2000000, never used for a choice" in shown
    assert "(the champion was chosen by validation sessions of seed 1000000:" in shown
    line = next(line for line in shown.splitlines() if line.startswith("champion "))
    assert line.endswith("acquisitions") and " %)" in line
    with contextlib.redirect_stdout(out := io.StringIO()):
        assert main(["league", "status", str(run)]) == 0
    assert "best (validation, seed 1000000):" in out.getvalue()
    (run / "test.json").write_text("{not json")
    assert main(["leaderboard", str(run)]) == 2


def test_two_anchors_both_play_every_rated_match_and_neither_moves(tmp_path: Path) -> None:
    anchors = {"hyperbola": 25.0, "golden-section": 22.0}
    league = tiny(tmp_path, ratings={"anchors": anchors})
    for _ in range(2):
        league.step()
    rated = sum(league.payoff.matches(a, m) for a, m in league.payoff.pairs())
    assert {name: record[0] for name, record in league.anchor_record.items()} == {
        "hyperbola": rated,
        "golden-section": rated,
    }
    assert {name: tuple(league.ratings.rating(name)) for name in anchors} == {
        "hyperbola": (25.0, 0.0),
        "golden-section": (22.0, 0.0),
    }


def test_a_ray_worker_plays_the_anchors_as_in_process(tmp_path: Path) -> None:
    pytest.importorskip("ray", reason="the Ray backend needs the ray extra")
    from alignrl.league.ray_backend import MatchWorker  # plain Python outside Ray

    league = tiny(tmp_path)
    config = league.config
    worker = MatchWorker(
        0,
        config.apparatus,
        config.apparatus_args,
        config.envs,
        config.resolved_task(),
        config.history,
        config.threads,
        (config.design, config.payoff, config.reference),
        tuple(config.anchor_ratings()),
    )
    aligner, misaligner = league.members["a-sac"], league.members["m-ppo"]
    seeds = np.random.default_rng(3).integers(0, 2**31 - 1, 4).tolist()  # as both backends draw
    policies = {"aligner": aligner.policy_state(), "misaligner": misaligner.policy_state()}
    played = worker.play(policies, seeds, config.complexity, (False, False), True, anchored=True)
    there = learn_from_matches(played, aligner, misaligner, set(), np.random.default_rng(0))
    here = league.backend.play(
        aligner, misaligner, 4, np.random.default_rng(3), set(), deterministic=True, anchored=True
    )

    def outcomes(result: Any) -> list[tuple[bool, float, bool]]:
        scores, successes = result.anchor_scores["hyperbola"], result.anchor_successes["hyperbola"]
        return sorted(zip(result.successes, scores, successes, strict=True))

    assert len(there.anchor_scores["hyperbola"]) == 4 and outcomes(there) == outcomes(here)


def test_a_league_rated_by_an_older_alignrl_is_refused_with_what_to_do(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from alignrl.checkpoints import load_checkpoint, save_checkpoint

    league = tiny(tmp_path)
    path = league.run_dir / "checkpoints" / "iteration-000000" / "league.pt"
    state = load_checkpoint(path)
    save_checkpoint(path, {**state, "format": "alignrl-league-1"})  # Elo ratings inside
    for command in (["league", "status"], ["leaderboard"], ["league", "resume"]):
        assert main([*command, str(league.run_dir)]) == 2
        error = capsys.readouterr().err
        assert "alignrl-league-1" in error and "start it again" in error
        assert "Traceback" not in error

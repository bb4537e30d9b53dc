"""Misaligners that design the instrument (issue 22): the design stays in the family's box,
the regret payoff is zero-sum and zero where aligner and reference end alike, a designer
learns to find the columns a weak aligner fails on, and a league of designers plays, rates,
snapshots, copies and resumes after kill -9 exactly as one never stopped."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import (
    TINY_SCHEDULE,
    create_league,
    iteration_outcomes,
    kill_league_after,
    read_csv,
    write_league,
)
from pettingzoo.test import api_test

from alignrl.agents.agent import MemberSpec
from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.family import FamilyColumn, design_names
from alignrl.apparatus.family_box import LOG_SCALE, family_path, load_family
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.cli import main
from alignrl.config_reading import ConfigError
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.design import reference_returns
from alignrl.envs.duel import ALIGNER, MISALIGNER, DuelBatch, env
from alignrl.envs.rewards import final_reward
from alignrl.envs.task import get_task
from alignrl.evaluation.references import make_reference
from alignrl.league.config import load_league, parse_league
from alignrl.league.exploit import exploit
from alignrl.league.loop import League

FAMILY = {"apparatus": "family:focus", "apparatus_args": {"analytic": True}}
EVALUATED_ON = {"eval_apparatus": "set:validation", "eval_apparatus_args": {"analytic": True}}
UNIT_FREE = {"quality_reference": "first", "final_reward_form": "log_ratio"}


def family_column(seed: int = 0) -> FamilyColumn:
    return FamilyColumn(load_family(family_path("focus")), seed=seed, analytic=True)


# --- the design action -----------------------------------------------------------------


def test_any_design_action_is_a_column_inside_the_box() -> None:
    column = family_column()
    box = column.family
    names = column.design_names()
    assert names == design_names(box, analytic=True)
    assert "blur_px_per_interval" in names and "dose_electrons_per_px" not in names  # analytic
    rng = np.random.default_rng(0)
    corners = [np.zeros(len(names)), np.ones(len(names))]
    for fractions in [*corners, *rng.uniform(-3.0, 4.0, (50, len(names)))]:
        column.reset(int(rng.integers(1000)))
        column.design(fractions)
        draw = column.draw
        assert box.interval_width[0] - 1e-9 <= draw.width <= box.interval_width[1] + 1e-9
        assert draw.low <= draw.optimum <= draw.high
        for name in (
            "blur_px_per_interval",
            "floor_sigma_px",
            "curve_power",
            "asymmetry",
            "drift_fraction",
            "hysteresis_fraction",
        ):
            low, high = getattr(box, name)
            assert low - 1e-9 <= getattr(draw, name) <= high + 1e-9, name
    # 0 and 1 are the range's ends; 1/2 the middle, of the log where the box draws in logs
    column.design(np.full(len(names), 0.5))
    low, high = box.blur_px_per_interval
    assert "blur_px_per_interval" in LOG_SCALE
    assert column.draw.blur_px_per_interval == pytest.approx(math.sqrt(low * high))
    low, high = box.curve_power
    assert column.draw.curve_power == pytest.approx(0.5 * (low + high))


def test_designing_the_uniform_draw_gives_the_column_the_seed_drew() -> None:
    column = family_column(seed=7)
    drawn, reading = column.draw, column.measure()
    column.reset(7)
    column.design(column.design_draw())
    assert column.draw == drawn
    assert column.measure() == reading  # the episode begins again, with its seed's noise


def test_a_design_of_the_wrong_size_or_not_finite_is_refused() -> None:
    column = family_column()
    with pytest.raises(ValueError, match="takes 15 finite fractions"):
        column.design(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        column.design(np.full(15, np.nan))


# --- the regret payoff -----------------------------------------------------------------


class EndWhereItStands:
    """A reference that takes one image where the column stands and stops there."""

    name = "stand-still"

    def align(self, twin, task):
        try:
            return float(twin.measure()), 0
        except NoEdgesError:
            return float("nan"), 0


def duel_batch(payoff: str, reference=None, design: bool = True, n: int = 6, **task_changes):
    task = replace(get_task("focus"), **UNIT_FREE, **task_changes)
    units = make_apparatus_copies("family:focus", {"analytic": True}, n)
    return DuelBatch(AlignmentEpisodes(units, task, 6), design, payoff, reference)


def play(duel: DuelBatch, seeds: list[int], start: np.ndarray, aligner_action: np.ndarray):
    """Totals of both teams per slot, with the given misaligner and aligner actions."""
    duel.reset(seeds)
    totals = {agent: np.zeros(len(seeds)) for agent in (MISALIGNER, ALIGNER)}
    duel.step(start)
    for agent in totals:
        totals[agent] += duel.rewards[agent][: len(seeds)]
    while duel.active.size:
        active = duel.active
        duel.step(np.tile(aligner_action, (len(active), 1)))
        for agent in totals:
            totals[agent][active] += duel.rewards[agent][active]
    return totals


def test_regret_is_zero_sum_and_zero_where_aligner_and_reference_end_alike() -> None:
    # The aligner stops at once: it ends on its start image. The reference images the twin
    # where it stands: with common random numbers that is the very same reading.
    duel = duel_batch("regret", EndWhereItStands(), verify_final=False, success_bonus=0.0)
    rng = np.random.default_rng(1)
    start = rng.uniform(-1, 1, (6, duel.misaligner_shape[1]))
    totals = play(duel, list(range(6)), start, np.array([0.0, 1.0]))
    np.testing.assert_allclose(totals[MISALIGNER] + totals[ALIGNER], 0.0, atol=1e-12)
    np.testing.assert_allclose(totals[MISALIGNER], 0.0, atol=1e-12)  # no regret
    task = duel.episodes.task
    ended = np.where(
        np.isfinite(duel.reference_cost[:6]), duel.reference_cost[:6], task.no_edges_px
    )
    np.testing.assert_allclose(ended, duel.episodes.cost_before[:6])
    # The seed's payoff, on the same columns and starts, pays the designer whatever nobody
    # recovered: a column nobody aligns is its best move.
    seeds = play(
        duel_batch("improvement", verify_final=False, success_bonus=0.0),
        list(range(6)),
        start,
        np.array([0.0, 1.0]),
    )
    assert np.all(seeds[MISALIGNER] > 0)


def test_regret_against_the_hyperbola_fit_pays_what_the_aligner_left_undone() -> None:
    task = replace(get_task("focus"), **UNIT_FREE, success_bonus=0.0)
    duel = duel_batch("regret", make_reference("hyperbola", task), n=8, success_bonus=0.0)
    rng = np.random.default_rng(2)
    start = rng.uniform(-1, 1, (8, duel.misaligner_shape[1]))
    totals = play(duel, list(range(8)), start, np.array([0.0, 1.0]))  # the aligner gives up
    np.testing.assert_allclose(totals[MISALIGNER] + totals[ALIGNER], 0.0, atol=1e-12)
    # The designer is paid what the hyperbola fit earned from the same start, less what the
    # aligner earned (the final reward of its verification image).
    episodes = duel.episodes
    earned = reference_returns(
        episodes.cost_before[:8],
        duel.reference_cost[:8],
        duel.reference_acquisitions[:8],
        episodes.task,
    )
    aligner = final_reward(episodes.cost_before[:8], episodes.cost[:8], 1.0, "log_ratio")
    assert episodes.task.final_reward_scale == 1.0
    np.testing.assert_allclose(totals[MISALIGNER], earned - aligner)
    assert np.all(duel.reference_acquisitions[:8] >= 5)  # it really aligned the twins
    assert duel.reference_success[:8].mean() > 0.5
    # Rated: 1/2 where both fail or both succeed, 0 where only the reference succeeded.
    rated = duel.rated()
    expected = 0.5 + 0.5 * (duel.successes().astype(float) - duel.reference_success[:8])
    np.testing.assert_allclose(rated, expected)


def test_the_reference_plays_a_twin_and_leaves_the_aligners_column_alone() -> None:
    task = replace(get_task("focus"), **UNIT_FREE)
    with_reference = duel_batch("regret", make_reference("hyperbola", task), n=3)
    without = duel_batch("improvement", n=3)
    rng = np.random.default_rng(3)
    start = rng.uniform(-1, 1, (3, with_reference.misaligner_shape[1]))
    for duel in (with_reference, without):
        duel.reset([5, 6, 7])
        duel.step(start)
    np.testing.assert_array_equal(with_reference.episodes.history, without.episodes.history)
    readings = [
        [unit.measure() for unit in duel.episodes.apparatus] for duel in (with_reference, without)
    ]
    assert readings[0] == readings[1]  # the same noise stream: nothing was read off it


def test_the_duel_env_of_a_designer_passes_the_pettingzoo_api_test() -> None:
    task = replace(get_task("focus"), **UNIT_FREE)
    duel = env(
        apparatus="family:focus",
        apparatus_args={"analytic": True},
        task=task,
        design=True,
        payoff="regret",
        reference=make_reference("hyperbola", task),
    )
    api_test(duel, num_cycles=20)
    assert duel.observation_space(MISALIGNER).shape == (16,)
    assert duel.action_space(MISALIGNER).shape == (16,)


def test_designs_and_regret_are_refused_where_they_cannot_be_played() -> None:
    units = make_apparatus_copies("synthetic", None, 2)
    episodes = AlignmentEpisodes(units, get_task("focus"), 4)
    with pytest.raises(ValueError, match="instrument family"):
        DuelBatch(episodes, design=True)
    with pytest.raises(ValueError, match="needs a reference"):
        DuelBatch(episodes, payoff="regret")
    with pytest.raises(ValueError, match="payoff must be one of"):
        DuelBatch(episodes, payoff="minimax")


def test_a_league_config_with_design_needs_a_family(tmp_path: Path) -> None:
    path = write_league(tmp_path, design=True)
    config, _, _ = load_league(path)
    with pytest.raises(ConfigError, match=r"design: true needs .*family:NAME"):
        config.misaligner_shape()
    with pytest.raises(ConfigError, match="payoff"):
        load_league(write_league(tmp_path, payoff="minimax"))


# --- learnability: a designer finds what a weak aligner fails on --------------------------


class GivesUp:
    """A fixed weak aligner: it stops at once, wherever the column was left."""

    def __init__(self, history: int, features: int) -> None:
        self.spec = MemberSpec("gives-up", "aligner", "sac", (history, features), 2, 1)
        self.id = self.spec.id

    def act(self, inputs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        return np.tile([0.0, 1.0], (len(inputs), 1))


def test_a_designer_learns_the_columns_a_weak_aligner_fails_on(tmp_path: Path) -> None:
    box = yaml.safe_load(family_path("focus").read_text())
    narrow = {key: value for key, value in box.items() if not isinstance(value, list)}
    narrow.update(
        {k: box[k][0] for k, v in box.items() if isinstance(v, list) and k != "specimens"}
    )
    narrow.update(
        optimum_fraction=[0.1, 0.9], blur_px_per_interval=[10.0, 120.0], specimens=["particles"]
    )
    (tmp_path / "box.yaml").write_text(yaml.safe_dump(narrow))
    config = parse_league(
        {
            "name": "learnability",
            "apparatus": f"family:{tmp_path / 'box.yaml'}",
            "apparatus_args": {"analytic": True},
            "task_options": UNIT_FREE,
            "history": 4,
            "envs": 8,
            "design": True,
            "payoff": "regret",
        }
    )
    assert config.misaligner_shape() == ((1, 4), 3)  # start, optimum, gain
    weak = GivesUp(4, 7)
    untrained = exploit(weak, config, matches=1, evaluate=128, seed=0)
    trained = exploit(weak, config, matches=480, evaluate=128, seed=0)
    # The uniform-ish untrained designer's columns against the learned ones: the learned
    # ones start farther out of focus on columns the hyperbola fit still aligns.
    assert trained.mean_regret > 1.25 * untrained.mean_regret
    assert trained.designs.shape == (128, 2)  # optimum, gain: fractions of their ranges


# --- a league of designers ----------------------------------------------------------------

DESIGN_LEAGUE = {
    **FAMILY,
    **EVALUATED_ON,
    "task_options": UNIT_FREE,
    "design": True,
    "payoff": "regret",
    "history": 4,
}


def designer_league(folder: Path, **changes: object) -> Path:
    return write_league(folder, **{**DESIGN_LEAGUE, **changes})


# The tiny league's schedule (8 iterations of 8 matches; snapshots at 3 and 6, PBT and
# evaluations at 4 and 8) with a checkpoint at every iteration, for a kill to land between two.
DESIGN_SCHEDULE = {**TINY_SCHEDULE, "checkpoint_every": 1}


@pytest.fixture(scope="module")
def designers(tmp_path_factory: pytest.TempPathFactory) -> League:
    """A league of designers played to its end, never stopped: what the tests of this module
    read (its ratings, snapshots and copies) and what a killed one must end as."""
    folder = tmp_path_factory.mktemp("designers")
    league = create_league(designer_league(folder, schedule=DESIGN_SCHEDULE), folder / "runs")
    assert league.members["m-sac"].spec.observation_shape == (1, 17)
    assert league.members["m-sac"].spec.action_dim == 16
    league.run(progress=False)
    return league


def test_a_league_of_designers_rates_snapshots_and_copies_them(designers: League) -> None:
    league, run = designers, designers.run_dir
    rows = read_csv(run / "metrics" / "iterations.csv")
    assert len(rows) == 8
    assert any("@" in row["misaligner"] or "@" in row["aligner"] for row in rows)  # PFSP pool
    designs = read_csv(run / "metrics" / "designs.csv")
    assert len(designs) == sum(int(row["matches"]) for row in rows)
    assert {row["misaligner"] for row in designs} <= {r["misaligner"] for r in rows}
    fractions = np.array([[float(row[name]) for name in league.design_names] for row in designs])
    assert fractions.min() >= 0.0 and fractions.max() <= 1.0
    snapshots = [p.name for p in (run / "snapshots").glob("m-*@*.pt")]
    assert snapshots  # frozen designers join the pool
    lineage = read_csv(run / "metrics" / "lineage.csv")
    assert any(row["member"].startswith("m-") for row in lineage)  # PBT copies designers too
    # Rated against the reference: the payoff table holds halves, not the aligners' successes.
    pairs = {(row["aligner"], row["misaligner"]) for row in rows}
    scored = sum(league.payoff.win_rate(*pair) * league.payoff.matches(*pair) for pair in pairs)
    succeeded = sum(round(float(row["success_rate"]) * int(row["matches"])) for row in rows)
    assert scored * 2 == pytest.approx(round(scored * 2)) and scored != pytest.approx(succeeded)
    # Its report (where the designers put the columns): the one `alignrl league resume` draws
    # in test_a_league_of_designers_killed_with_sigkill_resumes_as_one_never_stopped.


def test_a_league_of_designers_killed_with_sigkill_resumes_as_one_never_stopped(
    designers: League, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The league of `designers` SIGKILLed (a process of its own) once it has checkpointed
    iteration 4 or later, before the PBT copy, snapshot and evaluation still to come, and
    resumed (here): its iterations and its designs are those of the league never stopped, and
    the report the resume draws shows where the designers put the columns."""
    config = designer_league(tmp_path, schedule=DESIGN_SCHEDULE)
    runs = tmp_path / "runs"
    run = runs / "tiny"
    command = [sys.executable, "-m", "alignrl.cli", "league"]
    killed_at = kill_league_after(
        [*command, "run", str(config), "--runs-dir", str(runs), "--quiet"], run, checkpoint=4
    )
    assert 4 <= killed_at < 8
    assert main(["league", "resume", str(run), "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["iterations"] == 8
    reference = designers.run_dir
    assert iteration_outcomes(run) == iteration_outcomes(reference)
    assert read_csv(run / "metrics" / "designs.csv") == read_csv(
        reference / "metrics" / "designs.csv"
    )
    assert (run / "report" / "designs.png").stat().st_size > 10_000
    assert "report/designs.png" in (run / "report.md").read_text()


def test_a_designer_league_stops_at_its_aligner_steps(tmp_path: Path) -> None:
    path = designer_league(
        tmp_path,
        schedule={
            "iterations": 50,
            "aligner_steps": 60,
            "matches": 8,
            "snapshot_every": 100,
            "evaluate_every": 100,
            "eval_scenarios": 2,
            "checkpoint_every": 100,
        },
    )
    league = create_league(path, tmp_path / "runs")
    league.run(progress=False)
    assert league.iteration < 50
    steps = max(league.members[m].steps_seen for m in ("a-sac", "a-ppo"))
    assert steps >= 60
    assert (tmp_path / "runs" / "tiny" / "checkpoints" / "LATEST").exists()  # the last one


def test_the_experiments_runs_are_valid_experiments(tmp_path: Path) -> None:
    from alignrl.config.experiment import load_experiment
    from benchmarks.designers import CONDITIONS, wilson, write_config

    for condition in CONDITIONS:
        path, verb = write_config(tmp_path, condition, 1, 20000)
        if verb == "train":
            assert load_experiment(path).budget.env_steps == 20000
            continue
        config, aligners, _ = load_league(path)
        assert (config.design, config.payoff, config.schedule.aligner_steps) == (
            True,
            condition,
            20000,
        )
        assert (
            aligners.members[0].learner
            == load_experiment(write_config(tmp_path, "uniform", 1, 20000)[0]).learner
        )  # the same aligner in every condition
    low, high = wilson(42, 100)
    assert low < 0.42 < high and 0.3 < low and high < 0.53

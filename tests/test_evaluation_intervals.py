"""Honest figures from evaluation sessions (issue 23): every success count with its 95 %
Wilson interval, `--seeds` (one session per seed, each the session `--seed S` runs, and
their aggregate: the IQM of the per-seed rates with its bootstrap interval, the pooled
successes with their Wilson interval), the session kind on every `--json`, and the cards
of exported policies that say their figures are the validation sessions that chose them.

Sessions are small and fast: a classical controller on the recorded curves (`csv:default`,
with noise so that seeds differ) or on a set's analytic instruments."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest
from conftest import without_seconds

from alignrl.apparatus.instruments import instrument_names
from alignrl.cli import main
from alignrl.evaluation.baselines import BASELINES
from alignrl.intervals import bootstrap_interval, iqm, success_text, wilson

CURVES = ["--apparatus", "csv:default", "--apparatus-args", '{"noise": 0.05, "split": "test"}']
SEEDS = [0, 1, 2, 3]
SCENARIOS = 10
SET = "validation"


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> Any:
    assert main([*argv, "--quiet", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _check_wilson(figure: dict[str, Any], successes: int, total: int) -> None:
    """A success_interval object: the count, and the Wilson interval that holds its rate."""
    assert (figure["successes"], figure["total"]) == (successes, total)
    assert figure["rate"] == pytest.approx(successes / total)
    assert (figure["low"], figure["high"]) == pytest.approx(wilson(successes, total))
    assert figure["low"] <= figure["rate"] <= figure["high"]
    assert figure["confidence"] == 0.95


def _check_aggregate(aggregate: dict[str, Any], counts: list[tuple[int, int]]) -> None:
    """An aggregate over seeds against the per-seed (successes, alignments) it came from."""
    rates = [successes / total for successes, total in counts]
    assert aggregate["success_rates"] == pytest.approx(rates)
    assert aggregate["success_rate_iqm"] == pytest.approx(iqm(rates))
    interval = aggregate["success_rate_iqm_interval"]
    assert (interval["low"], interval["high"]) == pytest.approx(bootstrap_interval(rates, iqm))
    assert interval["low"] <= aggregate["success_rate_iqm"] <= interval["high"]
    pooled = sum(successes for successes, _ in counts)
    alignments = sum(total for _, total in counts)
    assert (aggregate["successes"], aggregate["alignments"]) == (pooled, alignments)
    _check_wilson(aggregate["success_interval"], pooled, alignments)


# --- one apparatus --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def hill_climb_seeds() -> dict[str, Any]:
    """`evaluate --seeds` of hill-climb, the controller whose successes vary with the seed."""
    argv = ["evaluate", "--policy", "hill-climb", *CURVES, "--scenarios", str(SCENARIOS)]
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert main([*argv, "--seeds", *map(str, SEEDS), "--quiet", "--json"]) == 0
    return json.loads(out.getvalue())


def test_evaluate_seeds_gives_each_seed_and_their_aggregate(
    hill_climb_seeds: dict[str, Any],
) -> None:
    report = hill_climb_seeds
    assert report["seeds"] == SEEDS and report["session"] == "test"
    assert report["controller"] == "hill-climb" and report["scenarios"] == SCENARIOS
    assert [entry["seed"] for entry in report["per_seed"]] == SEEDS
    counts = [(entry["successes"], entry["scenarios"]) for entry in report["per_seed"]]
    assert all(total == SCENARIOS for _, total in counts)
    _check_aggregate(report["aggregate"], counts)
    # The seeds are different sessions: hill-climb does not score alike at every one.
    assert len({successes for successes, _ in counts}) > 1
    for entry in report["per_seed"]:
        assert entry["session"] == "test"
        _check_wilson(entry["success_interval"], entry["successes"], entry["scenarios"])


def test_each_seed_is_the_session_seed_s_runs(
    hill_climb_seeds: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["evaluate", "--policy", "hill-climb", *CURVES, "--scenarios", str(SCENARIOS)]
    for index in (0, 2):
        single = _run([*argv, "--seed", str(SEEDS[index])], capsys)
        assert without_seconds(single) == without_seconds(hill_climb_seeds["per_seed"][index])


def test_evaluate_seeds_prints_each_seed_and_the_aggregate(
    hill_climb_seeds: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "hill.png"
    argv = ["evaluate", "--policy", "hill-climb", *CURVES, "--scenarios", str(SCENARIOS)]
    assert main([*argv, "--seeds", *map(str, SEEDS), "--plot", str(plot), "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in lines if line[:1].isdigit()}
    assert list(rows) == [str(seed) for seed in SEEDS]
    for entry in hill_climb_seeds["per_seed"]:
        assert success_text(entry["successes"], SCENARIOS) in rows[str(entry["seed"])]
    aggregate = hill_climb_seeds["aggregate"]
    line = next(line for line in lines if line.startswith("over seeds 0, 1, 2, 3: "))
    assert f"IQM success {100 * aggregate['success_rate_iqm']:.0f} %" in line
    assert f"pooled {success_text(aggregate['successes'], aggregate['alignments'])}" in line
    # One plot per seed, named by it.
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        f"hill-seed{seed}.png" for seed in SEEDS
    ]


def test_one_session_keeps_its_keys_and_gains_its_interval_and_kind(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["evaluate", "--policy", "hill-climb", *CURVES, "--scenarios", str(SCENARIOS)]
    report = _run([*argv, "--seed", "3"], capsys)
    assert "per_seed" not in report and report["seed"] == 3 and report["session"] == "test"
    _check_wilson(report["success_interval"], report["successes"], SCENARIOS)
    assert main([*argv, "--seed", "3", "--quiet"]) == 0
    head = capsys.readouterr().out.splitlines()[0]
    assert f"{success_text(report['successes'], SCENARIOS)} aligned" in head


def test_baselines_seeds_aggregates_every_controller(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["baselines", *CURVES, "--scenarios", str(SCENARIOS)]
    report = _run([*argv, "--seeds", "1", "2", "4"], capsys)
    assert report["seeds"] == [1, 2, 4] and report["session"] == "test"
    assert set(report["aggregate"]) == set(BASELINES)
    for name, aggregate in report["aggregate"].items():
        sessions = [entry["controllers"][name] for entry in report["per_seed"]]
        _check_aggregate(aggregate, [(s["successes"], s["scenarios"]) for s in sessions])
    single = _run([*argv, "--seed", "2"], capsys)
    assert without_seconds(single) == without_seconds(report["per_seed"][1])
    assert main([*argv, "--seeds", "1", "2", "4", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert all(f"seed {seed}:" in text for seed in (1, 2, 4)) and "over the seeds:" in text
    table = text[text.index("over the seeds:") :].splitlines()
    for name, aggregate in report["aggregate"].items():
        row = next(line for line in table if line.startswith(name))
        assert success_text(aggregate["successes"], aggregate["alignments"]) in row


# --- an instrument set ----------------------------------------------------------------------


def test_evaluate_a_set_at_several_seeds(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["evaluate", "--policy", "hyperbola", "--set", SET, "--analytic", "--scenarios", "3"]
    report = _run([*argv, "--seeds", "0", "5"], capsys)
    names = list(instrument_names(SET))
    assert report["seeds"] == [0, 5] and report["session"] == "test"
    assert [entry["seed"] for entry in report["per_seed"]] == [0, 5]
    totals = [entry["total"] for entry in report["per_seed"]]
    for total in totals:
        _check_wilson(total["success_interval"], total["successes"], total["alignments"])
    aggregate = report["aggregate"]
    _check_aggregate(aggregate, [(total["successes"], total["alignments"]) for total in totals])
    # Each instrument pooled over the seeds.
    assert [entry["instrument"] for entry in aggregate["instruments"]] == names
    for index, entry in enumerate(aggregate["instruments"]):
        per_seed = [seed["instruments"][index] for seed in report["per_seed"]]
        assert entry["successes"] == sum(session["successes"] for session in per_seed)
        assert entry["alignments"] == 3 * 2
        _check_wilson(entry["success_interval"], entry["successes"], entry["alignments"])
    shares = [entry["successes"] / entry["alignments"] for entry in aggregate["instruments"]]
    assert aggregate["worst_instrument"] == names[shares.index(min(shares))]
    single = _run([*argv, "--seed", "5"], capsys)
    assert without_seconds(single) == without_seconds(report["per_seed"][1])
    # The table: a column per seed and one that pools them, whose total is the aggregate's.
    assert main([*argv, "--seeds", "0", "5", "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header = [cell.strip() for cell in lines[2].strip("|").split("|")]
    assert header == ["instrument", "seed 0", "seed 5", "all seeds"]
    total = next(line for line in lines if line.startswith("| **total**"))
    assert success_text(aggregate["successes"], aggregate["alignments"]) in total.split("|")[-2]


def test_baselines_over_a_set_at_several_seeds(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["baselines", "--set", SET, "--analytic", "--scenarios", "2", "--seeds", "0", "1"]
    report = _run(argv, capsys)
    assert [entry["seed"] for entry in report["per_seed"]] == [0, 1]
    for name, aggregate in report["aggregate"].items():
        totals = [entry["controllers"][name]["total"] for entry in report["per_seed"]]
        _check_aggregate(aggregate, [(t["successes"], t["alignments"]) for t in totals])


# --- refusals -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seed", "1", "--seeds", "0", "1"], "--seed and --seeds are exclusive"),
        (["--seeds", "0", "1", "--seed", "1"], "--seed and --seeds are exclusive"),
        (["--seeds", "3", "1", "3"], "--seeds gives seed 3 twice"),
        (["--seeds", "0", "-1"], "--seeds"),
    ],
)
@pytest.mark.parametrize("verb", ["evaluate", "baselines"])
def test_bad_seeds_exit_2_with_a_clear_message(
    verb: str, argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # A policy that names nothing: the seeds are refused before any policy loads.
    policy = ["--policy", "runs/no-such-run"] if verb == "evaluate" else []
    try:
        code = main([verb, *policy, "--apparatus", "csv:default", *argv, "--quiet"])
    except SystemExit as exit:  # the parser's own refusal (a seed out of range)
        code = exit.code
    assert code == 2
    captured = capsys.readouterr()
    assert message in captured.err and "Traceback" not in captured.err
    assert captured.out == ""


# --- the cards of exported policies ---------------------------------------------------------


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("card") / "focus"
    argv = ["export", "champion:focus-v1", "--format", "safetensors", "--out", str(out)]
    assert main([*argv, "--json"]) == 0
    return out


def test_a_card_says_its_figures_are_the_validation_sessions_that_chose_it(
    exported: Path,
) -> None:
    card = json.loads((exported / "card.json").read_text())
    evaluations = card["evaluations"]
    assert evaluations["session"] == "validation" and evaluations["confidence"] == 0.95
    rows = evaluations["rows"]
    for row in rows:
        low, high = wilson(row["successes"], row["scenarios"])
        assert (row["success_low"], row["success_high"]) == pytest.approx((low, high))
        assert low <= row["successes"] / row["scenarios"] <= high
    # The champion is the checkpoint its league kept at its best session.
    chosen = evaluations["chosen_on"]
    assert chosen in rows and chosen["iteration"] == card["training"]["league_iteration"]
    assert chosen["successes"] == max(row["successes"] for row in rows)
    text = (exported / "model_card.md").read_text()
    assert "These are **validation** sessions" in text
    assert f"at iteration {chosen['iteration']}: " in text
    for row in rows:
        assert f"| {success_text(row['successes'], row['scenarios'])} |" in text


def test_a_snapshot_is_not_said_to_be_chosen(tmp_path: Path) -> None:
    # stigmation-v1 is a snapshot a person picked, not a checkpoint a session kept.
    out = tmp_path / "stigmation"
    argv = ["export", "champion:stigmation-v1", "--format", "safetensors", "--out", str(out)]
    assert main(argv) == 0
    card = json.loads((out / "card.json").read_text())
    assert card["evaluations"]["session"] == "validation"
    assert card["evaluations"]["chosen_on"] is None
    assert "is not one a session of the run kept as its best" in (out / "model_card.md").read_text()


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda ev: ev.update(session="training"), "evaluations.session"),
        (lambda ev: ev["rows"][0].update(success_high=1.5), "evaluations.rows[0].success_high"),
        (lambda ev: ev["rows"][1].update(success_low=0.99), "evaluations.rows[1].success_high"),
        (lambda ev: ev.update(confidence=95), "evaluations.confidence"),
    ],
)
def test_a_card_that_misstates_its_sessions_is_refused(
    exported: Path, tmp_path: Path, change: Any, field: str
) -> None:
    from alignrl.deploy.loading import load_exported
    from alignrl.runs.sources import ExportError

    folder = tmp_path / "bad"
    folder.mkdir()
    card = json.loads((exported / "card.json").read_text())
    change(card["evaluations"])
    (folder / "card.json").write_text(json.dumps(card))
    (folder / "policy.safetensors").write_bytes((exported / "policy.safetensors").read_bytes())
    with pytest.raises(ExportError, match=field.replace("[", r"\[").replace("]", r"\]")):
        load_exported(folder)

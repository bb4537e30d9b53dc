"""A controller over a whole instrument set: one session per instrument in set order, totals
that are the sums, the same columns and starts for every controller of a seed, the Markdown
table with its total row, and `alignrl evaluate|baselines --set` (JSON, refusals, Ctrl-C).

Everything runs on analytic readings with a few scenarios per instrument (the image path is
slower; one test checks only that the choice reaches the instruments)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import without_seconds

import alignrl.evaluation.instrument_sets as instrument_sets
from alignrl.apparatus.instruments import instrument_names, set_names
from alignrl.cli import main
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import BASELINES, CLASSICAL
from alignrl.evaluation.instrument_sets import SetResult, run_set, set_summary, set_table
from alignrl.intervals import success_text

FOCUS = get_task("focus")
SET = "validation"
NAMES = list(instrument_names(SET))
SCENARIOS = 3


@pytest.fixture(scope="module")
def hyperbola() -> SetResult:
    return run_set(CLASSICAL["hyperbola"](), SET, FOCUS, scenarios=SCENARIOS, analytic=True)


@pytest.fixture(scope="module")
def golden() -> SetResult:
    return run_set(CLASSICAL["golden-section"](), SET, FOCUS, scenarios=SCENARIOS, analytic=True)


def _rows(table: list[str]) -> list[list[str]]:
    """The data rows of a Markdown table (header and rule dropped), cells stripped."""
    assert table[1].replace("|", "").replace("-", "").replace(":", "").strip() == ""
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in table[2:]]


# --- run_set ------------------------------------------------------------------------------


def test_one_session_per_instrument_in_set_order_and_totals_are_the_sums(
    hyperbola: SetResult,
) -> None:
    assert len(NAMES) >= 2 and hyperbola.instruments == tuple(NAMES)
    assert len(hyperbola.sessions) == len(NAMES)
    assert all(session.scenarios == SCENARIOS for session in hyperbola.sessions)
    assert hyperbola.alignments == SCENARIOS * len(NAMES)
    assert hyperbola.successes == sum(session.successes for session in hyperbola.sessions)
    pooled = [r.acquisitions for session in hyperbola.sessions for r in session.records]
    assert hyperbola.median_acquisitions == np.median(pooled)
    assert hyperbola.p90_acquisitions == np.percentile(pooled, 90)
    shares = [session.successes for session in hyperbola.sessions]
    assert hyperbola.worst_successes == min(shares)
    assert hyperbola.worst == NAMES[shares.index(min(shares))]
    # The same seed on every instrument, yet each its own column (its own interval).
    assert len({tuple(r.seed for r in s.records) for s in hyperbola.sessions}) == 1
    intervals = {tuple(sorted(r.start for r in s.records)) for s in hyperbola.sessions}
    assert len(intervals) == len(NAMES)
    payload = hyperbola.to_dict()
    assert [entry["instrument"] for entry in payload["instruments"]] == NAMES
    assert [entry["apparatus"] for entry in payload["instruments"]] == [
        f"instrument:{name}" for name in NAMES
    ]
    total = payload["total"]
    assert total["successes"] == sum(entry["successes"] for entry in payload["instruments"])
    assert total["alignments"] == sum(entry["scenarios"] for entry in payload["instruments"])
    assert (total["instruments"], total["worst_instrument"]) == (len(NAMES), hyperbola.worst)


def test_two_controllers_meet_the_same_columns_and_starts(
    hyperbola: SetResult, golden: SetResult
) -> None:
    for ours, theirs in zip(hyperbola.sessions, golden.sessions, strict=True):
        assert [r.seed for r in ours.records] == [r.seed for r in theirs.records]
        assert [r.start for r in ours.records] == [r.start for r in theirs.records]
        assert [r.threshold_px for r in ours.records] == [r.threshold_px for r in theirs.records]


def test_the_same_seed_gives_the_same_result_and_another_seed_another(
    hyperbola: SetResult,
) -> None:
    again = run_set(CLASSICAL["hyperbola"](), SET, FOCUS, scenarios=SCENARIOS, analytic=True)
    assert without_seconds(again.to_dict()) == without_seconds(hyperbola.to_dict())
    for ours, theirs in zip(again.sessions, hyperbola.sessions, strict=True):
        assert [r.shots for r in ours.records] == [r.shots for r in theirs.records]
    other = run_set(
        CLASSICAL["hyperbola"](), SET, FOCUS, scenarios=SCENARIOS, seed=1, analytic=True
    )
    assert [r.start for r in other.sessions[0].records] != [
        r.start for r in hyperbola.sessions[0].records
    ]


def test_the_readings_choice_reaches_every_instrument(monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[tuple[str, dict[str, Any]]] = []
    real = instrument_sets.make_apparatus

    def spy(spec: str, args: dict[str, Any], **kwargs: Any) -> Any:
        opened.append((spec, dict(args)))
        return real(spec, args, **kwargs)

    monkeypatch.setattr(instrument_sets, "make_apparatus", spy)
    result = run_set(CLASSICAL["hyperbola"](), SET, FOCUS, scenarios=1)  # images
    assert opened == [(f"instrument:{name}", {"analytic": False}) for name in NAMES]
    assert result.analytic is False and result.to_dict()["analytic"] is False


def test_an_unknown_set_is_refused_naming_the_sets() -> None:
    with pytest.raises(ValueError, match="no instrument set 'nope'; the sets are: ") as error:
        run_set(CLASSICAL["hyperbola"](), "nope", FOCUS, scenarios=1, analytic=True)
    for name in set_names():
        assert name in str(error.value)


# --- the table ----------------------------------------------------------------------------


def test_the_table_has_a_row_per_instrument_and_a_total_row(
    hyperbola: SetResult, golden: SetResult
) -> None:
    table = set_table([hyperbola, golden])
    header = [cell.strip() for cell in table[0].strip("|").split("|")]
    assert header == ["instrument", "hyperbola", "golden-section"]
    rows = _rows(table)
    assert len(rows) == len(NAMES) + 1
    assert [row[0] for row in rows[:-1]] == NAMES and rows[-1][0] == "**total**"
    for row, session in zip(rows[:-1], hyperbola.sessions, strict=True):
        # Each count with its 95 % Wilson interval.
        counted = success_text(session.successes, SCENARIOS)
        assert row[1] == f"{counted} at {session.median_acquisitions:g}"
    for column, result in ((1, hyperbola), (2, golden)):
        counts = [int(row[column].split("/")[0]) for row in rows[:-1]]
        total, alignments = rows[-1][column].split(" (")[0].split("/")
        assert int(total) == sum(counts) == result.successes
        assert int(alignments) == SCENARIOS * len(NAMES)
        assert rows[-1][column].startswith(success_text(result.successes, result.alignments))
    assert len({len(line) for line in table}) == 1  # padded: the columns line up
    line = set_summary(hyperbola)
    assert f"{success_text(hyperbola.successes, hyperbola.alignments)} aligned" in line
    assert line.startswith("hyperbola: ") and f"worst {hyperbola.worst}" in line


def test_a_table_of_different_instruments_is_refused(
    hyperbola: SetResult, golden: SetResult
) -> None:
    fewer = dataclasses.replace(
        golden, instruments=golden.instruments[1:], sessions=golden.sessions[1:]
    )
    with pytest.raises(ValueError, match="the same instruments for every controller"):
        set_table([hyperbola, fewer])
    with pytest.raises(ValueError, match="one session per instrument"):
        dataclasses.replace(golden, sessions=golden.sessions[1:])


# --- the verbs ----------------------------------------------------------------------------

ARGV = ["--set", SET, "--analytic", "--scenarios", str(SCENARIOS)]


def test_evaluate_a_classical_controller_over_a_set(
    hyperbola: SetResult, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["evaluate", "--policy", "hyperbola", *ARGV, "--json"]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["set"] == SET and report["controller"] == "hyperbola"
    assert report["analytic"] is True and report["scenarios"] == SCENARIOS
    assert [entry["instrument"] for entry in report["instruments"]] == NAMES
    assert report["total"]["successes"] == sum(e["successes"] for e in report["instruments"])
    assert report["total"]["alignments"] == SCENARIOS * len(NAMES)
    # The CLI runs what run_set runs: the same seed, the same sessions.
    assert without_seconds(report) == without_seconds(hyperbola.to_dict())
    # One progress bar over every alignment of every instrument.
    total = SCENARIOS * len(NAMES)
    assert f"{total}/{total}" in captured.err
    assert main(["evaluate", "--policy", "hyperbola", *ARGV, "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "| **total**" in text and all(f"| {name} " in text for name in NAMES)


def test_evaluate_plots_one_png_per_instrument(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "sets" / "hyp.png"
    argv = ["evaluate", "--policy", "hyperbola", "--set", SET, "--analytic", "--scenarios", "1"]
    assert main([*argv, "--plot", str(plot), "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    for entry, name in zip(report["instruments"], NAMES, strict=True):
        assert entry["plot"] == str(tmp_path / "sets" / f"hyp-{name}.png")
        assert Path(entry["plot"]).read_bytes()[:4] == b"\x89PNG"


def test_baselines_over_a_set_side_by_side(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["baselines", *ARGV, "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert (report["set"], report["task"], report["instruments"]) == (SET, "focus", NAMES)
    assert set(report["controllers"]) == set(BASELINES)
    for name, result in report["controllers"].items():
        assert result["controller"] == name and len(result["instruments"]) == len(NAMES)
    assert main(["baselines", *ARGV, "--quiet"]) == 0
    text = capsys.readouterr().out.splitlines()
    header = next(line for line in text if line.startswith("| instrument"))
    assert all(name in header for name in BASELINES)
    rows = [line for line in text if line.startswith("| ") and line is not header]
    assert len(rows) == 1 + len(NAMES) + 1  # the rule, the instruments, the total


def test_a_trained_policy_over_a_set(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["evaluate", "--policy", "champion:focus-v1", "--set", SET, "--analytic"]
    assert main([*argv, "--scenarios", "2", "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["controller"] != "hyperbola" and report["task"] == "focus"
    assert [entry["instrument"] for entry in report["instruments"]] == NAMES
    assert report["total"]["alignments"] == 2 * len(NAMES)
    assert all(entry["median_acquisitions"] >= 1 for entry in report["instruments"])


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--set", "nope"], "no instrument set 'nope'; the sets are: heldout, heldout-aperture"),
        (["--set", SET, "--apparatus", "synthetic"], "--set and --apparatus are exclusive"),
        ([], "give --apparatus SPEC, or --set NAME"),
        (["--apparatus", "synthetic", "--analytic"], "--analytic applies to --set"),
        (["--set", SET, "--apparatus-args", '{"noise": 1}'], "--apparatus-args applies to"),
        ([*ARGV, "--scenarios", "0"], "--scenarios must be at least 1"),
    ],
)
@pytest.mark.parametrize("verb", ["evaluate", "baselines"])
def test_bad_set_input_exits_2_with_a_clear_message(
    verb: str, argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # A policy that names nothing: the set is checked first, before any policy loads.
    policy = ["--policy", "runs/no-such-run"] if verb == "evaluate" else []
    assert main([verb, *policy, *argv, "--quiet"]) == 2
    captured = capsys.readouterr()
    assert message in captured.err and "Traceback" not in captured.err
    assert captured.out == ""


def test_ctrl_c_over_a_set_ends_without_a_report(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    calls = []
    real = instrument_sets.run_session

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 2:  # the second instrument
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(instrument_sets, "run_session", interrupted)
    assert main(["baselines", *ARGV, "--quiet", "--json"]) == 130
    captured = capsys.readouterr()
    assert captured.out == "" and "interrupted" in captured.err and len(calls) == 2

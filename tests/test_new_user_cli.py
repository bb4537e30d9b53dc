"""What a new user met on a fresh clone, at the command line: an abbreviated option taken for
another (`--scen` for `--scenarios`), a mistyped option or verb answered with the top-level
usage and no suggestion, and `alignrl report` on a league run failing on a missing column."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from alignrl.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """What `alignrl ARGV` says on standard error; it must exit 2."""
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(argv)
    assert exit_.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    return captured.err


def _parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parser and every verb's below it."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                found += _parsers(sub)
    return found


def test_no_parser_of_the_command_takes_an_abbreviation() -> None:
    parsers = _parsers(build_parser())
    assert len(parsers) > 15  # every verb, `league run` and `scenarios validate` included
    assert all(parser.allow_abbrev is False for parser in parsers)


def test_an_abbreviated_option_is_refused_with_the_option_it_abbreviates(
    capsys: pytest.CaptureFixture[str],
) -> None:
    error = _refused(["evaluate", "--policy", "champion:focus", "--scen", "3"], capsys)
    assert error.startswith("usage: alignrl evaluate ")  # the verb's usage, not the top level's
    assert error.rstrip().endswith(
        "alignrl evaluate: error: unrecognized arguments: --scen (did you mean --scenarios?)"
    )
    args = build_parser().parse_args(["evaluate", "--policy", "x", "--scenarios", "3"])
    assert args.scenarios == 3  # the whole name still works


def test_a_mistyped_option_is_named_even_where_a_required_one_is_missing(
    capsys: pytest.CaptureFixture[str],
) -> None:
    error = _refused(["evaluate", "--polcy", "champion:focus"], capsys)
    assert "unrecognized arguments: --polcy (did you mean --policy?)" in error
    error = _refused(["league", "status", "--jsn", "runs/x"], capsys)
    assert error.startswith("usage: alignrl league status ")
    assert "(did you mean --json?)" in error


def test_a_mistyped_verb_is_answered_with_the_closest_verb(
    capsys: pytest.CaptureFixture[str],
) -> None:
    error = _refused(["evalute"], capsys)
    assert error.startswith("usage: alignrl [-h]")
    assert "invalid choice: 'evalute'" in error and "did you mean 'evaluate'?" in error
    error = _refused(["league", "stat", "runs/x"], capsys)
    assert error.startswith("usage: alignrl league [-h]")
    assert "did you mean 'status'?" in error and "league_verb" not in error
    error = _refused(["export", "r", "--format", "onx", "--out", "d"], capsys)
    assert "argument --format: invalid choice: 'onx'" in error and "did you mean 'onnx'?" in error


def test_the_command_refuses_a_mistyped_option_in_one_message_without_a_traceback() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "alignrl", "baselines", "--apparatus", "synthetic", "--scen", "3"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 2 and result.stdout == ""
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("usage: alignrl baselines ")
    assert "did you mean --scenarios?" in result.stderr


def test_report_on_a_league_run_says_which_command_reports_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A league run's metrics/evaluations.csv has no env_steps: `alignrl report` used to stop
    on that column. It now writes nothing and names `alignrl leaderboard RUN`."""
    run = tmp_path / "league-x"
    (run / "metrics").mkdir(parents=True)
    (run / "config.yaml").write_text(
        "name: league-x\naligners: populations/aligners.yaml\n"
        "misaligners: populations/misaligners.yaml\n"
    )
    (run / "metrics" / "evaluations.csv").write_text(
        "iteration,member,successes,scenarios,median_acquisitions,p90_acquisitions,rating\n"
        "40,a,3,5,4,6,20.0\n"
    )
    before = sorted(path.name for path in run.rglob("*"))
    assert main(["report", str(run)]) == 2
    error = capsys.readouterr().err
    assert error.startswith(f"alignrl: error: {run} is a league run")
    assert f"`alignrl leaderboard {run}`" in error and "env_steps" not in error
    assert sorted(path.name for path in run.rglob("*")) == before  # nothing written

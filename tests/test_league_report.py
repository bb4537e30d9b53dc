"""The league report: report.md and report.html list every member and link only figures that
exist, `alignrl leaderboard` writes it, and a run killed early still gets one that says what
is missing; the payoff grid and the teams are checked against numbers worked out by hand."""

from __future__ import annotations

import contextlib
import html
import io
import json
import re
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np
import pandas as pd
import pytest
from conftest import create_league, write_league
from test_report import PNG_MAGIC, snapshot

from alignrl.cli import main
from alignrl.league.loop import League, leaderboard
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.report import member_teams, payoff_grid, write_league_report
from alignrl.plots import ReportError, read_metrics_csv

SCHEDULE = {
    "iterations": 6,
    "matches": 4,
    "snapshot_every": 3,
    "pbt_every": 4,
    "evaluate_every": 3,
    "eval_scenarios": 2,
    "checkpoint_every": 3,
}
LEAGUE_FIGURES = ("ratings.png", "payoff.png", "curriculum.png", "evaluations.png")


def new_league(root: Path) -> League:
    return create_league(write_league(root, schedule=SCHEDULE), root / "runs")


def links(run: Path) -> tuple[list[str], list[str]]:
    """The figures report.md and report.html link, as paths relative to the run."""
    markdown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (run / "report.md").read_text())
    page = re.findall(r'<img src="([^"]+)"', (run / "report.html").read_text())
    return [unquote(link) for link in markdown], [unquote(html.unescape(link)) for link in page]


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, dict[str, Any]]:
    """A finished tiny league (snapshots, a PBT copy, evaluations), reported by
    `alignrl leaderboard RUN --json`: the run, the exit code and the payload."""
    root = tmp_path_factory.mktemp("league")
    new_league(root).run(progress=False)
    run = root / "runs" / "tiny"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["leaderboard", str(run), "--json"])
    return run, code, json.loads(out.getvalue())


def test_the_leaderboard_command_writes_the_report_and_says_where(
    finished: tuple[Path, int, dict[str, Any]],
) -> None:
    run, code, payload = finished
    assert code == 0
    assert payload["report"] == str(run / "report.md")
    assert (run / "report.md").is_file() and (run / "report.html").is_file()


def test_the_report_lists_every_member_of_the_leaderboard(
    finished: tuple[Path, int, dict[str, Any]],
) -> None:
    run, _, payload = finished
    markdown, page = (run / "report.md").read_text(), (run / "report.html").read_text()
    members = [row["member"] for row in payload["leaderboard"]]
    assert any("@" in member for member in members)  # snapshots are on it too
    for member in members:
        assert f"| {member} |" in markdown
        assert f"<td>{html.escape(member)}</td>" in page
    assert "## Lineage" in markdown and "-pbt4.0" in markdown  # the PBT copy and its parent


def test_both_documents_link_the_same_figures_and_each_is_a_png(
    finished: tuple[Path, int, dict[str, Any]],
) -> None:
    run, _, _ = finished
    markdown, page = links(run)
    assert markdown == page
    for link in markdown:
        assert (run / link).read_bytes().startswith(PNG_MAGIC), link
    assert {f"report/{name}" for name in LEAGUE_FIGURES} <= set(markdown)
    # Every member that learned has its losses drawn, every aligner that played its return.
    for folder in sorted((run / "metrics" / "members").iterdir()):
        updates = read_metrics_csv(folder / "updates.csv", ["env_steps"])
        episodes = read_metrics_csv(folder / "episodes.csv", ["env_steps"])
        for name, table in (("losses.png", updates), ("reward.png", episodes)):
            assert (f"report/members/{folder.name}/{name}" in markdown) == bool(len(table))


def test_a_run_killed_before_its_first_evaluation_gets_a_report_noting_what_is_missing(
    tmp_path: Path,
) -> None:
    league = new_league(tmp_path)
    for _ in range(2):
        league.step()
    league.checkpoint()
    run = league.run_dir
    before = snapshot(run)
    assert write_league_report(run, leaderboard(league)) == run / "report.md"
    markdown = (run / "report.md").read_text()
    assert "- **evaluations.png:** metrics/evaluations.csv has no rows yet" in markdown
    assert "No evaluation session yet" in markdown
    linked, _ = links(run)
    assert "report/evaluations.png" not in linked and "report/payoff.png" in linked
    # Only report.md, report.html and report/ are new; nothing else was touched (TensorBoard's
    # writer thread belongs to the league, not to the report).
    after = {path: stat for path, stat in snapshot(run).items() if "tensorboard" not in path}
    changed = {path for path, stat in after.items() if before.get(path) != stat}
    assert changed == {"report.md", "report.html"} | {
        path for path in after if path.startswith("report/")
    }


def test_a_run_with_no_checkpoint_and_empty_csvs_still_gets_a_report(tmp_path: Path) -> None:
    league = new_league(tmp_path)
    write_league_report(league.run_dir, leaderboard(league))
    markdown = (league.run_dir / "report.md").read_text()
    assert "0 of 6 planned; no checkpoint yet" in markdown
    assert "- **payoff.png:** no checkpoint yet" in markdown
    assert "- **curriculum.png:** metrics/iterations.csv has no rows yet" in markdown
    assert links(league.run_dir) == ([], [])


def test_the_payoff_grid_ranks_players_that_met_and_leaves_the_rest_blank() -> None:
    ratings = Ratings()
    # m3 is rated but never played, so it gets no column.
    for player, rating in {"a1": 1300, "a2": 1100, "a1@2": 1200, "m1": 1250, "m2": 1150}.items():
        ratings.add(player, rating)
    ratings.add("m3", 1400)
    payoff = PayoffTable()
    payoff.add("a2", "m1", 4, 1.0)
    payoff.add("a1", "m2", 2, 2.0)
    payoff.add("a1@2", "m1", 4, 3.0)
    grid = payoff_grid(payoff, ratings)
    assert grid.aligners == ["a1", "a1@2", "a2"] and grid.misaligners == ["m1", "m2"]
    np.testing.assert_array_equal(grid.win_rates, [[np.nan, 1.0], [0.75, np.nan], [0.25, np.nan]])
    np.testing.assert_array_equal(grid.matches, [[0, 2], [4, 0], [4, 0]])


def test_a_copy_joins_its_parents_team_and_an_unknown_parent_is_named() -> None:
    rosters = {"aligner": ["a"], "misaligner": ["m"]}
    lineage = pd.DataFrame(
        {"member": ["a-pbt4.0", "m-pbt4.0", "a-pbt8.0"], "parent": ["a", "m", "a-pbt4.0"]}
    )
    assert member_teams(rosters, lineage) == {
        "a": "aligner",
        "m": "misaligner",
        "a-pbt4.0": "aligner",
        "m-pbt4.0": "misaligner",
        "a-pbt8.0": "aligner",
    }
    stray = pd.DataFrame({"member": ["x-pbt4.0"], "parent": ["x"]})
    with pytest.raises(ReportError, match=r"'x-pbt4\.0' copies 'x'"):
        member_teams(rosters, stray)


def test_member_ids_are_read_as_text_and_numbers_still_strictly(tmp_path: Path) -> None:
    path = tmp_path / "evaluations.csv"
    path.write_text("iteration,member,successes\n3,a-ppo,1\n6,a-sac@3,2\n")
    table = read_metrics_csv(path, ["iteration", "member"], text_columns={"member"})
    assert list(table["member"]) == ["a-ppo", "a-sac@3"]
    assert list(table["successes"]) == [1.0, 2.0]
    path.write_text("iteration,member,successes\n3,a-ppo,one\n")
    with pytest.raises(ReportError, match="line 2, column successes: 'one' is not a number"):
        read_metrics_csv(path, ["iteration"], text_columns={"member"})

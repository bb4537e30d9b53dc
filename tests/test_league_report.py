"""The league report: report.md and report.html list every member and link only figures that
exist, `alignrl leaderboard` writes it, and a run killed early still gets one that says what
is missing; the payoff grid, the teams and a member's own env steps are checked against
numbers worked out by hand. Its figures, read back from the Figures it saved: a member has one
colour in every figure, snapshots are labelled, a member's curves are on its own env steps
(the counter its checkpoint keeps), the classical controllers are drawn at their test session
figures, and every success figure of a session carries its Wilson interval."""

from __future__ import annotations

import contextlib
import html
import io
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple
from urllib.parse import unquote

import numpy as np
import pandas as pd
import pytest
from conftest import create_league, read_csv, write_league
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from test_report import PNG_MAGIC, errorbars, snapshot

from alignrl import plots
from alignrl.checkpoints import load_checkpoint
from alignrl.cli import main
from alignrl.intervals import wilson
from alignrl.league import report as league_report
from alignrl.league.loop import League, leaderboard
from alignrl.league.ratings import PayoffTable, Rating, Ratings
from alignrl.league.report import member_teams, payoff_grid, write_league_report
from alignrl.league.report_data import (
    member_env_steps,
    on_own_env_steps,
    rated_matches,
    read_league_run,
)
from alignrl.league.report_figures import MEMBER_STEPS_LABEL, member_colours
from alignrl.run_tables import ReportError, RunMetrics, read_metrics_csv

SCHEDULE = {
    "iterations": 6,
    "matches": 4,
    "snapshot_every": 3,
    "pbt_every": 4,
    "evaluate_every": 3,
    "eval_scenarios": 2,
    "checkpoint_every": 3,
    "uniform_starts": 0.25,  # one match of an aligner's turn starts uniformly, unrated
}
LEAGUE_FIGURES = (
    "ratings.png",
    "payoff.png",
    "learning.png",
    "curriculum.png",
    "evaluations.png",
    "test.png",
)


def new_league(root: Path) -> League:
    return create_league(write_league(root, schedule=SCHEDULE), root / "runs")


def links(run: Path) -> tuple[list[str], list[str]]:
    """The figures report.md and report.html link, as paths relative to the run."""
    markdown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (run / "report.md").read_text())
    page = re.findall(r'<img src="([^"]+)"', (run / "report.html").read_text())
    return [unquote(link) for link in markdown], [unquote(html.unescape(link)) for link in page]


class Finished(NamedTuple):
    run: Path
    code: int  # of `alignrl leaderboard RUN --json`
    payload: dict[str, Any]  # its output
    figures: dict[str, Figure]  # every figure the report saved, by path relative to the run


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Finished:
    """A finished tiny league (snapshots, a PBT copy, evaluations, its test session),
    reported by `alignrl leaderboard RUN --json`, the figures kept as they were saved."""
    root = tmp_path_factory.mktemp("league")
    league = new_league(root)
    league.run(progress=False)
    league.test()
    run = root / "runs" / "tiny"
    out, figures = io.StringIO(), {}

    def keeping(save: Callable[..., None]) -> Callable[..., None]:
        def save_and_keep(figure: Figure, path: Path, *inputs: str | None) -> None:
            figures[str(path.relative_to(run))] = figure
            save(figure, path, *inputs)

        return save_and_keep

    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(out):
        for module in (league_report, plots):  # the league's figures, the members'
            patch.setattr(module, "save_png", keeping(module.save_png))
        code = main(["leaderboard", str(run), "--json"])
    return Finished(run, code, json.loads(out.getvalue()), figures)


def test_the_leaderboard_command_writes_the_report_and_says_where(
    finished: Finished,
) -> None:
    run, code, payload, _ = finished
    assert code == 0
    assert payload["report"] == str(run / "report.md")
    assert (run / "report.md").is_file() and (run / "report.html").is_file()


def test_the_report_lists_every_member_of_the_leaderboard(
    finished: Finished,
) -> None:
    run, _, payload, _ = finished
    markdown, page = (run / "report.md").read_text(), (run / "report.html").read_text()
    members = [row["member"] for row in payload["leaderboard"]]
    assert any("@" in member for member in members)  # snapshots are on it too
    for member in members:
        assert f"| {member} |" in markdown
        assert f"<td>{html.escape(member)}</td>" in page
    assert "## Lineage" in markdown and "-pbt4.0" in markdown  # the PBT copy and its parent


def test_both_documents_link_the_same_figures_and_each_is_a_png(
    finished: Finished,
) -> None:
    run = finished.run
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
    assert "No validation session yet" in markdown
    assert "No test session yet: it runs when the league has finished." in markdown
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
    # m3 is rated but never played, so it gets no column; ranked by mu - 3 sigma.
    for player, mu in {"a1": 30, "a2": 20, "a1@2": 25, "m1": 28, "m2": 22}.items():
        ratings.add(player, Rating(mu, 1.0))
    ratings.add("m3", Rating(40.0, 1.0))
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


# --- the figures, read back -------------------------------------------------------------


GREY = to_hex(plots.REFERENCE_COLOUR)  # the classical controllers' lines


def drawn_colours(name: str, figure: Figure, members: set[str]) -> list[tuple[str, str]]:
    """(member, colour) for everything `figure` draws for a member or its snapshots: lines
    and legend entries named by it, payoff tick labels, bars, a member's own figures."""
    found: list[tuple[str, str]] = []
    if name.startswith("members/"):
        member = name.split("/")[1]
        for axes in figure.axes:
            colours = {to_hex(line.get_color()) for line in axes.get_lines()} - {GREY}
            found += [(member, colour) for colour in colours]
    elif name == "payoff.png":
        (axes, _) = figure.axes  # the grid and its colour bar
        for label in [*axes.get_xticklabels(), *axes.get_yticklabels()]:
            found.append((label.get_text().split("@")[0], to_hex(label.get_color())))
    elif name == "test.png":
        champion = figure.axes[0].patches[0]
        found.append(
            (
                figure.axes[0].get_xticklabels()[0].get_text().split("\n")[1],
                to_hex(champion.get_facecolor()),
            )
        )
    else:
        legends = [axes.get_legend() for axes in figure.axes] + figure.legends
        handles = [
            (text.get_text(), handle)
            for legend in legends
            if legend is not None
            for text, handle in zip(legend.get_texts(), legend.legend_handles, strict=True)
        ]
        lines = [(line.get_label(), line) for axes in figure.axes for line in axes.get_lines()]
        for label, artist in handles + lines:
            member = re.split(r":| \(| snapshots", label)[0]
            if member in members:
                found.append((member, to_hex(artist.get_color())))
    return found


def test_a_member_has_one_colour_in_every_figure(finished: Finished) -> None:
    run, figures = finished.run, finished.figures
    colours = member_colours(read_league_run(run).teams)
    assert len(set(colours.values())) == len(colours)  # no two members alike
    assert GREY not in colours.values()
    where: dict[str, set[str]] = {}
    for path, figure in figures.items():
        name = path.removeprefix("report/")
        for member, colour in drawn_colours(name, figure, set(colours)):
            assert colour == colours[member], f"{member} in {name}"
            where.setdefault(member, set()).add(name.split("/")[0])
    champion = json.loads((run / "test.json").read_text())["chosen_by"]["member"]
    assert {"ratings.png", "payoff.png", "learning.png", "evaluations.png", "test.png"} | {
        "members"
    } <= where[champion]
    assert all("ratings.png" in where[member] for member in colours)  # every member ever
    for folder in (run / "metrics" / "members").iterdir():
        assert {"ratings.png", "payoff.png", "members"} <= where[folder.name]


def test_snapshots_are_drawn_lighter_in_their_members_colour_and_labelled(
    finished: Finished,
) -> None:
    # On the leaderboard, the snapshots frozen before the last iteration (one frozen at the end
    # has no rating after it to draw).
    last = SCHEDULE["iterations"]
    players = [row["member"] for row in finished.payload["leaderboard"]]
    snapshots = [p for p in players if "@" in p and int(p.split("@")[1]) < last]
    assert snapshots
    ratings = finished.figures["report/ratings.png"]
    entries = {
        text.get_text(): handle
        for axes in ratings.axes
        for text, handle in zip(
            axes.get_legend().get_texts(), axes.get_legend().legend_handles, strict=True
        )
    }
    marks = {text.get_text() for axes in ratings.axes for text in axes.texts}
    for frozen in snapshots:
        member, iteration = frozen.split("@")
        (label,) = [text for text in entries if text.startswith(f"{member} snapshots (")]
        assert f"@{iteration}" in label
        assert entries[label].get_linestyle() == "--" and entries[label].get_alpha() < 1
        assert f"@{iteration}" in marks  # each snapshot's line marked at its end
    payoff = finished.figures["report/payoff.png"].axes[0]
    for label in [*payoff.get_xticklabels(), *payoff.get_yticklabels()]:
        assert (label.get_fontstyle() == "italic") == ("@" in label.get_text())


def own_steps_by_hand(run: Path, member: str) -> dict[int, int]:
    """An aligner of the rosters: the images of the iterations it played as the aligner so
    far, at each iteration's end (league env steps -> its own)."""
    own, previous, at = 0, 0, {}
    for row in read_csv(run / "metrics" / "iterations.csv"):
        steps = int(row["env_steps"])
        if row["aligner"] == member:
            own += steps - previous
        previous, at[steps] = steps, own
    return at


def test_member_curves_are_on_the_members_own_env_steps(finished: Finished) -> None:
    run, figures = finished.run, finished.figures
    for member in ("a-sac", "a-ppo"):  # the rosters' aligners
        episodes = read_csv(run / "metrics" / "members" / member / "episodes.csv")
        if not episodes:
            continue
        at = own_steps_by_hand(run, member)
        expected = [at[int(row["env_steps"])] for row in episodes]
        (axes,) = figures[f"report/members/{member}/reward.png"].axes
        np.testing.assert_array_equal(axes.get_lines()[0].get_xdata(), expected)
        assert axes.get_xlabel() == MEMBER_STEPS_LABEL
        assert expected[-1] < int(episodes[-1]["env_steps"])  # not the league's
    # The last count of every active member is the counter its checkpoint keeps: an
    # aligner's images, a misaligner's chosen starts (not the uniform ones), a copy's
    # parent's before its own.
    league = read_league_run(run)
    rosters = [member for member in league.teams if "-pbt" not in member]
    steps = member_env_steps(league.iterations, league.lineage, rosters, league.uniform_starts)
    folder = run / "checkpoints" / (run / "checkpoints" / "LATEST").read_text().strip() / "members"
    active = sorted(path.stem for path in folder.glob("*.pt"))
    assert any("-pbt" in member for member in active)
    for member in active:
        assert steps[member][1][-1] == load_checkpoint(folder / f"{member}.pt")["steps_seen"]


def test_the_classical_controllers_are_lines_at_their_test_session_figures(
    finished: Finished,
) -> None:
    test = json.loads((finished.run / "test.json").read_text())
    classical = [row for row in test["rows"] if row["member"] is None]
    assert classical
    champion = test["chosen_by"]["member"]
    panels = {
        "learning.png": finished.figures["report/learning.png"].axes,
        "member": finished.figures[f"report/members/{champion}/success.png"].axes
        + finished.figures[f"report/members/{champion}/acquisitions.png"].axes,
        "evaluations.png": finished.figures["report/evaluations.png"].axes,
    }
    for where, (success, *acquisitions) in panels.items():
        lines = {line.get_label(): line for line in success.get_lines()}
        for row in classical:
            (label,) = [text for text in lines if text.startswith(f"{row['label']} (test session)")]
            rate = 100 * row["successes"] / row["scenarios"]
            np.testing.assert_allclose(lines[label].get_ydata(), [rate, rate], err_msg=where)
            for axes in acquisitions:
                (median,) = [
                    line.get_ydata()[0]
                    for line in axes.get_lines()
                    if line.get_label().startswith(f"{row['label']} (test session)")
                ]
                assert median == row["median_acquisitions"]


def test_the_champion_stands_beside_untrained_and_classical_on_the_test_session(
    finished: Finished,
) -> None:
    test = json.loads((finished.run / "test.json").read_text())
    success, acquisitions = finished.figures["report/test.png"].axes
    rows = test["rows"]
    assert [label.get_text().split("\n")[0] for label in success.get_xticklabels()] == [
        row["label"] for row in rows
    ]
    assert rows[0]["label"] == "champion" and rows[1]["label"] == "untrained"
    heights = [bar.get_height() for bar in success.patches]
    np.testing.assert_allclose(heights, [100 * r["successes"] / r["scenarios"] for r in rows])
    (bars,) = success.containers[-1:]  # the error bars, over the bars
    ends = np.array([segment[:, 1] for segment in bars.lines[2][0].get_segments()])
    np.testing.assert_allclose(
        ends, [100 * np.array(wilson(r["successes"], r["scenarios"])) for r in rows]
    )
    assert [bar.get_height() for bar in acquisitions.patches] == [
        row["median_acquisitions"] for row in rows
    ]
    assert "seed 2000000" in finished.figures["report/test.png"].texts[0].get_text()
    markdown = (finished.run / "report.md").read_text()
    test_section = markdown[markdown.index("## Test session") : markdown.index("## Lineage")]
    assert "](report/test.png)" in test_section


def test_every_validation_point_carries_its_wilson_interval(finished: Finished) -> None:
    rows = read_csv(finished.run / "metrics" / "evaluations.csv")
    (axes,) = finished.figures["report/evaluations.png"].axes
    series = errorbars(axes)
    assert set(series) == {row["member"] for row in rows}
    for member, (iterations, rates, ends) in series.items():
        mine = [row for row in rows if row["member"] == member]
        counts = [(int(row["successes"]), int(row["scenarios"])) for row in mine]
        held = [int(row["iteration"]) for row in mine]
        np.testing.assert_allclose(iterations, held, atol=0.5)  # drawn a little apart
        np.testing.assert_allclose(rates, [100 * k / n for k, n in counts])
        np.testing.assert_allclose(ends, 100 * np.array([wilson(k, n) for k, n in counts]))


def test_the_win_rate_of_the_last_iterations_carries_its_interval(finished: Finished) -> None:
    """The curriculum figure's line: the share of the last 10 iterations' rated matches (on
    an aligner's turn one of its 4 matches starts uniformly, unrated), its band the Wilson
    interval of that count."""
    rows = read_csv(finished.run / "metrics" / "iterations.csv")
    rated = [3 if row["learner"] == row["aligner"] else 4 for row in rows]
    wins = [round(float(row["success_rate"]) * n) for row, n in zip(rows, rated, strict=True)]
    (axes,) = finished.figures["report/curriculum.png"].axes
    (line,) = [line for line in axes.get_lines() if "last 10 iterations" in line.get_label()]
    assert line.get_ydata()[-1] == pytest.approx(sum(wins[-10:]) / sum(rated[-10:]))
    (band,) = axes.collections
    edge = band.get_paths()[0].vertices[:, 1]
    for bound in wilson(sum(wins[-10:]), sum(rated[-10:])):
        assert np.isclose(edge, bound).any()


def test_own_env_steps_worked_out_by_hand() -> None:
    # Iteration 1: a plays m (a's turn, one of 4 matches uniform: m chose 3 starts), 10
    # images; 2: a@1 (a snapshot) plays m (m's turn), 6 images; 3: a plays m2, 8 images.
    # After iteration 2, a-pbt2 copies a.
    iterations = pd.DataFrame(
        {
            "iteration": [1, 2, 3],
            "env_steps": [10, 16, 24],
            "aligner": ["a", "a@1", "a"],
            "misaligner": ["m", "m", "m2"],
            "learner": ["a", "m", "a"],
            "matches": [4, 4, 4],
        }
    )
    lineage = pd.DataFrame({"iteration": [2], "member": ["a-pbt2"], "parent": ["a"]})
    np.testing.assert_array_equal(rated_matches(iterations, 0.25), [3, 4, 3])
    steps = member_env_steps(iterations, lineage, ["a", "m", "m2", "b"], uniform_starts=0.25)
    assert set(steps) == {"a", "m", "m2", "b", "a-pbt2"}  # no snapshot: it learns nothing
    np.testing.assert_array_equal(steps["a"][0], [10, 16, 24])
    np.testing.assert_array_equal(steps["a"][1], [10, 10, 18])
    np.testing.assert_array_equal(steps["m"][1], [3, 7, 7])
    np.testing.assert_array_equal(steps["m2"][1], [0, 0, 3])
    np.testing.assert_array_equal(steps["b"][1], [0, 0, 0])  # on the roster, never played
    np.testing.assert_array_equal(steps["a-pbt2"][0], [16, 24])
    np.testing.assert_array_equal(steps["a-pbt2"][1], [10, 10])

    def metrics(league_steps: list[int]) -> RunMetrics:
        table = pd.DataFrame({"env_steps": league_steps, "success": [1] * len(league_steps)})
        return RunMetrics(Path("run"), table, table, table.iloc[:0], "metrics/members/a")

    sessions = pd.DataFrame({"env_steps": [16]})
    # A row of an iteration iterations.csv does not hold yet (a kill between the two writes)
    # is left out.
    moved = on_own_env_steps(metrics([10, 24, 30]), sessions, steps["a"])
    assert list(moved.episodes["env_steps"]) == [10, 18]
    assert list(moved.evaluations["env_steps"]) == [10]
    with pytest.raises(ReportError, match=r"members/a/updates\.csv: a row at an env step no"):
        on_own_env_steps(metrics([12]), sessions, steps["a"])

"""What a new user met reading a league: `alignrl league status` and `alignrl leaderboard`
silent for many seconds (status built the whole league, members and backend, to print a few
numbers; the leaderboard drew every league figure again at each call), the ratings figure's
legend over the curves and its snapshot marks piled at the right edge, and a payoff figure
mostly grey."""

from __future__ import annotations

import contextlib
import io
import json
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import create_league, write_league
from matplotlib.figure import Figure
from matplotlib.text import Text

from alignrl.cli import main
from alignrl.league import report as league_report
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.report_figures import member_colours, payoff_figure, payoff_grid
from alignrl.league.report_figures import ratings_figure as draw_ratings
from alignrl.league.standings import leaderboard, read_status

SCHEDULE = {
    "iterations": 6,
    "matches": 4,
    "snapshot_every": 2,
    "pbt_every": 100,
    "evaluate_every": 3,
    "eval_scenarios": 2,
    "checkpoint_every": 3,
}
# A curriculum that moves: the status must report the level the league resumes at.
CURRICULUM = {"enabled": True, "level": 0.3, "step": 0.2, "window": 2, "raise_at": 0.01}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny league played to its end (snapshots, validation sessions, a moving curriculum)."""
    root = tmp_path_factory.mktemp("league")
    league = create_league(
        write_league(root, schedule=SCHEDULE, curriculum={**CURRICULUM, "lower_at": 0.0}),
        root / "runs",
    )
    league.run(progress=False)
    league.close()
    return root / "runs" / "tiny"


def test_status_reads_what_resume_restores(run: Path) -> None:
    from alignrl.league.loop import League

    league = League.resume(run, read_only=True)
    status = read_status(run)
    assert status is not None
    assert (status.iteration, status.env_steps) == (league.iteration, league.env_steps)
    assert status.complexity == league.backend.complexity
    for team in ("aligner", "misaligner"):
        assert status.members[team] == league.pool.active(team)
        assert status.snapshots[team] == [s.id for s in league.pool.snapshots(team)]
        assert status.snapshots[team]  # the schedule froze some
    assert status.best == league.best and status.best
    league.close()


def test_status_loads_no_member(run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from alignrl.agents.agent import Agent

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("league status loaded a member")

    monkeypatch.setattr(Agent, "load", refuse)
    monkeypatch.setattr(Agent, "__init__", refuse)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["league", "status", str(run), "--json"]) == 0
    payload = json.loads(out.getvalue())
    assert payload["iteration"] == SCHEDULE["iterations"]
    assert set(payload["members"]) == {"aligner", "misaligner"}


def test_a_league_figure_drawn_from_the_same_data_is_not_drawn_again(
    run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from alignrl.league.loop import League

    league = League.resume(run, read_only=True)
    rows = leaderboard(league)
    league.close()
    league_report.write_league_report(run, rows)
    first = {path.name: path.read_bytes() for path in (run / "report").glob("*.png")}
    assert {"ratings.png", "payoff.png", "curriculum.png"} <= set(first)
    drawn: list[str] = []
    save = league_report.save_png
    monkeypatch.setattr(
        league_report, "save_png", lambda figure, path, *rest: drawn.append(path.name)
    )
    league_report.write_league_report(run, rows)
    assert drawn == []  # nothing changed: every league figure kept as it was
    again = {path.name: path.read_bytes() for path in (run / "report").glob("*.png")}
    assert again == first
    (run / "report" / "payoff.png").unlink()  # a missing one is drawn again, alone
    monkeypatch.setattr(league_report, "save_png", save)
    league_report.write_league_report(run, rows)
    assert (run / "report" / "payoff.png").read_bytes() == first["payoff.png"]


# --- the figures ---------------------------------------------------------------------------


def _ratings() -> tuple[Ratings, dict[str, str]]:
    """Two aligners and a misaligner over 12 iterations, each frozen at 3, 6 and 9: the
    snapshots of the aligner that never plays all end at one rating, as do those of the
    misaligner."""
    ratings = Ratings()
    ratings.pin("hyperbola", 25.0)
    for player in ("a", "b", "m"):
        ratings.add(player)
    for iteration in range(1, 13):
        ratings.update("a", "m", [1.0, 0.0, 1.0])
        if iteration % 3 == 0 and iteration < 12:
            for player in ("a", "b", "m"):
                ratings.add(f"{player}@{iteration}", ratings.rating(player))
        ratings.record(iteration)
    return ratings, {"a": "aligner", "b": "aligner", "m": "misaligner"}


def _drawn(figure: Figure) -> Any:
    figure.canvas.draw()
    return figure.canvas.get_renderer()


def test_the_ratings_legend_is_beside_the_axes_and_the_marks_do_not_overlap() -> None:
    ratings, teams = _ratings()
    figure = draw_ratings(ratings, teams, {}, member_colours(teams))
    renderer = _drawn(figure)
    for axes in figure.axes:
        box = axes.get_window_extent(renderer)
        legend = axes.get_legend().get_window_extent(renderer)
        assert legend.x0 >= box.x1  # beside the axes, over no curve
        marks = [text for text in axes.texts if text.get_text().startswith("@")]
        assert len(marks) >= 3
        # the text alone (an Annotation's own extent takes in its leader line too)
        extents = [Text.get_window_extent(mark, renderer) for mark in marks]
        for one, other in combinations(extents, 2):
            assert not one.overlaps(other)
        for extent in extents:  # inside the axes, not on the legend
            assert extent.x1 <= box.x1 + 1 and extent.x1 < legend.x0
    b_marks = {t.get_text() for t in figure.axes[0].texts}
    assert {"@3", "@6", "@9"} <= b_marks


def test_the_payoff_figure_counts_the_pairs_that_met_and_hatches_the_others() -> None:
    ratings, teams = _ratings()
    payoff = PayoffTable()
    payoff.add("a", "m", 8, 5.0)
    payoff.add("b", "m@3", 4, 1.0)
    payoff.add("a@3", "m@6", 4, 2.0)
    grid = payoff_grid(payoff, ratings)
    figure = payoff_figure(grid, member_colours(teams))
    axes = figure.axes[0]
    assert axes.get_title() == "Payoff table: 3 of 9 pairs met (hatched: never)"
    (image,) = axes.images
    assert image.cmap.get_bad()[3] == 0.0  # a pair that never met has no colour of its own
    hatched = [patch for patch in axes.patches if patch.get_hatch()]
    assert len(hatched) == 1 and hatched[0].get_zorder() < image.get_zorder()
    assert np.isnan(grid.win_rates).sum() == 6

"""The figures of a league report (alignrl.league.report), and what they show as plain data.

`rating_histories`, `payoff_grid` and `member_teams` turn the league's ratings, payoff table
and rosters into arrays and mappings (tested by hand); `ratings_figure`, `payoff_figure`,
`curriculum_figure` and `evaluations_figure` draw them. Ratings are Elo points; a win rate is
the share of matches an aligner aligned within spec; iterations are league iterations.
Matplotlib is imported only inside functions (alignrl.plots draws on the Agg canvas).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from alignrl.league.matchmaking import SNAPSHOT_MARK, TEAMS
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.plots import ReportError, new_figure, rolling_mean

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "LEAGUE_FIGURES",
    "PayoffGrid",
    "curriculum_figure",
    "designs_figure",
    "evaluations_figure",
    "member_teams",
    "payoff_figure",
    "payoff_grid",
    "rating_histories",
    "ratings_figure",
    "team_of",
]

ITERATION_WINDOW = 10  # iterations per point of the smoothed win rate
LEGEND_INSIDE_MAX = 6  # a legend with more entries goes beside the axes, not over the lines
ITERATION_LABEL = "league iteration"


# The league's own figures, in the order of the report, with heading and caption.
LEAGUE_FIGURES: dict[str, tuple[str, str]] = {
    "ratings.png": (
        "Elo ratings",
        "Every player's Elo rating after each iteration, one panel per team. Active members "
        "are solid lines, members replaced by population-based training thin ones, snapshots "
        "dashed in the colour of their member (a snapshot starts at its member's rating).",
    ),
    "payoff.png": (
        "Payoff table",
        "The aligner's win rate against each misaligner, with the matches they played in "
        "brackets; grey where the two never met. Rows are aligners, columns misaligners, each "
        "best rated first, snapshots included.",
    ),
    "curriculum.png": (
        "Curriculum and win rate",
        "The misalignment window (complexity, as a share of the knob interval) at the start of "
        "each iteration, and the share of the iteration's matches its aligner won (points; "
        f"the line is the mean of the last {ITERATION_WINDOW} iterations).",
    ),
    "evaluations.png": (
        "Held-out evaluations",
        "Successes per 100 held-out scenarios of the aligners evaluated at each evaluation "
        "session (the best rated ones at the time).",
    ),
    "designs.png": (
        "Where the designers put the column",
        "For each parameter the designing misaligners choose, the share of the matches of "
        "each tenth of the league (columns) whose column lay in each tenth of the family's "
        "range (rows, 0 its low end, 1 its high end, on a log scale where the box draws "
        "log-uniformly): a uniform designer fills every row alike, one that collapses "
        "darkens a single row.",
    ),
}
DESIGN_COLUMNS = ("iteration", "aligner", "misaligner", "match", "aligner_payoff", "success")
DESIGN_BINS = 10


# --- what the figures show, as plain data -----------------------------------------------


def rating_histories(ratings: Ratings) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per player, in order of first appearance: the iterations its rating was recorded at,
    and those ratings."""
    rows: dict[str, list[tuple[int, float]]] = {}
    for iteration, player, rating in ratings.history:
        rows.setdefault(player, []).append((iteration, rating))
    return {
        player: (np.array([i for i, _ in points]), np.array([r for _, r in points]))
        for player, points in rows.items()
    }


@dataclass(frozen=True)
class PayoffGrid:
    """The payoff table of every player that played, each side best rated first."""

    aligners: list[str]  # rows
    misaligners: list[str]  # columns
    win_rates: np.ndarray  # (aligners, misaligners), NaN where the two never played
    matches: np.ndarray  # (aligners, misaligners), matches played


def payoff_grid(payoff: PayoffTable, ratings: Ratings) -> PayoffGrid:
    """Only players that met someone get a row or column: a grid of every snapshot ever
    frozen would be mostly blank."""
    pairs = [(aligner, misaligner) for aligner, misaligner, *_ in payoff.state_dict()["pairs"]]

    def best_first(players: Collection[str]) -> list[str]:
        return [player for player, _ in ratings.ranking(players)]

    aligners = best_first(dict.fromkeys(aligner for aligner, _ in pairs))
    misaligners = best_first(dict.fromkeys(misaligner for _, misaligner in pairs))
    matches = np.array(
        [[payoff.matches(a, m) for m in misaligners] for a in aligners], dtype=int
    ).reshape(len(aligners), len(misaligners))
    return PayoffGrid(aligners, misaligners, payoff.matrix(aligners, misaligners), matches)


def member_teams(rosters: Mapping[str, Sequence[str]], lineage: pd.DataFrame) -> dict[str, str]:
    """The team of every member the league ever had: the rosters' members (team -> ids), and
    each copy made by population-based training (lineage.csv), which joins its parent's."""
    teams = {member: team for team, members in rosters.items() for member in members}
    for member, parent in zip(lineage["member"], lineage["parent"], strict=True):
        if parent not in teams:
            raise ReportError(
                f"metrics/lineage.csv: {member!r} copies {parent!r}, a member of neither "
                "roster nor an earlier copy; is the run directory complete?"
            )
        teams[member] = teams[parent]
    return teams


def team_of(player: str, teams: Mapping[str, str]) -> str:
    """The team of a player: its member's (a snapshot `x@N` is member x's)."""
    member = player.split(SNAPSHOT_MARK)[0]
    if member not in teams:
        raise ReportError(
            f"{player!r} was rated but is in neither roster (aligners.yaml, misaligners.yaml) "
            "nor metrics/lineage.csv; is the run directory complete?"
        )
    return teams[member]


# --- figures --------------------------------------------------------------------------


def _label_iterations(axes: Axes, title: str, y_label: str) -> None:
    from matplotlib.ticker import MaxNLocator

    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_title(title)
    axes.set_xlabel(ITERATION_LABEL)
    axes.set_ylabel(y_label)
    axes.grid(True, alpha=0.3)


def _legend(axes: Axes, handles: list[Any] | None = None) -> bool:
    """A legend inside the axes, or beside them when it is long; True if beside."""
    entries = len(handles if handles is not None else axes.get_legend_handles_labels()[0])
    beside = entries > LEGEND_INSIDE_MAX
    options: dict[str, Any] = (
        {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0), "ncols": 1 + entries // 25}
        if beside
        else {"loc": "best"}
    )
    axes.legend(handles=handles, fontsize="small", **options)
    return beside


def ratings_figure(
    ratings: Ratings, teams: Mapping[str, str], replaced: Mapping[str, int]
) -> Figure:
    """`replaced`: the iteration each replaced member left the league, where its line ends
    (the ratings keep recording it, unchanged)."""
    from matplotlib import colormaps
    from matplotlib.lines import Line2D

    histories = rating_histories(ratings)
    figure, panels = new_figure(len(TEAMS))
    beside = False
    for axes, team in zip(panels, TEAMS, strict=True):
        players = [player for player in histories if team_of(player, teams) == team]
        members = list(dict.fromkeys(player.split(SNAPSHOT_MARK)[0] for player in players))
        palette = colormaps["tab10" if len(members) <= 10 else "tab20"]
        colours = {member: palette(index % palette.N) for index, member in enumerate(members)}
        handles: list[Any] = []
        for player in players:
            iterations, values = histories[player]
            member = player.split(SNAPSHOT_MARK)[0]
            if player != member:
                axes.plot(iterations, values, "--", color=colours[member], lw=0.9, alpha=0.8)
                continue
            retired = player in replaced
            if retired:
                kept = iterations <= replaced[player]
                iterations, values = iterations[kept], values[kept]
            (line,) = axes.plot(
                iterations,
                values,
                color=colours[member],
                lw=1.0 if retired else 1.8,
                alpha=0.5 if retired else 1.0,
                label=f"{player} (replaced)" if retired else player,
            )
            handles.append(line)
        if len(players) > len(handles):
            handles.append(Line2D([], [], color="grey", ls="--", lw=0.9, label="snapshots"))
        _label_iterations(axes, f"{team.capitalize()}s", "Elo rating")
        beside |= _legend(axes, handles)
    if beside:
        figure.set_size_inches(8.5, figure.get_size_inches()[1])
    return figure


def payoff_figure(grid: PayoffGrid) -> Figure:
    """A heatmap of the aligners' win rates with the numbers in the cells; the cells and
    their text shrink as the grid grows."""
    from matplotlib import colormaps

    rows, columns = grid.win_rates.shape
    figure, (axes,) = new_figure()
    figure.set_size_inches(max(4.8, 2.6 + 0.8 * columns), max(3.2, 1.8 + 0.5 * rows))
    colormap = colormaps["RdBu"].with_extremes(bad="#d9d9d9")  # never played: grey
    image = axes.imshow(
        np.ma.masked_invalid(grid.win_rates), cmap=colormap, vmin=0.0, vmax=1.0, aspect="auto"
    )
    font_size = max(5.0, min(9.0, 80.0 / max(rows, columns)))
    for (row, column), rate in np.ndenumerate(grid.win_rates):
        if np.isnan(rate):
            continue
        axes.text(
            column,
            row,
            f"{rate:.2f}\n({grid.matches[row, column]})",
            ha="center",
            va="center",
            fontsize=font_size,
            color="white" if abs(rate - 0.5) > 0.3 else "black",  # readable on dark cells
        )
    axes.set_xticks(range(columns), grid.misaligners, rotation=40, ha="right")
    axes.set_yticks(range(rows), grid.aligners)
    axes.set_xlabel("misaligner")
    axes.set_ylabel("aligner")
    axes.set_title(LEAGUE_FIGURES["payoff.png"][0])
    figure.colorbar(image, ax=axes, label="aligner win rate")
    return figure


def curriculum_figure(iterations: pd.DataFrame) -> Figure:
    """Complexity and win rate share one axis: both are shares, and the curriculum raises or
    lowers the complexity by the aligners' successes, so the two are read together."""
    figure, (axes,) = new_figure()
    x = iterations["iteration"]
    axes.plot(
        x,
        iterations["complexity"],
        drawstyle="steps-post",
        lw=1.8,
        label="complexity (share of knob interval)",
    )
    (points,) = axes.plot(
        x, iterations["success_rate"], ".", alpha=0.35, label="aligner win rate, each iteration"
    )
    axes.plot(
        x,
        rolling_mean(iterations["success_rate"], ITERATION_WINDOW),
        color=points.get_color(),
        label=f"aligner win rate, last {ITERATION_WINDOW} iterations",
    )
    axes.set_ylim(-0.03, 1.05)
    _label_iterations(axes, LEAGUE_FIGURES["curriculum.png"][0], "share")
    _legend(axes)
    return figure


def evaluations_figure(evaluations: pd.DataFrame) -> Figure:
    figure, (axes,) = new_figure()
    for member, rows in evaluations.groupby("member", sort=False):
        axes.plot(
            rows["iteration"], 100.0 * rows["successes"] / rows["scenarios"], "o-", label=member
        )
    axes.set_ylim(-3, 103)
    _label_iterations(axes, LEAGUE_FIGURES["evaluations.png"][0], "successes per 100 scenarios")
    if _legend(axes):
        figure.set_size_inches(8.5, figure.get_size_inches()[1])
    return figure


def designs_figure(designs: pd.DataFrame) -> Figure:
    """One panel per design parameter: the share of each tenth of the league's matches whose
    column lay in each tenth of the parameter's range (metrics/designs.csv)."""
    parameters = [name for name in designs.columns if name not in DESIGN_COLUMNS]
    columns = min(5, len(parameters))
    figure, axes = new_figure(len(parameters), columns)
    figure.set_size_inches(2.6 * columns, 2.3 * math.ceil(len(parameters) / columns))
    last = max(int(designs["iteration"].max()), 1)
    stage = np.minimum((DESIGN_BINS * (designs["iteration"] - 1)) // last, DESIGN_BINS - 1)
    for panel, name in zip(axes, parameters, strict=True):
        share = np.zeros((DESIGN_BINS, DESIGN_BINS))
        row = np.minimum((designs[name].to_numpy() * DESIGN_BINS).astype(int), DESIGN_BINS - 1)
        np.add.at(share, (row, stage.to_numpy().astype(int)), 1.0)
        share /= np.maximum(share.sum(axis=0, keepdims=True), 1.0)
        panel.imshow(
            share,
            origin="lower",
            aspect="auto",
            extent=(0, last, 0, 1),
            cmap="Blues",
            vmin=0,
            vmax=1,
        )
        panel.set_title(name, fontsize=8)
        panel.tick_params(labelsize=7)
    axes[0].set_ylabel("fraction of range", fontsize=7)
    axes[-1].set_xlabel(ITERATION_LABEL, fontsize=7)
    return figure

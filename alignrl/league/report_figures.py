"""The figures of a league report (alignrl.league.report), and what they show as plain data.

`payoff_grid` and `member_colours` turn the league's payoff table and rosters into arrays
and mappings (tested by hand; the players' teams and rating histories are read by
alignrl.league.report_data);
`ratings_figure`, `payoff_figure`, `learning_figure`, `curriculum_figure`,
`evaluations_figure` and `test_session_figure` draw them. Every figure draws a member in the
one colour `member_colours` gives it, and a snapshot `x@N` in its member's colour, dashed or
lighter; the classical controllers are dark grey, the anchors black. Ratings are openskill's
mu ± sigma (alignrl.league.ratings), anchors fixed; a win rate is the share of matches an
aligner aligned within spec; iterations are league iterations; a member's own env steps are
the transitions it learned from (alignrl.league.report_data.member_env_steps); a success
figure of a session carries its 95 % Wilson interval.
Matplotlib is imported only inside functions (alignrl.plots draws on the Agg canvas).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from alignrl.intervals import success_text
from alignrl.league.matchmaking import SNAPSHOT_MARK, TEAMS
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.report_data import rating_histories, team_of
from alignrl.plots import (
    LEGEND_BESIDE_WIDTH,
    REFERENCE_COLOUR,
    REFERENCE_STYLES,
    Reference,
    draw_acquisition_references,
    draw_acquisitions,
    draw_session_points,
    draw_success,
    draw_success_references,
    new_figure,
    place_legend,
    rolling_mean,
    rolling_success_interval,
    success_points,
)
from alignrl.run_tables import ReportError

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "LEAGUE_FIGURES",
    "MEMBER_STEPS_LABEL",
    "TEST_FIGURE",
    "PayoffGrid",
    "colour_of",
    "curriculum_figure",
    "designs_figure",
    "evaluations_figure",
    "learning_figure",
    "member_colours",
    "payoff_figure",
    "payoff_grid",
    "ratings_figure",
    "test_session_figure",
]

ITERATION_WINDOW = 10  # iterations per point of the smoothed win rate
ITERATION_LABEL = "league iteration"
MEMBER_STEPS_LABEL = "the member's own env steps (transitions it learned from)"
SNAPSHOT_ALPHA = 0.55  # a snapshot is drawn lighter than its member
DODGE = 0.05  # evaluations.png: shift between members, a share of the spacing of sessions
CLASSICAL_BAR = "0.65"  # a classical controller's bar: grey, light enough for its error bar
MARK_GAP = 0.045  # ratings.png: the least gap between two snapshots' marks, a share of the y axis
MARK_MARGIN = 0.09  # ratings.png: room right of the lines for the marks, a share of the x axis
UNPLAYED = "#c8c8c8"  # payoff.png: the hatching of pairs that never met, on white


# The league's own figures, in the order of the report, with heading and caption.
LEAGUE_FIGURES: dict[str, tuple[str, str]] = {
    "ratings.png": (
        "Ratings",
        "Every player's rating (openskill's mean mu) after each iteration, one panel per team, "
        "the band mu ± sigma around each active member, each member in its own colour (the "
        "same in every figure of this report). Active members are solid lines, members "
        "replaced by population-based training thin ones; snapshots are dashed, lighter, in "
        "the colour of their member and marked @N right of their end (moved apart where "
        "they end close together, a thin line leading to each moved mark; a snapshot starts "
        "at its member's rating). The legend is beside the panels. The anchors, classical "
        "controllers of fixed rating that align the same starts as the aligners, are black "
        "lines in the aligners' panel: an aligner above one does better than it on those "
        "starts.",
    ),
    "payoff.png": (
        "Payoff table",
        "The aligner's win rate against each misaligner, with the matches they played in "
        "brackets; hatched, without colour, where the two never met (the title counts the "
        "pairs that met). Only players that met someone have a row or column. Rows are "
        "aligners, columns misaligners, each best rated first, snapshots included (their "
        "names lighter and slanted); each name in its member's colour.",
    ),
    "learning.png": (
        "Aligners' learning curves",
        "Each aligner against its own env steps, the images of the matches it learned from "
        "(not the league's: members play in turns). Left, the share of its last 100 matches "
        "it aligned within spec (line, the band its 95 % Wilson interval) and its validation "
        "sessions (points with their 95 % Wilson intervals); right, its images per match "
        "(mean of the last 100) and its validation sessions' medians. The horizontal lines "
        "are the classical controllers on the test session (its scenarios, not the "
        "validation sessions'): where the aligners stand against no learning.",
    ),
    "curriculum.png": (
        "Curriculum and win rate",
        "The misalignment window (complexity, as a share of the knob interval) at the start of "
        "each iteration, and the share of the iteration's rated matches its aligner won "
        f"(points; the line is the share of the rated matches of the last {ITERATION_WINDOW} "
        "iterations, the band its 95 % Wilson interval).",
    ),
    "evaluations.png": (
        "Validation sessions",
        "Successes per 100 held-out scenarios of the validation sessions (the seed that "
        "chooses the best members and the champion) of the aligners judged at each (the best "
        "rated ones at the time), with their 95 % Wilson intervals, against league iterations "
        "(members judged at the same iteration drawn a little apart). "
        "The horizontal lines are the classical controllers on the test session (other "
        "scenarios of the same held-out set), with their intervals in the legend.",
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
# Drawn in the report's test session section, not among the figures.
TEST_FIGURE = (
    "test.png",
    "Test session",
    "The champion beside the same member untrained and the classical controllers, on the "
    "same scenarios of the test session, which chose nothing: successes per 100 with their "
    "95 % Wilson intervals (left), median acquisitions with the 90th percentile marked "
    "(right). The champion is in its member's colour, untrained lighter and hatched, the "
    "classical controllers grey.",
)
DESIGN_COLUMNS = ("iteration", "aligner", "misaligner", "match", "aligner_payoff", "success")
DESIGN_BINS = 10


# --- what the figures show, as plain data -----------------------------------------------


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


def member_colours(teams: Mapping[str, str]) -> dict[str, str]:
    """One colour (hex) per member the league ever had, in the order of `teams` (the
    rosters, then the copies as they were made), so that a member has the same colour in
    every figure and in every report of the run. Matplotlib's tab10 for up to 9 members,
    tab20 beyond, without their greys (grey is the classical controllers'); past 18 members
    the colours repeat."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    greys = (7,) if len(teams) <= 9 else (14, 15)
    palette = colormaps["tab10" if len(teams) <= 9 else "tab20"].colors
    colours = [to_hex(colour) for index, colour in enumerate(palette) if index not in greys]
    return {member: colours[index % len(colours)] for index, member in enumerate(teams)}


def colour_of(player: str, colours: Mapping[str, str]) -> str:
    """The colour of a player: its member's (a snapshot `x@N` is drawn in x's)."""
    member = player.split(SNAPSHOT_MARK)[0]
    if member not in colours:
        raise ReportError(f"{player!r} is no member of the league's rosters or lineage")
    return colours[member]


# --- figures --------------------------------------------------------------------------


def _label_iterations(axes: Axes, title: str, y_label: str) -> None:
    from matplotlib.ticker import MaxNLocator

    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_title(title)
    axes.set_xlabel(ITERATION_LABEL)
    axes.set_ylabel(y_label)
    axes.grid(True, alpha=0.3)


def _draw_snapshots(
    axes: Axes,
    histories: Mapping[str, tuple[np.ndarray, ...]],
    snapshots: list[str],
    colour: str,
) -> tuple[Any, list[tuple[float, float, str, str]]]:
    """A member's snapshots: dashed and lighter in its colour; the legend entry that names
    them all, and the mark @N of each at its line's end as (x, y, text, colour), placed by
    `_place_marks` once every line of the panel is drawn."""
    from matplotlib.lines import Line2D

    marks = []
    for snapshot in snapshots:
        iterations, values, _ = histories[snapshot]
        axes.plot(iterations, values, "--", color=colour, lw=0.9, alpha=SNAPSHOT_ALPHA)
        mark = snapshot[snapshot.index(SNAPSHOT_MARK) :]
        marks.append((float(iterations[-1]), float(values[-1]), mark, colour))
    member = snapshots[0].split(SNAPSHOT_MARK)[0]
    marks_named = ", ".join(snapshot[snapshot.index(SNAPSHOT_MARK) :] for snapshot in snapshots)
    label = f"{member} snapshots ({marks_named})"
    handle = Line2D([], [], color=colour, ls="--", lw=0.9, alpha=SNAPSHOT_ALPHA, label=label)
    return handle, marks


def _spread(values: Sequence[float], gap: float, top: float) -> list[float]:
    """`values` (ascending) moved as little as a simple pass can so that neighbours are at
    least `gap` apart: up from the lowest, then down from `top` where they pass it."""
    placed: list[float] = []
    for value in values:
        placed.append(value if not placed else max(value, placed[-1] + gap))
    for index in reversed(range(len(placed))):
        ceiling = top if index == len(placed) - 1 else placed[index + 1] - gap
        placed[index] = min(placed[index], ceiling)
    return placed


def _place_marks(axes: Axes, marks: list[tuple[float, float, str, str]]) -> None:
    """The snapshots' marks right of their lines' ends, in a margin the x axis leaves for
    them, spread apart where their lines end close together (a thin line in the snapshot's
    colour leads to a mark that had to move)."""
    if not marks:
        return
    low, high = axes.get_ylim()
    left, right = axes.get_xlim()
    end = max(x for x, *_ in marks)
    axes.set_xlim(left, max(right, end + MARK_MARGIN * (end - left)))
    gap = MARK_GAP * (high - low)
    ordered = sorted(marks, key=lambda mark: mark[1])
    placed = _spread([y for _, y, _, _ in ordered], gap, high - gap / 2)
    for (x, y, text, colour), at in zip(ordered, placed, strict=True):
        moved = abs(at - y) > gap / 4
        axes.annotate(
            text,
            (x, y),
            xytext=(end + 0.025 * (end - left), at),
            textcoords="data",
            fontsize=6,
            color=colour,
            va="center",
            arrowprops=(
                {"arrowstyle": "-", "color": colour, "lw": 0.5, "alpha": SNAPSHOT_ALPHA}
                if moved
                else None
            ),
        )


def ratings_figure(
    ratings: Ratings,
    teams: Mapping[str, str],
    replaced: Mapping[str, int],
    colours: Mapping[str, str],
) -> Figure:
    """`replaced`: the iteration each replaced member left the league, where its line ends
    (the ratings keep recording it, unchanged); `colours`: member_colours."""
    histories = rating_histories(ratings)
    anchors = set(ratings.anchors)
    figure, panels = new_figure(len(TEAMS))
    for axes, team in zip(panels, TEAMS, strict=True):
        players = [p for p in histories if p not in anchors and team_of(p, teams) == team]
        handles: list[Any] = []
        snapshots: dict[str, list[str]] = {}
        for player in players:
            member = player.split(SNAPSHOT_MARK)[0]
            if player != member:
                snapshots.setdefault(member, []).append(player)
                continue
            iterations, values, spreads = histories[player]
            retired = player in replaced
            if retired:
                kept = iterations <= replaced[player]
                iterations, values, spreads = iterations[kept], values[kept], spreads[kept]
            else:
                band = (values - spreads, values + spreads)
                axes.fill_between(iterations, *band, color=colours[member], alpha=0.12, lw=0)
            (line,) = axes.plot(
                iterations,
                values,
                color=colours[member],
                lw=1.0 if retired else 1.8,
                alpha=0.5 if retired else 1.0,
                label=f"{player} (replaced)" if retired else player,
            )
            handles.append(line)
        marks: list[tuple[float, float, str, str]] = []
        for member, frozen in snapshots.items():
            handle, placed = _draw_snapshots(axes, histories, frozen, colours[member])
            handles.append(handle)
            marks += placed
        if team == TEAMS[0]:  # the anchors rate the aligners
            for index, anchor in enumerate(ratings.anchors):
                style = (":", "-.", "--")[index % 3]
                line = axes.axhline(
                    ratings.rating(anchor).mu,
                    color="black",
                    ls=style,
                    lw=1.2,
                    label=f"{anchor} (anchor)",
                )
                handles.append(line)
        _label_iterations(axes, f"{team.capitalize()}s", "rating (mu)")
        _place_marks(axes, marks)
        # Beside the axes, never over the lines; both panels' legends in the same place.
        axes.legend(
            handles=handles,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            borderaxespad=0.0,
            fontsize="small",
        )
    width, height = figure.get_size_inches()
    figure.set_size_inches(max(width, LEGEND_BESIDE_WIDTH + 1.0), height)
    return figure


def payoff_figure(grid: PayoffGrid, colours: Mapping[str, str]) -> Figure:
    """A heatmap of the aligners' win rates with the numbers in the cells; the cells and
    their text shrink as the grid grows; each name in its member's colour."""
    from matplotlib import colormaps
    from matplotlib.patches import Rectangle

    rows, columns = grid.win_rates.shape
    figure, (axes,) = new_figure()
    figure.set_size_inches(max(4.8, 2.6 + 0.8 * columns), max(3.2, 1.8 + 0.5 * rows))
    # A pair that never met shows the light hatching behind the grid, no colour of its own.
    axes.add_patch(
        Rectangle(
            (-0.5, -0.5),
            columns,
            rows,
            facecolor="white",
            edgecolor=UNPLAYED,
            hatch="////",
            lw=0.0,
            zorder=0,
        )
    )
    colormap = colormaps["RdBu"].with_extremes(bad=(0.0, 0.0, 0.0, 0.0))
    image = axes.imshow(
        np.ma.masked_invalid(grid.win_rates),
        cmap=colormap,
        vmin=0.0,
        vmax=1.0,
        aspect="auto",
        zorder=1,
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
    for label in [*axes.get_xticklabels(), *axes.get_yticklabels()]:
        player = label.get_text()
        label.set_color(colour_of(player, colours))
        if SNAPSHOT_MARK in player:
            label.set_alpha(SNAPSHOT_ALPHA + 0.2)
            label.set_fontstyle("italic")
    axes.set_xlabel("misaligner")
    axes.set_ylabel("aligner")
    met = int(np.count_nonzero(grid.matches))
    axes.set_title(
        f"{LEAGUE_FIGURES['payoff.png'][0]}: {met} of {rows * columns} pairs met (hatched: never)"
    )
    figure.colorbar(image, ax=axes, label="aligner win rate")
    return figure


def learning_figure(
    curves: Mapping[str, tuple[pd.DataFrame, pd.DataFrame]],
    colours: Mapping[str, str],
    references: Sequence[Reference],
) -> Figure:
    """`curves`: per aligner, its matches (episodes.csv) and its validation sessions, both at
    its own env steps (alignrl.league.report_data.on_own_env_steps). One legend below both
    panels: the aligners by colour, what each mark is, the classical controllers."""
    from matplotlib.lines import Line2D

    figure, (success, acquisitions) = new_figure(2, columns=2)
    for member, (episodes, sessions) in curves.items():
        draw_success(success, episodes, sessions, run=member, colour=colours[member])
        draw_acquisitions(acquisitions, episodes, sessions, run=member, colour=colours[member])
    draw_success_references(success, references)
    draw_acquisition_references(acquisitions, references)
    for axes in (success, acquisitions):
        axes.set_xlabel(MEMBER_STEPS_LABEL)
        axes.get_legend().remove()
    grey = "0.45"
    handles = [Line2D([], [], color=colours[member], lw=3, label=member) for member in curves]
    handles += [
        Line2D([], [], color=grey, label="its last 100 matches (band: 95 % interval)"),
        Line2D(
            [],
            [],
            color=grey,
            marker="o",
            ls="none",
            mec="black",
            label="validation sessions (95 % interval; right: median)",
        ),
        Line2D(
            [],
            [],
            color=grey,
            marker="^",
            mfc="none",
            ls="none",
            label="validation sessions' 90th percentile",
        ),
    ]
    handles += [
        Line2D(
            [],
            [],
            color=REFERENCE_COLOUR,
            ls=REFERENCE_STYLES[index % len(REFERENCE_STYLES)],
            label=f"{ref.name} ({ref.session}): {success_text(ref.successes, ref.scenarios)}, "
            f"median {ref.median_acquisitions:g} images",
        )
        for index, ref in enumerate(references)
    ]
    figure.legend(handles=handles, loc="outside lower center", ncols=2, fontsize="small")
    figure.set_size_inches(10.4, 4.0 + 0.12 * len(handles))
    return figure


def curriculum_figure(iterations: pd.DataFrame, rated: ArrayLike) -> Figure:
    """Complexity and win rate share one axis: both are shares, and the curriculum raises or
    lowers the complexity by the aligners' successes, so the two are read together. `rated`:
    each iteration's rated matches, those its success_rate is the share of
    (report_data.rated_matches)."""
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
    rated = np.asarray(rated, dtype=float)
    wins = np.rint(iterations["success_rate"].to_numpy() * rated)
    share = rolling_mean(wins, ITERATION_WINDOW) / rolling_mean(rated, ITERATION_WINDOW)
    low, high = rolling_success_interval(wins, ITERATION_WINDOW, rated)
    colour = points.get_color()
    axes.plot(x, share, color=colour, label=f"aligner win rate, last {ITERATION_WINDOW} iterations")
    axes.fill_between(x, low, high, color=colour, alpha=0.15, lw=0)
    axes.set_ylim(-0.03, 1.05)
    _label_iterations(axes, LEAGUE_FIGURES["curriculum.png"][0], "share")
    place_legend(axes)
    return figure


def evaluations_figure(
    evaluations: pd.DataFrame, colours: Mapping[str, str], references: Sequence[Reference]
) -> Figure:
    """The validation sessions' successes per 100, each with its Wilson interval, and the
    classical controllers of `references` across them."""
    figure, (axes,) = new_figure()
    groups = list(evaluations.groupby("member", sort=False))
    # Members judged at the same iteration side by side, not on top of each other: a small
    # shift each, a share of the iterations between sessions.
    held = np.unique(evaluations["iteration"])
    spacing = float(np.min(np.diff(held))) if len(held) > 1 else 1.0
    for index, (member, rows) in enumerate(groups):
        shift = DODGE * spacing * (index - (len(groups) - 1) / 2)
        colour = colour_of(str(member), colours)
        draw_session_points(
            axes,
            rows["iteration"] + shift,
            rows["successes"],
            rows["scenarios"],
            str(member),
            colour,
            fmt="o-",
            capsize=3,
        )
    axes.set_ylim(-3, 103)
    _label_iterations(axes, LEAGUE_FIGURES["evaluations.png"][0], "successes per 100 scenarios")
    draw_success_references(axes, references)
    place_legend(axes)
    return figure


def test_session_figure(test: Mapping[str, Any], colours: Mapping[str, str]) -> Figure:
    """test.json's rows as bars: successes per 100 with their Wilson intervals, and median
    acquisitions with the 90th percentile marked."""
    rows = test["rows"]
    figure, (success, acquisitions) = new_figure(2, columns=2)
    names = [f"{row['label']}\n{row['member']}" if row["member"] else row["label"] for row in rows]
    colours_of_rows = [
        colour_of(row["member"], colours) if row["member"] else CLASSICAL_BAR for row in rows
    ]
    untrained = [row["label"] == "untrained" for row in rows]
    rates, errors = success_points(
        [row["successes"] for row in rows], [row["scenarios"] for row in rows]
    )
    for axes, values in (
        (success, rates),
        (acquisitions, [r["median_acquisitions"] for r in rows]),
    ):
        bars = axes.bar(range(len(rows)), values, color=colours_of_rows, edgecolor="black", lw=0.6)
        for bar, lighter in zip(bars, untrained, strict=True):
            if lighter:
                bar.set_alpha(0.5)
                bar.set_hatch("//")
        axes.set_xticks(range(len(rows)), names, fontsize="small")
        axes.grid(True, axis="y", alpha=0.3)
    success.errorbar(range(len(rows)), rates, yerr=errors, fmt="none", ecolor="black", capsize=4)
    success.set_ylim(0, 103)
    success.set_ylabel("successes per 100 scenarios (95 % interval)")
    acquisitions.plot(
        range(len(rows)),
        [r["p90_acquisitions"] for r in rows],
        "v",
        color="black",
        label="90th percentile",
    )
    acquisitions.set_ylabel("median acquisitions per alignment")
    acquisitions.legend(fontsize="small")
    figure.suptitle(f"{TEST_FIGURE[1]}: {test['scenarios']} scenarios of seed {test['seed']}")
    figure.set_size_inches(min(14.0, max(9.0, 2.2 * len(rows))), 4.0)
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

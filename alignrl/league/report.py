"""The report of a league run: runs/<name>/report.md and report.html, figures in report/.

It reads what the league leaves in its run directory (the last checkpoint's ratings and payoff
table, the metrics CSVs, the rosters, best/best.json, config.yaml) and writes nothing else.
Ratings are Elo points (ratings.py); an aligner's win rate is its mean score, the share of
matches it aligned within spec. Iterations are league iterations: one batch of matches between
one aligner and one misaligner. Env steps are the image acquisitions of all matches so far.
Each member's learner figures are those of a training run (alignrl/plots.py), drawn from
metrics/members/<id>/. A figure whose data is not there yet (a run killed early) is left out,
and the report says why.
"""

from __future__ import annotations

import html
import json
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np
import yaml

from alignrl.checkpoints import atomic_write_text, load_checkpoint, remove_partial_writes
from alignrl.league.matchmaking import SNAPSHOT_MARK, TEAMS
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.metrics import LINEAGE_COLUMNS
from alignrl.plots import (
    FIGURES,
    ReportError,
    new_figure,
    read_metrics_csv,
    read_metrics_folder,
    rolling_mean,
    save_png,
    write_figures,
)
from alignrl.yaml_io import read_yaml_file

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "LEAGUE_FIGURES",
    "LeagueRun",
    "PayoffGrid",
    "curriculum_figure",
    "evaluations_figure",
    "member_teams",
    "payoff_figure",
    "payoff_grid",
    "rating_histories",
    "ratings_figure",
    "read_league_run",
    "write_league_report",
]

FIGURE_FOLDER = "report"  # beside report.md, so that both documents link it relatively
ITERATION_WINDOW = 10  # iterations per point of the smoothed win rate
LEGEND_INSIDE_MAX = 6  # a legend with more entries goes beside the axes, not over the lines
ITERATION_LABEL = "league iteration"

ITERATION_COLUMNS = ("iteration", "env_steps", "matches", "success_rate", "complexity", "seconds")
EVALUATION_COLUMNS = ("iteration", "member", "successes", "scenarios", "median_acquisitions")
# A misaligner plays one-step episodes logged as its aligners' (loop.py), so of the training
# figures only its losses apply.
MEMBER_FIGURES = {"aligner": tuple(FIGURES), "misaligner": ("losses.png",)}

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
}


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


def _team_of(player: str, teams: Mapping[str, str]) -> str:
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
        players = [player for player in histories if _team_of(player, teams) == team]
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


# --- a document, written as Markdown and as HTML ----------------------------------------
# The report is built once as a list of blocks and rendered twice, so that report.md and
# report.html cannot say different things.


@dataclass(frozen=True)
class Heading:
    level: int
    text: str


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Facts:
    items: list[tuple[str, str]]  # (label, what it is), one bullet each


@dataclass(frozen=True)
class Table:
    header: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class Image:
    title: str
    path: str  # relative to the document


Block = Heading | Paragraph | Facts | Table | Image


def to_markdown(blocks: Sequence[Block]) -> str:
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    lines: list[str] = []
    for block in blocks:
        match block:
            case Heading(level, text):
                lines.append(f"{'#' * level} {text}")
            case Paragraph(text):
                lines.append(text)
            case Facts(items):
                lines += [f"- **{label}:** {value}" for label, value in items]
            case Table(header, rows):
                lines += [
                    "| " + " | ".join(map(cell, header)) + " |",
                    "|" + " --- |" * len(header),
                    *("| " + " | ".join(map(cell, row)) + " |" for row in rows),
                ]
            case Image(title, path):
                lines.append(f"![{title}]({quote(path)})")
        lines.append("")
    return "\n".join(lines)


HTML_STYLE = (
    "body{font-family:sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem}"
    "table{border-collapse:collapse}th,td{border:1px solid #bbb;padding:.2rem .5rem}"
    "th{background:#eee}img{max-width:100%}"
)


def to_html(title: str, blocks: Sequence[Block]) -> str:
    escape = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        f'<head><meta charset="utf-8"><title>{escape(title)}</title>'
        f"<style>{HTML_STYLE}</style></head>",
        "<body>",
    ]
    for block in blocks:
        match block:
            case Heading(level, text):
                parts.append(f"<h{level}>{escape(text)}</h{level}>")
            case Paragraph(text):
                parts.append(f"<p>{escape(text)}</p>")
            case Facts(items):
                parts.append(
                    "<ul>"
                    + "".join(f"<li><b>{escape(k)}:</b> {escape(v)}</li>" for k, v in items)
                    + "</ul>"
                )
            case Table(header, rows):
                head = "".join(f"<th>{escape(text)}</th>" for text in header)
                body = "".join(
                    "<tr>" + "".join(f"<td>{escape(text)}</td>" for text in row) + "</tr>"
                    for row in rows
                )
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            case Image(title, path):
                parts.append(f'<p><img src="{escape(quote(path))}" alt="{escape(title)}"></p>')
    parts += ["</body>", "</html>", ""]
    return "\n".join(parts)


# --- reading the run ------------------------------------------------------------------


@dataclass(frozen=True)
class Checkpoint:
    """What the report takes from the league's last checkpoint."""

    iteration: int
    ratings: Ratings
    payoff: PayoffTable


@dataclass(frozen=True)
class LeagueRun:
    """Everything the report reads from a league's run directory."""

    run_dir: Path
    config: dict[str, Any]  # config.yaml as plain data: only shown
    iterations: pd.DataFrame  # metrics/iterations.csv
    evaluations: pd.DataFrame  # metrics/evaluations.csv
    lineage: pd.DataFrame  # metrics/lineage.csv
    best: list[dict[str, Any]] | None  # best/best.json; None before the first evaluation
    teams: dict[str, str]  # every member ever -> its team
    replaced: dict[str, int]  # replaced member -> the iteration it was replaced at
    checkpoint: Checkpoint | None  # None before the first checkpoint
    warm_starts: dict[str, str] = field(default_factory=dict)  # aligner -> init_from

    def why_empty(self, relative: str) -> str:
        """Why the CSV at `relative` has no rows, for the reader."""
        state = "has no rows yet" if (self.run_dir / relative).exists() else "is missing"
        return f"{relative} {state}"


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = read_yaml_file(path)
    except yaml.YAMLError as error:
        raise ReportError(f"{path}: not valid YAML: {error}") from None
    if not isinstance(data, dict):
        raise ReportError(f"{path}: expected a mapping at the top level")
    return data


def _last_checkpoint(run_dir: Path) -> Checkpoint | None:
    latest = run_dir / "checkpoints" / "LATEST"
    if not latest.exists():
        return None
    state = load_checkpoint(run_dir / "checkpoints" / latest.read_text().strip() / "league.pt")
    if int(state["iteration"]) == 0:
        return None  # the start League.create checkpoints: nothing rated or played yet
    ratings, payoff = Ratings(), PayoffTable()
    ratings.load_state_dict(state["ratings"])
    payoff.load_state_dict(state["payoff"])
    return Checkpoint(int(state["iteration"]), ratings, payoff)


def _best_rows(path: Path) -> list[dict[str, Any]] | None:
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ReportError(f"{path}: not valid JSON ({error})") from None


def read_league_run(run_dir: Path) -> LeagueRun:
    """Read strictly (a CSV cell that is not a number names its file, line and column), but
    a file the league has not written yet is no error: its table has zero rows."""
    if not (run_dir / "config.yaml").exists():
        raise ReportError(
            f"{run_dir} is not a league run (no config.yaml): give runs/<name> as written by "
            "`alignrl league run`"
        )
    metrics = run_dir / "metrics"
    lineage = read_metrics_csv(
        metrics / "lineage.csv", LINEAGE_COLUMNS, text_columns=("member", "parent", "replaced")
    )
    roster_files = {team: _read_yaml(run_dir / f"{team}s.yaml")["members"] for team in TEAMS}
    rosters = {team: [member["id"] for member in members] for team, members in roster_files.items()}
    warm_starts = {
        member["id"]: str(member["init_from"])
        for member in roster_files["aligner"]
        if member.get("init_from")
    }
    return LeagueRun(
        run_dir=run_dir,
        config=_read_yaml(run_dir / "config.yaml"),
        iterations=read_metrics_csv(
            metrics / "iterations.csv",
            ITERATION_COLUMNS,
            text_columns=("aligner", "misaligner", "learner"),
        ),
        evaluations=read_metrics_csv(
            metrics / "evaluations.csv", EVALUATION_COLUMNS, text_columns=("member",)
        ),
        lineage=lineage,
        best=_best_rows(run_dir / "best" / "best.json"),
        teams=member_teams(rosters, lineage),
        replaced={
            member: int(iteration)
            for member, iteration in zip(lineage["replaced"], lineage["iteration"], strict=True)
        },
        checkpoint=_last_checkpoint(run_dir),
        warm_starts=warm_starts,
    )


# --- figure files ---------------------------------------------------------------------


def _league_figures(run: LeagueRun) -> tuple[dict[str, Figure], dict[str, str]]:
    """Every league figure the run allows, and why each other one is left out."""
    built: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    checkpoint = run.checkpoint
    if checkpoint is None:
        skipped["ratings.png"] = skipped["payoff.png"] = "no checkpoint yet (checkpoints/LATEST)"
    else:
        if checkpoint.ratings.history:
            built["ratings.png"] = ratings_figure(checkpoint.ratings, run.teams, run.replaced)
        else:
            skipped["ratings.png"] = "the last checkpoint holds no rated iteration"
        grid = payoff_grid(checkpoint.payoff, checkpoint.ratings)
        if grid.aligners:
            built["payoff.png"] = payoff_figure(grid)
        else:
            skipped["payoff.png"] = "the last checkpoint holds no match"
    if len(run.iterations):
        built["curriculum.png"] = curriculum_figure(run.iterations)
    else:
        skipped["curriculum.png"] = run.why_empty("metrics/iterations.csv")
    if len(run.evaluations):
        built["evaluations.png"] = evaluations_figure(run.evaluations)
    else:
        skipped["evaluations.png"] = run.why_empty("metrics/evaluations.csv")
    return built, skipped


def _members_with_metrics(run_dir: Path, rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Members with a metrics folder: those on the leaderboard in its order, then the
    replaced ones by id."""
    folder = run_dir / "metrics" / "members"
    found = (
        sorted(path.name for path in folder.iterdir() if path.is_dir()) if folder.exists() else []
    )
    ranked = [row["member"] for row in rows if row["member"] in found]
    return ranked + [member for member in found if member not in ranked]


def _write_member_figures(
    run: LeagueRun, rows: Sequence[Mapping[str, Any]], out: Path
) -> tuple[dict[str, list[str]], dict[str, str]]:
    """Each member's training figures into out/members/<id>/: the names written per member,
    and why each figure that applies to the member was left out."""
    written: dict[str, list[str]] = {}
    skipped: dict[str, str] = {}
    for member in _members_with_metrics(run.run_dir, rows):
        folder = f"metrics/members/{member}"
        figures = write_figures(read_metrics_folder(run.run_dir, folder), out / member)
        if not figures.written:
            skipped[f"members/{member}/"] = f"nothing to draw yet: {folder}/ has no rows"
            continue
        written[member] = [path.name for path in figures.written]
        applies = MEMBER_FIGURES[_team_of(member, run.teams)]
        skipped |= {
            f"members/{member}/{name}": why
            for name, why in figures.skipped.items()
            if name in applies
        }
    return written, skipped


# --- the document ---------------------------------------------------------------------


def _duration(seconds: float) -> str:
    minutes, whole_seconds = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    if hours:
        return f"{hours} h {minutes:02d} min"
    if minutes:
        return f"{minutes} min {whole_seconds:02d} s"
    return f"{seconds:.1f} s"


def _per_100(successes: float, scenarios: float) -> str:
    """Successes per 100 scenarios, with the raw count when the session was not 100."""
    rate = f"{100.0 * successes / scenarios:.0f}"
    return rate if scenarios == 100 else f"{rate} ({successes:g}/{scenarios:g})"


def _summary(run: LeagueRun) -> Facts:
    iterations, checkpoint = run.iterations, run.checkpoint
    done = int(iterations["iteration"].iloc[-1]) if len(iterations) else 0
    env_steps = int(iterations["env_steps"].iloc[-1]) if len(iterations) else 0
    planned = (run.config.get("schedule") or {}).get("iterations", "?")
    progress = f"{done} of {planned} planned"
    if checkpoint is None:
        progress += "; no checkpoint yet, so no ratings or payoff table"
    elif checkpoint.iteration != done:  # killed between checkpoints
        progress += (
            "; the leaderboard, ratings and payoff table are those of the last checkpoint, "
            f"at iteration {checkpoint.iteration}"
        )
    facts = [
        ("Run directory", str(run.run_dir)),
        ("Iterations", progress),
        (
            "Env steps",
            f"{env_steps} image acquisitions in {int(iterations['matches'].sum())} matches",
        ),
        (
            "Wall time",
            f"{_duration(float(iterations['seconds'].sum()))} playing and learning "
            "(the iterations' seconds; evaluations and checkpoints not included)",
        ),
    ]
    if run.warm_starts:
        started = "; ".join(f"{member} from {source}" for member, source in run.warm_starts.items())
        facts.append(("Warm starts", f"{started} (init_from: trained before the league)"))
    return Facts(facts)


def _leaderboard_table(rows: Sequence[Mapping[str, Any]]) -> Table:
    def evaluation(row: Mapping[str, Any]) -> str:
        if row["successes"] is None:
            return "-"
        return _per_100(row["successes"], row["scenarios"])

    median = "median_acquisitions"
    return Table(
        [
            "member",
            "team",
            "architecture",
            "learner",
            "rating",
            "held-out successes /100",
            "median acquisitions",
            "parent",
        ],
        [
            [
                row["member"],
                row["team"],
                row["architecture"],
                row["learner"],
                f"{row['rating']:.1f}",
                evaluation(row),
                "-" if row[median] is None else f"{row[median]:g}",
                row["parent"] or "",
            ]
            for row in rows
        ],
    )


def _lineage(run: LeagueRun) -> Block:
    if not len(run.lineage):
        why = run.why_empty("metrics/lineage.csv")
        return Paragraph(f"No member was copied by population-based training ({why}).")
    return Table(
        ["iteration", "member", "parent", "replaced", "learning rate"],
        [
            [
                f"{row.iteration:.0f}",
                row.member,
                row.parent,
                row.replaced,
                f"{row.learning_rate:.3g}",
            ]
            for row in run.lineage.itertuples()
        ],
    )


def _best(run: LeagueRun) -> Block:
    if not run.best:
        return Paragraph("No evaluation session yet (best/best.json is missing).")
    return Table(
        [
            "member",
            "iteration",
            "held-out successes /100",
            "median acquisitions",
            "p90 acquisitions",
            "rating then",
        ],
        [
            [
                row["member"],
                str(row["iteration"]),
                _per_100(row["successes"], row["scenarios"]),
                f"{row['median_acquisitions']:g}",
                f"{row['p90_acquisitions']:.1f}",
                f"{row['rating']:.1f}",
            ]
            for row in run.best
        ],
    )


def _figures(
    run: LeagueRun, league_figures: Collection[str], member_figures: Mapping[str, list[str]]
) -> list[Block]:
    blocks: list[Block] = [Heading(2, "Figures")]
    for name, (title, caption) in LEAGUE_FIGURES.items():
        if name in league_figures:
            blocks += [
                Heading(3, title),
                Paragraph(caption),
                Image(title, f"{FIGURE_FOLDER}/{name}"),
            ]
    if member_figures:
        blocks += [
            Heading(2, "Members"),
            Paragraph(
                "Each member's learner figures, as in a training run's report (seed figs. "
                "6.1.1-6.1.7). The env steps are the whole league's. A misaligner's matches are "
                "logged as its aligners' episodes, so a misaligner has only its losses."
            ),
        ]
    for member, names in member_figures.items():
        team = _team_of(member, run.teams)
        retired = (
            f", replaced at iteration {run.replaced[member]}" if member in run.replaced else ""
        )
        blocks.append(Heading(3, f"{member} ({team}{retired})"))
        for name in names:
            title = FIGURES[name][0]
            path = f"{FIGURE_FOLDER}/members/{member}/{name}"
            blocks += [Heading(4, title), Image(f"{member}: {title}", path)]
    return blocks


def write_league_report(run_dir: str | Path, leaderboard_rows: Sequence[Mapping[str, Any]]) -> Path:
    """Write report.md and report.html into `run_dir` and their figures into
    `run_dir`/report/; return report.md's path. `leaderboard_rows` are those of
    alignrl.league.loop.leaderboard. Every file is replaced atomically, the figures first and
    report.md last, so that neither document ever links a figure not written yet; temporaries
    that a report killed midway left in report/ are removed."""
    run = read_league_run(Path(run_dir))
    out = run.run_dir / FIGURE_FOLDER
    remove_partial_writes(out)
    built, skipped = _league_figures(run)
    for name, figure in built.items():
        save_png(figure, out / name)
    member_figures, member_skipped = _write_member_figures(run, leaderboard_rows, out / "members")

    title = f"League report: {run.config.get('name', run.run_dir.name)}"
    blocks: list[Block] = [
        Heading(1, title),
        _summary(run),
        Heading(2, "Leaderboard"),
        Paragraph(
            "Every active member and kept snapshot, per team, best rated first. "
            f"'x{SNAPSHOT_MARK}N' is member x frozen at iteration N: it plays but never learns. "
            "Held-out successes and median acquisitions are the member's best evaluation "
            "session."
        ),
        _leaderboard_table(leaderboard_rows),
        Heading(2, "Lineage"),
        _lineage(run),
        Heading(2, "Best aligners"),
        _best(run),
        *_figures(run, built, member_figures),
    ]
    if skipped or member_skipped:
        blocks += [Heading(2, "Not plotted"), Facts([*skipped.items(), *member_skipped.items()])]
    markdown = run.run_dir / "report.md"
    atomic_write_text(run.run_dir / "report.html", to_html(title, blocks))
    atomic_write_text(markdown, to_markdown(blocks))
    return markdown

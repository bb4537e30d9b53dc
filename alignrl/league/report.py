"""The report of a league run: runs/<name>/report.md and report.html, figures in report/.

It reads what the league leaves in its run directory (alignrl.league.report_data: the last
checkpoint's ratings and payoff table, the metrics CSVs, the rosters, best/best.json,
config.yaml) and writes nothing else. Ratings are Elo points (ratings.py); an aligner's win
rate is its mean score, the share of matches it aligned within spec. Iterations are league
iterations: one batch of matches between one aligner and one misaligner. Env steps are the
image acquisitions of all matches so far. The league's figures are drawn by
alignrl.league.report_figures; each member's learner figures are those of a training run
(alignrl/plots.py), drawn from metrics/members/<id>/. A figure whose data is not there yet (a
run killed early) is left out, and the report says why. The document is built once as blocks
and written as Markdown and as HTML (alignrl.league.report_document).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.checkpoints import atomic_write_text, remove_partial_writes
from alignrl.league.matchmaking import SNAPSHOT_MARK
from alignrl.league.report_data import LeagueRun, read_league_run
from alignrl.league.report_document import (
    Block,
    Facts,
    Heading,
    Image,
    Paragraph,
    Table,
    to_html,
    to_markdown,
)
from alignrl.league.report_figures import (
    LEAGUE_FIGURES,
    PayoffGrid,
    curriculum_figure,
    designs_figure,
    evaluations_figure,
    member_teams,
    payoff_figure,
    payoff_grid,
    rating_histories,
    ratings_figure,
    team_of,
)
from alignrl.plots import FIGURES, read_metrics_folder, save_png, write_figures

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# The figures, the run's data and the document writers live beside this module; their
# public names are kept importable from here.
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
# A misaligner plays one-step episodes logged as its aligners' (alignrl.league.logs), so of
# the training figures only its losses apply.
MEMBER_FIGURES = {"aligner": tuple(FIGURES), "misaligner": ("losses.png",)}


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
    if run.designs is not None:  # (only a league whose misaligners design the column)
        built["designs.png"] = designs_figure(run.designs)
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
        applies = MEMBER_FIGURES[team_of(member, run.teams)]
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
        team = team_of(member, run.teams)
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

"""The report of a league run: runs/<name>/report.md and report.html, figures in report/.

It reads what the league leaves in its run directory (alignrl.league.report_data: the last
checkpoint's ratings, payoff table and anchors' record, the metrics CSVs, the rosters,
best/best.json, test.json, config.yaml) and writes nothing else. Ratings are openskill's mu ±
sigma (ratings.py), pinned to the anchors; an aligner's win rate is its mean score, the share
of matches it aligned within spec. Every success figure says which session it comes from
(validation sessions choose, the test session reports: alignrl.league.sessions) and carries
its 95 % Wilson interval. Iterations are league iterations: one batch of matches between one
aligner and one misaligner. The league's env steps are the image acquisitions of all matches
so far; a member's own are the transitions it learned from (report_data.member_env_steps),
and its curves are drawn on them. The league's figures are drawn by
alignrl.league.report_figures, every member in one colour throughout; each member's learner
figures are those of a training run (alignrl/plots.py), drawn from metrics/members/<id>/. The
classical controllers of the test session are the reference lines of the success and
acquisitions figures. A figure whose data is not there yet (a run killed early) is left out,
and the report says why. The document is built once as blocks and written as Markdown and as
HTML (alignrl.report_document).
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from alignrl.checkpoints import remove_partial_writes
from alignrl.intervals import success_text
from alignrl.league.matchmaking import SNAPSHOT_MARK
from alignrl.league.report_data import (
    LeagueRun,
    classical_references,
    member_env_steps,
    member_sessions,
    member_teams,
    on_own_env_steps,
    rated_matches,
    rating_histories,
    read_league_run,
    team_of,
)
from alignrl.league.report_figures import (
    LEAGUE_FIGURES,
    MEMBER_STEPS_LABEL,
    TEST_FIGURE,
    PayoffGrid,
    colour_of,
    curriculum_figure,
    designs_figure,
    evaluations_figure,
    learning_figure,
    member_colours,
    payoff_figure,
    payoff_grid,
    ratings_figure,
    test_session_figure,
)
from alignrl.plots import FIGURES, Reference, drawn_from, save_png, write_figures
from alignrl.report_document import Block, Facts, Heading, Image, Paragraph, Table, write_documents
from alignrl.run_tables import RunMetrics, read_metrics_folder

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
    "member_colours",
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


@dataclass(frozen=True)
class _Drawing:
    """What every figure of one report shares: one colour per member, each member's own env
    steps, the classical controllers of the test session."""

    colours: dict[str, str]
    steps: dict[str, tuple[np.ndarray, np.ndarray]]  # report_data.member_env_steps
    references: list[Reference]

    @classmethod
    def of(cls, run: LeagueRun) -> _Drawing:
        copies = set(run.lineage["member"])
        rosters = [member for member in run.teams if member not in copies]
        steps = member_env_steps(run.iterations, run.lineage, rosters, run.uniform_starts)
        return cls(member_colours(run.teams), steps, classical_references(run.test))

    def member_metrics(self, run: LeagueRun, member: str) -> RunMetrics:
        """A member's tables and validation sessions at its own env steps."""
        metrics = read_metrics_folder(run.run_dir, f"metrics/members/{member}")
        return on_own_env_steps(metrics, member_sessions(run, member), self.steps.get(member))


# A league figure as `_league_figures` gives it: what it is drawn from (for its digest: a
# figure drawn from the same is not drawn again), and what draws it.
Maker = tuple[tuple[Any, ...], Callable[[], "Figure"]]


def _league_figures(run: LeagueRun, drawing: _Drawing) -> tuple[dict[str, Maker], dict[str, str]]:
    """Every league figure the run allows, and why each other one is left out."""
    makers: dict[str, Maker] = {}
    skipped: dict[str, str] = {}
    checkpoint, colours, references = run.checkpoint, drawing.colours, drawing.references
    if checkpoint is None:
        skipped["ratings.png"] = skipped["payoff.png"] = "no checkpoint yet (checkpoints/LATEST)"
    else:
        ratings = checkpoint.ratings
        if ratings.history:
            anchors = {anchor: ratings.rating(anchor).mu for anchor in ratings.anchors}
            makers["ratings.png"] = (
                (ratings.history, anchors, run.teams, run.replaced, colours),
                lambda: ratings_figure(ratings, run.teams, run.replaced, colours),
            )
        else:
            skipped["ratings.png"] = "the last checkpoint holds no rated iteration"
        grid = payoff_grid(checkpoint.payoff, ratings)
        if grid.aligners:
            makers["payoff.png"] = ((grid, colours), lambda: payoff_figure(grid, colours))
        else:
            skipped["payoff.png"] = "the last checkpoint holds no match"
    curves = {}
    for member in (m for m, team in run.teams.items() if team == "aligner"):
        if (run.run_dir / "metrics" / "members" / member).is_dir():
            metrics = drawing.member_metrics(run, member)
            if len(metrics.episodes):
                curves[member] = (metrics.episodes, metrics.evaluations)
    if curves:
        makers["learning.png"] = (
            (curves, colours, references),
            lambda: learning_figure(curves, colours, references),
        )
    else:
        skipped["learning.png"] = "no aligner has played a match yet (metrics/members/)"
    if len(run.iterations):
        rated = rated_matches(run.iterations, run.uniform_starts)
        makers["curriculum.png"] = (
            (run.iterations, rated),
            lambda: curriculum_figure(run.iterations, rated),
        )
    else:
        skipped["curriculum.png"] = run.why_empty("metrics/iterations.csv")
    if len(run.evaluations):
        makers["evaluations.png"] = (
            (run.evaluations, colours, references),
            lambda: evaluations_figure(run.evaluations, colours, references),
        )
    else:
        skipped["evaluations.png"] = run.why_empty("metrics/evaluations.csv")
    designs, test = run.designs, run.test
    if designs is not None:  # (only a league whose misaligners design the column)
        makers["designs.png"] = ((designs,), lambda: designs_figure(designs))
    if test is not None:
        makers[TEST_FIGURE[0]] = ((test, colours), lambda: test_session_figure(test, colours))
    return makers, skipped


@functools.cache
def _drawing_code() -> bytes:
    """What draws a league figure besides its data: the modules that draw it and the
    versions of matplotlib and alignrl."""
    import matplotlib

    from alignrl import __version__, intervals, plots
    from alignrl.league import report_figures

    digest = hashlib.blake2b(digest_size=16)
    for module in (__file__, report_figures.__file__, plots.__file__, intervals.__file__):
        digest.update(Path(module).read_bytes())
    digest.update(f"{matplotlib.__version__} {__version__}".encode())
    return digest.digest()


def _digest(name: str, inputs: tuple[Any, ...]) -> str:
    """The digest of a league figure: its name, what it is drawn from (tables, arrays,
    plain values, nested) and the drawing code; kept in its PNG (alignrl.plots.save_png)."""
    import pandas as pd

    digest = hashlib.blake2b(_drawing_code(), digest_size=16)

    def feed(value: Any) -> None:
        digest.update(f"<{type(value).__name__}>".encode())
        if isinstance(value, pd.DataFrame):
            digest.update(repr((list(value.columns), list(map(str, value.dtypes)))).encode())
            digest.update(pd.util.hash_pandas_object(value, index=True).to_numpy().tobytes())
        elif isinstance(value, np.ndarray):
            digest.update(repr((value.dtype.str, value.shape)).encode())
            digest.update(np.ascontiguousarray(value).tobytes())
        elif isinstance(value, Mapping):
            for key, item in value.items():
                feed(key)
                feed(item)
        elif isinstance(value, list | tuple):
            for item in value:
                feed(item)
        elif is_dataclass(value) and not isinstance(value, type):
            feed([getattr(value, field.name) for field in fields(value)])
        else:
            digest.update(repr(value).encode())
        digest.update(b"</>")

    feed((name, inputs))
    return digest.hexdigest()


def _members_with_metrics(run_dir: Path, rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Members with a metrics folder: those on the leaderboard in its order, then the
    replaced ones by id."""
    folder = run_dir / "metrics" / "members"
    found = (
        sorted(path.name for path in folder.iterdir() if path.is_dir()) if folder.exists() else []
    )
    ranked = [row["member"] for row in rows if row["member"] in found]
    return ranked + [member for member in found if member not in ranked]


def _progress(total: int) -> Any:
    """A progress bar of the figures to draw on stderr, where that is a terminal (never in
    a log or a pipe), gone once they are drawn."""
    import sys

    from tqdm import tqdm

    return tqdm(
        total=total,
        desc="drawing the report",
        unit="figure",
        file=sys.stderr,
        leave=False,
        disable=None if total else True,
    )


def _write_member_figures(
    run: LeagueRun,
    drawing: _Drawing,
    members: Sequence[str],
    out: Path,
    done: Callable[[], Any] = lambda: None,
) -> tuple[dict[str, list[str]], dict[str, str]]:
    """Each member's training figures (`members`: _members_with_metrics) into
    out/members/<id>/, in its colour and on its own env steps: the names written per member,
    and why each figure that applies to the member was left out. `done` is called after
    each member."""
    written: dict[str, list[str]] = {}
    skipped: dict[str, str] = {}
    for member in members:
        folder = f"metrics/members/{member}"
        team = team_of(member, run.teams)
        figures = write_figures(
            drawing.member_metrics(run, member),
            out / member,
            colour=colour_of(member, drawing.colours),
            steps_label=MEMBER_STEPS_LABEL,
            references=drawing.references if team == "aligner" else (),
        )
        done()
        if not figures.written:
            skipped[f"members/{member}/"] = f"nothing to draw yet: {folder}/ has no rows"
            continue
        written[member] = [path.name for path in figures.written]
        applies = MEMBER_FIGURES[team]
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


def _sessions(config: Mapping[str, Any]) -> str:
    """Which sessions choose and which reports, with their seeds."""
    from alignrl.league.config import TEST_SEED, VALIDATION_SEED

    sessions = config.get("sessions") or {}
    schedule = config.get("schedule") or {}
    size = schedule.get("eval_scenarios", "?")
    test_size = sessions.get("test_scenarios") or size
    return (
        f"validation sessions of seed {sessions.get('validation_seed', VALIDATION_SEED)} "
        f"({size} held-out scenarios each) choose the best members and the champion; the test "
        f"session of seed {sessions.get('test_seed', TEST_SEED)} ({test_size} scenarios, other "
        "scenarios and starts) reports the champion and chose nothing"
    )


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
    facts.append(("Sessions", _sessions(run.config)))
    if run.warm_starts:
        started = "; ".join(f"{member} from {source}" for member, source in run.warm_starts.items())
        facts.append(("Warm starts", f"{started} (init_from: trained before the league)"))
    return Facts(facts)


def _leaderboard_table(rows: Sequence[Mapping[str, Any]]) -> Table:
    def evaluation(row: Mapping[str, Any]) -> str:
        if row["successes"] is None:
            return "-"
        return success_text(row["successes"], row["scenarios"])

    def rating(row: Mapping[str, Any]) -> str:
        shown = f"{row['rating']:.1f} ± {row['sigma']:.1f}"
        return f"{shown} (fixed)" if row["anchor"] else shown

    median = "median_acquisitions"
    return Table(
        [
            "member",
            "team",
            "architecture",
            "learner",
            "rating (mu ± sigma)",
            "best validation session (95 % interval)",
            "median acquisitions",
            "parent",
        ],
        [
            [
                row["member"],
                row["team"],
                row["architecture"],
                row["learner"],
                rating(row),
                evaluation(row),
                "-" if row[median] is None else f"{row[median]:g}",
                row["parent"] or "",
            ]
            for row in rows
        ],
    )


def _anchors(run: LeagueRun) -> list[Block]:
    if run.checkpoint is None or not run.checkpoint.anchors["anchors"]:
        return []
    records = run.checkpoint.anchors
    blocks: list[Block] = [
        Heading(2, "Anchors"),
        Paragraph(
            "Classical controllers on the leaderboard at a fixed rating: in every rated match "
            "each aligns a twin of the same column from the same start as the aligner, and the "
            "aligner scores 1 where only it meets the spec, 0 where only the anchor does, 1/2 "
            "where both do (where neither does, the narrower final width wins). These matches "
            "move the aligner's rating, never the anchor's, so an aligner rated above an "
            "anchor does better than it on the starts the misaligners chose."
        ),
        Table(
            [
                "anchor",
                "rating",
                "aligned within spec (league matches, 95 % interval)",
                "aligners' mean score against it",
            ],
            [
                [
                    row["anchor"],
                    f"{row['rating']:.1f} (fixed)",
                    success_text(row["successes"], row["matches"]) if row["matches"] else "-",
                    ", ".join(f"{a} {v:.2f}" for a, v in row["aligner_scores"].items()) or "-",
                ]
                for row in records["anchors"]
            ],
        ),
    ]
    if records["unanchored_matches"]:
        blocks.append(
            Paragraph(
                f"{records['unanchored_matches']} rated matches were played without anchors: "
                "their apparatus gives no twin of its column (a real microscope)."
            )
        )
    return blocks


def _test(run: LeagueRun, figures: Collection[str]) -> list[Block]:
    blocks: list[Block] = [Heading(2, "Test session")]
    test = run.test
    if test is None:
        return [*blocks, Paragraph("No test session yet: it runs when the league has finished.")]
    chosen = test["chosen_by"]
    blocks += [
        Paragraph(
            f"The champion, {chosen['member']}, was chosen by the validation sessions (seed "
            f"{chosen['seed']}: {success_text(chosen['successes'], chosen['scenarios'])} at "
            f"iteration {chosen['iteration']}). The test session, {test['scenarios']} held-out "
            f"scenarios of seed {test['seed']} (other scenarios and starts, at iteration "
            f"{test['iteration']}), chose nothing: it reports the champion beside the same "
            "member as it started (untrained) and the classical controllers, all on the same "
            "scenarios from the same starts."
        ),
        Table(
            ["", "member", "successes (95 % interval)", "median acquisitions", "p90 acquisitions"],
            [
                [
                    row["label"],
                    row["member"] or "-",
                    success_text(row["successes"], row["scenarios"]),
                    f"{row['median_acquisitions']:g}",
                    f"{row['p90_acquisitions']:.1f}",
                ]
                for row in test["rows"]
            ],
        ),
    ]
    name, title, caption = TEST_FIGURE
    if name in figures:
        blocks += [Paragraph(caption), Image(title, f"{FIGURE_FOLDER}/{name}")]
    return blocks


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
        return Paragraph("No validation session yet (best/best.json is missing).")
    return Table(
        [
            "member",
            "iteration",
            "validation successes (95 % interval)",
            "median acquisitions",
            "p90 acquisitions",
            "rating then (mu)",
        ],
        [
            [
                row["member"],
                str(row["iteration"]),
                success_text(row["successes"], row["scenarios"]),
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
                "6.1.1-6.1.7), in the member's colour. Their env steps are the member's own, "
                "the transitions it learned from: an aligner's, the images of its matches; a "
                "misaligner's, one step per match whose start it chose; a copy made by "
                "population-based training continues from its parent's count. An aligner's "
                "success and acquisitions figures show its validation sessions and, as "
                "horizontal lines, the classical controllers on the test session. A "
                "misaligner's matches are logged as its aligners' episodes, so a misaligner "
                "has only its losses."
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
    that a report killed midway left in report/ are removed. A figure whose PNG carries the
    digest of the same data and drawing code (`_digest`) is kept as it is, not drawn again
    (as alignrl.plots.write_figures keeps a member's): `alignrl leaderboard` after `league run`
    draws nothing. Where stderr is a terminal, a progress bar counts the figures."""
    run = read_league_run(Path(run_dir))
    out = run.run_dir / FIGURE_FOLDER
    remove_partial_writes(out)
    drawing = _Drawing.of(run)
    built, skipped = _league_figures(run, drawing)
    digests = {name: _digest(name, inputs) for name, (inputs, _) in built.items()}
    stale = [name for name, digest in digests.items() if drawn_from(out / name) != digest]
    members = _members_with_metrics(run.run_dir, leaderboard_rows)
    with _progress(len(stale) + len(members)) as progress:
        for name in stale:  # a figure drawn from the same data is kept as it is
            save_png(built[name][1](), out / name, digests[name])
            progress.update()
        member_figures, member_skipped = _write_member_figures(
            run, drawing, members, out / "members", progress.update
        )

    title = f"League report: {run.config.get('name', run.run_dir.name)}"
    blocks: list[Block] = [
        Heading(1, title),
        _summary(run),
        Heading(2, "Leaderboard"),
        Paragraph(
            "Every active member, kept snapshot and anchor, per team, best first by the "
            "rating's ordinal mu - 3 sigma (openskill ratings: mu the skill, sigma how unsure "
            f"it is). 'x{SNAPSHOT_MARK}N' is member x frozen at iteration N: it plays but never "
            "learns. The successes (with their 95 % Wilson interval) and median acquisitions "
            "are the member's best validation session."
        ),
        _leaderboard_table(leaderboard_rows),
        *_anchors(run),
        *_test(run, built),
        Heading(2, "Lineage"),
        _lineage(run),
        Heading(2, "Best aligners (validation sessions)"),
        _best(run),
        *_figures(run, built, member_figures),
    ]
    if skipped or member_skipped:
        blocks += [Heading(2, "Not plotted"), Facts([*skipped.items(), *member_skipped.items()])]
    markdown, _ = write_documents(run.run_dir / "report", title, blocks)
    return markdown

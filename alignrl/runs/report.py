"""The report of a training run (`alignrl report RUN`): report.md and report.html in
RUN/report/ (or another folder), with the figures of alignrl.plots beside them.

It reads config.yaml and metrics/ (alignrl.run_tables) and writes nothing else. The
validation sessions (metrics/evaluations.csv) chose checkpoints/best.pt; the test session
(metrics/test.csv, another seed, once the run has finished) tested best.pt and chose nothing.
Every success figure carries its 95 % Wilson interval. The document is built once as blocks
and written as Markdown and as HTML (alignrl.report_document), as a league's report is.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from alignrl.intervals import success_text
from alignrl.plots import FIGURES, TrainingFigures, write_figures
from alignrl.report_document import Block, Facts, Heading, Image, Paragraph, Table, write_documents
from alignrl.run_tables import ReportError, RunMetrics, read_run_metrics, read_yaml_mapping

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["RunReport", "write_run_report"]

FINAL_WIDTH = "median final edge width (px)"


@dataclass(frozen=True)
class RunReport:
    """Where report.md and report.html went, and the figures beside them."""

    markdown: Path
    html: Path
    figures: TrainingFigures


def _session_cells(row: pd.Series) -> dict[str, str]:
    """A session's figures as shown (a row of evaluations.csv or test.csv); a blank
    median_final_px (no edges measured) as '-'."""
    final = row["median_final_px"]
    return {
        "aligned (95 % interval)": success_text(row["successes"], row["scenarios"]),
        "median acquisitions": f"{row['median_acquisitions']:g}",
        "p90 acquisitions": f"{row['p90_acquisitions']:.1f}",
        FINAL_WIDTH: "-" if math.isnan(final) else f"{final:.2f}",
        "seconds": f"{row['seconds']:.1f}",
    }


def _session_line(row: pd.Series, where: str) -> str:
    cells = _session_cells(row)
    width = cells[FINAL_WIDTH]
    return (
        f"{cells['aligned (95 % interval)']} aligned {where}, median "
        f"{cells['median acquisitions']} acquisitions (p90 {cells['p90 acquisitions']}), "
        + (
            "no final edge width measured"
            if width == "-"
            else f"median final edge width {width} px"
        )
    )


def _table(rows: list[dict[str, str]]) -> Table:
    return Table(list(rows[0]), [list(cells.values()) for cells in rows])


def _sessions(metrics: RunMetrics) -> tuple[list[tuple[str, str]], list[Block]]:
    """The facts and sections of the validation sessions and the test session."""
    evaluations, test = metrics.evaluations, metrics.test
    facts: list[tuple[str, str]] = []
    blocks: list[Block] = [Heading(2, "Validation sessions")]
    if len(evaluations):
        best = evaluations.iloc[int(np.argmax(evaluations["successes"]))]
        at = "at {:.0f} env steps".format
        facts += [
            (
                "Last validation session",
                _session_line(evaluations.iloc[-1], at(evaluations["env_steps"].iloc[-1])),
            ),
            (
                "Best validation session (kept in checkpoints/best.pt)",
                _session_line(best, at(best["env_steps"])),
            ),
        ]
        blocks += [
            Paragraph(
                "The sessions held during training (metrics/evaluations.csv). They choose: "
                "the learner of the one with most successes (the earliest of equals) is kept "
                "as checkpoints/best.pt."
            ),
            _table(
                [
                    {"env steps": f"{row['env_steps']:.0f}", **_session_cells(row)}
                    for _, row in evaluations.iterrows()
                ]
            ),
        ]
    else:
        facts.append(("Validation sessions", f"none yet ({metrics.why_empty('evaluations')})"))
        blocks.append(Paragraph(f"None yet: {metrics.why_empty('evaluations')}."))
    blocks.append(Heading(2, "Test session"))
    if test is None or not len(test):
        why = metrics.why_empty("test")
        facts.append(("Test session", f"none yet: it runs when the training has finished ({why})"))
        blocks.append(Paragraph(f"None yet: it runs when the training has finished ({why})."))
        return facts, blocks
    last = test.iloc[-1]
    tested = (
        f"on seed {last['seed']:.0f} by best.pt of {last['checkpoint_env_steps']:.0f} env steps"
    )
    facts.append(("Test session", _session_line(last, tested)))
    blocks += [
        Paragraph(
            "Once the run had finished, best.pt aligned the scenarios of another seed than the "
            "validation sessions' (metrics/test.csv). No choice saw them: this is the figure "
            "to report."
        ),
        _table(
            [
                {
                    "seed": f"{row['seed']:.0f}",
                    "best.pt of (env steps)": f"{row['checkpoint_env_steps']:.0f}",
                    **_session_cells(row),
                }
                for _, row in test.iterrows()
            ]
        ),
    ]
    return facts, blocks


def _blocks(
    run_dir: Path, config: dict[str, Any], metrics: RunMetrics, figures: TrainingFigures
) -> tuple[str, list[Block]]:
    learner = config.get("learner") or {}
    budget = config.get("budget") or {}
    updates, episodes, evaluations = metrics.updates, metrics.episodes, metrics.evaluations
    env_steps = max(
        (int(table["env_steps"].max()) for table in (updates, episodes, evaluations) if len(table)),
        default=0,
    )
    gradient_updates = int(updates["updates"].iloc[-1]) if len(updates) else 0

    def apparatus(key: str) -> str:
        arguments = config.get(f"{key}_args") or {}
        return str(config.get(key, "?")) + (f" {json.dumps(arguments)}" if arguments else "")

    title = f"Training report: {config.get('name', run_dir.name)}"
    session_facts, session_blocks = _sessions(metrics)
    blocks: list[Block] = [
        Heading(1, title),
        Facts(
            [
                ("Run directory", str(run_dir)),
                (
                    "Learner",
                    f"{learner.get('algorithm', '?')}, encoder {learner.get('encoder', '?')}",
                ),
                (
                    "Apparatus",
                    f"trained on {apparatus('apparatus')}, evaluated on "
                    f"{apparatus('eval_apparatus')}",
                ),
                (
                    "Trained",
                    f"{env_steps} env steps of a budget of {budget.get('env_steps', '?')}, "
                    f"{len(episodes)} episodes, {gradient_updates} gradient updates",
                ),
                *session_facts,
            ]
        ),
        *session_blocks,
        Heading(2, "Figures"),
    ]
    for path in figures.written:
        heading, caption = FIGURES[path.name]
        blocks += [Heading(3, heading), Paragraph(caption), Image(heading, path.name)]
    if figures.skipped:
        blocks += [Heading(2, "Not plotted"), Facts(list(figures.skipped.items()))]
    return title, blocks


def _not_a_league(run_dir: Path) -> None:
    """A league run (its config names the two rosters) is refused with the command that
    reports it: its tables are a league's, not a training run's."""
    config = run_dir / "config.yaml"
    if not config.is_file():
        return  # read_run_metrics says what is missing
    data = read_yaml_mapping(config)
    if "aligners" in data and "misaligners" in data:
        raise ReportError(
            f"{run_dir} is a league run: `alignrl report` reports a training run (`alignrl "
            f"train`, `alignrl adapt`); the league's report is written by `alignrl leaderboard "
            f"{run_dir}` into {run_dir / 'report.md'} and report.html beside it (`alignrl "
            "league run` and `league resume` write it too when they end)"
        )


def write_run_report(run_dir: Path, out_dir: Path | None = None) -> RunReport:
    """Write the figures, report.md and report.html of a run into `out_dir` (default
    <run_dir>/report/). Nothing else in the run directory is touched, and every file is
    replaced atomically, the documents last, so that neither links a figure not yet written.
    Temporaries that a report killed midway left in `out_dir` are removed."""
    from alignrl.checkpoints import remove_partial_writes

    run_dir = Path(run_dir)
    out_dir = run_dir / "report" if out_dir is None else Path(out_dir)
    _not_a_league(run_dir)
    remove_partial_writes(out_dir, recursive=False)
    metrics = read_run_metrics(run_dir)
    config = read_yaml_mapping(run_dir / "config.yaml")
    figures = write_figures(metrics, out_dir)
    title, blocks = _blocks(run_dir, config, metrics, figures)
    markdown, page = write_documents(out_dir / "report", title, blocks)
    return RunReport(markdown=markdown, html=page, figures=figures)

"""Reports of evaluation sessions: the JSON object of `alignrl evaluate --json` (keys documented
in docs/evaluation.md and kept stable), a side-by-side text table, and a PNG of the
trajectories. Edge widths in px, knob settings in the knob's units (volts), times in s.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from alignrl.evaluation.session import SessionResult

__all__ = ["plot_trajectories", "session_notes", "session_summary", "summary_table"]


def _rounded(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def session_summary(result: SessionResult, apparatus: str) -> dict[str, Any]:
    """The JSON object of one session (see docs/evaluation.md for every key)."""
    widths = result.final_width_stats()
    errors = result.optimum_error_stats()
    return {
        "controller": result.controller,
        "apparatus": apparatus,
        "knob": result.knob,
        "seed": result.seed,
        "budget": result.budget,
        "scenarios": result.scenarios,
        "successes": result.successes,
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": round(result.p90_acquisitions, 2),
        "budget_exhausted": result.budget_exhausted,
        "final_quality": {
            "median_px": _rounded(widths["median"]),
            "p90_px": _rounded(widths["p90"]),
            "max_px": _rounded(widths["max"]),
            "unmeasured": result.unmeasured,
        },
        "threshold_px": _rounded(result.median_threshold_px),
        "optimum_error_v": None
        if errors is None
        else {
            "median": _rounded(errors["median"]),
            "p90": _rounded(errors["p90"]),
            "max": _rounded(errors["max"]),
        },
        "seconds": round(result.seconds, 3),
    }


def _cell(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def summary_table(results: Sequence[SessionResult]) -> list[str]:
    """One line per controller, aligned columns, for the terminal."""
    header = (
        "controller",
        "successes",
        "acq median",
        "acq p90",
        "width median",
        "width p90",
        "|V-Vopt| median",
        "seconds",
    )
    rows = [header]
    for result in results:
        widths = result.final_width_stats()
        errors = result.optimum_error_stats()
        rows.append(
            (
                result.controller,
                f"{result.successes}/{result.scenarios}",
                f"{result.median_acquisitions:g}",
                f"{result.p90_acquisitions:.1f}",
                _cell(widths["median"]),
                _cell(widths["p90"]),
                _cell(None if errors is None else errors["median"]),
                f"{result.seconds:.1f}",
            )
        )
    sizes = [max(len(row[column]) for row in rows) for column in range(len(header))]
    lines = []
    for number, row in enumerate(rows):
        cells = [row[0].ljust(sizes[0])] + [
            cell.rjust(size) for cell, size in zip(row[1:], sizes[1:], strict=True)
        ]
        lines.append("  ".join(cells).rstrip())
        if number == 0:
            lines.append("  ".join("-" * size for size in sizes))
    return lines


def session_notes(results: Sequence[SessionResult]) -> list[str]:
    """Lines on what the table does not show: spent budgets, verifications without edges."""
    notes = []
    for result in results:
        if result.budget_exhausted:
            notes.append(
                f"{result.controller}: {result.budget_exhausted} alignments spent their whole "
                f"budget of {result.budget} acquisitions and were stopped"
            )
        if result.unmeasured:
            notes.append(
                f"{result.controller}: {result.unmeasured} verification images had no edges "
                "(counted as failures)"
            )
    return notes


def plot_trajectories(result: SessionResult, out: Path, title: str = "") -> None:
    """Two panels: each alignment's knob setting (relative to the optimum where the
    apparatus knows it) and its edge widths, acquisition by acquisition; green alignments
    passed the verification, red ones failed. The threshold is the dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    relative = all(record.optimum is not None for record in result.records)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=100)
    # Failures last, so that their red lines lie on top.
    for record in sorted(result.records, key=lambda record: record.success, reverse=True):
        colour, weight = ("tab:green", 0.7) if record.success else ("tab:red", 1.2)
        offset = record.optimum if relative and record.optimum is not None else 0.0
        steps = range(len(record.trajectory) + 2)  # start, acquisitions, final setting
        settings = [
            record.start - offset,
            *(setting - offset for setting, _ in record.trajectory),
            record.final_setting - offset,
        ]
        left.plot(steps, settings, "-", color=colour, lw=weight, alpha=0.6)
        widths = [width for _, width in record.trajectory]
        shots = [n + 1 for n, width in enumerate(widths) if width is not None]
        measured = [width for width in widths if width is not None]
        if record.final_width_px is not None:
            shots.append(len(widths) + 1)
            measured.append(record.final_width_px)
        right.plot(shots, measured, ".-", color=colour, lw=weight, ms=3, alpha=0.6)
    right.axhline(result.median_threshold_px, color="black", ls="--", lw=1, label="threshold")
    knob = result.knob
    left.set_xlabel("acquisition (0: start, last: where the controller stopped)")
    left.set_ylabel(f"{knob} - optimum (V)" if relative else f"{knob} (V)")
    left.set_title("knob setting")
    right.set_yscale("log")
    right.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 3.0, 5.0)))
    right.yaxis.set_major_formatter(ScalarFormatter())
    right.yaxis.set_minor_formatter(NullFormatter())
    right.set_xlabel("acquisition (last: the verification image)")
    right.set_ylabel("edge width (px)")
    right.set_title(f"{result.successes}/{result.scenarios} aligned")
    right.legend(loc="upper right")
    figure.suptitle(title or f"{result.controller}: {result.scenarios} scenarios")
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    plt.close(figure)

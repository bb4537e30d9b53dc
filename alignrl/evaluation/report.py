"""Reports of evaluation sessions: the JSON object of `alignrl evaluate --json` (keys documented
in docs/evaluation.md and kept stable), a side-by-side text table, and a PNG of the
trajectories. Edge widths and wobble shifts in px, knob settings in the knobs' units (volts,
percent, micrometres), times in s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from alignrl.evaluation.session import ScenarioResult, SessionResult

__all__ = ["plot_trajectories", "session_notes", "session_summary", "summary_table"]


def _rounded(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def session_summary(result: SessionResult, apparatus: str) -> dict[str, Any]:
    """The JSON object of one session (see docs/evaluation.md for every key).

    The focus keys keep their meaning; a session of several knobs has `knob` and
    `optimum_error_v` null (its knobs have different units) and reports per knob in
    `knobs` and `optimum_errors`.
    """
    widths = result.final_width_stats()
    errors = result.optimum_error_stats()
    one_knob = len(result.knobs) == 1
    return {
        "controller": result.controller,
        "apparatus": apparatus,
        "task": result.task.name,
        "knob": result.knob if one_knob else None,
        "knobs": list(result.knobs),
        "seed": result.seed,
        "budget": result.budget,
        "scenarios": result.scenarios,
        "successes": result.successes,
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": round(result.p90_acquisitions, 2),
        "budget_exhausted": result.budget_exhausted,
        "final_quality": {**_rounded_stats(widths), "unmeasured": result.unmeasured},
        "threshold_px": _rounded(result.median_threshold_px),
        "optimum_error_v": None if errors is None else _rounded_stats(errors, suffix=""),
        "optimum_errors": {
            knob: _rounded_stats(stats, suffix="")
            for knob, stats in result.optimum_errors_stats().items()
        }
        or None,
        "final_directional_px": _measure_summary(
            result.final_directional_stats(),
            result.unmeasured_directional,
            "threshold_px",
            result.median_directional_threshold_px,
        ),
        "final_wobble_px": _measure_summary(
            result.final_wobble_stats(),
            result.unmeasured_wobbles,
            "spec_px",
            result.task.wobble_spec_px,
        ),
        "seconds": round(result.seconds, 3),
    }


def _rounded_stats(stats: dict[str, float | None], suffix: str = "_px") -> dict[str, Any]:
    return {f"{name}{suffix}": _rounded(stats[name]) for name in ("median", "p90", "max")}


def _measure_summary(
    stats: dict[str, float | None] | None, unmeasured: int, limit_key: str, limit: float | None
) -> dict[str, Any] | None:
    """A further measure of the verifications: None where the task does not take it."""
    if stats is None:
        return None
    return {**_rounded_stats(stats), "unmeasured": unmeasured, limit_key: _rounded(limit)}


def _cell(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def summary_table(results: Sequence[SessionResult]) -> list[str]:
    """One line per controller, aligned columns, for the terminal. The |V-Vopt| column is
    there where every session aligns one knob; the widest directional width and the wobble
    shift (medians over the verifications) where a session's task measures them."""
    one_knob = all(len(result.knobs) == 1 for result in results)
    directional = any(result.task.directional for result in results)
    wobble = any(result.task.wobble for result in results)
    header = (
        "controller",
        "successes",
        "acq median",
        "acq p90",
        "width median",
        "width p90",
        *(["|V-Vopt| median"] if one_knob else []),
        *(["widest dir. median"] if directional else []),
        *(["wobble median"] if wobble else []),
        "seconds",
    )
    rows = [header]
    for result in results:
        widths = result.final_width_stats()
        errors = result.optimum_error_stats()
        further = []
        if one_knob:
            further.append(_cell(None if errors is None else errors["median"]))
        for measured, stats in (
            (directional, result.final_directional_stats()),
            (wobble, result.final_wobble_stats()),
        ):
            if measured:
                further.append(_cell(None if stats is None else stats["median"]))
        rows.append(
            (
                result.controller,
                f"{result.successes}/{result.scenarios}",
                f"{result.median_acquisitions:g}",
                f"{result.p90_acquisitions:.1f}",
                _cell(widths["median"]),
                _cell(widths["p90"]),
                *further,
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
    """Lines on what the table does not show: spent budgets, verifications without edges,
    without directional widths or whose wobble failed."""
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
        if result.unmeasured_directional > result.unmeasured:
            notes.append(
                f"{result.controller}: {result.unmeasured_directional} verifications had no "
                "directional widths (counted as failures)"
            )
        if result.unmeasured_wobbles:
            notes.append(
                f"{result.controller}: {result.unmeasured_wobbles} verification wobbles failed "
                "(counted as failures)"
            )
    return notes


def plot_trajectories(result: SessionResult, out: Path, title: str = "") -> None:
    """Two panels, acquisition by acquisition; green alignments passed the verification, red
    ones failed. Right: the edge widths, the threshold dashed (wobble frames of a native
    wobble have none). Left, one knob: its setting (relative to the optimum where the
    apparatus knows it). Left, several knobs (different units): where the optima are known,
    the misalignment left, max over the knobs of |setting - optimum| / |start - optimum|
    (1 at the start, 0 aligned); elsewhere the panel says that it cannot be drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    one_knob = len(result.knobs) == 1
    relative = all(record.optima is not None for record in result.records)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=100)
    # Failures last, so that their red lines lie on top.
    for record in sorted(result.records, key=lambda record: record.success, reverse=True):
        colour, weight = ("tab:green", 0.7) if record.success else ("tab:red", 1.2)
        steps = range(len(record.shots) + 2)  # start, acquisitions, final setting
        if one_knob:
            offset = record.optimum if relative and record.optimum is not None else 0.0
            settings = [
                record.start - offset,
                *(setting - offset for setting, _ in record.trajectory),
                record.final_setting - offset,
            ]
            left.plot(steps, settings, "-", color=colour, lw=weight, alpha=0.6)
        elif record.optima is not None and relative:
            left_share = _misalignment_left(record, record.optima)
            left.plot(steps, left_share, "-", color=colour, lw=weight, alpha=0.6)
        widths = [shot.width_px for shot in record.shots]
        shots = [n + 1 for n, width in enumerate(widths) if width is not None]
        measured = [width for width in widths if width is not None]
        if record.final_width_px is not None:
            shots.append(len(widths) + 1)
            measured.append(record.final_width_px)
        right.plot(shots, measured, ".-", color=colour, lw=weight, ms=3, alpha=0.6)
    right.axhline(result.median_threshold_px, color="black", ls="--", lw=1, label="threshold")
    left.set_xlabel("acquisition (0: start, last: where the controller stopped)")
    if one_knob:
        knob = result.knob
        left.set_ylabel(f"{knob} - optimum" if relative else knob)
        left.set_title("knob setting")
    elif relative:
        left.set_ylabel("max |knob - optimum| / |start - optimum|")
        left.set_title(f"misalignment left ({', '.join(result.knobs)})")
    else:
        left.text(0.5, 0.5, "optima unknown", ha="center", va="center", transform=left.transAxes)
        left.set_title("misalignment left")
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


def _misalignment_left(record: ScenarioResult, optima: Mapping[str, float]) -> list[float]:
    """Per step (start, acquisitions, final): the largest share of a knob's misalignment at
    the start that is left (knobs that started aligned do not count)."""
    starts = record.starts
    knobs = [knob for knob in record.knobs if starts[knob] != optima[knob]]

    def left(settings: Mapping[str, float]) -> float:
        return max(
            (abs(settings[k] - optima[k]) / abs(starts[k] - optima[k]) for k in knobs),
            default=0.0,
        )

    return [
        left(starts),
        *(left(shot.settings) for shot in record.shots),
        left(record.final_settings),
    ]

"""Reports of evaluation sessions: the JSON object of `alignrl evaluate --json` (keys documented
in docs/evaluation.md and kept stable), a side-by-side text table, a PNG of the trajectories,
and the aggregate of the same session run at several seeds. Edge widths and wobble shifts in
px, knob settings in the knobs' units (volts, percent, micrometres), times in s.

Every success figure carries its 95 % interval (alignrl.intervals): a count of alignments the
Wilson interval of its rate, an aggregate over seeds the bootstrap interval of the
interquartile mean of the per-seed rates. A figure also says what kind of session it came
from (`SESSION_KINDS`): a *validation* session chose something (a best checkpoint, a champion)
and so flatters what it chose; a *test* session chose nothing. `alignrl evaluate` and
`alignrl baselines` choose nothing: their sessions are test sessions.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from alignrl.evaluation.session import ScenarioResult, SessionResult
from alignrl.intervals import (
    CONFIDENCE,
    bootstrap_interval,
    iqm,
    success_interval,
    success_text,
)

__all__ = [
    "SESSION_KINDS",
    "aggregate_line",
    "aggregate_table",
    "plot_trajectories",
    "seeds_aggregate",
    "session_notes",
    "session_summary",
    "summary_table",
]

# What a session was for, as every `--json`, report and card labels its figures.
SESSION_KINDS = {
    "validation": "a session something was chosen on (a best checkpoint, a champion): its "
    "figure is the best of several tries and flatters what it chose",
    "test": "a session that chose nothing: the figure to report",
}
BOOTSTRAP_METHOD = "percentile bootstrap of the IQM over the seeds (scipy.stats.bootstrap)"


class SeededResult(Protocol):
    """One seed's result, of one apparatus (SessionResult) or a whole set (SetResult)."""

    seed: int

    @property
    def successes(self) -> int: ...

    @property
    def alignments(self) -> int: ...

    def acquisitions(self) -> np.ndarray: ...


def _check_session(session: str) -> str:
    if session not in SESSION_KINDS:
        raise ValueError(f"a session is one of {', '.join(SESSION_KINDS)}, got {session!r}")
    return session


def _rounded(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def session_summary(result: SessionResult, apparatus: str, session: str = "test") -> dict[str, Any]:
    """The JSON object of one session (see docs/evaluation.md for every key), labelled with
    what the session was for (`session`, one of SESSION_KINDS).

    The focus keys keep their meaning; a session of several knobs has `knob` and
    `optimum_error_v` null (its knobs have different units) and reports per knob in
    `knobs` and `optimum_errors`. `success_interval` is the Wilson interval of `successes`.
    """
    widths = result.final_width_stats()
    errors = result.optimum_error_stats()
    one_knob = len(result.knobs) == 1
    return {
        "controller": result.controller,
        "apparatus": apparatus,
        "session": _check_session(session),
        "task": result.task.name,
        "knob": result.knob if one_knob else None,
        "knobs": list(result.knobs),
        "seed": result.seed,
        "budget": result.budget,
        "scenarios": result.scenarios,
        "successes": result.successes,
        "success_interval": success_interval(result.successes, result.scenarios),
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


def summary_table(
    results: Sequence[SessionResult], labels: tuple[str, Sequence[str]] | None = None
) -> list[str]:
    """One line per session, aligned columns, for the terminal; each row is named by its
    controller, or by `labels` (the first column's heading, one name per result: the seeds
    of one controller). The successes carry their 95 % Wilson interval. The |V-Vopt| column
    is there where every session aligns one knob; the widest directional width and the wobble
    shift (medians over the verifications) where a session's task measures them."""
    heading, names = labels or ("controller", [result.controller for result in results])
    if len(names) != len(results):
        raise ValueError(f"summary_table: {len(names)} labels for {len(results)} sessions")
    one_knob = all(len(result.knobs) == 1 for result in results)
    directional = any(result.task.directional for result in results)
    wobble = any(result.task.wobble for result in results)
    header = (
        heading,
        "successes (95 %)",
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
    for name, result in zip(names, results, strict=True):
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
                name,
                success_text(result.successes, result.scenarios),
                f"{result.median_acquisitions:g}",
                f"{result.p90_acquisitions:.1f}",
                _cell(widths["median"]),
                _cell(widths["p90"]),
                *further,
                f"{result.seconds:.1f}",
            )
        )
    return _aligned(rows)


def _aligned(rows: Sequence[Sequence[str]]) -> list[str]:
    """Rows as terminal lines: the first column left-aligned, the others right-aligned, a
    rule of dashes under the header."""
    sizes = [max(len(row[column]) for row in rows) for column in range(len(rows[0]))]
    lines = []
    for number, row in enumerate(rows):
        cells = [row[0].ljust(sizes[0])] + [
            cell.rjust(size) for cell, size in zip(row[1:], sizes[1:], strict=True)
        ]
        lines.append("  ".join(cells).rstrip())
        if number == 0:
            lines.append("  ".join("-" * size for size in sizes))
    return lines


def session_notes(
    results: Sequence[SessionResult], labels: Sequence[str] | None = None
) -> list[str]:
    """Lines on what the table does not show: spent budgets, verifications without edges,
    without directional widths or whose wobble failed. Each names its session by its
    controller, or by `labels` (one per result: "hyperbola, seed 1")."""
    notes = []
    names = labels or [result.controller for result in results]
    for name, result in zip(names, results, strict=True):
        if result.budget_exhausted:
            notes.append(
                f"{name}: {result.budget_exhausted} alignments spent their whole "
                f"budget of {result.budget} acquisitions and were stopped"
            )
        if result.unmeasured:
            notes.append(
                f"{name}: {result.unmeasured} verification images had no edges "
                "(counted as failures)"
            )
        if result.unmeasured_directional > result.unmeasured:
            notes.append(
                f"{name}: {result.unmeasured_directional} verifications had no "
                "directional widths (counted as failures)"
            )
        if result.unmeasured_wobbles:
            notes.append(
                f"{name}: {result.unmeasured_wobbles} verification wobbles failed "
                "(counted as failures)"
            )
    return notes


def seeds_aggregate(results: Sequence[SeededResult]) -> dict[str, Any]:
    """The aggregate of one controller's sessions at several seeds (one result per seed, the
    same scenarios count): the interquartile mean of the per-seed success rates with its
    percentile-bootstrap interval (rliable's aggregate; with fewer than four seeds nothing is
    trimmed and it is the mean), the successes pooled over every alignment with their
    Wilson interval, and the median and 90th percentile of the acquisitions of every
    alignment. Keys in docs/evaluation.md. ValueError for no result or a seed twice."""
    if not results:
        raise ValueError("an aggregate over seeds needs at least one seed's result")
    seeds = [int(result.seed) for result in results]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"an aggregate over seeds takes each seed once, got {seeds}")
    rates = [result.successes / result.alignments for result in results]
    low, high = bootstrap_interval(rates, iqm)
    successes = sum(result.successes for result in results)
    alignments = sum(result.alignments for result in results)
    acquisitions = np.concatenate([result.acquisitions() for result in results])
    return {
        "seeds": seeds,
        "success_rates": rates,
        "success_rate_iqm": iqm(rates),
        "success_rate_iqm_interval": {
            "low": low,
            "high": high,
            "confidence": CONFIDENCE,
            "method": BOOTSTRAP_METHOD,
        },
        "alignments": alignments,
        "successes": successes,
        "success_interval": success_interval(successes, alignments),
        "median_acquisitions": float(np.median(acquisitions)),
        "p90_acquisitions": round(float(np.percentile(acquisitions, 90)), 2),
    }


def _percent(rate: float) -> str:
    return f"{100 * rate:.0f} %"


def _iqm_text(aggregate: Mapping[str, Any]) -> str:
    """`97 % (90-100 %)`: the IQM success rate and its bootstrap interval, whole percent."""
    interval = aggregate["success_rate_iqm_interval"]
    return (
        f"{_percent(aggregate['success_rate_iqm'])} "
        f"({100 * interval['low']:.0f}-{100 * interval['high']:.0f} %)"
    )


def aggregate_line(results: Sequence[SeededResult]) -> str:
    """One controller over its seeds, in a line: the IQM success rate with its bootstrap
    interval, the pooled successes with their Wilson interval, the acquisitions."""
    aggregate = seeds_aggregate(results)
    seeds = ", ".join(str(seed) for seed in aggregate["seeds"])
    interval = aggregate["success_rate_iqm_interval"]
    return (
        f"over seeds {seeds}: IQM success {_percent(aggregate['success_rate_iqm'])}, 95 % "
        f"bootstrap interval {100 * interval['low']:.0f}-{100 * interval['high']:.0f} %; "
        f"pooled {success_text(aggregate['successes'], aggregate['alignments'])}; "
        f"acquisitions median {aggregate['median_acquisitions']:g} "
        f"(p90 {aggregate['p90_acquisitions']:.1f})"
    )


def aggregate_table(controllers: Sequence[tuple[str, Sequence[SeededResult]]]) -> list[str]:
    """One line per controller over its seeds: each seed's successes, the IQM of the
    per-seed success rates with its 95 % bootstrap interval, the pooled successes with their
    95 % Wilson interval, and the median acquisitions of every alignment. Every controller
    must have run the same seeds (ValueError otherwise)."""
    seeds = [result.seed for result in controllers[0][1]]
    rows: list[Sequence[str]] = [
        (
            "controller",
            *(f"seed {seed}" for seed in seeds),
            "IQM success (95 % bootstrap)",
            "pooled successes (95 %)",
            "acq median",
        )
    ]
    for name, results in controllers:
        if [result.seed for result in results] != seeds:
            raise ValueError(f"aggregate_table: {name} ran other seeds than {controllers[0][0]}")
        aggregate = seeds_aggregate(results)
        rows.append(
            (
                name,
                *(success_text(result.successes, result.alignments) for result in results),
                _iqm_text(aggregate),
                success_text(aggregate["successes"], aggregate["alignments"]),
                f"{aggregate['median_acquisitions']:g}",
            )
        )
    return _aligned(rows)


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
    right.set_title(f"{success_text(result.successes, result.scenarios)} aligned (95 % Wilson)")
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

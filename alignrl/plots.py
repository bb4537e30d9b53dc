"""Training figures of one run directory: what `alignrl report RUN` draws, and what a league
report draws for each member.

Reads runs/<name>/metrics/*.csv as alignrl/training.py writes them and draws the seed's
training figures (6.1.1 return, 6.1.2-6.1.7 losses, entropy and α) with the success rate,
acquisitions and curriculum complexity beside them, all against env steps (one env step is
one image acquisition). Every success figure of a session (validation points, the test
session, a classical reference) carries its 95 % Wilson interval, and the training success
curve the interval of its window. Three layers, so that a league report can reuse the lower
two: `draw_*` puts one run on an Axes in one colour (call it again to overlay another run),
`panel_figure` and `losses_figure` build a Figure, `write_figures` writes the PNGs (the
documents around them: alignrl.runs.report, alignrl.league.report). Matplotlib is imported
only inside functions and draws on the Agg canvas, never through pyplot's global state.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from alignrl.intervals import success_text, wilson
from alignrl.run_tables import RunMetrics, update_metric_columns

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "FIGURES",
    "Reference",
    "TrainingFigures",
    "draw_acquisition_references",
    "draw_acquisitions",
    "draw_complexity",
    "draw_return",
    "draw_session_points",
    "draw_success",
    "draw_success_references",
    "draw_update_metric",
    "drawn_from",
    "inputs_digest",
    "losses_figure",
    "new_figure",
    "panel_figure",
    "place_legend",
    "rolling_mean",
    "rolling_success_interval",
    "save_png",
    "success_points",
    "write_figures",
]

EPISODE_WINDOW = 100  # training episodes per point of a curve, as in seed fig. 6.1.1
UPDATE_WINDOW = 10  # rows of updates.csv per smoothed point (SAC logs a row per 50 updates)
DPI = 120
INPUTS_KEY = "alignrl-inputs"  # a PNG's text: the digest of what it was drawn from
ENV_STEPS_LABEL = "env steps (image acquisitions)"
LEGEND_INSIDE_MAX = 6  # a legend with more entries goes beside the axes, not over the lines
LEGEND_BESIDE_WIDTH = 8.5  # inches: a figure with its legend beside widens to at least this


# Title and y-axis label of the updates.csv columns we know; any other column is plotted
# under its own name, so a new learner's metrics need no change here.
UPDATE_METRICS: dict[str, tuple[str, str]] = {
    "policy_loss": ("Policy loss (seed fig. 6.1.2)", "loss"),
    "q1_loss": ("Q1 loss (seed fig. 6.1.3)", "loss"),
    "q2_loss": ("Q2 loss (seed fig. 6.1.4)", "loss"),
    "v_loss": ("V loss (seed fig. 6.1.5)", "loss"),
    "entropy": ("Policy entropy (seed fig. 6.1.6)", "entropy (nats)"),
    "alpha": ("Entropy coefficient α (seed fig. 6.1.7)", "α"),
    "value_loss": ("Value loss", "loss"),
    "approx_kl": ("Approximate KL divergence", "KL (nats)"),
    "clip_fraction": ("Clipped fraction", "share of samples clipped"),
}

# Every figure of a report, in the order of report.md, with its heading and what it shows.
FIGURES: dict[str, tuple[str, str]] = {
    "reward.png": (
        "Training return (seed fig. 6.1.1)",
        f"Episode return averaged over the last {EPISODE_WINDOW} training episodes.",
    ),
    "losses.png": (
        "Learner losses, entropy and α (seed figs. 6.1.2-6.1.7)",
        "One panel per column of metrics/updates.csv: the thin line is each logged row, the "
        f"thick one the mean of the last {UPDATE_WINDOW} rows.",
    ),
    "success.png": (
        "Success rate",
        f"Training episodes that ended within spec, over the last {EPISODE_WINDOW} episodes "
        "(line; the band is its 95 % Wilson interval), and the validation sessions (points) "
        "with their 95 % Wilson intervals. Where the report has them, the test session (a "
        "star at the env steps of the checkpoint it tested) and classical controllers "
        "(horizontal lines, each labelled with the session it comes from).",
    ),
    "acquisitions.png": (
        "Acquisitions per alignment",
        f"Images per training episode, mean of the last {EPISODE_WINDOW} (line); median and "
        "90th percentile of each validation session (points). Where the report has them, the "
        "test session's median (a star) and each classical controller's median (horizontal "
        "lines, labelled with their session).",
    ),
    "complexity.png": (
        "Curriculum complexity",
        "The misalignment window of each training episode, as a share of the knob interval.",
    ),
}


REFERENCE_STYLES = (":", "-.", (0, (5, 2, 1, 2, 1, 2)), (0, (1, 3)))  # one a controller
REFERENCE_COLOUR = "0.25"  # dark grey: no member's colour (alignrl.league.report_figures)


@dataclass(frozen=True)
class Reference:
    """A classical controller's figures on one session, drawn across a learner's success and
    acquisitions plots as a horizontal line: what no learning achieves."""

    name: str  # e.g. "hyperbola"
    session: str  # the session the figures come from, in words ("test session, seed 2000000")
    successes: int
    scenarios: int
    median_acquisitions: float


# --- the maths ----------------------------------------------------------------------------


def rolling_mean(values: ArrayLike, window: int) -> np.ndarray:
    """Mean of each value and the `window - 1` before it. The first points average what there
    is so far, so that a short run still draws a curve from its first episode."""
    if window < 1:
        raise ValueError(f"window must be at least 1, got {window}")
    values = np.asarray(values, dtype=np.float64)
    sums = np.concatenate(([0.0], np.cumsum(values)))
    ends = np.arange(1, len(values) + 1)
    counts = np.minimum(ends, window)
    return (sums[ends] - sums[ends - counts]) / counts


def rolling_success_interval(
    successes: ArrayLike, window: int, trials: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The 95 % Wilson interval (low, high, as rates) of the successes among the trials of the
    last `window` values at each point: `successes` of `trials` each (default one trial a
    value, an episode that succeeded or not: the interval of rolling_mean(successes,
    window))."""
    successes = np.asarray(successes, dtype=np.int64)
    trials = np.ones_like(successes) if trials is None else np.asarray(trials, dtype=np.int64)
    ends = np.arange(1, len(successes) + 1)
    starts = ends - np.minimum(ends, window)

    def in_window(values: np.ndarray) -> list[int]:
        sums = np.concatenate(([0], np.cumsum(values)))
        return (sums[ends] - sums[starts]).tolist()

    pairs = list(zip(in_window(successes), in_window(trials), strict=True))
    bounds = {pair: wilson(*pair) for pair in set(pairs)}  # few distinct pairs: cached
    low_high = np.array([bounds[pair] for pair in pairs], dtype=np.float64).reshape(-1, 2)
    return low_high[:, 0], low_high[:, 1]


def success_points(successes: ArrayLike, scenarios: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Sessions' success figures as Axes.errorbar takes them: the rates in percent, and the
    distances (2, n) from each down and up to the ends of its 95 % Wilson interval."""
    successes = np.asarray(successes).astype(int).reshape(-1)
    scenarios = np.asarray(scenarios).astype(int).reshape(-1)
    rates = 100.0 * successes / scenarios
    pairs = zip(successes.tolist(), scenarios.tolist(), strict=True)
    bounds = 100.0 * np.array([wilson(k, n) for k, n in pairs], dtype=np.float64).reshape(-1, 2)
    return rates, np.vstack([rates - bounds[:, 0], bounds[:, 1] - rates])


# --- one run on an Axes -------------------------------------------------------------------


def _legend(run: str | None, what: str) -> str:
    return what if run is None else f"{run}: {what}"


def place_legend(axes: Axes, handles: list[Any] | None = None) -> bool:
    """A legend inside the axes, or beside them when it is long (the figure then widens);
    True if beside."""
    entries = len(handles if handles is not None else axes.get_legend_handles_labels()[0])
    beside = entries > LEGEND_INSIDE_MAX
    options: dict[str, Any] = (
        {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0), "ncols": 1 + entries // 25}
        if beside
        else {"loc": "best"}
    )
    axes.legend(handles=handles, fontsize="small", **options)
    if beside:
        figure = axes.get_figure()
        width, height = figure.get_size_inches()
        figure.set_size_inches(max(width, LEGEND_BESIDE_WIDTH), height)
    return beside


def _steps_tick(value: float, _position: int) -> str:
    """200000 -> '200k', 1500000 -> '1.5M': six-digit step counts overlap on a shared axis."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def _finish(axes: Axes, title: str, y_label: str) -> None:
    from matplotlib.ticker import FuncFormatter

    axes.set_title(title)
    axes.xaxis.set_major_formatter(FuncFormatter(_steps_tick))
    axes.set_xlabel(ENV_STEPS_LABEL)
    axes.set_ylabel(y_label)
    axes.grid(True, alpha=0.3)


def draw_return(
    axes: Axes, episodes: pd.DataFrame, run: str | None = None, colour: Any = None
) -> None:
    """Seed fig. 6.1.1: the return of the last 100 training episodes."""
    returns = rolling_mean(episodes["return"], EPISODE_WINDOW)
    axes.plot(episodes["env_steps"], returns, color=colour, label=run)
    _finish(axes, FIGURES["reward.png"][0], f"return, mean of last {EPISODE_WINDOW} episodes")


def draw_update_metric(
    axes: Axes, updates: pd.DataFrame, column: str, run: str | None = None, colour: Any = None
) -> None:
    """One column of updates.csv: faint as logged, bold smoothed (the logged values of a
    minibatch loss are too noisy to read a trend from)."""
    (smoothed,) = axes.plot(
        updates["env_steps"],
        rolling_mean(updates[column], UPDATE_WINDOW),
        lw=1.6,
        color=colour,
        label=run,
    )
    axes.plot(updates["env_steps"], updates[column], color=smoothed.get_color(), lw=0.6, alpha=0.35)
    title, y_label = UPDATE_METRICS.get(column, (column, column))
    _finish(axes, title, y_label)


def draw_session_points(
    axes: Axes,
    x: ArrayLike,
    successes: ArrayLike,
    scenarios: ArrayLike,
    label: str,
    colour: Any = None,
    **style: Any,
) -> Any:
    """Sessions' successes per 100 at `x`, each with its 95 % Wilson interval as an error
    bar, in `style` (Axes.errorbar's); returns the colour drawn."""
    rates, errors = success_points(successes, scenarios)
    points = axes.errorbar(x, rates, yerr=errors, color=colour, label=label, **style)
    return points.lines[0].get_color()


def draw_success(
    axes: Axes,
    episodes: pd.DataFrame,
    evaluations: pd.DataFrame,
    run: str | None = None,
    colour: Any = None,
    test: pd.DataFrame | None = None,
) -> None:
    """Training success rate (line, its window's interval a band), validation sessions
    (points) and the test session of `test` (test.csv rows: a star at the env steps of the
    checkpoint it tested), in percent, the sessions with their 95 % Wilson intervals."""
    if len(episodes):
        steps = episodes["env_steps"]
        (line,) = axes.plot(
            steps,
            100.0 * rolling_mean(episodes["success"], EPISODE_WINDOW),
            color=colour,
            label=_legend(run, f"training, last {EPISODE_WINDOW} episodes"),
        )
        colour = line.get_color()
        low, high = rolling_success_interval(episodes["success"], EPISODE_WINDOW)
        axes.fill_between(steps, 100.0 * low, 100.0 * high, color=colour, alpha=0.15, lw=0)
    if len(evaluations):
        colour = draw_session_points(
            axes,
            evaluations["env_steps"],
            evaluations["successes"],
            evaluations["scenarios"],
            _legend(run, "validation sessions (95 % interval)"),
            colour,
            fmt="o",
            markeredgecolor="black",  # visible where the training line passes through it
            capsize=3,
            zorder=3,
        )
    if test is not None and len(test):
        draw_session_points(
            axes,
            test["checkpoint_env_steps"],
            test["successes"],
            test["scenarios"],
            _legend(run, f"test session, seed {int(test['seed'].iloc[0])} (95 % interval)"),
            colour,
            fmt="*",
            markersize=13,
            markeredgecolor="black",
            capsize=4,
            zorder=4,
        )
    axes.set_ylim(-3, 103)
    place_legend(axes)
    _finish(axes, FIGURES["success.png"][0], "alignments within spec (%)")


def draw_acquisitions(
    axes: Axes,
    episodes: pd.DataFrame,
    evaluations: pd.DataFrame,
    run: str | None = None,
    colour: Any = None,
    test: pd.DataFrame | None = None,
) -> None:
    """Images per training episode (line), per validation alignment (median and p90) and the
    test session's median (a star at the env steps of the checkpoint it tested)."""
    if len(episodes):
        (line,) = axes.plot(
            episodes["env_steps"],
            rolling_mean(episodes["acquisitions"], EPISODE_WINDOW),
            color=colour,
            label=_legend(run, f"training, mean of last {EPISODE_WINDOW} episodes"),
        )
        colour = line.get_color()
    if len(evaluations):
        (median,) = axes.plot(
            evaluations["env_steps"],
            evaluations["median_acquisitions"],
            "o",
            color=colour,
            label=_legend(run, "validation median"),
        )
        colour = median.get_color()
        axes.plot(
            evaluations["env_steps"],
            evaluations["p90_acquisitions"],
            "^",
            color=colour,
            mfc="none",
            label=_legend(run, "validation 90th percentile"),
        )
    if test is not None and len(test):
        axes.plot(
            test["checkpoint_env_steps"],
            test["median_acquisitions"],
            "*",
            markersize=13,
            color=colour,
            markeredgecolor="black",
            zorder=4,
            label=_legend(run, "test session median"),
        )
    axes.set_ylim(bottom=0)
    place_legend(axes)
    _finish(axes, FIGURES["acquisitions.png"][0], "acquisitions per alignment (images)")


def draw_complexity(
    axes: Axes, episodes: pd.DataFrame, run: str | None = None, colour: Any = None
) -> None:
    axes.plot(
        episodes["env_steps"],
        episodes["complexity"],
        drawstyle="steps-post",
        color=colour,
        label=run,
    )
    axes.set_ylim(0, 1.05)
    _finish(axes, FIGURES["complexity.png"][0], "misalignment window (share of interval)")


def _reference_lines(
    axes: Axes, references: Sequence[Reference], levels: list[float], labels: list[str]
) -> None:
    for index, (level, label) in enumerate(zip(levels, labels, strict=True)):
        style = REFERENCE_STYLES[index % len(REFERENCE_STYLES)]
        axes.axhline(level, color=REFERENCE_COLOUR, ls=style, lw=1.4, zorder=1.5, label=label)
    if references:
        place_legend(axes)


def draw_success_references(axes: Axes, references: Sequence[Reference]) -> None:
    """Each classical controller's success rate (percent) as a horizontal line, labelled
    with its session, successes and 95 % interval."""
    _reference_lines(
        axes,
        references,
        [100.0 * ref.successes / ref.scenarios for ref in references],
        [
            f"{ref.name} ({ref.session}): {success_text(ref.successes, ref.scenarios)}"
            for ref in references
        ],
    )


def draw_acquisition_references(axes: Axes, references: Sequence[Reference]) -> None:
    """Each classical controller's median acquisitions as a horizontal line."""
    _reference_lines(
        axes,
        references,
        [ref.median_acquisitions for ref in references],
        [f"{ref.name} ({ref.session}): median {ref.median_acquisitions:g}" for ref in references],
    )


# --- figures ------------------------------------------------------------------------------


def new_figure(panels: int = 1, columns: int = 1) -> tuple[Figure, list[Axes]]:
    """A Figure on its own Agg canvas with `panels` Axes in a grid; nothing global is touched,
    so nothing needs closing and no GUI backend can be picked up."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = math.ceil(panels / columns)
    figure = Figure(figsize=(5.2 * columns, 3.6 * rows), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    grid = figure.subplots(rows, columns, squeeze=False)
    axes = list(grid.flat)
    for spare in axes[panels:]:
        spare.remove()
    return figure, axes[:panels]


def panel_figure(draw: Callable[..., None], *tables: pd.DataFrame, **options: Any) -> Figure:
    """A one-panel figure of one `draw_*` function, e.g. panel_figure(draw_return, episodes,
    colour="C1")."""
    figure, (axes,) = new_figure()
    draw(axes, *tables, **options)
    return figure


def losses_figure(updates: pd.DataFrame, colour: Any = None) -> Figure:
    """One panel per metric column, three panels a row."""
    columns = update_metric_columns(updates)
    if not columns:
        raise ValueError("updates has no columns to plot besides env_steps and updates")
    figure, panels = new_figure(len(columns), columns=min(3, len(columns)))
    for axes, column in zip(panels, columns, strict=True):
        draw_update_metric(axes, updates, column, colour=colour)
    return figure


# --- files --------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainingFigures:
    """The PNGs written, and for each figure left out the reason (for the reader)."""

    written: list[Path]
    skipped: dict[str, str]


def save_png(figure: Figure, path: Path, inputs: str | None = None) -> None:
    """Atomically: a report read while it is rewritten shows the old figure or the new one.
    `inputs` (`inputs_digest`) goes into the PNG as the text INPUTS_KEY."""
    from alignrl.checkpoints import atomic_write

    metadata = {INPUTS_KEY: inputs} if inputs is not None else None
    atomic_write(path, lambda handle: figure.savefig(handle, format="png", metadata=metadata))


@functools.cache
def _drawing() -> bytes:
    """What draws a figure besides its inputs: this module and the intervals it draws, and
    the versions of matplotlib and alignrl."""
    import matplotlib

    from alignrl import __version__, intervals

    digest = hashlib.blake2b(digest_size=16)
    for module in (__file__, intervals.__file__):
        digest.update(Path(module).read_bytes())
    digest.update(f"{matplotlib.__version__} {__version__}".encode())
    return digest.digest()


def inputs_digest(metrics: RunMetrics, *drawn_with: Any) -> str:
    """A digest of what a run's figures are drawn from: its metrics tables, the options
    `drawn_with` (colour, labels, references, by their repr) and the drawing code."""
    import pandas as pd

    digest = hashlib.blake2b(_drawing(), digest_size=16)
    for table in (metrics.updates, metrics.episodes, metrics.evaluations, metrics.test):
        if table is None:
            digest.update(b"no table")
            continue
        digest.update(repr((list(table.columns), list(map(str, table.dtypes)))).encode())
        digest.update(pd.util.hash_pandas_object(table, index=True).to_numpy().tobytes())
    digest.update(repr(drawn_with).encode())
    return digest.hexdigest()


def drawn_from(path: Path) -> str | None:
    """The inputs digest a PNG written by `save_png` carries; None for a missing, damaged or
    foreign file."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            image.load()
            found = image.info.get(INPUTS_KEY)
    except (OSError, ValueError, SyntaxError, UnidentifiedImageError):
        return None
    return found if isinstance(found, str) else None


def _figure_makers(
    metrics: RunMetrics, colour: Any, references: Sequence[Reference]
) -> tuple[dict[str, Callable[[], Figure]], dict[str, str]]:
    """What draws each figure the metrics allow (called only for those drawn), and why each
    other one is left out."""
    updates, episodes, evaluations = metrics.updates, metrics.episodes, metrics.evaluations
    makers: dict[str, Callable[[], Figure]] = {}
    skipped: dict[str, str] = {}
    if len(episodes):
        makers["reward.png"] = lambda: panel_figure(draw_return, episodes, colour=colour)
    else:
        skipped["reward.png"] = metrics.why_empty("episodes")
    if not len(updates):
        skipped["losses.png"] = metrics.why_empty("updates")
    elif not update_metric_columns(updates):
        skipped["losses.png"] = "metrics/updates.csv has no columns besides the step counters"
    else:
        makers["losses.png"] = lambda: losses_figure(updates, colour)
    if len(episodes) or len(evaluations):
        sessions = {"colour": colour, "test": metrics.test}

        def with_references(draw: Callable[..., None], mark: Callable[..., None]) -> Figure:
            figure = panel_figure(draw, episodes, evaluations, **sessions)
            mark(figure.axes[0], references)
            return figure

        makers["success.png"] = lambda: with_references(draw_success, draw_success_references)
        makers["acquisitions.png"] = lambda: with_references(
            draw_acquisitions, draw_acquisition_references
        )
    else:
        neither = f"{metrics.why_empty('episodes')} and {metrics.why_empty('evaluations')}"
        skipped["success.png"] = skipped["acquisitions.png"] = neither
    if not len(episodes):
        skipped["complexity.png"] = metrics.why_empty("episodes")
    elif episodes["complexity"].min() == episodes["complexity"].max():
        level = episodes["complexity"].iloc[0]
        skipped["complexity.png"] = f"the complexity was {level:g} in every episode"
    else:
        makers["complexity.png"] = lambda: panel_figure(draw_complexity, episodes, colour=colour)
    return makers, skipped


def write_figures(
    metrics: RunMetrics,
    out_dir: Path,
    colour: Any = None,
    steps_label: str = ENV_STEPS_LABEL,
    references: Sequence[Reference] = (),
) -> TrainingFigures:
    """Write every figure the metrics allow as PNGs into `out_dir` (created if needed): the
    run's curves in `colour` (a league member's own), `steps_label` under the horizontal axes
    (what the env_steps columns count), `references` across the success and acquisitions.
    A PNG there drawn from the same tables and options (its INPUTS_KEY text) is kept as it
    is, not drawn again: a report written again (`alignrl leaderboard` after `alignrl league
    run`) draws only the figures whose tables changed."""
    makers, skipped = _figure_makers(metrics, colour, references)
    inputs = inputs_digest(metrics, colour, steps_label, tuple(references))
    written = []
    for name in FIGURES:
        if name in makers:
            path = out_dir / name
            if drawn_from(path) != inputs:  # else drawn from these very tables already
                figure = makers[name]()
                for axes in figure.axes:
                    axes.set_xlabel(steps_label)
                save_png(figure, path, inputs)
            written.append(path)
    return TrainingFigures(
        written=written, skipped={name: skipped[name] for name in FIGURES if name in skipped}
    )

"""Training figures and the Markdown report of one run directory (`alignrl report RUN`).

Reads runs/<name>/metrics/*.csv as alignrl/training.py writes them and draws the seed's
training figures (6.1.1 return, 6.1.2-6.1.7 losses, entropy and α) with the success rate,
acquisitions and curriculum complexity beside them, all against env steps (one env step is
one image acquisition). Three layers, so that a league leaderboard can reuse the lower two:
`draw_*` puts one run on an Axes (call it again to overlay another run), `panel_figure` and
`losses_figure` build a Figure, `training_figures` and `write_run_report` write files.
Matplotlib is imported only inside functions and draws on the Agg canvas, never through
pyplot's global state.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from alignrl.metrics import EPISODE_COLUMNS, EVALUATION_COLUMNS

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "ReportError",
    "RunMetrics",
    "RunReport",
    "TrainingFigures",
    "draw_acquisitions",
    "draw_complexity",
    "draw_return",
    "draw_success",
    "draw_update_metric",
    "losses_figure",
    "new_figure",
    "panel_figure",
    "read_metrics_csv",
    "read_metrics_folder",
    "read_run_metrics",
    "read_yaml_mapping",
    "rolling_mean",
    "save_png",
    "training_figures",
    "update_metric_columns",
    "write_figures",
    "write_run_report",
]

EPISODE_WINDOW = 100  # training episodes per point of a curve, as in seed fig. 6.1.1
UPDATE_WINDOW = 10  # rows of updates.csv per smoothed point (SAC logs a row per 50 updates)
DPI = 120
ENV_STEPS_LABEL = "env steps (image acquisitions)"

UPDATE_COUNTERS = ("env_steps", "updates")  # the columns of updates.csv that are not plotted

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
        "(line), and held-out evaluation sessions (points).",
    ),
    "acquisitions.png": (
        "Acquisitions per alignment",
        f"Images per training episode, mean of the last {EPISODE_WINDOW} (line); median and "
        "90th percentile of each held-out evaluation session (points).",
    ),
    "complexity.png": (
        "Curriculum complexity",
        "The misalignment window of each training episode, as a share of the knob interval.",
    ),
}


class ReportError(ValueError):
    """A run directory or metrics file that cannot be reported on; the message names it."""


# --- reading a run ------------------------------------------------------------------------


def _number(cell: str, blank_allowed: bool) -> float:
    if cell == "" and blank_allowed:
        return math.nan  # e.g. median_final_px of a session whose images all lacked edges
    try:
        value = float(cell)
    except ValueError:
        raise ValueError(f"{cell!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{cell!r} is not a finite number")
    return value


def read_metrics_csv(
    path: Path,
    required: Sequence[str],
    blank_allowed: Collection[str] = (),
    text_columns: Collection[str] = (),
) -> pd.DataFrame:
    """A metrics CSV as float64 columns, read strictly: every column must hold numbers (blank
    cells only in `blank_allowed`, as NaN), except `text_columns`, kept as strings (the
    member ids of a league's CSVs). A missing or empty file gives zero rows, because a run
    killed before its first update or evaluation is a run, not an error; so is a last line
    without its line break, the row a kill cut short (left out: the resumed run rewrites it)."""
    import pandas as pd

    try:
        text = path.read_text(encoding="utf-8") if path.exists() else ""
        text = text[: text.rfind("\n") + 1]
        header, *rows = csv.reader(io.StringIO(text, newline="")) if text else [[]]
    except (UnicodeDecodeError, csv.Error) as error:
        raise ReportError(f"{path}: not a CSV text file ({error})") from None
    if not header:
        return pd.DataFrame(
            {name: np.empty(0, object if name in text_columns else float) for name in required}
        )
    missing = [name for name in required if name not in header]
    if missing:
        raise ReportError(f"{path}: no column {missing[0]!r} (the header is {','.join(header)})")
    if len(set(header)) < len(header):
        raise ReportError(f"{path}: a column name appears twice in the header")
    values = np.full((len(rows), len(header)), np.nan)
    blank = [name in blank_allowed for name in header]
    numeric = [name not in text_columns for name in header]
    for index, row in enumerate(rows):
        line = index + 2  # the trainer never quotes a line break, so rows and lines agree
        if len(row) != len(header):
            raise ReportError(
                f"{path}, line {line}: {len(row)} fields, the header has {len(header)}"
            )
        for column, cell in enumerate(row):
            if not numeric[column]:
                continue
            try:
                values[index, column] = _number(cell, blank[column])
            except ValueError as problem:
                raise ReportError(
                    f"{path}, line {line}, column {header[column]}: {problem}"
                ) from None
    frame = pd.DataFrame(values, columns=header)
    for column, name in enumerate(header):
        if not numeric[column]:
            frame[name] = [row[column] for row in rows]
    return frame


@dataclass(frozen=True)
class RunMetrics:
    """The three metrics tables of a run, or of a league member; a table whose file is
    missing has zero rows."""

    run_dir: Path
    updates: pd.DataFrame
    episodes: pd.DataFrame
    evaluations: pd.DataFrame
    folder: str = "metrics"  # where the CSVs are, relative to run_dir

    def why_empty(self, table: str) -> str:
        """Why `table` ('updates', 'episodes' or 'evaluations') has no rows, for the reader."""
        path = self.run_dir / self.folder / f"{table}.csv"
        state = "is missing" if not path.exists() else "has no rows yet"
        return f"{self.folder}/{table}.csv {state}"


def _check_run_dir(run_dir: Path) -> None:
    if not run_dir.is_dir():
        raise ReportError(f"run directory {run_dir} does not exist")
    for needed in ("config.yaml", "metrics"):
        if not (run_dir / needed).exists():
            raise ReportError(
                f"{run_dir} is not a run directory (no {needed}): give runs/<name> as "
                "written by `alignrl train`"
            )


def read_metrics_folder(run_dir: Path, folder: str = "metrics") -> RunMetrics:
    """The updates, episodes and evaluations CSVs in run_dir/folder. A training run keeps
    them in metrics/; a league keeps each member's first two in metrics/members/<id>/."""
    metrics = run_dir / folder
    return RunMetrics(
        run_dir=run_dir,
        updates=read_metrics_csv(metrics / "updates.csv", UPDATE_COUNTERS),
        episodes=read_metrics_csv(metrics / "episodes.csv", EPISODE_COLUMNS),
        evaluations=read_metrics_csv(
            metrics / "evaluations.csv", EVALUATION_COLUMNS, blank_allowed={"median_final_px"}
        ),
        folder=folder,
    )


def read_run_metrics(run_dir: Path) -> RunMetrics:
    """The metrics of a run directory, after checking that it is one."""
    _check_run_dir(run_dir)
    return read_metrics_folder(run_dir)


def update_metric_columns(updates: pd.DataFrame) -> list[str]:
    """The columns of updates.csv to plot: all but the step counters, in file order."""
    return [name for name in updates.columns if name not in UPDATE_COUNTERS]


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


# --- one run on an Axes -------------------------------------------------------------------


def _legend(run: str | None, what: str) -> str:
    return what if run is None else f"{run}: {what}"


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


def draw_return(axes: Axes, episodes: pd.DataFrame, run: str | None = None) -> None:
    """Seed fig. 6.1.1: the return of the last 100 training episodes."""
    axes.plot(episodes["env_steps"], rolling_mean(episodes["return"], EPISODE_WINDOW), label=run)
    _finish(axes, FIGURES["reward.png"][0], f"return, mean of last {EPISODE_WINDOW} episodes")


def draw_update_metric(
    axes: Axes, updates: pd.DataFrame, column: str, run: str | None = None
) -> None:
    """One column of updates.csv: faint as logged, bold smoothed (the logged values of a
    minibatch loss are too noisy to read a trend from)."""
    (smoothed,) = axes.plot(
        updates["env_steps"], rolling_mean(updates[column], UPDATE_WINDOW), lw=1.6, label=run
    )
    axes.plot(updates["env_steps"], updates[column], color=smoothed.get_color(), lw=0.6, alpha=0.35)
    title, y_label = UPDATE_METRICS.get(column, (column, column))
    _finish(axes, title, y_label)


def draw_success(
    axes: Axes, episodes: pd.DataFrame, evaluations: pd.DataFrame, run: str | None = None
) -> None:
    """Training success rate (line) and held-out sessions (points), in percent."""
    color = None
    if len(episodes):
        (line,) = axes.plot(
            episodes["env_steps"],
            100.0 * rolling_mean(episodes["success"], EPISODE_WINDOW),
            label=_legend(run, f"training, last {EPISODE_WINDOW} episodes"),
        )
        color = line.get_color()
    if len(evaluations):
        axes.plot(
            evaluations["env_steps"],
            100.0 * evaluations["successes"] / evaluations["scenarios"],
            "o",
            color=color,
            markeredgecolor="black",  # visible where the training line passes through it
            zorder=3,
            label=_legend(run, "held-out evaluation"),
        )
    axes.set_ylim(-3, 103)
    axes.legend(loc="lower right")
    _finish(axes, FIGURES["success.png"][0], "alignments within spec (%)")


def draw_acquisitions(
    axes: Axes, episodes: pd.DataFrame, evaluations: pd.DataFrame, run: str | None = None
) -> None:
    """Images per training episode (line) and per held-out alignment (median and p90)."""
    color = None
    if len(episodes):
        (line,) = axes.plot(
            episodes["env_steps"],
            rolling_mean(episodes["acquisitions"], EPISODE_WINDOW),
            label=_legend(run, f"training, mean of last {EPISODE_WINDOW} episodes"),
        )
        color = line.get_color()
    if len(evaluations):
        (median,) = axes.plot(
            evaluations["env_steps"],
            evaluations["median_acquisitions"],
            "o",
            color=color,
            label=_legend(run, "held-out median"),
        )
        axes.plot(
            evaluations["env_steps"],
            evaluations["p90_acquisitions"],
            "^",
            color=median.get_color(),
            mfc="none",
            label=_legend(run, "held-out 90th percentile"),
        )
    axes.set_ylim(bottom=0)
    axes.legend(loc="upper right")
    _finish(axes, FIGURES["acquisitions.png"][0], "acquisitions per alignment (images)")


def draw_complexity(axes: Axes, episodes: pd.DataFrame, run: str | None = None) -> None:
    axes.plot(episodes["env_steps"], episodes["complexity"], drawstyle="steps-post", label=run)
    axes.set_ylim(0, 1.05)
    _finish(axes, FIGURES["complexity.png"][0], "misalignment window (share of interval)")


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


def panel_figure(draw: Callable[..., None], *tables: pd.DataFrame) -> Figure:
    """A one-panel figure of one `draw_*` function, e.g. panel_figure(draw_return, episodes)."""
    figure, (axes,) = new_figure()
    draw(axes, *tables)
    return figure


def losses_figure(updates: pd.DataFrame) -> Figure:
    """One panel per metric column, three panels a row."""
    columns = update_metric_columns(updates)
    if not columns:
        raise ValueError("updates has no columns to plot besides env_steps and updates")
    figure, panels = new_figure(len(columns), columns=min(3, len(columns)))
    for axes, column in zip(panels, columns, strict=True):
        draw_update_metric(axes, updates, column)
    return figure


# --- files --------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainingFigures:
    """The PNGs written, and for each figure left out the reason (for the reader)."""

    written: list[Path]
    skipped: dict[str, str]


@dataclass(frozen=True)
class RunReport:
    """Where report.md went, and the figures beside it."""

    markdown: Path
    figures: TrainingFigures


def save_png(figure: Figure, path: Path) -> None:
    """Atomically: a report read while it is rewritten shows the old figure or the new one."""
    from alignrl.checkpoints import atomic_write

    atomic_write(path, lambda handle: figure.savefig(handle, format="png"))


def _build_figures(metrics: RunMetrics) -> tuple[dict[str, Figure], dict[str, str]]:
    """Every figure the metrics allow, and why each other one is left out."""
    updates, episodes, evaluations = metrics.updates, metrics.episodes, metrics.evaluations
    built: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    if len(episodes):
        built["reward.png"] = panel_figure(draw_return, episodes)
    else:
        skipped["reward.png"] = metrics.why_empty("episodes")
    if not len(updates):
        skipped["losses.png"] = metrics.why_empty("updates")
    elif not update_metric_columns(updates):
        skipped["losses.png"] = "metrics/updates.csv has no columns besides the step counters"
    else:
        built["losses.png"] = losses_figure(updates)
    if len(episodes) or len(evaluations):
        built["success.png"] = panel_figure(draw_success, episodes, evaluations)
        built["acquisitions.png"] = panel_figure(draw_acquisitions, episodes, evaluations)
    else:
        neither = f"{metrics.why_empty('episodes')} and {metrics.why_empty('evaluations')}"
        skipped["success.png"] = skipped["acquisitions.png"] = neither
    if not len(episodes):
        skipped["complexity.png"] = metrics.why_empty("episodes")
    elif episodes["complexity"].min() == episodes["complexity"].max():
        level = episodes["complexity"].iloc[0]
        skipped["complexity.png"] = f"the complexity was {level:g} in every episode"
    else:
        built["complexity.png"] = panel_figure(draw_complexity, episodes)
    return built, skipped


def write_figures(metrics: RunMetrics, out_dir: Path) -> TrainingFigures:
    """Write every figure the metrics allow as PNGs into `out_dir` (created if needed)."""
    built, skipped = _build_figures(metrics)
    written = []
    for name in FIGURES:
        if name in built:
            save_png(built[name], out_dir / name)
            written.append(out_dir / name)
    return TrainingFigures(
        written=written, skipped={name: skipped[name] for name in FIGURES if name in skipped}
    )


def training_figures(run_dir: Path, out_dir: Path) -> TrainingFigures:
    """Write the training figures of `run_dir` as PNGs into `out_dir` (created if needed)."""
    return write_figures(read_run_metrics(Path(run_dir)), Path(out_dir))


def read_yaml_mapping(path: Path) -> dict[str, Any]:
    """A run's YAML file (config.yaml, a league's rosters) as plain data, for a report: only
    shown, so an older or newer config still reports. Not a mapping is a ReportError."""
    from alignrl.yaml_io import YAMLInputError, read_yaml_file

    try:
        data = read_yaml_file(path)
    except YAMLInputError as error:  # names the file and what is wrong
        raise ReportError(str(error)) from None
    if not isinstance(data, dict):
        raise ReportError(f"{path}: expected a mapping at the top level")
    return data


def _evaluation_cells(row: pd.Series) -> dict[str, str]:
    """One row of evaluations.csv as shown; a blank median_final_px (no edges) as '-'."""
    final = row["median_final_px"]
    return {
        "env steps": f"{row['env_steps']:.0f}",
        "aligned": f"{row['successes']:.0f}/{row['scenarios']:.0f}",
        "median acquisitions": f"{row['median_acquisitions']:g}",
        "p90 acquisitions": f"{row['p90_acquisitions']:.1f}",
        "median final edge width (px)": "-" if math.isnan(final) else f"{final:.2f}",
        "seconds": f"{row['seconds']:.1f}",
    }


def _evaluation_line(row: pd.Series) -> str:
    cells = _evaluation_cells(row)
    width = cells["median final edge width (px)"]
    return (
        f"{cells['aligned']} aligned at {cells['env steps']} env steps, median "
        f"{cells['median acquisitions']} acquisitions (p90 {cells['p90 acquisitions']}), "
        + (
            "no final edge width measured"
            if width == "-"
            else f"median final edge width {width} px"
        )
    )


def _evaluation_table(evaluations: pd.DataFrame) -> list[str]:
    rows = [_evaluation_cells(row) for _, row in evaluations.iterrows()]
    return [
        "| " + " | ".join(rows[0]) + " |",
        "|" + " ---: |" * len(rows[0]),
        *("| " + " | ".join(cells.values()) + " |" for cells in rows),
    ]


def _markdown(
    run_dir: Path, config: dict[str, Any], metrics: RunMetrics, figures: TrainingFigures
) -> str:
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
        return f"`{config.get(key, '?')}`" + (f" {json.dumps(arguments)}" if arguments else "")

    lines = [
        f"# Training report: {config.get('name', run_dir.name)}",
        "",
        f"- **Run directory:** `{run_dir}`",
        f"- **Learner:** {learner.get('algorithm', '?')}, encoder {learner.get('encoder', '?')}",
        f"- **Apparatus:** trained on {apparatus('apparatus')}, evaluated on "
        f"{apparatus('eval_apparatus')}",
        f"- **Trained:** {env_steps} env steps of a budget of {budget.get('env_steps', '?')}, "
        f"{len(episodes)} episodes, {gradient_updates} gradient updates",
    ]
    if len(evaluations):
        best = evaluations.iloc[int(np.argmax(evaluations["successes"]))]
        lines += [
            f"- **Last held-out evaluation:** {_evaluation_line(evaluations.iloc[-1])}",
            f"- **Best held-out evaluation** (kept in checkpoints/best.pt): "
            f"{_evaluation_line(best)}",
            "",
            "## Held-out evaluations",
            "",
            *_evaluation_table(evaluations),
        ]
    else:
        lines.append(f"- **Held-out evaluations:** none yet ({metrics.why_empty('evaluations')})")
    lines += ["", "## Figures"]
    for path in figures.written:
        title, caption = FIGURES[path.name]
        lines += ["", f"### {title}", "", caption, "", f"![{title}]({path.name})"]
    if figures.skipped:
        lines += ["", "## Not plotted", ""]
        lines += [f"- {name}: {why}" for name, why in figures.skipped.items()]
    return "\n".join(lines) + "\n"


def write_run_report(run_dir: Path, out_dir: Path | None = None) -> RunReport:
    """Write the figures and report.md of a run into `out_dir` (default <run_dir>/report/).
    Nothing else in the run directory is touched, and every file is replaced atomically;
    report.md goes last, so that it never links a figure not yet written. Temporaries that a
    report killed midway left in `out_dir` are removed."""
    from alignrl.checkpoints import atomic_write_text, remove_partial_writes

    run_dir = Path(run_dir)
    out_dir = run_dir / "report" if out_dir is None else Path(out_dir)
    remove_partial_writes(out_dir, recursive=False)
    metrics = read_run_metrics(run_dir)
    config = read_yaml_mapping(run_dir / "config.yaml")
    figures = write_figures(metrics, out_dir)
    markdown = out_dir / "report.md"
    atomic_write_text(markdown, _markdown(run_dir, config, metrics, figures))
    return RunReport(markdown=markdown, figures=figures)

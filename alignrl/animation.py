"""One alignment as pictures: frame by frame, the image the apparatus acquired beside the walk
on the focus curve so far, as RGB arrays and as an animated GIF (`alignrl align --gif`,
`alignrl evaluate --gif`, and AlignmentEnv's `render_mode="rgb_array"`).

A frame, left to right:

* the image acquired at that step (`Apparatus.image()`), grey levels on one scale for the
  whole alignment, so that the blur shows. An apparatus with analytic readings (the scenario
  simulator, the synthetic SEM's analytic mode) gives no images: its frames have the curve
  panel alone, and say so;
* the walk: for each knob of the task, every reading so far as (knob setting, measured edge
  width in px, log scale) in the order taken, numbered, the current one ringed; the spec's
  threshold dashed and, where the apparatus knows it (a simulator), the optimum dotted.
  The axes span the knob's interval and every width of the readings given (for a GIF, the
  whole alignment's), so they stand still from frame to frame.

Pure drawing: matplotlib on its own Agg canvas (nothing global), Pillow for the GIF file.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = [
    "Reading",
    "Scene",
    "alignment_frames",
    "alignment_gif",
    "check_gif_path",
    "draw_frame",
    "write_gif",
]

DPI = 80  # a frame of 10 x 4.2 inches is 800 x 336 pixels
FRAME_S = 0.8  # seconds each frame shows in a GIF
LAST_FRAME_S = 3.0  # the last one stays longer: how the alignment ended
WALK_COLOUR, NOW_COLOUR, FAILED_COLOUR = "tab:blue", "tab:orange", "tab:red"


@dataclass(frozen=True)
class Reading:
    """One acquisition: the knob settings it was taken at (instrument units), its edge width
    in px (None: the measurement failed, or a wobble, which measures a shift), the image
    (None: the apparatus gives none), the optimum where the apparatus knows it, and how many
    images it took (a wobble: two, of which `image` is the last)."""

    settings: Mapping[str, float]
    width_px: float | None
    image: np.ndarray | None = None
    optimum: Mapping[str, float] | None = None
    kind: Literal["image", "wobble"] = "image"
    images: int = 1


@dataclass(frozen=True)
class Scene:
    """What every frame of one alignment shares.

    `knobs`: the knobs drawn, each with its interval (the curve panel's x axis).
    `acquisitions`: how many images were the alignment's own; readings after them are the
    verification (the final image a session or `align` judges). None: every reading is
    the alignment's (an env episode). `ending`: how it ended, written on the last frame."""

    knobs: Mapping[str, tuple[float, float]]
    title: str = ""
    threshold_px: float | None = None
    acquisitions: int | None = None
    ending: str | None = None


def check_gif_path(path: str | Path, option: str = "--gif") -> Path:
    """`path` as a GIF file to write, refused (ValueError) before any work where it cannot
    be one: its folder does not exist, it is a folder, or its name does not end in .gif."""
    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"{option} {path}: give a file name ending in .gif")
    if path.is_dir():
        raise ValueError(f"{option} {path}: that is a folder; give a file name ending in .gif")
    folder = path.parent
    if not folder.is_dir():
        raise ValueError(
            f"{option} {path}: the folder {folder} does not exist; create it first, or write "
            "the GIF elsewhere"
        )
    return path


# --- one frame ----------------------------------------------------------------------------


def _label(index: int, readings: Sequence[Reading], scene: Scene) -> str:
    """'acquisition 3 of 7', or 'verification' for a reading after the alignment's own."""
    taken = sum(reading.images for reading in readings[: index + 1])
    if scene.acquisitions is not None and taken > scene.acquisitions:
        return "verification image (not counted)"
    total = f" of {scene.acquisitions}" if scene.acquisitions is not None else ""
    word = "wobble" if readings[index].kind == "wobble" else "acquisition"
    return f"{word} {taken}{total}"


def _reading_text(reading: Reading, knobs: Sequence[str]) -> str:
    settings = ", ".join(
        f"{knob} {reading.settings[knob]:.4g}" for knob in knobs if knob in reading.settings
    )
    if reading.kind == "wobble":
        return f"{settings}: a wobble (two images, no edge width)"
    width = "no edges" if reading.width_px is None else f"edge width {reading.width_px:.2f} px"
    return f"{settings}: {width}"


def _heading(readings: Sequence[Reading], scene: Scene, index: int, with_images: bool) -> list[str]:
    """The lines above frame `index`: the title, the reading, the ending on the last frame."""
    knobs = list(scene.knobs)
    heading = [scene.title] if scene.title else []
    heading.append(f"{_label(index, readings, scene)}: {_reading_text(readings[index], knobs)}")
    if not with_images:
        heading.append("(no images: this apparatus gives readings, not images)")
    if index == len(readings) - 1 and scene.ending:
        heading.append(scene.ending)
    columns = 110 if with_images else 70
    return [wrapped for line in heading for wrapped in textwrap.wrap(line, columns)]


def _width_limits(readings: Sequence[Reading], threshold_px: float | None) -> tuple[float, float]:
    widths = [r.width_px for r in readings if r.width_px is not None and r.width_px > 0]
    if threshold_px is not None and math.isfinite(threshold_px) and threshold_px > 0:
        widths.append(threshold_px)
    if not widths:
        return 1.0, 10.0
    return min(widths) / 1.25, max(widths) * 1.4  # room above for the failed marks


def _image_range(readings: Sequence[Reading]) -> tuple[float, float] | None:
    """One grey scale for every image: the 1st and 99th percentiles over all of them."""
    images = [np.asarray(r.image, dtype=np.float64) for r in readings if r.image is not None]
    if not images:
        return None
    values = np.concatenate([image.ravel() for image in images])
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    low, high = np.percentile(values, [1, 99])
    return float(low), float(max(high, low + 1e-12))


def _draw_image(axes: Axes, reading: Reading, grey: tuple[float, float] | None) -> None:
    axes.set_xticks([])
    axes.set_yticks([])
    if reading.image is None:
        axes.text(0.5, 0.5, "no image", ha="center", va="center", transform=axes.transAxes)
        return
    low, high = grey if grey is not None else (None, None)
    axes.imshow(np.asarray(reading.image), cmap="gray", vmin=low, vmax=high)


def _draw_walk(
    axes: Axes,
    knob: str,
    shown: Sequence[Reading],
    scene: Scene,
    widths: tuple[float, float],
    legend: bool,
) -> None:
    """Width against `knob` for the readings `shown` so far, the last one ringed."""
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    low, high = scene.knobs[knob]
    margin = 0.03 * (high - low) if high > low else 1.0
    axes.set_xlim(low - margin, high + margin)
    axes.set_yscale("log")
    axes.set_ylim(*widths)
    if scene.threshold_px is not None and math.isfinite(scene.threshold_px):
        axes.axhline(
            scene.threshold_px,
            color="black",
            ls="--",
            lw=1,
            label=f"spec {scene.threshold_px:.2f} px",
        )
    now = shown[-1]
    if now.optimum is not None and knob in now.optimum:
        axes.axvline(now.optimum[knob], color="grey", ls=":", lw=1.2, label="optimum (simulator)")
    numbered = [
        (number, r)
        for number, r in enumerate(shown, start=1)
        if r.kind == "image" and knob in r.settings
    ]
    measured = [(n, r.settings[knob], r.width_px) for n, r in numbered if r.width_px is not None]
    if measured:
        _, xs, ys = zip(*measured, strict=True)
        axes.plot(xs, ys, "-o", color=WALK_COLOUR, lw=1, ms=4, alpha=0.7, label="readings")
        for number, x, y in measured:
            axes.annotate(
                str(number), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7
            )
    failed = [r.settings[knob] for _, r in numbered if r.width_px is None]
    if failed:
        top = widths[1] / 1.15
        axes.plot(failed, [top] * len(failed), "x", color=FAILED_COLOUR, ms=7, label="no edges")
    if now.kind == "image" and knob in now.settings:
        y = now.width_px if now.width_px is not None else widths[1] / 1.15
        axes.plot(
            [now.settings[knob]], [y], "o", ms=13, mfc="none", mec=NOW_COLOUR, mew=2.5, label="now"
        )
    axes.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 3.0, 5.0)))
    axes.yaxis.set_major_formatter(ScalarFormatter())
    axes.yaxis.set_minor_formatter(NullFormatter())
    axes.set_xlabel(knob)
    axes.set_ylabel("edge width (px)")
    if legend:  # above the panel, in one row: it stays put and covers no reading
        axes.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=5, fontsize=7, frameon=False)


def draw_frame(readings: Sequence[Reading], scene: Scene, upto: int | None = None) -> np.ndarray:
    """The frame of reading `upto` (default: the last) as an (H, W, 3) uint8 RGB array: its
    image beside the walk of readings[: upto + 1]. Axes, grey levels and heading lines are
    those of all `readings`, so that the frames of one alignment line up."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not readings:
        raise ValueError("draw_frame needs at least one reading (reset the env first)")
    upto = len(readings) - 1 if upto is None else upto
    if not 0 <= upto < len(readings):
        raise IndexError(f"reading {upto} of an alignment of {len(readings)} readings")
    shown, now = readings[: upto + 1], readings[upto]
    knobs = list(scene.knobs)
    with_images = any(r.image is not None for r in readings)
    rows = max(1, len(knobs))
    height = max(4.2, 1.9 * rows + 0.9)
    figure = Figure(figsize=(10.0 if with_images else 6.4, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    if with_images:
        grid = figure.add_gridspec(rows, 2, width_ratios=(1.0, 1.35))
        _draw_image(figure.add_subplot(grid[:, 0]), now, _image_range(readings))
        walks = [figure.add_subplot(grid[row, 1]) for row in range(rows)]
    else:
        walks = [figure.add_subplot(rows, 1, row + 1) for row in range(rows)]
    widths = _width_limits(readings, scene.threshold_px)
    for row, (axes, knob) in enumerate(zip(walks, knobs, strict=False)):
        _draw_walk(axes, knob, shown, scene, widths, legend=row == 0)
    # Every frame of an alignment gets as many heading lines as its last, which says how it
    # ended: the panels keep their place from frame to frame.
    heading = _heading(readings, scene, upto, with_images)
    lines = len(_heading(readings, scene, len(readings) - 1, with_images))
    figure.suptitle("\n".join(heading + [" "] * (lines - len(heading))), fontsize=10)
    figure.canvas.draw()
    return np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()  # (H, W, 3) uint8


def alignment_frames(readings: Sequence[Reading], scene: Scene) -> list[np.ndarray]:
    """One frame per reading, all on the same axes."""
    return [draw_frame(readings, scene, index) for index in range(len(readings))]


def alignment_gif(readings: Sequence[Reading], scene: Scene, path: str | Path) -> Path:
    """The GIF of one alignment, a frame per reading (`write_gif`)."""
    return write_gif(alignment_frames(readings, scene), path)


# --- the file -----------------------------------------------------------------------------


def write_gif(
    frames: Sequence[np.ndarray],
    path: str | Path,
    frame_s: float = FRAME_S,
    last_frame_s: float = LAST_FRAME_S,
) -> Path:
    """Write `frames` ((H, W, 3) uint8, all one size) as an animated GIF that loops, each
    shown `frame_s` seconds and the last `last_frame_s`; atomically (a reader never sees
    half a file)."""
    from PIL import Image

    from alignrl.checkpoints import atomic_write

    if not frames:
        raise ValueError("an animation needs at least one frame")
    sizes = {frame.shape for frame in frames}
    if len(sizes) != 1:
        raise ValueError(f"the frames differ in size: {sorted(sizes)}")
    pictures = [Image.fromarray(np.asarray(frame, dtype=np.uint8), "RGB") for frame in frames]
    durations = [round(1000 * frame_s)] * (len(pictures) - 1) + [round(1000 * last_frame_s)]
    path = Path(path)
    atomic_write(
        path,
        lambda handle: pictures[0].save(
            handle,
            format="GIF",
            save_all=True,
            append_images=pictures[1:],
            duration=durations,
            loop=0,
        ),
    )
    return path

"""What an instrument's images read against what its file's reading model says, blur by
blur: the diagnosis of docs/benchmarks.md, "focus-v2 from its one file" (issue 21).

    python -m benchmarks.image_levels --instrument val-steep --instrument val-mid

Per instrument (its column as drawn at --seed; the specimen is the draw's), one row per blur
width (the 10-90 % width of the probe, px): the reading the analytic model gives (the file's
`saturation_px` levelling, no noise), the median edge width of FRAMES rendered frames
measured as a session measures them, and how many of those frames had no edges (where the
analytic model's chance of none is shown beside). The held-out set is refused: this is a
look at what goes wrong, and the held-out set is only for reporting.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.edge_profiles import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.family import NO_EDGES_SPREAD, FamilyColumn
from alignrl.apparatus.family_box import load_family
from alignrl.apparatus.instruments import VALIDATION_SET, diagnosis_problem, instrument_names
from alignrl.apparatus.probe import levelled_px, logistic
from alignrl.apparatus.quality import edge_width

BLURS_PX = (3, 5, 8, 12, 16, 20, 25, 30, 40, 50, 60, 80, 100, 140)


@dataclass(frozen=True)
class Level:
    blur_px: float
    analytic_px: float
    no_edges_chance: float  # the analytic model's
    images_px: float | None  # median of the frames that had edges; None: none had
    no_edges: int  # frames without edges, of `frames`
    frames: int


def image_levels(
    instrument: str, frames: int = 6, seed: int = 0, blurs: tuple[float, ...] = BLURS_PX
) -> tuple[FamilyColumn, list[Level]]:
    """The validation instrument's column at `seed` and its levels, blur by blur."""
    column = FamilyColumn(load_family(instrument_names(VALIDATION_SET)[instrument]), seed=seed)
    column.reset(seed=seed)
    draw = column.draw
    rng = np.random.default_rng([seed, 1])
    levels = []
    for blur in blurs:
        widths = []
        for _ in range(frames):
            try:
                widths.append(edge_width(column._render(blur / TEN_NINETY_PER_SIGMA, rng)))
            except NoEdgesError:
                continue
        chance = logistic(blur, draw.no_edges_px, NO_EDGES_SPREAD * draw.no_edges_px)
        median = float(np.median(widths)) if widths else None
        levels.append(
            Level(
                blur,
                float(levelled_px(blur, draw.saturation_px)),
                chance,
                median,
                frames - len(widths),
                frames,
            )
        )
    return column, levels


def table(instrument: str, column: FamilyColumn, levels: list[Level]) -> list[str]:
    draw = column.draw
    lines = [
        f"{instrument}: specimen {draw.specimen}, saturation_px {draw.saturation_px:.3g}, "
        f"no_edges_px {draw.no_edges_px:.3g}",
        "",
        "| blur (px) | analytic reading (px) | images (px) | frames without edges | "
        "analytic chance of none |",
        "| --- | --- | --- | --- | --- |",
    ]
    for level in levels:
        shown = "-" if level.images_px is None else f"{level.images_px:.1f}"
        lines.append(
            f"| {level.blur_px:g} | {level.analytic_px:.1f} | {shown} | "
            f"{level.no_edges}/{level.frames} | {level.no_edges_chance:.2f} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--instrument", action="append", required=True, help="a validation instrument's name"
    )
    parser.add_argument("--frames", type=int, default=6, help="rendered per blur width")
    parser.add_argument("--seed", type=int, default=0, help="the column's draw")
    args = parser.parse_args(argv)
    for name in args.instrument:
        problem = diagnosis_problem(name, "image levels")
        if problem is not None:
            print(problem, file=sys.stderr)
            return 2
    if args.frames < 1:
        print("--frames must be at least 1", file=sys.stderr)
        return 2
    blocks = []
    for name in args.instrument:
        column, levels = image_levels(name, args.frames, args.seed)
        blocks.append("\n".join(table(name, column, levels)))
    print("\n\n".join(blocks))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

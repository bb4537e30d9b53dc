"""Where each specimen's edge widths level off on rendered frames: the table behind the task
option `posterior_saturation_px` (docs/benchmarks.md, "Readings that level off as images
do, and probes for information", issue 21).

    python -m benchmarks.specimen_levels

Per specimen kind, DRAWS specimens drawn and each rendered at every dose of --dose and every
blur of BLURS_SIGMA_PX (the probe's sigma, px), each frame's edge width measured as a
session measures it (alignrl/apparatus/quality.py). For every drawn specimen and dose the
level w_sat whose `w_sat tanh(w / w_sat)` (w: the blur's true 10-90 % width, the analytic
reading without a floor) fits the log of the measured widths best, over a log grid of
levels; the row gives the range and median of those levels, the median rms log error of
the fits and the widest width measured. Frames without edges are left out of the fit.

It looks at the renderer, not at any instrument: no instrument file, held-out or not, is
read.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.edge_profiles import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.quality import edge_width
from alignrl.apparatus.specimens import SPECIMENS, draw_specimen, render

BLURS_SIGMA_PX = tuple(float(s) for s in np.geomspace(0.8, 40.0, 16))
LEVELS_PX = np.geomspace(5.0, 200.0, 400)  # the levels a fit chooses among
SIZE = 256  # px, the rendered frames' side
DETECTOR_NOISE = 0.01


@dataclass(frozen=True)
class SpecimenLevel:
    specimen: str
    low_px: float  # the least fitted level over the draws and doses
    high_px: float
    median_px: float
    rms_log_error: float  # median over the fits
    widest_px: float  # the widest width measured on any frame
    fits: int
    frames_without_edges: int


def fitted_level(true_px: np.ndarray, measured_px: np.ndarray) -> tuple[float, float]:
    """The level of LEVELS_PX whose `level tanh(true / level)` fits log(measured) best, and
    that fit's rms log error."""
    model = LEVELS_PX[:, None] * np.tanh(true_px[None, :] / LEVELS_PX[:, None])
    errors = np.sqrt(np.mean((np.log(measured_px)[None, :] - np.log(model)) ** 2, axis=1))
    best = int(np.argmin(errors))
    return float(LEVELS_PX[best]), float(errors[best])


def specimen_level(
    specimen: str,
    draws: int = 4,
    doses: tuple[float, ...] = (100.0, 400.0),
    blurs: tuple[float, ...] = BLURS_SIGMA_PX,
) -> SpecimenLevel:
    """One specimen kind's row (module docstring); seeded, so the same every run."""
    levels, errors, widest, blank = [], [], 0.0, 0
    for draw in range(draws):
        spectrum = np.fft.rfft2(draw_specimen(specimen, SIZE, np.random.default_rng([draw, 4])))
        for dose in doses:
            true, measured = [], []
            for sigma in blurs:
                rng = np.random.default_rng([draw, round(sigma * 10), round(dose)])
                frame = render(spectrum, sigma, SIZE, dose, DETECTOR_NOISE, rng)
                try:
                    measured.append(edge_width(frame))
                except NoEdgesError:
                    blank += 1
                    continue
                true.append(TEN_NINETY_PER_SIGMA * sigma)
            if len(measured) < 2:
                continue  # nothing to fit a level to
            level, error = fitted_level(np.array(true), np.array(measured))
            levels.append(level)
            errors.append(error)
            widest = max(widest, max(measured))
    if not levels:
        raise ValueError(f"{specimen}: no frame with edges to fit a level to")
    return SpecimenLevel(
        specimen,
        min(levels),
        max(levels),
        float(np.median(levels)),
        float(np.median(errors)),
        widest,
        len(levels),
        blank,
    )


def table(rows: list[SpecimenLevel]) -> list[str]:
    lines = [
        "| specimen | w_sat fitted (px) | median (px) | rms log error | widest reading (px) "
        "| frames without edges |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        lines.append(
            f"| {row.specimen} | {row.low_px:.1f}-{row.high_px:.1f} | {row.median_px:.1f} | "
            f"{row.rms_log_error:.2f} | {row.widest_px:.0f} | {row.frames_without_edges} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--specimen", action="append", help=f"one of {', '.join(SPECIMENS)} (default: all)"
    )
    parser.add_argument("--draws", type=int, default=4, help="specimens drawn per kind")
    parser.add_argument(
        "--dose", type=float, action="append", help="electrons per px (default: 100 and 400)"
    )
    args = parser.parse_args(argv)
    specimens = args.specimen or list(SPECIMENS)
    unknown = [name for name in specimens if name not in SPECIMENS]
    if unknown:
        print(
            f"no such specimen: {', '.join(unknown)} (known: {', '.join(SPECIMENS)})",
            file=sys.stderr,
        )
        return 2
    doses = tuple(args.dose or (100.0, 400.0))
    if args.draws < 1 or not all(np.isfinite(dose) and dose > 0 for dose in doses):
        print("--draws must be at least 1 and every --dose a positive number", file=sys.stderr)
        return 2
    rows = []
    for done, name in enumerate(specimens, 1):
        rows.append(specimen_level(name, args.draws, doses))
        print(f"[{done}/{len(specimens)}] {name}", file=sys.stderr, flush=True)
    print("\n".join(table(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

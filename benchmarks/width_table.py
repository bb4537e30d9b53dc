"""What an edge width means: the reading against the probe's width, by focus error.

    python -m benchmarks.width_table [--scenarios 20]

For each preset (`synthetic`, `synthetic-b`, drift and hysteresis off so that the focus error
is set exactly) and each focus error, it sets `scenarios` scenarios that far from their
optimum (above it, or below where above leaves the interval), reads one frame each, and
prints the Markdown rows of docs/apparatus.md's table: the probe's 10-90 % width 2.563 sigma,
and the median (range) of the readings. Frames without a measurable edge are left out and
counted.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from alignrl.apparatus import NoEdgesError
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.synthetic import PRESET_DIR, SyntheticSEM, load_sem_config

PRESETS = ("synthetic", "synthetic-b")
FOCUS_ERRORS_V = (0, 2, 5, 10, 15, 20, 30, 40)


def readings(preset: str, error_v: float, scenarios: int) -> tuple[float, list[float]]:
    """(the probe's 10-90 % width, the readings of `scenarios` frames) at one focus error."""
    config = load_sem_config(PRESET_DIR / f"{preset}.yaml").model_copy(
        update={"drift_v_per_acquisition": 0.0, "hysteresis_v": 0.0}
    )
    sem = SyntheticSEM(config, seed=0)
    high = config.defocus_interval_v[1]
    widths = []
    for scenario in range(scenarios):
        sem.reset(scenario)
        optimum = sem.optimum()["defocus"]
        sem.write(
            {"defocus": optimum + error_v if optimum + error_v <= high else optimum - error_v}
        )
        try:
            widths.append(sem.measure())
        except NoEdgesError:
            continue
    probe = TEN_NINETY_PER_SIGMA * float(
        np.hypot(config.probe_sigma0_px, config.gain_px_per_v * error_v)
    )
    return probe, widths


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", type=int, default=20)
    args = parser.parse_args(argv)
    header = "| focus error (V) |"
    for preset in PRESETS:
        header += f" `{preset}`: 2.563 σ (px) | `{preset}`: measured, median (range) px |"
    print(header)
    print("| ---: " * (1 + 2 * len(PRESETS)) + "|")
    for error_v in FOCUS_ERRORS_V:
        row = f"| {error_v} |"
        for preset in PRESETS:
            probe, widths = readings(preset, error_v, args.scenarios)
            missing = args.scenarios - len(widths)
            note = f", {missing} without edges" if missing else ""
            row += (
                f" {probe:.1f} | {np.median(widths):.1f} "
                f"({min(widths):.1f}–{max(widths):.1f}){note} |"
            )
        print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

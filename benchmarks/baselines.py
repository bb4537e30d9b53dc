"""Classical autofocus figures: the reference a trained agent must beat (seed section 6.3).

`bench_baselines(N)` runs the evaluation session of every baseline on `synthetic` (the noisy
column with hysteresis and drift) and on the held-out recordings `csv:default` split "test",
N scenarios each, seed 0 (the same scenarios and starts for every controller), and returns
Markdown lines for docs/benchmarks.md.
"""

from __future__ import annotations

import json
from typing import Any

from alignrl.apparatus import make_apparatus
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import BASELINES
from alignrl.evaluation.session import run_session

__all__ = ["bench_baselines"]

APPARATUS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("synthetic", {}),
    # The same held-out apparatus as the trained aligners' evaluations (2 % re-measurement).
    ("csv:default", {"noise": 0.02, "split": "test"}),
)
SEED = 0


def bench_baselines(scenarios: int) -> list[str]:
    """One Markdown table per apparatus: successes, acquisitions, final width, time."""
    task = get_task("focus")
    lines = [
        f"### Classical autofocus, {scenarios} scenarios per session",
        "",
        f"`alignrl baselines --apparatus SPEC --scenarios {scenarios} --seed {SEED}`: every "
        "controller aligns the same scenarios from the same starts; success is an edge width "
        "at most 1.15 x the best the apparatus can reach, on one verification image "
        "(docs/evaluation.md). Acquisitions exclude the verification image.",
        "",
    ]
    for spec, args in APPARATUS:
        apparatus = make_apparatus(spec, args)
        lines += [
            f"`{spec}`" + (f" with `{json.dumps(args)}`" if args else "") + ":",
            "",
            f"| controller | successes / {scenarios} | acquisitions median | acquisitions p90 "
            f"| final edge width median (px) | threshold median (px) | seconds per session |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for name, make in BASELINES.items():
            result = run_session(make(), apparatus, task, scenarios=scenarios, seed=SEED)
            width = result.final_width_stats()["median"]
            lines.append(
                f"| {name} | {result.successes} | {result.median_acquisitions:g} | "
                f"{result.p90_acquisitions:.1f} | "
                f"{'-' if width is None else f'{width:.2f}'} | "
                f"{result.median_threshold_px:.2f} | {result.seconds:.1f} |"
            )
        lines.append("")
    return lines


if __name__ == "__main__":
    print("\n".join(bench_baselines(100)))

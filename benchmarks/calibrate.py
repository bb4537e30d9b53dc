"""A champion calibrated on each instrument of a set, then judged there: the adaptation target
of issue 21 ("adapting focus-v2 on a held-out instrument where zero-shot falls short: 100/100
within 2,000 steps") met by `alignrl calibrate` rather than by training.

    python -m benchmarks.calibrate --policy champion:focus-v2 --set heldout --out runs/cal

Per instrument: `calibrate_policy` runs ALIGNMENTS alignments of the policy on the
instrument's session at the validation seed (1,000,000: never the judging session's
columns), fits the column's reading model to what they read and exports the policy with it
to OUT/INSTRUMENT; that policy is then judged on the held-out table's session (seed 0, 100
alignments, as benchmarks/heldout.py), and the result written to OUT/INSTRUMENT/judged.json
(read back with --reuse where the same options, today's calibrated stop and the same far
noise, or its search, made it). The table: per instrument, the calibration's session (the
champion as it is), the steps it took (every image: its acquisitions, the verification
after each alignment, which the calibration reads too, and the readings from above,
--from-above), the far noise the column was fitted with, and the calibrated policy on the
judging session. Images unless --analytic. Not a test:
about three minutes per instrument on 2 cores with ten alignments.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from alignrl.apparatus.instruments import load_set
from alignrl.apparatus.registry import make_apparatus
from alignrl.cli.common import _at_least_zero, _share
from alignrl.deploy.calibrate import calibrate_policy
from alignrl.evaluation.instrument_sets import instrument_spec
from alignrl.evaluation.session import VALIDATION_SEED, run_session
from alignrl.intervals import success_text
from alignrl.posterior.calibration import (
    ALIGNMENTS,
    CALIBRATED_STOP,
    FAR_NOISE_SEARCHED,
    FROM_ABOVE,
    POPULATION,
    ROUNDS,
)
from benchmarks.heldout import _controller as policy_controller

JUDGED = "judged.json"
# what a saved result must share with the command (its options of the same names) for
# --reuse to read it; a result saved before readings from above has none. It must also have
# been judged with today's calibrated stop (CALIBRATED_STOP) and its far noise found as the
# command finds it: searched over today's FAR_NOISE_SEARCHED, or the --far-noise given (a
# result saved before the search had none: its far noise was given).
REUSED = ("policy", "alignments", "scenarios", "seed", "analytic", "from_above")


def _far_noise_as_asked(saved: dict[str, Any], far_noise: float | None) -> bool:
    """Whether a saved result's far noise was found as `far_noise` (None: searched) asks."""
    if far_noise is None:
        return saved.get("far_noise_searched") == list(FAR_NOISE_SEARCHED)
    return saved.get("far_noise_searched") is None and saved.get("far_noise") == far_noise


def _judge(args: argparse.Namespace, name: str) -> dict[str, Any]:
    """Calibrate on instrument `name`, then judge the calibrated policy (module docstring)."""
    out = args.out / name
    path = out / JUDGED
    if args.reuse and path.exists():
        saved = json.loads(path.read_text())
        same = all(saved.get(key, 0) == getattr(args, key) for key in REUSED)
        today = saved.get("stop") == CALIBRATED_STOP
        if same and today and _far_noise_as_asked(saved, args.far_noise):
            print(f"{name}: read {path}", file=sys.stderr)
            return saved
    apparatus = make_apparatus(instrument_spec(name), {"analytic": args.analytic})
    started = time.perf_counter()
    calibrated = calibrate_policy(
        args.policy,
        apparatus,
        out,
        alignments=args.alignments,
        seed=VALIDATION_SEED,
        population=args.population,
        rounds=args.rounds,
        from_above=args.from_above,
        far_noise=args.far_noise,
        force=True,
        command=f"python -m benchmarks.calibrate --policy {args.policy} (instrument {name})",
    )
    controller = policy_controller(str(out))
    judged = run_session(controller, apparatus, controller.task, args.scenarios, args.seed)
    result = {
        "instrument": name,
        "policy": args.policy,
        "alignments": args.alignments,
        "from_above": args.from_above,
        "stop": controller.task.ending.settings.stop_when_sure,
        "far_noise": controller.task.ending.settings.far_noise,
        "far_noise_searched": calibrated.calibration.far_noise_searched,
        # every image the calibration took and read: the alignments' acquisitions, their
        # verifications and the readings from above
        "steps": calibrated.calibration.readings,
        "calibration_successes": calibrated.session.successes,
        "calibration_median": calibrated.session.median_acquisitions,
        "column": calibrated.calibration.column,
        "seed": args.seed,
        "scenarios": args.scenarios,
        "analytic": args.analytic,
        "successes": judged.successes,
        "median_acquisitions": judged.median_acquisitions,
        "p90_acquisitions": judged.p90_acquisitions,
        "seconds": round(time.perf_counter() - started, 1),
    }
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{name}: {_cell(result)} ({result['seconds']:.0f} s)", file=sys.stderr)
    return result


def _cell(result: dict[str, Any]) -> str:
    shown = success_text(result["successes"], result["scenarios"])
    return f"{shown} at {result['median_acquisitions']:g} (p90 {result['p90_acquisitions']:g})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default="champion:focus-v2")
    parser.add_argument("--set", default="heldout", dest="set_name")
    parser.add_argument("--instrument", action="append", help="only these (default: the set)")
    parser.add_argument("--alignments", type=int, default=ALIGNMENTS, help="to calibrate on")
    parser.add_argument("--population", type=int, default=POPULATION, help="of the search")
    parser.add_argument("--rounds", type=int, default=ROUNDS, help="of the search")
    parser.add_argument(
        "--from-above",
        type=_at_least_zero,
        default=FROM_ABOVE,
        help="readings from above per alignment",
    )
    parser.add_argument(
        "--far-noise",
        type=_share,
        default=None,
        help="the calibration's far noise (default: searched with the column)",
    )
    parser.add_argument("--scenarios", type=int, default=100, help="judged on")
    parser.add_argument("--seed", type=int, default=0, help="of the judging session")
    parser.add_argument("--analytic", action="store_true", help="analytic readings, no images")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--reuse", action="store_true", help="read results OUT already holds")
    args = parser.parse_args(argv)
    names = args.instrument or [name for name, _ in load_set(args.set_name)]
    results = [_judge(args, name) for name in names]
    readings = "analytic readings" if args.analytic else "images"
    judged = f"judged on {args.scenarios} (seed {args.seed}), {readings}"
    print(
        f"{args.policy} calibrated on {args.alignments} alignments per instrument "
        f"(seed {VALIDATION_SEED}), {judged}"
    )
    print()
    print("| instrument | calibration session (steps) | far noise | calibrated |")
    print("| --- | --- | --- | --- |")
    for result in results:
        shown = success_text(result["calibration_successes"], result["alignments"])
        print(
            f"| {result['instrument']} | {shown} at {result['calibration_median']:g} "
            f"({result['steps']}) | {result['far_noise']:.3g} | {_cell(result)} |"
        )
    total = sum(result["successes"] for result in results)
    print(f"| **total** | | | {success_text(total, args.scenarios * len(results))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

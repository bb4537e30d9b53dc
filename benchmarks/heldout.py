"""Aligners and classical autofocus on every instrument of a set, side by side: the held-out
table of docs/benchmarks.md ("Champions on instruments they never saw", issue 21).

    python -m benchmarks.heldout --policy champion:focus-v1 --policy champion:focus-v2

Every controller runs one session per instrument (alignrl.evaluation.instrument_sets) on the
same seeded columns and starts; the table has one row per instrument and the total, and
below it, per instrument, whether each policy met the issue's target there (at least 99/100
at a median of at most 4 acquisitions, and fewer acquisitions than the hyperbola fit in the
same session). Images unless --analytic. Not a test: minutes per policy on images.
"""

from __future__ import annotations

import argparse
import sys
import time

from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import CLASSICAL
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.instrument_sets import SetResult, run_set, set_summary, set_table

TARGET_SUCCESSES = 0.99  # share of a session's alignments (issue 21)
TARGET_MEDIAN = 4.0  # acquisitions


def _controller(spec: str):
    if spec in CLASSICAL:
        return CLASSICAL[spec]()
    from alignrl.deploy.policy import load_deployable

    policy = load_deployable(spec)
    return PolicyController(name=spec, act=policy.act, task=policy.task, history=policy.history)


def _verdicts(results: list[SetResult], reference: SetResult | None) -> list[str]:
    lines = []
    for result in results:
        if result.controller in CLASSICAL:
            continue
        met = []
        for position, name in enumerate(result.instruments):
            session = result.sessions[position]
            share = session.successes / session.scenarios
            median = session.median_acquisitions
            fewer = reference is None or median < reference.sessions[position].median_acquisitions
            ok = share >= TARGET_SUCCESSES and median <= TARGET_MEDIAN and fewer
            met.append(f"{name} {'met' if ok else 'missed'}")
        lines.append(f"{result.controller}: {', '.join(met)}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", action="append", default=[], help="an aligner (repeatable)")
    parser.add_argument(
        "--controller",
        action="append",
        default=None,
        help="classical controllers beside them (default: hyperbola, golden-section)",
    )
    parser.add_argument("--set", default="heldout", dest="set_name")
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--analytic", action="store_true", help="analytic readings, no images")
    args = parser.parse_args(argv)
    classical = args.controller or ["hyperbola", "golden-section"]
    task = get_task("focus")
    results = []
    started = time.perf_counter()
    for spec in [*args.policy, *classical]:
        began = time.perf_counter()
        result = run_set(
            _controller(spec),
            args.set_name,
            task,
            scenarios=args.scenarios,
            seed=args.seed,
            analytic=args.analytic,
        )
        results.append(result)
        print(f"{set_summary(result)} ({time.perf_counter() - began:.0f} s)", file=sys.stderr)
    readings = "analytic readings" if args.analytic else "images"
    print(
        f"set:{args.set_name}, {args.scenarios} scenarios per instrument, seed {args.seed}, "
        f"{readings} ({time.perf_counter() - started:.0f} s)"
    )
    print()
    print("\n".join(set_table(results)))
    print()
    reference = next((r for r in results if r.controller == "hyperbola"), None)
    print("\n".join(_verdicts(results, reference)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Aligners and classical autofocus on every instrument of a set, side by side: the held-out
table of docs/benchmarks.md ("Champions on instruments they never saw", issue 21).

    python -m benchmarks.heldout --policy champion:focus-v1 --policy champion:focus-v2 \
        --out runs/heldout

Every controller runs one session per instrument (alignrl.evaluation.instrument_sets) on the
same seeded columns and starts. Each controller's result is written to OUT/NAME.json (the
object of `alignrl evaluate --set --json`); with --reuse a controller whose file is there, of
the same set, seed, scenarios and readings, is read instead of run again, so a new policy can
join a table of old ones. The table (instrument_sets.set_table) has one row per instrument
and the total, and below it, per instrument, whether each policy met the issue's target
there: at least 99/100 at a median of at most 4 acquisitions, and fewer acquisitions than the
hyperbola fit in the same session.
Images unless --analytic. Not a test: minutes per controller on images.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import CLASSICAL
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.instrument_sets import run_set, set_summary, set_table

TARGET_SUCCESSES = 0.99  # share of a session's alignments (issue 21)
TARGET_MEDIAN = 4.0  # acquisitions


def _controller(spec: str) -> Any:
    if spec in CLASSICAL:
        return CLASSICAL[spec]()
    from alignrl.deploy.policy import load_deployable

    policy = load_deployable(spec)
    return PolicyController(name=spec, act=policy.act, task=policy.task, history=policy.history)


def _file(out: Path, spec: str) -> Path:
    return out / f"{spec.replace(':', '-').replace('/', '-')}.json"


def same_sessions(saved: dict[str, Any], args: argparse.Namespace) -> bool:
    """Whether a saved set result was measured on the sessions `args` asks for."""
    measured = (saved.get("set"), saved.get("seed"), saved.get("scenarios"), saved.get("analytic"))
    return measured == (args.set_name, args.seed, args.scenarios, args.analytic)


def stored_or_run(
    name: str, make: Callable[[], Any], args: argparse.Namespace, path: Path | None, **hooks: Any
) -> dict[str, Any]:
    """Controller `name`'s set result as a dict: read from `path` with --reuse where it was
    measured on the same sessions, else `make()` run over the set (run_set, with `hooks`)
    and written to `path`."""
    if args.reuse and path is not None and path.exists():
        saved = json.loads(path.read_text())
        if same_sessions(saved, args):
            print(f"{name}: read {path}", file=sys.stderr)
            return saved
    began = time.perf_counter()
    result = run_set(
        make(),
        args.set_name,
        get_task("focus"),
        scenarios=args.scenarios,
        seed=args.seed,
        analytic=args.analytic,
        **hooks,
    )
    print(f"{set_summary(result)} ({time.perf_counter() - began:.0f} s)", file=sys.stderr)
    data = result.to_dict()
    data["controller"] = name
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=1))
    return data


def _result(spec: str, args: argparse.Namespace) -> dict[str, Any]:
    """The controller's set result (stored_or_run, in OUT under its name)."""
    path = _file(args.out, spec) if args.out else None
    return stored_or_run(spec, lambda: _controller(spec), args, path)


def verdicts(results: list[dict[str, Any]]) -> list[str]:
    """Per policy and instrument: the issue's target met or missed."""
    reference = next((r for r in results if r["controller"] == "hyperbola"), None)
    lines = []
    for result in results:
        if result["controller"] in CLASSICAL:
            continue
        met = []
        for position, session in enumerate(result["instruments"]):
            share = session["successes"] / session["scenarios"]
            median = session["median_acquisitions"]
            fewer = (
                reference is None
                or median < reference["instruments"][position]["median_acquisitions"]
            )
            ok = share >= TARGET_SUCCESSES and median <= TARGET_MEDIAN and fewer
            met.append(f"{session['instrument']} {'met' if ok else 'missed'}")
        lines.append(f"{result['controller']}: {', '.join(met)}")
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
    parser.add_argument("--out", type=Path, help="write each controller's result here")
    parser.add_argument("--reuse", action="store_true", help="read results OUT already holds")
    args = parser.parse_args(argv)
    classical = args.controller or ["hyperbola", "golden-section"]
    started = time.perf_counter()
    results = [_result(spec, args) for spec in [*args.policy, *classical]]
    readings = "analytic readings" if args.analytic else "images"
    print(
        f"set:{args.set_name}, {args.scenarios} scenarios per instrument, seed {args.seed}, "
        f"{readings} ({time.perf_counter() - started:.0f} s)"
    )
    print()
    print("\n".join(set_table(results)))
    print()
    print("\n".join(verdicts(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

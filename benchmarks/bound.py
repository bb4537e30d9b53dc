"""What a controller that knows the column's model reaches on every instrument of a set: the
Bayesian autofocus of alignrl/evaluation/posterior.py, in two kinds (issue 21):

* `oracle`: on each instrument, the posterior over that instrument's own file (its every
  parameter known, the optimum anywhere in the interval). What it cannot do in a number of
  acquisitions, no controller does reliably there on analytic readings;
* `posterior`: the posterior over the training box (alignrl/apparatus/families/focus.yaml),
  the same for every instrument: it knows what training knows, no more (`alignrl evaluate
  --policy posterior`); `--reach R` widens the box by R of each range at both ends.

    python -m benchmarks.bound --set heldout --analytic --out runs/bound

Each is a session per instrument on the same seeded columns and starts as
benchmarks/heldout.py's (same set, seed and scenarios: the tables line up); each result is
written to OUT/KIND.json in that script's format (read back instead of run with --reuse),
and `--beside DIR` shows the results a `python -m benchmarks.heldout --out DIR` wrote (of the
same sessions) in the same table. Not a test: seconds (oracle) to minutes (posterior) per
instrument.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from alignrl.apparatus.family import family_path, load_family
from alignrl.apparatus.instruments import load_set
from alignrl.apparatus.registry import make_apparatus
from alignrl.envs.task import get_task
from alignrl.evaluation.instrument_sets import SetResult, instrument_spec, set_summary, set_table
from alignrl.evaluation.posterior import FAMILY_REACH, PosteriorFocus, widened
from alignrl.evaluation.session import run_session

KINDS = ("oracle", "posterior")


def run_kind(kind: str, args: argparse.Namespace) -> SetResult:
    """One session per instrument of the set for controller `kind` (module docstring)."""
    task = get_task("focus")
    box = widened(load_family(family_path(args.family)), args.reach)
    shared = PosteriorFocus(box, name="posterior", draws=args.draws)
    names, sessions = [], []
    started = time.perf_counter()
    for name, instrument in load_set(args.set_name):
        controller = shared if kind == "posterior" else PosteriorFocus(instrument, name="oracle")
        apparatus = make_apparatus(instrument_spec(name), {"analytic": args.analytic})
        began = time.perf_counter()
        session = run_session(controller, apparatus, task, scenarios=args.scenarios, seed=args.seed)
        print(
            f"{kind} {name}: {session.successes}/{session.scenarios} at a median of "
            f"{session.median_acquisitions:g} ({time.perf_counter() - began:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
        names.append(name)
        sessions.append(session)
    return SetResult(
        set_name=args.set_name,
        controller=kind,
        task=task,
        seed=args.seed,
        analytic=args.analytic,
        instruments=tuple(names),
        sessions=tuple(sessions),
        seconds=time.perf_counter() - started,
    )


def _same(saved: dict, args: argparse.Namespace) -> bool:
    """Whether a saved result was measured on the sessions `args` asks for."""
    measured = (saved.get("set"), saved.get("seed"), saved.get("scenarios"), saved.get("analytic"))
    return measured == (args.set_name, args.seed, args.scenarios, args.analytic)


def _beside(args: argparse.Namespace) -> list[dict]:
    """The results in the --beside folders that were measured on the same sessions."""
    found = []
    for folder in args.beside:
        for path in sorted(folder.glob("*.json")):
            saved = json.loads(path.read_text())
            if _same(saved, args):
                found.append(saved)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", action="append", choices=KINDS, help="default: both")
    parser.add_argument("--set", default="heldout", dest="set_name")
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--analytic", action="store_true", help="analytic readings, no images")
    parser.add_argument("--family", default="focus", help="the box `posterior` knows")
    parser.add_argument("--draws", type=int, default=PosteriorFocus.draws)
    parser.add_argument(
        "--reach",
        type=float,
        default=FAMILY_REACH,
        help="`posterior` looks this share of each range beyond the box (posterior.widened)",
    )
    parser.add_argument("--out", type=Path, help="write each kind's result here")
    parser.add_argument("--reuse", action="store_true", help="read results OUT already holds")
    parser.add_argument(
        "--beside",
        type=Path,
        action="append",
        default=[],
        help="a folder of benchmarks.heldout results (NAME.json) to show in the table too, "
        "those of the same set, seed, scenarios and readings (repeatable)",
    )
    args = parser.parse_args(argv)
    results: list[SetResult | dict] = [*_beside(args)]
    for kind in args.kind or KINDS:
        path = args.out / f"{kind}.json" if args.out is not None else None
        if (
            args.reuse
            and path is not None
            and path.exists()
            and _same(json.loads(path.read_text()), args)
        ):
            print(f"{kind}: read {path}", file=sys.stderr)
            results.append(json.loads(path.read_text()))
            continue
        result = run_kind(kind, args)
        print(set_summary(result), file=sys.stderr)
        results.append(result)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(result.to_dict(), indent=1))
    readings = "analytic readings" if args.analytic else "images"
    per = f"{args.scenarios} scenarios per instrument"
    print(f"set:{args.set_name}, {per}, seed {args.seed}, {readings}")
    print()
    print("\n".join(set_table(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

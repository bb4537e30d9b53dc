"""What a controller that knows the column's model reaches on every instrument of a set: the
Bayesian autofocus of alignrl/evaluation/posterior.py, in five kinds (issue 21):

* `oracle`: on each instrument, the posterior over that instrument's own file (its every
  parameter known, the optimum anywhere in the interval). What it cannot do in a number of
  acquisitions, no controller does reliably there on analytic readings;
* `posterior`: the posterior over the training box (alignrl/apparatus/families/focus.yaml),
  the same for every instrument: it knows what training knows, no more (`alignrl evaluate
  --policy posterior`); `--reach R` widens the box by R of each range at both ends;
* `oracle-scale-free` (only where asked): the oracle with its readings in an unknown pixel
  scale (BayesianAutofocus.scale_free): every parameter of the column known but its pixels, as a
  unit-free aligner must read them. What it cannot do in a number of acquisitions, no
  unit-free controller does reliably there;
* `scale-free` (only where asked): the same box, its readings in an unknown pixel scale
  (BayesianAutofocus.scale_free): what a unit-free aligner could learn from it;
* `robust` (only where asked): `alignrl evaluate --policy posterior-robust`, scale-free with
  more columns and far readings trusted less (posterior.ROBUST), as the champion's ending
  posterior reads images.

`--probe-rule chance` has every kind probe where the final setting's expected chance gains
most rather than where the optimum's variance falls most (FamilyPosterior.probe_rule); its
results are KIND-chance.

    python -m benchmarks.bound --set heldout --analytic --out runs/bound

Each is a session per instrument on the same seeded columns and starts as
benchmarks/heldout.py's (same set, seed and scenarios: the tables line up); each result is
written to OUT/KIND.json by that script's own stored_or_run (read back with --reuse),
and `--beside DIR` shows the results a `python -m benchmarks.heldout --out DIR` wrote (of the
same sessions) in the same table. Not a test: seconds (oracle) to minutes (posterior) per
instrument.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from alignrl.apparatus.base import Apparatus
from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.instruments import load_set
from alignrl.evaluation.instrument_sets import set_table
from alignrl.evaluation.posterior import ROBUST, BayesianAutofocus
from alignrl.posterior.inference import PROBE_RULES, SCALE_FREE
from alignrl.posterior.models import FAMILY_REACH, widened
from benchmarks.heldout import same_sessions, stored_or_run

KINDS = ("oracle", "oracle-scale-free", "posterior", "scale-free", "robust")
DEFAULT_KINDS = ("oracle", "posterior")
# How each kind reads beyond the posterior's defaults (robust: its draws too)
READS = {"oracle-scale-free": SCALE_FREE, "scale-free": SCALE_FREE, "robust": ROBUST}


class _Oracle:
    """The posterior over each instrument's own file, switched to as its session starts
    (run_set's on_instrument)."""

    def __init__(self, set_name: str, label: str, probe_rule: str, reads: dict) -> None:
        self.name = label
        self.by_instrument = {
            name: BayesianAutofocus(instrument, name=label, probe_rule=probe_rule, **reads)
            for name, instrument in load_set(set_name)
        }
        self.present: BayesianAutofocus | None = None

    def switch(self, instrument: str) -> None:
        self.present = self.by_instrument[instrument]

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        assert self.present is not None, "run_set names the instrument before its session"
        self.present.align(apparatus, knob, budget)


def _result(kind: str, args: argparse.Namespace) -> dict:
    """Controller `kind`'s set result (module docstring), read back or run."""
    name = kind if args.probe_rule == "variance" else f"{kind}-{args.probe_rule}"
    path = args.out / f"{name}.json" if args.out is not None else None
    reads = READS.get(kind, {})
    if kind.startswith("oracle"):
        oracle = _Oracle(args.set_name, name, args.probe_rule, reads)
        return stored_or_run(name, lambda: oracle, args, path, on_instrument=oracle.switch)
    box = widened(load_family(family_path(args.family)), args.reach)
    settings = {"draws": args.draws, **reads, "probe_rule": args.probe_rule}
    return stored_or_run(name, lambda: BayesianAutofocus(box, name=name, **settings), args, path)


def _beside(args: argparse.Namespace) -> list[dict]:
    """The results in the --beside folders that were measured on the same sessions."""
    saved = [
        json.loads(path.read_text())
        for folder in args.beside
        for path in sorted(folder.glob("*.json"))
    ]
    return [result for result in saved if same_sessions(result, args)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--kind", action="append", choices=KINDS, help="default: oracle and posterior"
    )
    parser.add_argument("--set", default="heldout", dest="set_name")
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--analytic", action="store_true", help="analytic readings, no images")
    parser.add_argument("--family", default="focus", help="the box `posterior` knows")
    parser.add_argument(
        "--draws", type=int, default=BayesianAutofocus.draws, help="columns (robust: 1024)"
    )
    parser.add_argument(
        "--probe-rule", choices=PROBE_RULES, default="variance", help="FamilyPosterior.probe_rule"
    )
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
    results = [*_beside(args), *(_result(kind, args) for kind in args.kind or DEFAULT_KINDS)]
    readings = "analytic readings" if args.analytic else "images"
    per = f"{args.scenarios} scenarios per instrument"
    print(f"set:{args.set_name}, {per}, seed {args.seed}, {readings}")
    print()
    print("\n".join(set_table(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

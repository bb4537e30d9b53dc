"""CPU-seconds per alignment of `champion:focus-v2`, whose moves and stop a Bayesian posterior
makes (alignrl/posterior/inference.py, FamilyPosterior; fed by alignrl/envs/ending.py): the
whole alignment and the posterior's part of it (issue 61, item 4).

    python -m benchmarks.posterior_cost [--scenarios 6] [--seed 1000000] [--kinds analytic images]
    python -m benchmarks.posterior_cost --save-reference runs/posterior-cost.json
    python -m benchmarks.posterior_cost --reference runs/posterior-cost.json
    python -m benchmarks.posterior_cost --draws 256   # fewer columns: other numbers

Runs `alignrl evaluate --policy champion:focus-v2 --apparatus set:validation --task focus`
in this process, one session per kind of reading (`analytic`: the analytic readings;
`images`: edge widths measured on rendered frames), and times each with
`time.process_time` (the CPU-seconds of every thread of the process): the whole session,
and the part spent inside FamilyPosterior (its construction, begin, observe, decide, probe,
final, use_columns; nested calls counted once). Nothing tunes the C library's allocator: the
figures are what the commands take with glibc as it comes.

The results are checked, not only timed: every alignment's readings (setting and width), its
end, its verification and success, every answer the posterior gave (final's setting and
chance, probe's setting, bit for bit as Python's repr writes them) and the session's JSON
summary (`alignrl evaluate --json`, less its seconds). `--save-reference FILE` writes them;
`--reference FILE` compares with them and exits 1 naming the first difference: run the first
on the code before a change, the second after it (the same options; numbers from another
machine may differ in their last bits). Without either, the digest of the results is printed.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from alignrl.apparatus.registry import make_apparatus
from alignrl.deploy.policy import load_deployable
from alignrl.envs.endings import with_ending
from alignrl.envs.option_table import OPTIONS
from alignrl.envs.task import get_task
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.report import session_summary
from alignrl.evaluation.session import VALIDATION_SEED, run_session
from alignrl.posterior.inference import FamilyPosterior

KINDS = {"analytic": True, "images": False}  # the apparatus' `analytic` argument
APPARATUS = "set:validation"
TIMED = ("__post_init__", "begin", "observe", "decide", "probe", "final", "use_columns")
ANSWERS = ("decide", "probe", "final")  # whose returns are kept and compared


class PosteriorMeter:
    """Times every call of FamilyPosterior's TIMED methods (once where one calls another)
    and keeps each answer of ANSWERS, while installed (`with`)."""

    def __init__(self) -> None:
        self.seconds, self.calls, self.depth = 0.0, 0, 0
        self.answers: list[list[Any]] = []
        self._saved: dict[str, Callable[..., Any]] = {}

    def __enter__(self) -> PosteriorMeter:
        for name in TIMED:
            original = getattr(FamilyPosterior, name)
            self._saved[name] = original
            setattr(FamilyPosterior, name, self._timed(name, original))
        return self

    def __exit__(self, *exc: object) -> None:
        for name, original in self._saved.items():
            setattr(FamilyPosterior, name, original)

    def _timed(self, name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(method)
        def timed(*args: Any, **kwargs: Any) -> Any:
            self.depth += 1
            started = time.process_time()
            try:
                answer = method(*args, **kwargs)
            finally:
                self.depth -= 1
                if not self.depth:
                    self.seconds += time.process_time() - started
                    self.calls += 1
            if name in ANSWERS and not self.depth:
                self.answers.append([name, *map(repr, _flat(answer))])
            return answer

        return timed


def _flat(answer: Any) -> tuple[Any, ...]:
    return tuple(answer) if isinstance(answer, tuple) else (answer,)


def _record(record: Any) -> dict[str, Any]:
    """What one alignment did, exactly (floats as their repr)."""
    return {
        "trajectory": [[repr(setting), repr(width)] for setting, width in record.trajectory],
        "final_setting": repr(record.final_setting),
        "final_width_px": repr(record.final_width_px),
        "success": bool(record.success),
    }


def run_kind(
    policy: str, kind: str, scenarios: int, seed: int, draws: int | None = None
) -> dict[str, Any]:
    """One session of `policy` on the validation set with `kind` readings: its CPU-seconds,
    the posterior's, and its results (module docstring); with `draws`, its posterior draws
    that many columns instead of its card's."""
    deployed = load_deployable(policy)
    task = deployed.task if draws is None else with_ending(deployed.task, posterior_draws=draws)
    controller = PolicyController(
        name=deployed.name, act=deployed.act, task=task, history=deployed.history
    )
    apparatus = make_apparatus(APPARATUS, {"analytic": KINDS[kind]})
    answers: list[list[Any]] = []
    with PosteriorMeter() as meter:

        def each(_record: Any) -> None:  # the answers of one alignment, apart
            answers.append([item for answer in meter.answers for item in answer])
            meter.answers.clear()

        wall, started = time.perf_counter(), time.process_time()
        task = get_task("focus")
        result = run_session(controller, apparatus, task, scenarios, seed, on_scenario=each)
        seconds = time.process_time() - started
        wall = time.perf_counter() - wall
    summary = session_summary(result, APPARATUS)
    summary.pop("seconds", None)
    records = [
        {**_record(record), "posterior": answer}
        for record, answer in zip(result.records, answers, strict=True)
    ]
    return {
        "kind": kind,
        "alignments": scenarios,
        "cpu_s": seconds,
        "posterior_cpu_s": meter.seconds,
        "posterior_calls": meter.calls,
        "wall_s": wall,
        "results": {"summary": summary, "records": records},
    }


def first_difference(results: dict[str, Any], reference: dict[str, Any]) -> str | None:
    """Where `results` first differ from `reference` (None: nowhere)."""
    if results["summary"] != reference["summary"]:
        keys = sorted(set(results["summary"]) | set(reference["summary"]))
        key = next(k for k in keys if results["summary"].get(k) != reference["summary"].get(k))
        return f"summary key {key!r}"
    if len(results["records"]) != len(reference["records"]):
        return "the number of alignments"
    pairs = zip(results["records"], reference["records"], strict=True)
    for index, (mine, theirs) in enumerate(pairs):
        for key in theirs:
            if mine.get(key) != theirs[key]:
                return f"alignment {index}: {key}"
    return None


def digest(results: dict[str, Any]) -> str:
    return hashlib.blake2b(json.dumps(results, sort_keys=True).encode(), digest_size=8).hexdigest()


def table(rows: list[dict[str, Any]]) -> list[str]:
    lines = [
        "readings   alignments  aligned  acq median  CPU-s/alignment  posterior CPU-s/alignment  "
        "posterior share  posterior calls  wall s",
        "-" * 126,
    ]
    for row in rows:
        count, summary = row["alignments"], row["results"]["summary"]
        lines.append(
            f"{row['kind']:<9}  {count:>10}  {summary['successes']:>7}  "
            f"{summary['median_acquisitions']:>10g}  {row['cpu_s'] / count:>15.3f}  "
            f"{row['posterior_cpu_s'] / count:>25.3f}  "
            f"{row['posterior_cpu_s'] / max(row['cpu_s'], 1e-9):>15.0%}  "
            f"{row['posterior_calls']:>15}  {row['wall_s']:>6.1f}"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default="champion:focus-v2")
    parser.add_argument("--scenarios", type=int, default=6, help="alignments per kind")
    parser.add_argument("--seed", type=int, default=VALIDATION_SEED)
    parser.add_argument("--kinds", nargs="+", choices=list(KINDS), default=list(KINDS))
    parser.add_argument(
        "--draws", type=int, help="the posterior's columns (default: the policy card's)"
    )
    checks = parser.add_mutually_exclusive_group()
    checks.add_argument("--save-reference", type=Path, help="write the results here")
    checks.add_argument("--reference", type=Path, help="compare the results with these")
    args = parser.parse_args(argv)
    if args.scenarios < 1:
        parser.error(f"--scenarios must be at least 1, got {args.scenarios}")
    if args.draws is not None:  # the task option's own interval (alignrl/envs/option_table.py)
        problem = OPTIONS["posterior_draws"].problem("posterior_draws", args.draws)
        if problem is not None:
            parser.error(f"--draws: {problem}")
    options = {"policy": args.policy, "scenarios": args.scenarios, "seed": args.seed}
    if args.draws is not None:
        options["draws"] = args.draws
    reference = json.loads(args.reference.read_text()) if args.reference else None
    if reference is not None and reference["options"] != options:
        parser.error(f"{args.reference} holds other sessions: {reference['options']}")
    rows = [
        run_kind(args.policy, kind, args.scenarios, args.seed, args.draws) for kind in args.kinds
    ]
    drawn = "" if args.draws is None else f", its posterior drawing {args.draws} columns"
    print(
        f"{args.policy} on {APPARATUS}: {args.scenarios} alignments per kind, seed {args.seed}"
        f"{drawn}"
    )
    print()
    print("\n".join(table(rows)))
    print()
    results = {row["kind"]: row["results"] for row in rows}
    if args.save_reference:
        args.save_reference.parent.mkdir(parents=True, exist_ok=True)
        saved = {"options": options, "results": results}
        args.save_reference.write_text(json.dumps(saved, indent=1) + "\n")
        print(f"results (digest {digest(results)}) written to {args.save_reference}")
        return 0
    if reference is None:
        print(f"results digest {digest(results)} (no reference given)")
        return 0
    differences = []
    for kind, mine in results.items():
        if kind not in reference["results"]:
            differences.append(f"{kind}: not in the reference")
        elif (where := first_difference(mine, reference["results"][kind])) is not None:
            differences.append(f"{kind}: {where}")
    if differences:
        print(f"results DIFFER from {args.reference}: " + "; ".join(differences))
        return 1
    print(f"results the same as {args.reference} (digest {digest(results)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

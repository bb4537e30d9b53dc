"""`alignrl record` and `alignrl scenarios validate`: sweep an apparatus into a scenario CSV
(voltages in V, edge widths in px) and check a recording before anything trains on it."""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.apparatus.recorder import SweepPlan, scenario_seed, sweep_many, sweep_plan
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.scenarios import (
    MIN_PAIRS,
    ScenarioFormatError,
    ScenarioWriter,
    read_scenarios,
)
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_apparatus_options,
    _add_shield_options,
    _at_least_one,
    _emit,
    _json_object,
    _scenarios,
    _seed,
    _shield_options,
)


def _continue_from(out: Path, plan: SweepPlan, seed: int) -> int:
    """First scenario id to record when appending to `out`, after checking it is the same
    recording (same knob, interval and seeds), so that --append never mixes two sweeps."""
    existing = read_scenarios(out)
    if existing.knob != plan.knob:
        raise CommandError(f"{out} sweeps knob {existing.knob!r}, this recording {plan.knob!r}")
    if np.any(existing.lows != plan.low) or np.any(existing.highs != plan.high):
        raise CommandError(
            f"{out} was recorded over another interval than [{plan.low:g}, {plan.high:g}]"
        )
    for scenario, row_seed in zip(existing.scenario_ids, existing.seeds, strict=True):
        if row_seed != scenario_seed(seed, int(scenario)):
            raise CommandError(
                f"{out}: scenario {scenario} was recorded with another --seed; append with "
                "the seed of the original recording"
            )
    return int(existing.scenario_ids.max()) + 1


def cmd_record(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    if args.scenarios < 1:
        raise CommandError("--scenarios must be at least 1")
    apparatus_args = _json_object(args.apparatus_args, "--apparatus-args")
    factory = functools.partial(
        make_apparatus, args.apparatus, apparatus_args, shield=_shield_options(args)
    )
    apparatus = factory()  # opened once; worker processes open their own
    plan = sweep_plan(apparatus.knobs, knob=args.knob, step=args.step)
    out = Path(args.out)
    existed = out.exists()
    first = _continue_from(out, plan, args.seed) if args.append and existed else 0
    mode = "append" if args.append else "force" if args.force else "new"
    todo = range(first, args.scenarios)
    written = skipped = failed = 0
    pairs: list[int] = []
    started = time.perf_counter()
    rows = sweep_many(factory, plan, todo, args.seed, args.workers, apparatus=apparatus)
    with ScenarioWriter(out, plan.max_pairs, mode=mode) as writer:
        bar = tqdm(
            total=args.scenarios,
            initial=first,
            unit="scenario",
            desc="recording",
            disable=args.quiet,
            file=sys.stderr,
        )
        try:
            for scenario, record in rows:
                failed += record.n_failed
                if record.usable:
                    writer.write(record)
                    written += 1
                    pairs.append(len(record.voltages))
                else:
                    skipped += 1
                    bar.write(
                        f"scenario {scenario}: only {len(record.voltages)} measurable point(s) "
                        f"({record.n_failed} failed acquisitions), not written",
                        file=sys.stderr,
                    )
                bar.update(1)
        except KeyboardInterrupt:
            bar.close()
            print(
                f"\ninterrupted: {written} scenarios written to {out} are kept; continue with "
                f"the same command and --append",
                file=sys.stderr,
            )
            return EXIT_INTERRUPTED
        bar.close()
    if written == 0 and skipped > 0:
        # The writer only gives a file its name with its first row: nothing was replaced.
        raise CommandError(
            f"no scenario had {MIN_PAIRS} measurable points ({failed} failed acquisitions): "
            f"check that {args.apparatus} shows edges over its interval; {out} was not written"
        )
    elapsed = time.perf_counter() - started
    payload = {
        "out": str(out),
        "apparatus": args.apparatus,
        "knob": plan.knob,
        "step": plan.step,
        "seed": args.seed,
        "first_scenario": first,
        "scenarios_written": written,
        "scenarios_skipped": skipped,
        "failed_acquisitions": failed,
        "median_pairs": float(np.median(pairs)) if pairs else 0.0,
        "seconds": round(elapsed, 3),
    }
    _emit(
        payload,
        args.json,
        [
            f"recorded {written} scenarios of {args.apparatus} into {out} "
            f"({skipped} skipped, {failed} failed acquisitions, "
            f"median {payload['median_pairs']:.0f} pairs per sweep, {elapsed:.1f} s)"
        ],
    )
    return 0


def scenario_summary(path: Path) -> dict[str, Any]:
    """Facts a microscopist checks first about a recording."""
    from alignrl.apparatus.simulator import ScenarioSimulator

    data = read_scenarios(path)
    simulator = ScenarioSimulator(scenarios=data)
    rows = np.arange(len(data))
    best_width = np.array(
        [data.edge_widths[s, : data.n_pairs[s]].min() for s in rows], dtype=np.float64
    )
    low, high = simulator.knobs[data.knob]
    return {
        "file": str(path),
        "valid": True,
        "scenarios": len(data),
        "knob": data.knob,
        "interval": [low, high],
        "pairs": {
            "min": int(data.n_pairs.min()),
            "median": float(np.median(data.n_pairs)),
            "max": int(data.n_pairs.max()),
        },
        "failed_acquisitions": int(data.n_failed.sum()),
        "optimum_v": {
            "min": float(simulator.optima.min()),
            "median": float(np.median(simulator.optima)),
            "max": float(simulator.optima.max()),
        },
        "best_edge_width_px": {
            "min": float(best_width.min()),
            "median": float(np.median(best_width)),
            "max": float(best_width.max()),
        },
    }


def plot_scenarios(path: Path, out: Path, curves: int = 24) -> None:
    """Focus curves of a recording and the spread of their optima, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from alignrl.apparatus.simulator import ScenarioSimulator

    data = read_scenarios(path)
    simulator = ScenarioSimulator(scenarios=data)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4), dpi=100)
    for s in np.linspace(0, len(data) - 1, min(curves, len(data))).astype(int):
        count = data.n_pairs[s]
        left.plot(data.voltages[s, :count], data.edge_widths[s, :count], ".-", lw=0.8, ms=3)
    left.set_xlabel(f"{data.knob} voltage (V)")
    left.set_ylabel("edge width (px)")
    left.set_title(f"focus curves ({min(curves, len(data))} of {len(data)} scenarios)")
    right.hist(simulator.optima, bins=30, color="tab:blue")
    right.set_xlabel("optimum voltage (V)")
    right.set_ylabel("scenarios")
    right.set_title("where the focus lies")
    figure.suptitle(str(path.name))
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    plt.close(figure)


def cmd_scenarios_validate(args: argparse.Namespace) -> int:
    path = Path(args.file)
    try:
        summary = scenario_summary(path)
    except (ScenarioFormatError, FileNotFoundError) as error:
        if args.json:
            print(json.dumps({"file": str(path), "valid": False, "error": str(error)}, indent=2))
        raise CommandError(str(error)) from None
    if args.plot:
        plot_scenarios(path, Path(args.plot))
        summary["plot"] = args.plot
    pairs, optimum, best = summary["pairs"], summary["optimum_v"], summary["best_edge_width_px"]
    low, high = summary["interval"]
    lines = [
        f"{path}: valid, {summary['scenarios']} scenarios of knob {summary['knob']!r} "
        f"in [{low:g}, {high:g}] V",
        f"  points per sweep   min {pairs['min']}, median {pairs['median']:g}, max {pairs['max']}",
        f"  failed acquisitions {summary['failed_acquisitions']}",
        f"  optimum (V)        min {optimum['min']:.2f}, median {optimum['median']:.2f}, "
        f"max {optimum['max']:.2f}",
        f"  sharpest edge (px) min {best['min']:.2f}, median {best['median']:.2f}, "
        f"max {best['max']:.2f}",
    ]
    if args.plot:
        lines.append(f"  plot: {args.plot}")
    _emit(summary, args.json, lines)
    return 0


def add_record_parsers(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    record = verbs.add_parser(
        "record",
        help="sweep an apparatus into a scenario CSV (section 4.3 of the method's paper, "
        "docs/index.md)",
    )
    _add_apparatus_options(record)
    record.add_argument(
        "--scenarios", type=_scenarios, required=True, help="total scenarios wanted"
    )
    record.add_argument("--out", required=True, help="output CSV (.csv or .csv.gz)")
    record.add_argument("--seed", type=_seed, default=0, help="base seed of the scenarios")
    record.add_argument("--step", choices=("constant", "adaptive"), default="adaptive")
    record.add_argument("--knob", default="defocus", help="the knob to sweep")
    record.add_argument(
        "--workers", type=_at_least_one, default=1, help="processes (simulated apparatus only)"
    )
    existing = record.add_mutually_exclusive_group()
    existing.add_argument("--force", action="store_true", help="replace an existing file")
    existing.add_argument("--append", action="store_true", help="continue an existing file")
    record.add_argument("--quiet", action="store_true", help="no progress bar")
    record.add_argument("--json", action="store_true", help="machine-readable summary")
    _add_shield_options(record, limits=False)
    record.set_defaults(handler=cmd_record)

    scenarios = verbs.add_parser("scenarios", help="inspect scenario CSV files")
    scenario_verbs = scenarios.add_subparsers(dest="scenarios_verb", required=True)
    validate = scenario_verbs.add_parser("validate", help="check a scenario CSV strictly")
    validate.add_argument("file")
    validate.add_argument("--plot", help="write the focus curves to this PNG")
    validate.add_argument("--json", action="store_true")
    validate.set_defaults(handler=cmd_scenarios_validate)

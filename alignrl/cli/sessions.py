"""`alignrl evaluate` and `alignrl baselines`: evaluation sessions, N alignments on the same
seeded scenarios, each judged against the spec (an edge width in px), of a trained aligner or
of a task's classical controllers.

Where: one apparatus (`--apparatus SPEC`), or every instrument of an instrument set
(`--set NAME`, alignrl/evaluation/instrument_sets.py: one session per instrument, the same
seed on each, one table row each and the total; `--analytic` for analytic readings instead of
images). The two are exclusive."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.apparatus.registry import make_apparatus
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_policy_option,
    _add_session_options,
    _emit,
    _json_object,
    _shield_options,
)


def _check_counts(args: argparse.Namespace) -> None:
    """--scenarios and --budget, checked before any policy loads."""
    if args.scenarios < 1:
        raise CommandError("--scenarios must be at least 1")
    if args.budget is not None and args.budget < 1:
        raise CommandError("--budget must be at least 1 acquisition")


def _check_where(args: argparse.Namespace) -> None:
    """One apparatus or one instrument set, never both; the set's options only with a set;
    a set that exists. Checked before any policy loads."""
    from alignrl.apparatus.instruments import set_names

    sets = ", ".join(set_names())
    if args.set is not None and args.apparatus is not None:
        raise CommandError(
            "--set and --apparatus are exclusive: give --set NAME to run every instrument of "
            "a set, or --apparatus SPEC for one apparatus"
        )
    if args.set is None and args.apparatus is None:
        raise CommandError(f"give --apparatus SPEC, or --set NAME (the sets: {sets})")
    if args.set is None:
        if args.analytic:
            raise CommandError(
                "--analytic applies to --set; for one apparatus give --apparatus-args "
                "'{\"analytic\": true}'"
            )
        return
    if args.apparatus_args != "{}":
        raise CommandError(
            "--apparatus-args applies to --apparatus; a set's instruments take only --analytic"
        )
    if args.set not in set_names():
        raise CommandError(f"no instrument set {args.set!r}; the sets are: {sets}")


def _progress(args: argparse.Namespace, total: int) -> Any:
    """The progress bar of a session (tqdm on standard error: rate and ETA)."""
    from tqdm import tqdm

    return tqdm(
        total=total, unit="alignment", desc="evaluating", disable=args.quiet, file=sys.stderr
    )


def _run_evaluations(
    args: argparse.Namespace, controllers: Sequence[Any], task: Any
) -> tuple[list[Any], float]:
    """Run one session per controller on the same scenarios of `task`, with a progress bar."""
    from alignrl.evaluation.session import run_session

    apparatus = make_apparatus(
        args.apparatus,
        _json_object(args.apparatus_args, "--apparatus-args"),
        shield=_shield_options(args),
    )
    bar = _progress(args, args.scenarios * len(controllers))
    results = []
    started = time.perf_counter()
    try:
        for controller in controllers:
            bar.set_description(controller.name)
            results.append(
                run_session(
                    controller,
                    apparatus,
                    task,
                    scenarios=args.scenarios,
                    seed=args.seed,
                    spec_px=args.spec_px,
                    budget=args.budget,
                    on_scenario=lambda _record: bar.update(1),
                )
            )
    finally:
        bar.close()
    return results, time.perf_counter() - started


def _run_set_evaluations(
    args: argparse.Namespace, controllers: Sequence[Any], task: Any
) -> tuple[list[Any], float]:
    """Run every controller over every instrument of --set, with one progress bar over all
    alignments of all instruments."""
    from alignrl.apparatus.instruments import instrument_names
    from alignrl.evaluation.instrument_sets import run_set

    shield = _shield_options(args)
    total = args.scenarios * len(instrument_names(args.set)) * len(controllers)
    bar = _progress(args, total)
    results = []
    started = time.perf_counter()
    try:
        for controller in controllers:
            results.append(
                run_set(
                    controller,
                    args.set,
                    task,
                    scenarios=args.scenarios,
                    seed=args.seed,
                    analytic=args.analytic,
                    budget=args.budget,
                    spec_px=args.spec_px,
                    on_scenario=lambda _record: bar.update(1),
                    on_instrument=lambda name, c=controller: bar.set_description(
                        f"{c.name} on {name}"
                    ),
                    shield=shield,
                )
            )
    finally:
        bar.close()
    return results, time.perf_counter() - started


def _plot_set(result: Any, path_of: Any, payload: dict[str, Any]) -> None:
    """One trajectory PNG per instrument of a set result, at path_of(instrument); each
    instrument's object in `payload` (SetResult.to_dict()) names its file."""
    from alignrl.evaluation.report import plot_trajectories

    for entry, name, session in zip(
        payload["instruments"], result.instruments, result.sessions, strict=True
    ):
        out = path_of(name)
        plot_trajectories(session, out, f"{result.controller} on instrument:{name}")
        entry["plot"] = str(out)


def _interrupted() -> int:
    print("\ninterrupted: no report (a session counts only when complete)", file=sys.stderr)
    return EXIT_INTERRUPTED


def _evaluate_set(args: argparse.Namespace, controller: Any, task: Any) -> int:
    from alignrl.evaluation.instrument_sets import set_heading, set_notes, set_summary, set_table

    try:
        (result,), _ = _run_set_evaluations(args, [controller], task)
    except KeyboardInterrupt:
        return _interrupted()
    payload = result.to_dict()
    lines = [
        f"{result.controller} {set_heading(result)}",
        "",
        *set_table([result]),
        "",
        set_summary(result),
        *set_notes([result]),
    ]
    if args.plot:
        plot = Path(args.plot)
        _plot_set(result, lambda name: plot.with_name(f"{plot.stem}-{name}{plot.suffix}"), payload)
        lines.append(f"plots: {plot.with_name(f'{plot.stem}-INSTRUMENT{plot.suffix}')}")
    _emit(payload, args.json, lines)
    return 0


def _baselines_set(args: argparse.Namespace, controllers: Sequence[Any], task: Any) -> int:
    from alignrl.evaluation.instrument_sets import set_heading, set_notes, set_summary, set_table

    try:
        results, elapsed = _run_set_evaluations(args, controllers, task)
    except KeyboardInterrupt:
        return _interrupted()
    payload: dict[str, Any] = {
        "set": args.set,
        "task": task.name,
        "analytic": args.analytic,
        "instruments": list(results[0].instruments),
        "scenarios": args.scenarios,
        "seed": args.seed,
        "controllers": {result.controller: result.to_dict() for result in results},
        "seconds": round(elapsed, 3),
    }
    what = "autofocus" if task.name == "focus" else f"{task.name} alignment"
    lines = [
        f"classical {what} {set_heading(results[0])}",
        "",
        *set_table(results),
        "",
        *(set_summary(result) for result in results),
        *set_notes(results),
    ]
    if args.plot_dir:
        folder = Path(args.plot_dir)
        for result in results:
            _plot_set(
                result,
                lambda name, c=result.controller: folder / f"{c}-{name}.png",
                payload["controllers"][result.controller],
            )
        lines.append(f"plots: {folder}/CONTROLLER-INSTRUMENT.png")
    _emit(payload, args.json, lines)
    return 0


def _check_trained_source(spec: str) -> None:
    """Refuse a --policy that names nothing at all, with the classical names too, before any
    policy of a sequence loads. What it names is decided by alignrl.runs.sources, as for
    align and export; something there that is no policy is refused as it loads."""
    from alignrl.evaluation.baselines import CLASSICAL
    from alignrl.runs.sources import MissingSourceError, PolicySpecError, locate_source

    try:
        locate_source(spec)
    except MissingSourceError:
        raise CommandError(
            f"unknown policy {spec!r}: give a run directory, a checkpoint file, an "
            f"exported policy directory, champion:NAME, or one of {', '.join(sorted(CLASSICAL))}"
        ) from None
    except PolicySpecError:
        pass  # loading it says what is wrong (an unknown champion: the shipped ones)


def _trained_controller(spec: str) -> Any:
    """A trained aligner as a session controller: whatever `align` runs (a run directory, a
    checkpoint, an exported policy, champion:NAME), loaded the same way."""
    from alignrl.deploy.policy import load_deployable
    from alignrl.evaluation.controllers import PolicyController

    policy = load_deployable(spec)
    return PolicyController(
        name=policy.name, act=policy.act, task=policy.task, history=policy.history
    )


def cmd_evaluate(args: argparse.Namespace) -> int:
    from alignrl.envs.task import get_task
    from alignrl.evaluation.baselines import CLASSICAL
    from alignrl.evaluation.controllers import SequenceController
    from alignrl.evaluation.report import (
        plot_trajectories,
        session_notes,
        session_summary,
        summary_table,
    )

    _check_where(args)
    _check_counts(args)
    policy = args.policy[0]
    if len(args.policy) > 1:
        # Stage aligners run in sequence (a column: its aperture stage, then its focus and
        # stigmators), judged together on --task.
        classical = [name for name in args.policy if name in CLASSICAL]
        if classical:
            raise CommandError(
                f"{', '.join(classical)}: a classical controller aligns a whole task; only "
                "trained aligners run in sequence (several --policy)"
            )
        if args.task is None:
            raise CommandError(
                "several --policy run in sequence and need --task, the task the column is "
                "judged on (e.g. --task column)"
            )
        for name in args.policy:
            _check_trained_source(name)
        controller = SequenceController(tuple(_trained_controller(p) for p in args.policy))
        task = get_task(args.task)
    elif policy in CLASSICAL:
        controller = CLASSICAL[policy]()
        task = get_task(args.task or "focus")
    else:
        _check_trained_source(policy)
        controller = _trained_controller(policy)
        # Unless one is named, the built-in task of the aligner's (judged by its rule, as a
        # focus aligner always was, whatever options it trained with).
        task = get_task(args.task or controller.task.name)
    if args.set is not None:
        return _evaluate_set(args, controller, task)
    try:
        (result,), _ = _run_evaluations(args, [controller], task)
    except KeyboardInterrupt:
        return _interrupted()
    payload = session_summary(result, args.apparatus)
    lines = [
        f"{result.controller} on {args.apparatus}: {result.successes}/{result.scenarios} "
        f"aligned (threshold {payload['threshold_px']:.2f} px, median)",
        "",
        *summary_table([result]),
        *session_notes([result]),
    ]
    if args.plot:
        plot_trajectories(result, Path(args.plot), f"{result.controller} on {args.apparatus}")
        payload["plot"] = args.plot
        lines.append(f"plot: {args.plot}")
    _emit(payload, args.json, lines)
    return 0


def cmd_baselines(args: argparse.Namespace) -> int:
    from alignrl.envs.task import get_task
    from alignrl.evaluation.baselines import task_baselines
    from alignrl.evaluation.report import (
        plot_trajectories,
        session_notes,
        session_summary,
        summary_table,
    )

    _check_where(args)
    _check_counts(args)
    task = get_task(args.task or "focus")
    controllers = [make() for make in task_baselines(task.name).values()]
    if args.set is not None:
        return _baselines_set(args, controllers, task)
    try:
        results, elapsed = _run_evaluations(args, controllers, task)
    except KeyboardInterrupt:
        return _interrupted()
    payload: dict[str, Any] = {
        "apparatus": args.apparatus,
        "task": task.name,
        "scenarios": args.scenarios,
        "seed": args.seed,
        "controllers": {r.controller: session_summary(r, args.apparatus) for r in results},
        "seconds": round(elapsed, 3),
    }
    threshold = float(np.median([r.median_threshold_px for r in results]))
    what = "autofocus" if task.name == "focus" else f"{task.name} alignment"
    lines = [
        f"classical {what} on {args.apparatus}: {args.scenarios} scenarios, seed "
        f"{args.seed}, threshold {threshold:.2f} px (median)",
        "",
        *summary_table(results),
        *session_notes(results),
    ]
    if args.plot_dir:
        folder = Path(args.plot_dir)
        for result in results:
            out = folder / f"{result.controller}.png"
            plot_trajectories(result, out, f"{result.controller} on {args.apparatus}")
            payload["controllers"][result.controller]["plot"] = str(out)
        lines.append(f"plots: {folder}/")
    _emit(payload, args.json, lines)
    return 0


def _add_set_options(parser: argparse.ArgumentParser) -> None:
    """--set NAME (instead of --apparatus) and --analytic."""
    from alignrl.apparatus.instruments import set_names

    parser.add_argument(
        "--set",
        metavar="NAME",
        default=None,
        help=f"instead of --apparatus: every instrument of an instrument set "
        f"({', '.join(set_names())}), one session each with the same seed, one row each and "
        "the total",
    )
    parser.add_argument(
        "--analytic",
        action="store_true",
        help="with --set: analytic readings instead of images (fast)",
    )


def add_session_parsers(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    evaluate = verbs.add_parser(
        "evaluate", help="an evaluation session: N alignments checked against the spec"
    )
    _add_policy_option(
        evaluate,
        "a run directory (training: its best checkpoint; league: its champion), a "
        "checkpoint file, an exported policy directory, champion:NAME, or a classical "
        "controller: golden-section, hyperbola, hill-climb (focus), stigmator-search "
        "(stigmation), wobble-center (aperture), column-sequence (column); give trained "
        "aligners several times (with --task) to run them in that order, e.g. the column's "
        "stages: column-aperture, then column-focus-stigmation, with --task column",
    )
    _add_session_options(evaluate, apparatus_required=False)
    _add_set_options(evaluate)
    evaluate.add_argument(
        "--plot",
        help="write the trajectories to this PNG (--set: one per instrument, NAME-INSTRUMENT.png)",
    )
    evaluate.set_defaults(handler=cmd_evaluate)

    baselines = verbs.add_parser(
        "baselines", help="a task's classical controllers side by side, on the same scenarios"
    )
    _add_session_options(baselines, apparatus_required=False)
    _add_set_options(baselines)
    baselines.add_argument(
        "--plot-dir",
        help="write one trajectory PNG per controller here (--set: CONTROLLER-INSTRUMENT.png)",
    )
    baselines.set_defaults(handler=cmd_baselines)

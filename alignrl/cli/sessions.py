"""`alignrl evaluate` and `alignrl baselines`: evaluation sessions, N alignments on the same
seeded scenarios, each judged against the spec (an edge width in px), of a trained aligner or
of a task's classical controllers."""

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


def _run_evaluations(
    args: argparse.Namespace, controllers: Sequence[Any], task: Any
) -> tuple[list[Any], float]:
    """Run one session per controller on the same scenarios of `task`, with a progress bar."""
    from tqdm import tqdm

    from alignrl.evaluation.session import run_session

    if args.scenarios < 1:
        raise CommandError("--scenarios must be at least 1")
    if args.budget is not None and args.budget < 1:
        raise CommandError("--budget must be at least 1 acquisition")
    apparatus = make_apparatus(
        args.apparatus,
        _json_object(args.apparatus_args, "--apparatus-args"),
        shield=_shield_options(args),
    )
    bar = tqdm(
        total=args.scenarios * len(controllers),
        unit="alignment",
        desc="evaluating",
        disable=args.quiet,
        file=sys.stderr,
    )
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
    try:
        (result,), _ = _run_evaluations(args, [controller], task)
    except KeyboardInterrupt:
        print("\ninterrupted: no report (a session counts only when complete)", file=sys.stderr)
        return EXIT_INTERRUPTED
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

    task = get_task(args.task or "focus")
    controllers = [make() for make in task_baselines(task.name).values()]
    try:
        results, elapsed = _run_evaluations(args, controllers, task)
    except KeyboardInterrupt:
        print("\ninterrupted: no report (a session counts only when complete)", file=sys.stderr)
        return EXIT_INTERRUPTED
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
    _add_session_options(evaluate)
    evaluate.add_argument("--plot", help="write the trajectories to this PNG")
    evaluate.set_defaults(handler=cmd_evaluate)

    baselines = verbs.add_parser(
        "baselines", help="a task's classical controllers side by side, on the same scenarios"
    )
    _add_session_options(baselines)
    baselines.add_argument("--plot-dir", help="write one trajectory PNG per controller here")
    baselines.set_defaults(handler=cmd_baselines)

"""`alignrl evaluate` and `alignrl baselines`: evaluation sessions, N alignments on the same
seeded scenarios, each judged against the spec (an edge width in px), of a trained aligner or
of a task's classical controllers.

Where: one apparatus (`--apparatus SPEC`), or every instrument of an instrument set
(`--set NAME`, alignrl/evaluation/instrument_sets.py: one session per instrument, the same
seed on each, one table row each and the total; `--analytic` for analytic readings instead of
images). The two are exclusive.

How many: one session at `--seed S` (default 0), or one per seed of `--seeds S1 S2 ...`
(each the session `--seed S` runs), printed per seed and then aggregated across the seeds:
the interquartile mean of the per-seed success rates with its bootstrap interval, the pooled
successes with their Wilson interval, the median acquisitions (alignrl.evaluation.report).
Every success count carries its 95 % Wilson interval, and every `--json` says that these are
test sessions: they choose nothing."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.apparatus.filming import Film, FilmedApparatus
from alignrl.apparatus.registry import make_apparatus
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_policy_option,
    _add_session_options,
    _emit,
    _json_object,
    _seed,
    _shield_options,
)
from alignrl.cli.gifs import add_gif_options, check_gif, session_film, write_session_gif

SESSION = "test"  # what evaluate and baselines sessions are: they choose nothing


def _check_counts(args: argparse.Namespace) -> None:
    """--scenarios and --budget, checked before any policy loads."""
    if args.scenarios < 1:
        raise CommandError("--scenarios must be at least 1")
    if args.budget is not None and args.budget < 1:
        raise CommandError("--budget must be at least 1 acquisition")


def _session_seeds(args: argparse.Namespace) -> tuple[int, ...]:
    """The seeds of the sessions: those of --seeds, or --seed (default 0), never both; a seed
    given twice is refused. `args.seed` is resolved to the first session's seed, for what
    needs one. Checked before any policy loads."""
    if args.seeds is None:
        args.seed = 0 if args.seed is None else args.seed
        return (args.seed,)
    if args.seed is not None:
        raise CommandError(
            "--seed and --seeds are exclusive: give --seed S for one session, or --seeds S1 "
            "S2 ... for one session per seed and their aggregate"
        )
    twice = sorted({seed for seed in args.seeds if args.seeds.count(seed) > 1})
    if twice:
        raise CommandError(f"--seeds gives seed {twice[0]} twice: each seed is one session")
    args.seed = args.seeds[0]
    return tuple(args.seeds)


def _seeded(path: Path, seed: int | str, seeds: bool) -> Path:
    """A plot path, with `-seedS` before its suffix where the command ran --seeds (`seed`
    "S": the pattern, as the command prints it)."""
    return path.with_name(f"{path.stem}-seed{seed}{path.suffix}") if seeds else path


def _plot_name(result: Any, several: bool) -> str:
    """A --plot-dir file's name: the controller, and `-seedS` where the command ran --seeds."""
    return result.controller + (f"-seed{result.seed}" if several else "")


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


def _described(name: str, seed: int, seeds: Sequence[int]) -> str:
    return name if len(seeds) == 1 else f"{name}, seed {seed}"


def _run_evaluations(
    args: argparse.Namespace,
    controllers: Sequence[Any],
    task: Any,
    seeds: Sequence[int],
    film: Film | None = None,
) -> tuple[list[list[Any]], list[float]]:
    """Run one session per seed and controller, the controllers of a seed on the same
    scenarios of `task`, with one progress bar. Per seed: the results (one per controller)
    and the seconds they took. `film`: keep its scenario's acquisitions as they happen."""
    from alignrl.evaluation.session import run_session

    apparatus = make_apparatus(
        args.apparatus,
        _json_object(args.apparatus_args, "--apparatus-args"),
        shield=_shield_options(args),
    )
    if film is not None:  # --gif (alignrl/cli/gifs.py)
        apparatus = FilmedApparatus(apparatus, film)
    bar = _progress(args, args.scenarios * len(controllers) * len(seeds))
    per_seed, seconds = [], []
    try:
        for seed in seeds:
            started, results = time.perf_counter(), []
            for controller in controllers:
                bar.set_description(_described(controller.name, seed, seeds))
                results.append(
                    run_session(
                        controller,
                        apparatus,
                        task,
                        scenarios=args.scenarios,
                        seed=seed,
                        spec_px=args.spec_px,
                        budget=args.budget,
                        on_scenario=lambda _record: bar.update(1),
                    )
                )
            per_seed.append(results)
            seconds.append(time.perf_counter() - started)
    finally:
        bar.close()
    return per_seed, seconds


def _run_set_evaluations(
    args: argparse.Namespace, controllers: Sequence[Any], task: Any, seeds: Sequence[int]
) -> tuple[list[list[Any]], list[float]]:
    """Run every controller over every instrument of --set at every seed, with one progress
    bar over all alignments. Per seed: the set results (one per controller), the seconds."""
    from alignrl.apparatus.instruments import instrument_names, set_names, task_set
    from alignrl.evaluation.instrument_sets import run_set

    shield = _shield_options(args)
    set_name = task_set(args.set, task.name)  # the task's own: heldout-stigmation, ...
    if set_name not in set_names():
        raise CommandError(
            f"no instrument set {set_name!r} for task {task.name!r}; the sets are: "
            f"{', '.join(set_names())}"
        )
    total = args.scenarios * len(instrument_names(set_name)) * len(controllers) * len(seeds)
    bar = _progress(args, total)
    per_seed, seconds = [], []
    try:
        for seed in seeds:
            started, results = time.perf_counter(), []
            for controller in controllers:
                name = _described(controller.name, seed, seeds)
                results.append(
                    run_set(
                        controller,
                        set_name,
                        task,
                        scenarios=args.scenarios,
                        seed=seed,
                        analytic=args.analytic,
                        budget=args.budget,
                        spec_px=args.spec_px,
                        on_scenario=lambda _record: bar.update(1),
                        on_instrument=lambda instrument, n=name: bar.set_description(
                            f"{n} on {instrument}"
                        ),
                        shield=shield,
                    )
                )
            per_seed.append(results)
            seconds.append(time.perf_counter() - started)
    finally:
        bar.close()
    return per_seed, seconds


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


def _over_seeds(
    head: dict[str, Any],
    seeds: Sequence[int],
    payloads: list,
    aggregate: Any,
    seconds: Sequence[float],
) -> dict[str, Any]:
    """The `--json` of --seeds: `head` (what ran where), each seed's object as `--seed S
    --json` prints it (`per_seed`), their `aggregate` and the seconds of them all."""
    return {
        **head,
        "session": SESSION,
        "seeds": list(seeds),
        "per_seed": payloads,
        "aggregate": aggregate,
        "seconds": round(sum(seconds), 3),
    }


def _by_controller(per_seed: Sequence[Sequence[Any]]) -> list[tuple[str, list[Any]]]:
    """Per controller (in order), its results at every seed."""
    return [
        (result.controller, [results[index] for results in per_seed])
        for index, result in enumerate(per_seed[0])
    ]


def _evaluate_set(args: argparse.Namespace, controller: Any, task: Any, seeds: tuple) -> int:
    from alignrl.evaluation import instrument_sets as sets
    from alignrl.evaluation.report import aggregate_line

    try:
        per_seed, seconds = _run_set_evaluations(args, [controller], task, seeds)
    except KeyboardInterrupt:
        return _interrupted()
    results, several = [results[0] for results in per_seed], args.seeds is not None
    payloads = [result.to_dict(SESSION) for result in results]
    if args.plot:
        for result, payload in zip(results, payloads, strict=True):
            plot = _seeded(Path(args.plot), result.seed, several)
            _plot_set(result, lambda n, p=plot: p.with_name(f"{p.stem}-{n}{p.suffix}"), payload)
    first = results[0]
    if not several:
        payload = payloads[0]
        table, summary = sets.set_table([first]), [sets.set_summary(first)]
    else:
        head = {"set": args.set, "controller": first.controller, "task": task.name}
        head |= {"analytic": args.analytic, "scenarios": args.scenarios}
        aggregate = sets.set_seeds_aggregate(results)
        payload = _over_seeds(head, seeds, payloads, aggregate, seconds)
        columns = [{**data, "controller": f"seed {data['seed']}"} for data in payloads]
        table = sets.set_table([*columns, sets.pooled_over_seeds(results, "all seeds")])
        summary = [aggregate_line(results)]
    heading = sets.set_heading(first, seeds if several else None)
    lines = [f"{first.controller} {heading}", "", *table, "", *summary]
    lines += sets.set_notes(results, seeded=several)
    if args.plot:
        plot = _seeded(Path(args.plot), "S", several)
        lines.append(f"plots: {plot.with_name(f'{plot.stem}-INSTRUMENT{plot.suffix}')}")
    _emit(payload, args.json, lines)
    return 0


def _baselines_set(
    args: argparse.Namespace, controllers: Sequence[Any], task: Any, seeds: tuple
) -> int:
    from alignrl.evaluation import instrument_sets as sets
    from alignrl.evaluation.report import aggregate_table

    try:
        per_seed, seconds = _run_set_evaluations(args, controllers, task, seeds)
    except KeyboardInterrupt:
        return _interrupted()
    several = args.seeds is not None
    head = {"set": args.set, "task": task.name, "analytic": args.analytic}
    head |= {"instruments": list(per_seed[0][0].instruments), "scenarios": args.scenarios}
    payloads: list[dict[str, Any]] = [
        {
            **head,
            "session": SESSION,
            "seed": seed,
            "controllers": {result.controller: result.to_dict(SESSION) for result in results},
            "seconds": round(elapsed, 3),
        }
        for seed, results, elapsed in zip(seeds, per_seed, seconds, strict=True)
    ]
    for results, payload in zip(per_seed, payloads, strict=True):
        for result in results if args.plot_dir else ():
            name = Path(args.plot_dir) / _plot_name(result, several)
            entry = payload["controllers"][result.controller]
            _plot_set(result, lambda instrument, n=name: Path(f"{n}-{instrument}.png"), entry)
    what = "autofocus" if task.name == "focus" else f"{task.name} alignment"
    every = [result for results in per_seed for result in results]
    if not several:
        payload, results = payloads[0], per_seed[0]
        lines = [f"classical {what} {sets.set_heading(results[0])}", "", *sets.set_table(results)]
        lines += ["", *(sets.set_summary(result) for result in results)]
    else:
        by_controller = _by_controller(per_seed)
        aggregate = {name: sets.set_seeds_aggregate(runs) for name, runs in by_controller}
        payload = _over_seeds(head, seeds, payloads, aggregate, seconds)
        heading = sets.set_heading(every[0], seeds)
        pooled = [sets.pooled_over_seeds(runs, name) for name, runs in by_controller]
        lines = [f"classical {what} {heading}; each cell pools the seeds", ""]
        lines += [*sets.set_table(pooled), "", "totals over the set, per seed and aggregated:"]
        lines += ["", *aggregate_table(by_controller)]
    lines += sets.set_notes(every, seeded=several)
    if args.plot_dir:
        seeded = "-seedS" if several else ""
        lines.append(f"plots: {args.plot_dir}/CONTROLLER{seeded}-INSTRUMENT.png")
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

    _check_where(args)
    _check_counts(args)
    seeds = _session_seeds(args)
    check_gif(args)
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
        return _evaluate_set(args, controller, task, seeds)
    return _evaluate_apparatus(args, controller, task, seeds)


def _evaluate_apparatus(args: argparse.Namespace, controller: Any, task: Any, seeds: tuple) -> int:
    """`alignrl evaluate --apparatus`: one session, or one per seed and their aggregate."""
    from alignrl.evaluation import report
    from alignrl.intervals import success_text

    film = session_film(args)
    try:
        per_seed, seconds = _run_evaluations(args, [controller], task, seeds, film)
    except KeyboardInterrupt:
        return _interrupted()
    results, several = [results[0] for results in per_seed], args.seeds is not None
    summaries = [report.session_summary(result, args.apparatus, SESSION) for result in results]
    if args.plot:
        for result, summary in zip(results, summaries, strict=True):
            out = _seeded(Path(args.plot), result.seed, several)
            report.plot_trajectories(result, out, f"{result.controller} on {args.apparatus}")
            summary["plot"] = str(out)
    first, threshold = results[0], summaries[0]["threshold_px"]
    where = f"{first.controller} on {args.apparatus}"
    if not several:
        payload = summaries[0]
        aligned = success_text(first.successes, first.scenarios)
        lines = [f"{where}: {aligned} aligned (threshold {threshold:.2f} px, median)", ""]
        lines += [*report.summary_table(results), *report.session_notes(results)]
    else:
        head = {"controller": first.controller, "apparatus": args.apparatus, "task": task.name}
        head["scenarios"] = args.scenarios
        aggregate = report.seeds_aggregate(results)
        payload = _over_seeds(head, seeds, summaries, aggregate, seconds)
        lines = [
            f"{where}: {args.scenarios} scenarios at each of {len(seeds)} seeds (threshold "
            f"{threshold:.2f} px, median)",
            "",
            *report.summary_table(results, ("seed", [str(seed) for seed in seeds])),
            *report.session_notes(results, [f"seed {seed}" for seed in seeds]),
            "",
            report.aggregate_line(results),
        ]
    if args.plot:
        lines.append(f"plot: {_seeded(Path(args.plot), 'S', several)}")
    if film is not None:
        write_session_gif(args, film, first, payload, lines)
    _emit(payload, args.json, lines)
    return 0


def cmd_baselines(args: argparse.Namespace) -> int:
    from alignrl.envs.task import get_task
    from alignrl.evaluation import report
    from alignrl.evaluation.baselines import task_baselines

    _check_where(args)
    _check_counts(args)
    seeds = _session_seeds(args)
    task = get_task(args.task or "focus")
    controllers = [make() for make in task_baselines(task.name).values()]
    if args.set is not None:
        return _baselines_set(args, controllers, task, seeds)
    try:
        per_seed, seconds = _run_evaluations(args, controllers, task, seeds)
    except KeyboardInterrupt:
        return _interrupted()
    several = args.seeds is not None
    head = {"apparatus": args.apparatus, "task": task.name, "scenarios": args.scenarios}
    payloads: list[dict[str, Any]] = [
        {
            **head,
            "session": SESSION,
            "seed": seed,
            "controllers": {
                r.controller: report.session_summary(r, args.apparatus, SESSION) for r in results
            },
            "seconds": round(elapsed, 3),
        }
        for seed, results, elapsed in zip(seeds, per_seed, seconds, strict=True)
    ]
    for results, payload in zip(per_seed, payloads, strict=True):
        for result in results if args.plot_dir else ():
            out = Path(args.plot_dir) / f"{_plot_name(result, several)}.png"
            report.plot_trajectories(result, out, f"{result.controller} on {args.apparatus}")
            payload["controllers"][result.controller]["plot"] = str(out)
    every = [result for results in per_seed for result in results]
    threshold = float(np.median([r.median_threshold_px for r in every]))
    what = "autofocus" if task.name == "focus" else f"{task.name} alignment"
    heading = f"classical {what} on {args.apparatus}: {args.scenarios} scenarios, seed"
    if not several:
        payload = payloads[0]
        lines = [f"{heading} {seeds[0]}, threshold {threshold:.2f} px (median)", ""]
        lines += [*report.summary_table(per_seed[0]), *report.session_notes(per_seed[0])]
    else:
        by_controller = _by_controller(per_seed)
        aggregate = {name: report.seeds_aggregate(runs) for name, runs in by_controller}
        payload = _over_seeds(head, seeds, payloads, aggregate, seconds)
        lines = [f"{heading}s {', '.join(map(str, seeds))}, threshold {threshold:.2f} px (median)"]
        for seed, results in zip(seeds, per_seed, strict=True):
            names = [f"{result.controller}, seed {seed}" for result in results]
            lines += ["", f"seed {seed}:", *report.summary_table(results)]
            lines += report.session_notes(results, names)
        lines += ["", "over the seeds:", "", *report.aggregate_table(by_controller)]
    if args.plot_dir:
        lines.append(f"plots: {args.plot_dir}/" + ("CONTROLLER-seedS.png" if several else ""))
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
        "the total; heldout and validation name the task's own (heldout-stigmation for "
        "--task stigmation)",
    )
    parser.add_argument(
        "--analytic",
        action="store_true",
        help="with --set: analytic readings instead of images (fast)",
    )


def _add_seeds_option(parser: argparse.ArgumentParser) -> None:
    """--seeds S1 S2 ... (instead of --seed): one session per seed, and their aggregate."""
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=_seed,
        metavar="S",
        default=None,
        help="instead of --seed: one session per seed (the same --scenarios each), printed "
        "per seed, then their aggregate: the interquartile mean of the per-seed success rates "
        "with its 95 %% bootstrap interval, the pooled successes and the median acquisitions",
    )
    # None until given, so that --seed with --seeds is refused; _session_seeds resolves it.
    parser.set_defaults(seed=None)


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
    _add_seeds_option(evaluate)
    evaluate.add_argument(
        "--plot",
        help="write the trajectories to this PNG (--set: one per instrument, NAME-INSTRUMENT.png)",
    )
    add_gif_options(evaluate, session=True)
    evaluate.set_defaults(handler=cmd_evaluate)

    baselines = verbs.add_parser(
        "baselines", help="a task's classical controllers side by side, on the same scenarios"
    )
    _add_session_options(baselines, apparatus_required=False)
    _add_set_options(baselines)
    _add_seeds_option(baselines)
    baselines.add_argument(
        "--plot-dir",
        help="write one trajectory PNG per controller here (--set: CONTROLLER-INSTRUMENT.png)",
    )
    baselines.set_defaults(handler=cmd_baselines)

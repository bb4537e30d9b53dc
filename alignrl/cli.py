"""The `alignrl` command. Verbs read like the work; every reporting verb has `--json`
(keys documented in docs/cli.md and kept stable).

    alignrl record --apparatus SPEC --scenarios N --out FILE.csv [--seed S] [--step adaptive]
    alignrl scenarios validate FILE [--plot PNG] [--json]
    alignrl evaluate --policy NAME --apparatus SPEC [--task T] --scenarios N [--seed S]
                     [--spec-px X]
    alignrl baselines --apparatus SPEC [--task T] --scenarios N [--seed S] [--spec-px X]
                      [--plot-dir DIR]
    alignrl report RUN [--out DIR] [--json]
    alignrl export RUN [--member ID] --format onnx|torchscript|safetensors --out DIR
                   [--force] [--json]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl import __version__
from alignrl.apparatus.base import ApparatusError
from alignrl.apparatus.recorder import SweepPlan, scenario_seed, sweep_many, sweep_plan
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.scenarios import (
    MIN_PAIRS,
    ScenarioFormatError,
    ScenarioWriter,
    read_scenarios,
)
from alignrl.apparatus.shield import DEFAULT_CALL_TIMEOUT_S, DriverFailure, ShieldStop

EXIT_USAGE = 2  # bad input: a clear message, nothing written
EXIT_SHIELD_STOP = 3  # the shield ended the work: watchdog, refused write, abort (as align)
EXIT_DRIVER_FAILURE = 4  # a driver call failed, hung or answered what cannot be (as align)
EXIT_INTERNAL = 70  # a bug in alignrl (EX_SOFTWARE): one line, never a refusal of input
EXIT_INTERRUPTED = 130


class CommandError(Exception):
    """A user-facing failure: printed as one line, exit code 2."""


JSON_LIMIT = 100_000  # characters of a JSON option: arguments, limits, steps are a few dozen


def _json_object(text: str, option: str) -> dict[str, Any]:
    if len(text) > JSON_LIMIT:
        raise CommandError(f"{option}: {len(text)} characters of JSON; at most {JSON_LIMIT}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise CommandError(f"{option}: not valid JSON ({error})") from None
    except RecursionError:
        raise CommandError(f"{option}: the JSON nests too deeply") from None
    except ValueError as error:  # e.g. an integer of more than 4300 digits
        raise CommandError(f"{option}: not usable JSON ({str(error)[:200]})") from None
    if not isinstance(value, dict):
        raise CommandError(f"{option}: expected a JSON object such as '{{\"noise\": 0.02}}'")
    return value


def _parsed(text: str, kind: type[int] | type[float]) -> Any:
    """An option's text as an int or a float; argparse's one-line error where it is not."""
    try:
        return kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"{text[:40]!r} is not {what}") from None


def _seed(text: str) -> int:
    """A --seed: an integer in [0, 2^63), as numpy and the scenario files store seeds."""
    value = _parsed(text, int)
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"{text[:40]} is outside [0, 2^63 - 1]")
    return value


def _at_least_one(text: str) -> int:
    """A count option (processes, ...): an integer of at least 1."""
    value = _parsed(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be at least 1")
    return value


def _updates_per_step(text: str) -> float:
    """--updates-per-step: gradient updates per acquisition, in (0, MAX_UPDATES_PER_STEP]."""
    from alignrl.config import MAX_UPDATES_PER_STEP

    value = _parsed(text, float)
    if not 0 < value <= MAX_UPDATES_PER_STEP:
        raise argparse.ArgumentTypeError(
            f"{text[:40]} must be above 0 and at most {MAX_UPDATES_PER_STEP} updates per "
            "acquisition"
        )
    return value


def _renamed(config: Any, name: str) -> Any:
    """`config` under the run name of --name, validated as a name in the file would be."""
    from alignrl.config import parse_config

    return parse_config(type(config), {**config.model_dump(), "name": name}, "--name")


def _emit(payload: dict[str, Any], as_json: bool, lines: Sequence[str]) -> None:
    if as_json:
        print(json.dumps(payload, indent=2, sort_keys=True))
    else:
        print("\n".join(lines))


# --- record -----------------------------------------------------------------------------


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


# --- scenarios validate -----------------------------------------------------------------


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


# --- evaluate and baselines ---------------------------------------------------------------


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
    """Refuse a --policy that names nothing evaluate can load."""
    from alignrl.evaluation.baselines import CLASSICAL

    if not (spec.startswith("champion:") or Path(spec).exists()):
        raise CommandError(
            f"unknown policy {spec!r}: give a run directory, a checkpoint file, an "
            f"exported policy directory, champion:NAME, or one of {', '.join(sorted(CLASSICAL))}"
        )


def _trained_controller(spec: str):
    """A trained aligner as a session controller: whatever `align` runs (a run directory, a
    checkpoint, an exported policy, champion:NAME), resolved the same way."""
    from alignrl.deploy.policy import load_deployable
    from alignrl.evaluation.controllers import PolicyController

    policy = load_deployable(spec)
    return PolicyController(
        name=policy.name, act=policy.act, task=policy.task, history=policy.history
    )


def cmd_train(args: argparse.Namespace) -> int:
    from alignrl.config import load_experiment
    from alignrl.training import Trainer

    if args.resume:
        if args.config or args.name is not None:
            given = "an experiment config" if args.config else "--name"
            raise CommandError(
                f"--resume RUN continues RUN with its own config and name: give {given} or "
                "--resume, not both"
            )
        trainer = Trainer.resume(args.resume)
    else:
        if not args.config:
            raise CommandError("give an experiment config (experiments/X.yaml) or --resume RUN")
        config = load_experiment(args.config)
        if args.name is not None:
            config = _renamed(config, args.name)
        if config.adaptation is not None:
            # An adaptation written as a YAML (e.g. a copy of a run's config.yaml with other
            # settings): it starts from its source, as `alignrl adapt` does, never from scratch.
            from alignrl.adaptation import start_adaptation
            from alignrl.deploy.export import ExportError, resolve_source

            try:
                source = resolve_source(config.adaptation.source)
            except ExportError as error:
                raise CommandError(f"{args.config}: adaptation.source: {error}") from None
            trainer = start_adaptation(config, source, args.runs_dir)
            return _train_to_the_end(trainer, args, "alignrl adapt --resume")
        trainer = Trainer.create(config, args.runs_dir)
    return _train_to_the_end(trainer, args, "alignrl train --resume")


def _train_to_the_end(trainer: Any, args: argparse.Namespace, resume: str) -> int:
    """Run a Trainer (alignrl train or adapt) to its budget; one summary at the end. SIGTERM
    (a `kill`, a job scheduler) stops it as Ctrl-C does."""
    from alignrl.agents.sac import NonFiniteError
    from alignrl.deploy.align import operator_signals

    run_dir = trainer.run_dir
    from tqdm import tqdm

    log = None if args.quiet else (lambda line: tqdm.write(line, file=sys.stderr))
    if trainer.finished:
        finished = f"{run_dir} is finished at {trainer.env_steps} env steps: nothing to train"
        print(finished, file=sys.stderr)
    started = time.perf_counter()
    try:
        with operator_signals():
            result = trainer.run(progress=not args.quiet, log=log)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted at {trainer.env_steps} env steps; the last checkpoint is kept: "
            f"continue with `{resume} {run_dir}`",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except NonFiniteError as error:
        raise CommandError(
            f"training stopped: {error}; the last checkpoint in {run_dir} is intact"
        ) from None
    except ShieldStop as error:  # main() says which kind; here, what the run keeps
        raise type(error)(
            f"{error}; the last checkpoint in {run_dir} is kept: continue with "
            f"`{resume} {run_dir}` once the instrument answers"
        ) from None
    payload = {
        "run": str(run_dir),
        "env_steps": trainer.env_steps,
        "updates": trainer.agent.updates,
        "episodes": trainer.episodes,
        "successes": result.successes,
        "scenarios": result.scenarios,
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": result.p90_acquisitions,
        "best_successes": trainer.best_successes,
        "seconds": round(time.perf_counter() - started, 1),
    }
    _emit(
        payload,
        args.json,
        [
            f"{run_dir}: {trainer.env_steps} env steps, {trainer.agent.updates} updates; "
            f"held-out {result.successes}/{result.scenarios} aligned, median "
            f"{result.median_acquisitions:g} acquisitions (best {trainer.best_successes})"
        ],
    )
    return 0


def cmd_adapt(args: argparse.Namespace) -> int:
    from alignrl.training import Trainer

    if args.resume:
        trainer = Trainer.resume(args.resume)
        if trainer.config.adaptation is None:
            raise CommandError(f"{args.resume} is a training run, not an adaptation: use train")
        return _train_to_the_end(trainer, args, "alignrl adapt --resume")
    from alignrl.adaptation import adaptation_config, start_adaptation
    from alignrl.deploy.export import ExportError, resolve_source

    if not (args.source and args.apparatus and args.steps):
        raise CommandError("give --from RUN_OR_POLICY, --apparatus SPEC and --steps N")
    try:
        source = resolve_source(args.source, args.member)
    except ExportError as error:
        raise CommandError(str(error)) from None
    apparatus_args = _json_object(args.apparatus_args, "--apparatus-args")
    eval_args = (
        _json_object(args.eval_apparatus_args, "--eval-apparatus-args")
        if args.eval_apparatus_args is not None
        else None
    )
    safe_name = "".join(c if c.isalnum() or c in "-_." else "-" for c in args.apparatus)
    config = adaptation_config(
        source,
        name=args.name or f"{source.agent.id}-on-{safe_name}".strip("-"),
        apparatus=args.apparatus,
        apparatus_args=apparatus_args,
        steps=args.steps,
        eval_apparatus=args.eval_apparatus,
        eval_apparatus_args=eval_args,
        eval_every=args.eval_every,
        eval_scenarios=args.eval_scenarios,
        envs=args.envs,
        seed=args.seed,
        limits=_json_object(args.limits, "--limits"),
        max_step=_json_object(args.max_step, "--max-step"),
        call_timeout_s=args.call_timeout,
        spec_px=args.spec_px,
        updates_per_step=args.updates_per_step,
        critic_warmup_steps=args.critic_warmup,
        hindsight_secrets=args.hindsight_secrets,
        hindsight_optimum=args.hindsight_optimum,
    )
    try:
        trainer = start_adaptation(config, source, args.runs_dir)
    except ShieldStop as error:
        run_dir = Path(args.runs_dir) / config.name
        raise type(error)(
            f"{error}; the adaptation stopped in its zero-shot session, before its first "
            f"checkpoint: {run_dir} keeps only its audit log; run the same command again once "
            "the instrument answers"
        ) from None
    return _train_to_the_end(trainer, args, "alignrl adapt --resume")


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


def cmd_report(args: argparse.Namespace) -> int:
    from alignrl.plots import write_run_report

    report = write_run_report(Path(args.run), Path(args.out) if args.out else None)
    figures = report.figures
    payload = {
        "run": args.run,
        "report": str(report.markdown),
        "figures": [str(path) for path in figures.written],
        "skipped": figures.skipped,
    }
    lines = [
        f"{args.run}: report in {report.markdown}",
        *(f"  {path}" for path in figures.written),
        *(f"  not plotted: {name} ({why})" for name, why in figures.skipped.items()),
    ]
    _emit(payload, args.json, lines)
    return 0


def _leaderboard_lines(rows: list[dict[str, Any]]) -> list[str]:
    header = (
        f"{'member':28} {'team':10} {'architecture':36} {'learner':7} {'rating':>7} "
        f"{'eval':>7} {'median acq':>10}  parent"
    )
    lines = [header, "-" * len(header)]
    for row in rows:
        evaluation = (
            f"{row['successes']}/{row['scenarios']}" if row["successes"] is not None else "-"
        )
        median = row["median_acquisitions"]
        lines.append(
            f"{row['member']:28} {row['team']:10} {row['architecture'][:36]:36} "
            f"{row['learner']:7} {row['rating']:7.1f} {evaluation:>7} "
            f"{'-' if median is None else f'{median:g}':>10}  {row['parent'] or ''}"
        )
    return lines


def _emit_with_league_report(
    payload: dict[str, Any],
    as_json: bool,
    lines: list[str],
    run_dir: Path,
    rows: list[dict[str, Any]],
) -> None:
    """The table first (drawing the report takes a while), then the report and where it went."""
    from alignrl.league.report import write_league_report

    if not as_json:
        print("\n".join(lines), flush=True)
    report = write_league_report(run_dir, rows)
    _emit(
        {**payload, "report": str(report)},
        as_json,
        [f"report: {report} and {report.with_suffix('.html')}"],
    )


def _run_league(league: Any, args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from alignrl.agents.sac import NonFiniteError
    from alignrl.deploy.align import operator_signals
    from alignrl.league.loop import WorkerFailedError, leaderboard

    log = None if args.quiet else (lambda line: tqdm.write(line, file=sys.stderr))
    started = time.perf_counter()
    try:
        with operator_signals():  # SIGTERM stops the league as Ctrl-C does
            league.run(progress=not args.quiet, log=log)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted at iteration {league.iteration}; the last checkpoint is kept: "
            f"continue with `alignrl league resume {league.run_dir}`",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except (NonFiniteError, WorkerFailedError) as error:
        raise CommandError(
            f"league stopped: {error}; the last checkpoint in {league.run_dir} is intact"
        ) from None
    except ShieldStop as error:  # main() says which kind; here, what the run keeps
        raise type(error)(
            f"{error}; the last checkpoint in {league.run_dir} is kept: continue with "
            f"`alignrl league resume {league.run_dir}` once the instrument answers"
        ) from None
    finally:
        league.close()  # a Ray backend's workers
    rows = leaderboard(league)
    champion = league.champion()
    payload = {
        "run": str(league.run_dir),
        "iterations": league.iteration,
        "env_steps": league.env_steps,
        "seconds": round(time.perf_counter() - started, 1),
        "leaderboard": rows,
        "champion": champion,
    }
    lines = _leaderboard_lines(rows)
    if champion:
        lines.append("")
        lines += [
            f"{label:9}: {row['member']} aligned {row['successes']}/{row['scenarios']} "
            f"held-out, median {row['median_acquisitions']:g} acquisitions"
            for label, row in champion.items()
        ]
    _emit_with_league_report(payload, args.json, lines, league.run_dir, rows)
    return 0


def cmd_league_run(args: argparse.Namespace) -> int:
    from alignrl.league.config import load_league
    from alignrl.league.loop import League

    config, aligners, misaligners = load_league(args.config)
    if args.name is not None:
        config = _renamed(config, args.name)
    return _run_league(League.create(config, aligners, misaligners, args.runs_dir), args)


def cmd_league_resume(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League

    return _run_league(League.resume(args.run), args)


def cmd_league_status(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League

    league = League.resume(args.run, read_only=True)
    schedule = league.config.schedule
    payload = {
        "run": args.run,
        "iteration": league.iteration,
        "iterations": schedule.iterations,
        "env_steps": league.env_steps,
        "complexity": league.backend.complexity,
        "members": {team: league.pool.active(team) for team in ("aligner", "misaligner")},
        "snapshots": {
            team: [snapshot.id for snapshot in league.pool.snapshots(team)]
            for team in ("aligner", "misaligner")
        },
        "best": list(league.best.values()),
    }
    lines = [
        f"{args.run}: iteration {league.iteration} of {schedule.iterations}, "
        f"{league.env_steps} env steps, complexity {payload['complexity']:g}",
        *(f"  {team}s: {', '.join(ids)}" for team, ids in payload["members"].items()),
        *(
            f"  best: {row['member']} {row['successes']}/{row['scenarios']} at iteration "
            f"{row['iteration']}"
            for row in payload["best"]
        ),
    ]
    _emit(payload, args.json, lines)
    return 0


def cmd_leaderboard(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League, leaderboard

    league = League.resume(args.run, read_only=True)
    rows = leaderboard(league)
    payload = {"run": args.run, "leaderboard": rows}
    _emit_with_league_report(payload, args.json, _leaderboard_lines(rows), league.run_dir, rows)
    return 0


# --- align ------------------------------------------------------------------------------


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _setting_text(setting: dict[str, float] | None) -> str:
    if setting is None:
        return "unknown"
    return ", ".join(f"{knob} {value:.4g}" for knob, value in setting.items())


def cmd_align(args: argparse.Namespace) -> int:
    """One alignment through the safety shield; the exit code says how it ended
    (alignrl/deploy/align.py: 0 aligned, 1 not, 2 config, 3 aborted, 4 driver failure)."""
    from alignrl.apparatus.registry import build_apparatus
    from alignrl.apparatus.shield import JsonLinesAudit, MemoryAudit, resolve_limits
    from alignrl.deploy.align import EXIT_ABORTED, EXIT_DRIVER, align, operator_signals
    from alignrl.deploy.policy import load_deployable
    from alignrl.envs.task import get_task

    apparatus_args = _json_object(args.apparatus_args, "--apparatus-args")
    site_limits = _json_object(args.limits, "--limits")
    max_step = _json_object(args.max_step, "--max-step")
    with operator_signals():
        try:
            policies = []
            for source in args.policy:
                try:
                    policies.append(load_deployable(source))
                except ImportError as error:  # an ONNX policy without onnxruntime
                    raise CommandError(f"cannot run policy {source}: {error}") from None
            judged = get_task(args.task) if args.task is not None else None
            if len(policies) > 1 and judged is None:
                raise CommandError(
                    "several --policy run in sequence and need --task, the task the column "
                    "is judged on (e.g. --task column)"
                )
            if len(policies) == 1 and judged is not None and judged.name != policies[0].task.name:
                raise CommandError(
                    f"policy {policies[0].name!r} aligns task {policies[0].task.name!r}, "
                    f"not {args.task!r}"
                )
            try:
                # Unshielded here: align() puts its own shield (with the watchdog) around it.
                apparatus = build_apparatus(
                    args.apparatus, apparatus_args, args.seed, args.call_timeout
                )
            except ApparatusError as error:
                print(f"alignrl: apparatus error: {error}", file=sys.stderr)
                return EXIT_DRIVER
            limits = resolve_limits(apparatus.knobs, site_limits, max_step)
        except KeyboardInterrupt:
            print("\ninterrupted before the alignment started: nothing written", file=sys.stderr)
            return EXIT_ABORTED
        audit = JsonLinesAudit(args.log) if args.log else MemoryAudit()
        try:
            result = align(
                policies,
                apparatus,
                limits,
                audit,
                task=judged,
                apparatus_spec=args.apparatus,
                spec_px=args.spec_px,
                dry_run=args.dry_run,
                timeout_s=args.timeout,
                call_timeout_s=args.call_timeout,
                max_acquisitions=args.max_acquisitions,
                restore_on_abort=args.restore_on_abort,
                log_path=args.log,
            )
        except KeyboardInterrupt:  # before the alignment began: it handles its own
            print("\ninterrupted before the alignment started: nothing written", file=sys.stderr)
            return EXIT_ABORTED
        finally:
            if isinstance(audit, JsonLinesAudit):
                audit.close()
    lines = [
        f"{result.outcome}: {result.reason}",
        f"  policy {result.policy} on {result.apparatus}: "
        f"{_count(result.acquisitions, 'acquisition')}, {_count(result.writes, 'write')} "
        f"({result.clamped} clamped, {result.refused} refused)"
        + (" - dry run: nothing was written" if result.dry_run else ""),
        f"  start {_setting_text(result.start_setting)}; "
        f"left at {_setting_text(result.final_setting)}"
        + (" (start restored)" if result.restored else ""),
    ]
    if result.log:
        lines.append(f"  audit log: {result.log}")
    _emit(result.to_dict(), args.json, lines)
    return result.exit_code


# --- export -----------------------------------------------------------------------------


def cmd_export(args: argparse.Namespace) -> int:
    from alignrl.deploy.export import export_command, export_policy, resolve_source

    started = time.perf_counter()
    source = resolve_source(args.run, args.member)
    command = export_command(args.run, args.member, args.format, args.out)
    try:
        result = export_policy(source, args.out, args.format, force=args.force, command=command)
    except ImportError as error:  # the optional extra: its message says what to install
        raise CommandError(str(error)) from None
    card, parity = result.card, result.parity
    payload = {
        "run": args.run,
        "member": card["member"]["id"],
        "chosen_as": card["source"]["chosen_as"],
        "format": args.format,
        "out": str(result.out),
        "policy": str(result.policy_file),
        "card": str(result.out / "card.json"),
        "model_card": str(result.out / "model_card.md"),
        "inputs": card["inputs"],
        "outputs": card["outputs"],
        "history": card["history"],
        "knobs": card["knobs"],
        "memory": card["memory"]["kind"],
        "parity_histories": parity.histories,
        "parity_max_abs_difference": parity.max_abs_difference,
        "seconds": round(time.perf_counter() - started, 2),
    }

    def shapes(side: str) -> str:
        return ", ".join(
            f"{entry['name']} {entry['dtype']} ({', '.join(map(str, entry['shape']))})"
            for entry in card[side]
        )

    lines = [
        f"exported {payload['member']} ({payload['chosen_as']} of {args.run}) as "
        f"{args.format}: {result.policy_file}",
        f"  inputs:  {shapes('inputs')}",
        f"  outputs: {shapes('outputs')}",
        *(
            f"  knob:    {knob['name']} in [{knob['low']:g}, {knob['high']:g}], at most "
            f"{knob['max_step']:g} per action"
            for knob in card["knobs"]
        ),
        f"  memory:  {card['memory']['note']}",
        f"  parity:  max |{args.format} - PyTorch| = {parity.max_abs_difference:.2g} on "
        f"{parity.histories} random histories (allowed {parity.tolerance:g})",
        f"  model card: {payload['model_card']} and {payload['card']}",
    ]
    _emit(payload, args.json, lines)
    return 0


def _add_shield_options(
    parser: argparse.ArgumentParser, limits: bool = True, log: bool = True
) -> None:
    """The options of every verb that may touch an instrument: a driver's calls all pass the
    shield (alignrl/apparatus/shield.py); these set its site limits, largest step, call time
    limit and audit log."""
    if limits:
        parser.add_argument(
            "--limits",
            default="{}",
            metavar="JSON",
            help="site limits inside the knobs' intervals, e.g. '{\"defocus\": [40, 60]}'",
        )
        parser.add_argument(
            "--max-step",
            default="{}",
            metavar="JSON",
            help="largest change per write, e.g. '{\"defocus\": 2.0}' (instrument units)",
        )
    parser.add_argument(
        "--call-timeout",
        type=float,
        default=DEFAULT_CALL_TIMEOUT_S,
        metavar="S",
        help="longest one driver call may take before it is abandoned and the work ends "
        f"(default: {DEFAULT_CALL_TIMEOUT_S:g} s)",
    )
    if log:
        parser.add_argument("--log", metavar="FILE", help="audit log of driver calls, JSON lines")


def _shield_options(args: argparse.Namespace) -> Any:
    """The ShieldOptions of a verb with _add_shield_options; the audit log (a file with
    --log, else the newest records in memory) is closed by the caller."""
    from alignrl.apparatus.shield import JsonLinesAudit, ShieldOptions

    if not (args.call_timeout > 0 and np.isfinite(args.call_timeout)):
        raise CommandError(f"--call-timeout must be positive seconds, got {args.call_timeout}")
    return ShieldOptions(
        site_limits=_json_object(getattr(args, "limits", "{}"), "--limits"),
        max_step=_json_object(getattr(args, "max_step", "{}"), "--max-step"),
        call_timeout_s=args.call_timeout,
        audit=JsonLinesAudit(args.log) if args.log else None,
    )


def _add_session_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--apparatus", required=True, help="apparatus spec, e.g. synthetic")
    parser.add_argument("--apparatus-args", default="{}", help="JSON keyword arguments")
    parser.add_argument(
        "--task",
        default=None,
        help="alignment task: focus, stigmation, aperture or column (default: focus; for a "
        "trained aligner, its own task)",
    )
    parser.add_argument(
        "--scenarios", type=int, default=100, help="alignments in the session (default: 100)"
    )
    parser.add_argument("--seed", type=_seed, default=0, help="seed of the scenarios and starts")
    parser.add_argument(
        "--spec-px",
        type=float,
        default=None,
        help="absolute success threshold, edge width in px (default: relative to the best "
        "the apparatus can reach; required where it cannot say)",
    )
    # The default is resolved by the handler: importing the session here would load the
    # RL environments (gymnasium) for every verb.
    parser.add_argument(
        "--budget",
        type=int,
        default=None,
        help="most acquisitions per alignment (default: 50; column: 63, the most a column "
        "episode takes)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="machine-readable summary")
    _add_shield_options(parser)


# --- the parser -------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    from alignrl.config import HINDSIGHT_OPTIMA

    parser = argparse.ArgumentParser(
        prog="alignrl",
        description="Train and run reinforcement-learning agents that align electron microscopes.",
    )
    parser.add_argument("--version", action="version", version=f"alignrl {__version__}")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")

    record = verbs.add_parser(
        "record", help="sweep an apparatus into a scenario CSV (seed section 4.3)"
    )
    record.add_argument("--apparatus", required=True, help="apparatus spec, e.g. synthetic")
    record.add_argument("--apparatus-args", default="{}", help="JSON keyword arguments")
    record.add_argument("--scenarios", type=int, required=True, help="total scenarios wanted")
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

    evaluate = verbs.add_parser(
        "evaluate", help="an evaluation session: N alignments checked against the spec"
    )
    evaluate.add_argument(
        "--policy",
        required=True,
        action="append",
        help="a run directory (training: its best checkpoint; league: its champion), a "
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

    train = verbs.add_parser(
        "train", help="train one aligner against the built-in misalignment (pre-training)"
    )
    train.add_argument("config", nargs="?", help="experiment YAML, e.g. experiments/X.yaml")
    train.add_argument("--name", help="run name (default: the config's name)")
    train.add_argument("--runs-dir", default="runs", help="where run directories go")
    train.add_argument("--resume", metavar="RUN", help="continue runs/NAME from its checkpoint")
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.add_argument("--json", action="store_true", help="machine-readable summary")
    train.set_defaults(handler=cmd_train)

    adapt = verbs.add_parser(
        "adapt", help="continue training a pre-trained aligner on another apparatus, shielded"
    )
    adapt.add_argument(
        "--from",
        dest="source",
        metavar="RUN_OR_POLICY",
        help="a league run (its champion), a training run or a member .pt file",
    )
    adapt.add_argument("--member", help="a league run's member id instead of its champion")
    adapt.add_argument(
        "--apparatus", help="the new apparatus spec (preset, csv:, sem:, import path)"
    )
    adapt.add_argument("--apparatus-args", default="{}", help="JSON arguments of the apparatus")
    adapt.add_argument("--steps", type=int, help="adaptation env steps (acquisitions)")
    adapt.add_argument("--name", help="run name (default: <member>-on-<apparatus>)")
    adapt.add_argument("--runs-dir", default="runs", help="where run directories go")
    adapt.add_argument(
        "--eval-apparatus", help="apparatus of the evaluation sessions (default: the new one)"
    )
    adapt.add_argument("--eval-apparatus-args", help="JSON arguments of the evaluation apparatus")
    adapt.add_argument(
        "--eval-every", type=int, help="env steps between evaluations (default: steps/4)"
    )
    adapt.add_argument("--eval-scenarios", type=int, default=100, help="alignments per evaluation")
    adapt.add_argument("--envs", type=int, default=8, help="apparatus instances stepped together")
    adapt.add_argument("--seed", type=_seed, default=0, help="seeds the adaptation run")
    _add_shield_options(adapt, log=False)  # the audit log is the run's audit.jsonl
    adapt.add_argument(
        "--spec-px",
        type=float,
        help="absolute success spec, edge width in px (needed where the apparatus cannot "
        "tell its best width)",
    )
    adapt.add_argument(
        "--updates-per-step",
        type=_updates_per_step,
        help="(SAC) gradient updates per acquisition (default: the source's)",
    )
    adapt.add_argument(
        "--critic-warmup",
        type=int,
        default=0,
        metavar="STEPS",
        help="env steps in which only the critics learn (the policy acts as the source did)",
    )
    adapt.add_argument(
        "--no-hindsight-secrets",
        dest="hindsight_secrets",
        action="store_false",
        help="on an apparatus that cannot tell its optimum, give the critics zeros for the "
        "secret instead of the episode's optimum found in hindsight",
    )
    adapt.add_argument(
        "--hindsight-optimum",
        choices=HINDSIGHT_OPTIMA,
        default="posterior",
        help="what stands in for an episode's optimum in hindsight: a draw from its posterior "
        "on the column's pooled focus curve (default), or the setting of its sharpest reading",
    )
    adapt.add_argument("--resume", metavar="RUN", help="continue an adaptation run")
    adapt.add_argument("--quiet", action="store_true", help="no progress bar")
    adapt.add_argument("--json", action="store_true", help="machine-readable summary")
    adapt.set_defaults(handler=cmd_adapt)

    report = verbs.add_parser("report", help="training figures and a Markdown report of a run")
    report.add_argument("run", metavar="RUN", help="a run directory of `alignrl train`")
    report.add_argument("--out", metavar="DIR", help="where to write (default: RUN/report)")
    report.add_argument("--json", action="store_true", help="machine-readable summary")
    report.set_defaults(handler=cmd_report)

    league = verbs.add_parser("league", help="the two-team league: run, resume, status")
    league_verbs = league.add_subparsers(dest="league_verb", required=True)
    league_run = league_verbs.add_parser("run", help="start a league from an experiment")
    league_run.add_argument("config", help="league experiment YAML, e.g. experiments/X.yaml")
    league_run.add_argument("--name", help="run name (default: the config's name)")
    league_run.add_argument("--runs-dir", default="runs", help="where run directories go")
    league_resume = league_verbs.add_parser("resume", help="continue a league from its checkpoint")
    league_resume.add_argument("run", metavar="RUN", help="a league run directory")
    for parser_ in (league_run, league_resume):
        parser_.add_argument("--quiet", action="store_true", help="no progress bar")
        parser_.add_argument("--json", action="store_true", help="machine-readable summary")
    league_run.set_defaults(handler=cmd_league_run)
    league_resume.set_defaults(handler=cmd_league_resume)
    league_status = league_verbs.add_parser("status", help="where a league run stands")
    league_status.add_argument("run", metavar="RUN", help="a league run directory")
    league_status.add_argument("--json", action="store_true", help="machine-readable summary")
    league_status.set_defaults(handler=cmd_league_status)

    board = verbs.add_parser("leaderboard", help="the members of a league run, best first")
    board.add_argument("run", metavar="RUN", help="a league run directory")
    board.add_argument("--json", action="store_true", help="machine-readable summary")
    board.set_defaults(handler=cmd_leaderboard)

    align = verbs.add_parser(
        "align", help="align an apparatus with a trained policy, through the safety shield"
    )
    align.add_argument(
        "--policy",
        required=True,
        action="append",
        help="a run directory (training or league), a checkpoint .pt, an exported policy "
        "directory, or champion:NAME; give it several times (with --task) to run task "
        "champions in that order, e.g. aperture, focus, stigmation for --task column",
    )
    align.add_argument("--apparatus", required=True, help="apparatus spec, e.g. synthetic")
    align.add_argument("--apparatus-args", default="{}", help="JSON keyword arguments")
    align.add_argument(
        "--task",
        default=None,
        help="the task the alignment is judged on (default: the policy's own; required with "
        "several --policy)",
    )
    align.add_argument(
        "--spec-px",
        type=float,
        default=None,
        help="success threshold, edge width in px (default: relative to the best the "
        "apparatus can reach, where it can say)",
    )
    _add_shield_options(align)
    align.add_argument(
        "--dry-run", action="store_true", help="decide and log every write, make none"
    )
    align.add_argument(
        "--timeout", type=float, default=None, metavar="S", help="watchdog: end after S seconds"
    )
    align.add_argument(
        "--max-acquisitions",
        type=int,
        default=None,
        metavar="N",
        help="watchdog: at most N images (default: the task's episode steps + 1)",
    )
    align.add_argument(
        "--restore-on-abort",
        action="store_true",
        help="after Ctrl-C, SIGTERM or the watchdog, write the starting setting back",
    )
    align.add_argument("--seed", type=_seed, default=0, help="seed of a simulated apparatus")
    align.add_argument("--json", action="store_true", help="machine-readable result")
    align.set_defaults(handler=cmd_align)

    export = verbs.add_parser(
        "export",
        help="an aligner as a self-contained ONNX, TorchScript or safetensors policy with its card",
    )
    export.add_argument(
        "run",
        metavar="RUN",
        help="a league run (its champion), a training run (its best checkpoint) or a member "
        ".pt file",
    )
    export.add_argument("--member", metavar="ID", help="this member of a league run instead")
    export.add_argument(
        "--format",
        required=True,
        choices=("onnx", "torchscript", "safetensors"),
        help="policy.onnx (needs: pip install 'alignrl[onnx]'), policy.pt (torch.jit) or "
        "policy.safetensors (the network's weights; no extra dependencies)",
    )
    export.add_argument("--out", required=True, metavar="DIR", help="folder to write")
    export.add_argument("--force", action="store_true", help="replace a non-empty --out")
    export.add_argument("--json", action="store_true", help="machine-readable summary")
    export.set_defaults(handler=cmd_export)
    return parser


MESSAGE_LIMIT = 2000  # characters of one error message: never an echo of an unbounded value


def _message(error: BaseException) -> str:
    text = str(error)
    if len(text) <= MESSAGE_LIMIT:
        return text
    return f"{text[:MESSAGE_LIMIT]}... ({len(text) - MESSAGE_LIMIT} more characters not shown)"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Ctrl-C must reach the recorder's handler as KeyboardInterrupt, also under `make`.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return int(args.handler(args))
    except ShieldStop as error:  # the shield ended work on an instrument: nothing more sent
        failure = isinstance(error, DriverFailure)
        print(
            f"alignrl: {'driver failure' if failure else 'stopped by the shield'}: "
            f"{_message(error)}; nothing more was sent to the apparatus",
            file=sys.stderr,
        )
        return EXIT_DRIVER_FAILURE if failure else EXIT_SHIELD_STOP
    except ApparatusError as error:  # before ValueError: NoEdgesError is both
        print(f"alignrl: apparatus error: {_message(error)}", file=sys.stderr)
        return EXIT_USAGE
    except (CommandError, ValueError, OSError) as error:
        print(f"alignrl: error: {_message(error)}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as error:  # the last resort: a bug, said in one line, never a traceback
        if os.environ.get("ALIGNRL_DEBUG"):
            raise
        print(
            f"alignrl: internal error ({type(error).__name__}: {_message(error)}); this is a "
            "bug in alignrl: please report it with the command (ALIGNRL_DEBUG=1 shows the "
            "traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())

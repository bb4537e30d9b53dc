"""`alignrl train`, `alignrl adapt` and `alignrl report`: train one aligner (pre-training,
against the built-in misalignment), continue a trained one on another apparatus through the
shield, and draw a training run's figures. Ctrl-C or SIGTERM keeps the last checkpoint."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.apparatus.shield import ShieldStop
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_apparatus_options,
    _add_override_options,
    _add_shield_options,
    _checkpoint_kept,
    _emit,
    _json_object,
    _new_run,
    _overrides,
    _replace_run,
    _seed,
    _updates_per_step,
)

if TYPE_CHECKING:
    from alignrl.runs.lock import RunLock


def cmd_train(args: argparse.Namespace) -> int:
    from alignrl.config.experiment import load_experiment
    from alignrl.training import Trainer

    overrides = _overrides(args)
    if args.resume:
        given = [
            what
            for what, there in (
                ("an experiment config", args.config),
                ("--name", args.name is not None),
                ("--set or --seed", overrides),
                ("--force", args.force),
            )
            if there
        ]
        if given:
            raise CommandError(
                f"--resume RUN continues RUN with its own config and name: give {given[0]} or "
                "--resume, not both (--steps N gives it a new budget)"
            )
        return _train_to_the_end(
            lambda _: _resumed(args), args, "alignrl train --resume", Path(args.resume), new=False
        )
    if not args.config:
        raise CommandError("give an experiment config (experiments/X.yaml) or --resume RUN")
    if args.steps is not None:
        overrides.append(f"budget.env_steps={args.steps}")
    config = load_experiment(args.config, overrides)
    config, run_dir = _new_run(config, overrides, args)

    def replaced(lock: RunLock) -> None:
        _replace_run(lock, args.force, "alignrl train --resume")

    if config.adaptation is not None:
        # An adaptation written as a YAML (e.g. a copy of a run's config.yaml with other
        # settings): it starts from its source, as `alignrl adapt` does, never from scratch.
        from alignrl.adaptation import check_adaptable
        from alignrl.runs.sources import ExportError, resolve_source
        from alignrl.training import start_adaptation

        try:
            source = resolve_source(config.adaptation.source)
            check_adaptable(source, config.adaptation.source)
        except ExportError as error:
            raise CommandError(f"{args.config}: adaptation.source: {error}") from None

        def adaptation(lock: RunLock) -> Any:
            replaced(lock)
            return start_adaptation(config, source, args.runs_dir)

        return _train_to_the_end(adaptation, args, "alignrl adapt --resume", run_dir)

    def training(lock: RunLock) -> Any:
        replaced(lock)
        return Trainer.create(config, args.runs_dir)

    return _train_to_the_end(training, args, "alignrl train --resume", run_dir)


def _resumed(args: argparse.Namespace) -> Any:
    """The Trainer of --resume RUN, with the budget of --steps N where given."""
    from alignrl.training import Trainer

    return Trainer.resume(args.resume, env_steps=args.steps)


def _train_to_the_end(
    start: Callable[[RunLock], Any],
    args: argparse.Namespace,
    resume: str,
    run_dir: Path,
    new: bool = True,
) -> int:
    """The one way of every training run (alignrl train and adapt, new or resumed): lock
    `run_dir` (a second process on the same run is refused at once, before either reads or
    writes a file of it), `start` its Trainer under the lock, and run it to its budget."""
    from alignrl.runs.lock import RunLock

    with RunLock(run_dir, create=new) as lock:
        return _trained(start(lock), args, resume)


def _trained(trainer: Any, args: argparse.Namespace, resume: str) -> int:
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
    except ShieldStop as error:
        raise _checkpoint_kept(error, run_dir, resume) from None
    from alignrl.intervals import success_interval, success_text
    from alignrl.training import VALIDATION_SEED, test_line

    test = trainer.test_result
    payload = {
        "run": str(run_dir),
        "env_steps": trainer.env_steps,
        "updates": trainer.agent.updates,
        "episodes": trainer.episodes,
        "validation_seed": VALIDATION_SEED,
        "successes": result.successes,
        "scenarios": result.scenarios,
        "success_interval": success_interval(result.successes, result.scenarios),
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": result.p90_acquisitions,
        "best_successes": trainer.best_successes,
        "test": None
        if test is None
        else {
            **asdict(test),
            "success_interval": success_interval(test.successes, test.scenarios),
        },
        "seconds": round(time.perf_counter() - started, 1),
    }
    lines = [
        f"{run_dir}: {trainer.env_steps} env steps, {trainer.agent.updates} updates; last "
        f"validation session {success_text(result.successes, result.scenarios)} aligned, "
        f"median {result.median_acquisitions:g} acquisitions (best {trainer.best_successes})"
    ]
    _emit(payload, args.json, lines + ([test_line(test)] if test else []))
    return 0


def cmd_adapt(args: argparse.Namespace) -> int:

    if args.resume:

        def resumed(_: RunLock) -> Any:
            trainer = _resumed(args)
            if trainer.config.adaptation is None:
                raise CommandError(f"{args.resume} is a training run, not an adaptation: use train")
            return trainer

        resume = "alignrl adapt --resume"
        return _train_to_the_end(resumed, args, resume, Path(args.resume), new=False)
    from alignrl.adaptation import adaptation_config, check_adaptable
    from alignrl.runs.sources import ExportError, resolve_source
    from alignrl.training import check_evaluation_apparatus, start_adaptation

    if not (args.source and args.apparatus and args.steps):
        raise CommandError("give --from RUN_OR_POLICY, --apparatus SPEC and --steps N")
    try:
        source = resolve_source(args.source, args.member)
        check_adaptable(source, args.source)
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
    overrides = _overrides(args)
    if overrides:  # the strict model checks the changed config, key paths named
        from alignrl.config.experiment import ExperimentConfig
        from alignrl.config_reading import overridden, parse_config

        data, where = overridden(config.model_dump(mode="json"), "alignrl adapt", overrides)
        config = parse_config(ExperimentConfig, data, where, check_device=True)
    from alignrl.runs.state import with_provenance

    config = with_provenance(config, overrides, args.argv)
    check_evaluation_apparatus(config)  # before the run directory exists
    run_dir = Path(args.runs_dir) / config.name

    def started(_: RunLock) -> Any:
        try:
            return start_adaptation(config, source, args.runs_dir)
        except ShieldStop as error:
            raise type(error)(
                f"{error}; the adaptation stopped in its zero-shot session, before its first "
                f"checkpoint: {run_dir} keeps only its audit log; run the same command again "
                "once the instrument answers"
            ) from None

    return _train_to_the_end(started, args, "alignrl adapt --resume", run_dir)


def cmd_report(args: argparse.Namespace) -> int:
    from alignrl.runs.report import write_run_report

    report = write_run_report(Path(args.run), Path(args.out) if args.out else None)
    figures = report.figures
    payload = {
        "run": args.run,
        "report": str(report.markdown),
        "html": str(report.html),
        "figures": [str(path) for path in figures.written],
        "skipped": figures.skipped,
    }
    lines = [
        f"{args.run}: report in {report.markdown} and {report.html}",
        *(f"  {path}" for path in figures.written),
        *(f"  not plotted: {name} ({why})" for name, why in figures.skipped.items()),
    ]
    _emit(payload, args.json, lines)
    return 0


def add_training_parsers(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from alignrl.envs.hindsight import HINDSIGHT_OPTIMA

    train = verbs.add_parser(
        "train", help="train one aligner against the built-in misalignment (pre-training)"
    )
    train.add_argument("config", nargs="?", help="experiment YAML, e.g. experiments/X.yaml")
    train.add_argument("--name", help="run name (default: the config's name)")
    train.add_argument("--runs-dir", default="runs", help="where run directories go")
    train.add_argument("--resume", metavar="RUN", help="continue runs/NAME from its checkpoint")
    train.add_argument(
        "--steps",
        type=int,
        metavar="N",
        help="env steps to train (as --set budget.env_steps=N); with --resume, the run's new "
        "budget: a finished run goes on to N",
    )
    _add_override_options(train)
    train.add_argument(
        "--force", action="store_true", help="replace a run of the same name (it is removed)"
    )
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
        help="a league run (its champion), a training run or a member .pt file: a source "
        "with its critics (an exported policy or champion:NAME has none and is refused)",
    )
    adapt.add_argument("--member", help="a league run's member id instead of its champion")
    _add_apparatus_options(
        adapt,
        required=False,
        spec_help="the new apparatus spec (preset, csv:, sem:, import path)",
        args_help="JSON arguments of the apparatus",
    )
    adapt.add_argument(
        "--steps",
        type=int,
        help="adaptation env steps (acquisitions); with --resume, the run's new budget",
    )
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
    _add_override_options(adapt, seed=False)
    adapt.add_argument("--quiet", action="store_true", help="no progress bar")
    adapt.add_argument("--json", action="store_true", help="machine-readable summary")
    adapt.set_defaults(handler=cmd_adapt)

    report = verbs.add_parser(
        "report", help="training figures and a Markdown and HTML report of a run"
    )
    report.add_argument(
        "run",
        metavar="RUN",
        help="a run directory of `alignrl train` or `alignrl adapt` (a league run's report: "
        "`alignrl leaderboard RUN`)",
    )
    report.add_argument("--out", metavar="DIR", help="where to write (default: RUN/report)")
    report.add_argument("--json", action="store_true", help="machine-readable summary")
    report.set_defaults(handler=cmd_report)

"""Clone the Bayesian autofocus over the training box into an aligner (benchmarks/imitation.py).

    python -m benchmarks.imitate collect --config benchmarks/configs/focus-v2-imitate.yaml \
        --episodes 1500 --seed 1 --out runs/s12/teacher-1.npz
    python -m benchmarks.imitate clone --config benchmarks/configs/focus-v2-imitate.yaml \
        --data runs/s12/teacher-1.npz --data runs/s12/teacher-2.npz --runs-dir runs/s12
    python -m benchmarks.imitate collect ... --student runs/s12/focus-v2-imitate --out ...

`collect` plays episodes of the config's training apparatus (the family's columns; never a
held-out instrument: the config is checked as `alignrl train` checks it), the posterior
labelling every step; with `--student RUN` the run's best.pt acts and the posterior only
labels (a DAgger round). `clone` creates the run (as `alignrl train` would), fits its actor to
every file's labels, keeps the replay of the transitions, runs a validation session (best.pt)
and a checkpoint: `alignrl evaluate --policy runs/s12/NAME` judges it, and `alignrl train
--resume` (or `alignrl adapt --from`) continues it with SAC. `agreement` fits a fresh actor on
nine tenths of the steps and prints how closely it follows the teacher on the rest, per
number of readings in its history.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.config.experiment import load_experiment
from alignrl.envs.core import feature_layout
from alignrl.envs.task import knob_change
from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import BayesianAutofocus
from alignrl.posterior.inference import SCALE_FREE
from alignrl.transitions import Transition
from benchmarks.imitation import Demonstrations, PosteriorTeacher, clone, collect


def _collect(args: argparse.Namespace) -> None:
    config = load_experiment(args.config)
    torch.set_num_threads(1)
    task = config.resolved_task()
    apparatus = make_apparatus_copies(config.apparatus, config.apparatus_args, config.envs)
    env = VectorAlignmentEnv(apparatus, task, config.history, complexity=config.complexity)
    student = None
    if args.student:
        from alignrl.runs.training_runs import load_policy

        agent, _ = load_policy(args.student)
        student = lambda observation: agent.act(observation, deterministic=True)  # noqa: E731
    box = load_family(family_path("focus"))
    options = SCALE_FREE if args.teacher == "scale-free" else {}
    teacher = PosteriorTeacher(env, lambda: BayesianAutofocus(box, **options))
    if args.teacher_ends:
        if student is None:
            raise SystemExit(
                "--teacher-ends: the student's stops end as the teacher's; name --student"
            )
        acting = student

        def student(observation: np.ndarray) -> np.ndarray:
            action = np.array(acting(observation), np.float64)
            stops = np.flatnonzero(action[:, 1] > 0)
            action[stops, 0] = teacher.ends(stops)
            return action

    bar = tqdm(total=args.episodes, unit="episode", desc=Path(args.out).stem, dynamic_ncols=True)
    start = time.monotonic()
    data = collect(env, teacher, args.episodes, args.seed, student, progress=bar.update)
    bar.close()
    data.save(args.out)
    acquisitions = np.array(data.acquisitions)
    print(
        f"{args.out}: {data.episodes} episodes, {len(data.label)} steps, "
        f"{data.successes}/{data.episodes} aligned at a median of "
        f"{np.median(acquisitions):g} acquisitions ({time.monotonic() - start:.0f} s)"
    )


def _demonstrations(paths: list[str], config) -> Demonstrations:
    """The files' steps joined, with fit features where the config's task shows them and
    the files were collected without (Demonstrations.with_fit_features), their stopping
    actions moved from the fit where its last move starts there (moved_from_fit)."""
    parts = [Demonstrations.load(path) for path in paths]
    task = config.resolved_task()
    if task.max_step and (task.fit_features or task.ending.at == "fit"):
        raise SystemExit("steps are changed afterwards for max_step_fraction tasks only")
    if task.ending.at == "fit":
        parts = [
            part.moved_from_fit(
                task.max_step_fraction,
                task.action_power,
                task.ending.finish_window,
                task.ending.final_move_reach,
            )
            for part in parts
        ]
    elif any(part.ends_from_fit for part in parts):
        raise SystemExit("steps whose ends move from a fit need a task with finish_at_fit")
    if task.fit_features:
        plain = feature_layout(1)["steps_left"].stop
        parts = [
            part.with_fit_features(2.0 * task.max_step_fraction, task.fit_window)
            if part.observation.shape[2] == plain
            else part
            for part in parts
        ]
    return Demonstrations.joined(parts)


def _clone(args: argparse.Namespace) -> None:
    from alignrl.training import Trainer

    config = load_experiment(args.config, args.set)
    data = _demonstrations(args.data, config)
    trainer = Trainer.create(config, args.runs_dir)
    learner = trainer.agent.learner
    start = time.monotonic()
    loss = clone(
        learner.actor,
        data,
        args.epochs,
        config.seed,
        continue_weight=args.continue_weight,
        learning_rate=args.learning_rate,
        anneal=args.anneal,
        end_weight=args.end_weight,
        log=lambda epoch, value: print(f"epoch {epoch + 1}: loss {value:.4f}", flush=True),
    )
    trainer.agent.observe(
        Transition(
            data.observation,
            data.secret,
            data.action,
            data.reward,
            data.next_observation,
            data.next_secret,
            data.done,
        )
    )
    result = trainer.evaluate_and_keep_best()
    trainer.checkpoint()
    print(
        f"{trainer.run_dir}: cloned on {len(data.label)} steps of {data.episodes} episodes "
        f"(loss {loss:.4f}, {time.monotonic() - start:.0f} s); validation "
        f"{result.successes}/{result.scenarios} at a median of {result.median_acquisitions:g}"
    )


def _agreement(args: argparse.Namespace) -> None:
    """How well a network that sees what a policy sees can follow the teacher: fitted on
    nine tenths of the steps, judged on the rest, per number of readings in its history."""
    from alignrl.agents.sac import Actor
    from alignrl.runs.training_runs import member_spec

    config = load_experiment(args.config, args.set)
    torch.manual_seed(config.seed)
    data = _demonstrations(args.data, config)
    order = np.random.default_rng(config.seed).permutation(len(data.label))
    judged, fitted = order[: len(order) // 10], order[len(order) // 10 :]
    spec = member_spec(config)
    actor = Actor(*spec.observation_shape, spec.action_dim, spec.learner_config())
    clone(
        actor,
        data.rows(fitted),
        args.epochs,
        config.seed,
        learning_rate=args.learning_rate,
        anneal=args.anneal,
        end_weight=args.end_weight,
    )
    test = data.rows(judged)
    with torch.no_grad():
        mean, _ = actor(torch.as_tensor(test.observation))
    action = np.tanh(mean.numpy())
    readings = test.observation[:, :, 0].sum(axis=1).astype(int)
    print("| readings in the history | steps | knob action, mean absolute error | stop agrees |")
    print("| --- | --- | --- | --- |")
    for count in range(1, int(readings.max()) + 1):
        rows = readings == count
        if rows.sum() < 10:
            continue
        error = np.abs(action[rows, 0] - test.label[rows, 0]).mean()
        agree = np.mean((action[rows, 1] > 0) == (test.label[rows, 1] > 0))
        print(f"| {count} | {rows.sum()} | {error:.3f} | {agree:.1%} |")
    error = np.abs(action[:, 0] - test.label[:, 0]).mean()
    agree = np.mean((action[:, 1] > 0) == (test.label[:, 1] > 0))
    print(f"| all | {len(test.label)} | {error:.3f} | {agree:.1%} |")
    # Where the teacher stops: how far from its end the network's last move ends, in shares
    # of the interval, beside a last move of 0 (the fit's optimum with finish_at_fit, else
    # the present setting).
    task = config.resolved_task()
    stops = test.label[:, 1] > 0
    reach = np.full((int(stops.sum()), 1), task.max_step_fraction * task.ending.final_move_reach)
    ends = knob_change(test.label[stops, :1], reach, task.action_power)[:, 0]
    print("\n| last move | stops | end error, median | p90 | within 0.005 of the interval |")
    print("| --- | --- | --- | --- | --- |")
    for name, end in (
        ("the network's", knob_change(action[stops, :1], reach, task.action_power)[:, 0]),
        ("none", np.zeros_like(ends)),
    ):
        error = np.abs(end - ends)
        print(
            f"| {name} | {stops.sum()} | {np.median(error):.4f} | "
            f"{np.percentile(error, 90):.4f} | {np.mean(error < 0.005):.0%} |"
        )
    beyond = np.mean(np.abs(test.label[stops, 0]) >= 1.0)
    print(f"\nthe teacher's ends beyond one last move's reach (clipped to it): {beyond:.1%}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.imitate", description=__doc__)
    verbs = parser.add_subparsers(dest="verb", required=True)
    one = verbs.add_parser("collect", help="play episodes, the posterior labelling every step")
    one.add_argument("--config", required=True)
    one.add_argument("--episodes", type=int, default=1000)
    one.add_argument("--seed", type=int, default=1)
    one.add_argument("--student", help="a run whose best.pt acts (a DAgger round)")
    one.add_argument(
        "--teacher-ends",
        action="store_true",
        help="the student's stops end where the teacher would end (a diagnosis: its probes "
        "and stops, with the teacher's last move)",
    )
    one.add_argument(
        "--teacher",
        choices=("scale-free", "posterior"),
        default="scale-free",
        help="the box posterior in an unknown pixel scale (default), or in the box's pixels",
    )
    one.add_argument("--out", required=True)
    two = verbs.add_parser("clone", help="fit a new run's actor to collected labels")
    two.add_argument("--config", required=True)
    two.add_argument("--data", action="append", required=True)
    two.add_argument("--epochs", type=int, default=30)
    two.add_argument("--runs-dir", default="runs")
    two.add_argument(
        "--continue-weight",
        type=float,
        default=1.0,
        help="weight of the stop component where the teacher goes on (benchmarks.imitation.clone)",
    )
    three = verbs.add_parser("agreement", help="how well the teacher can be followed")
    three.add_argument("--config", required=True)
    three.add_argument("--data", action="append", required=True)
    three.add_argument("--epochs", type=int, default=40)
    for verb in (two, three):
        verb.add_argument("--set", action="append", default=[], help="config override key=value")
        verb.add_argument("--learning-rate", type=float, default=1e-3)
        verb.add_argument(
            "--end-weight",
            type=float,
            default=1.0,
            help="weight of the last move's knob error where the teacher stops (clone)",
        )
        verb.add_argument(
            "--anneal",
            action="store_true",
            help="the learning rate falls to zero along a half cosine (benchmarks.imitation.clone)",
        )
    args = parser.parse_args(argv)
    {"collect": _collect, "clone": _clone, "agreement": _agreement}[args.verb](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())

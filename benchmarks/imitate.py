"""Clone the Bayesian autofocus over the training box into an aligner (alignrl/imitation.py).

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
--resume` (or `alignrl adapt --from`) continues it with SAC.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from alignrl.apparatus.family import family_path, load_family
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.config import load_experiment
from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import PosteriorFocus
from alignrl.imitation import Demonstrations, PosteriorTeacher, clone, collect


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
    options = {"scale_free": True, "specimen_points": 1} if args.teacher == "scale-free" else {}
    teacher = PosteriorTeacher(env, lambda: PosteriorFocus(box, **options))
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


def _clone(args: argparse.Namespace) -> None:
    from alignrl.training import Trainer

    config = load_experiment(args.config, args.set)
    data = Demonstrations.joined([Demonstrations.load(path) for path in args.data])
    trainer = Trainer.create(config, args.runs_dir)
    learner = trainer.agent.learner
    start = time.monotonic()
    loss = clone(
        learner.actor, data, args.epochs, config.seed,
        log=lambda epoch, value: print(f"epoch {epoch + 1}: loss {value:.4f}", flush=True),
    )  # fmt: skip
    trainer.agent.observe(
        data.observation, data.secret, data.action, data.reward, data.next_observation,
        data.next_secret, data.done,
    )  # fmt: skip
    result = trainer.evaluate_and_keep_best()
    trainer.checkpoint()
    print(
        f"{trainer.run_dir}: cloned on {len(data.label)} steps of {data.episodes} episodes "
        f"(loss {loss:.4f}, {time.monotonic() - start:.0f} s); validation "
        f"{result.successes}/{result.scenarios} at a median of {result.median_acquisitions:g}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.imitate", description=__doc__)
    verbs = parser.add_subparsers(dest="verb", required=True)
    one = verbs.add_parser("collect", help="play episodes, the posterior labelling every step")
    one.add_argument("--config", required=True)
    one.add_argument("--episodes", type=int, default=1000)
    one.add_argument("--seed", type=int, default=1)
    one.add_argument("--student", help="a run whose best.pt acts (a DAgger round)")
    one.add_argument(
        "--teacher", choices=("scale-free", "posterior"), default="scale-free",
        help="the box posterior in an unknown pixel scale (default), or in the box's pixels",
    )  # fmt: skip
    one.add_argument("--out", required=True)
    two = verbs.add_parser("clone", help="fit a new run's actor to collected labels")
    two.add_argument("--config", required=True)
    two.add_argument("--data", action="append", required=True)
    two.add_argument("--epochs", type=int, default=30)
    two.add_argument("--runs-dir", default="runs")
    two.add_argument("--set", action="append", default=[], help="config override key=value")
    args = parser.parse_args(argv)
    {"collect": _collect, "clone": _clone}[args.verb](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())

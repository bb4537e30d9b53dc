"""Alignments step by step: where an aligner walks on a column, what it reads and what it
does, for the diagnoses of docs/benchmarks.md (issue 21).

    python -m benchmarks.trace --policy runs/s3/focus-v2-fit --instrument val-steep \
        --episodes 6 --seed 100

One block per episode (seeds SEED, SEED + 1, ...: the column's draw and the start, uniform
over the interval): the best width and the spec, where the optimum lies in the interval, then
a line per step with the setting and its error (fractions of the interval), the reading, the
fit features where the policy has them (valid, step to the fit's optimum, log floor ratio)
and the action (move in maximum steps, stop > 0); then where the episode left the column
(its narrowest reading, or the fit's optimum: `finish_at_fit`) and the verification image
taken there, which judges it as a session's does. Analytic readings (no images; the same
column physics, seconds per instrument) unless --images (rendered frames measured as a
session measures them). The held-out set is refused: a diagnosis is a look at what went
wrong, and the held-out set is only for reporting.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from alignrl.apparatus.instruments import diagnosis_problem
from alignrl.apparatus.registry import make_apparatus
from alignrl.deploy.policy import load_deployable
from alignrl.envs.core import AlignmentEpisodes, feature_layout
from alignrl.envs.fit_features import FIT_FEATURES
from alignrl.evaluation.session import verify_task

SLOT = np.array([0])  # the one apparatus an engine of one_slot drives


def one_slot(policy_spec: str, apparatus_spec: str, images: bool) -> tuple:
    """(policy, its acting task, the column, an engine of one slot on it): analytic
    readings unless `images`."""
    policy = load_deployable(policy_spec)
    task = policy.task.for_acting()
    column = make_apparatus(apparatus_spec, {"analytic": not images})
    return policy, task, column, AlignmentEpisodes([column], task, policy.history)


def begin_episode(engine: AlignmentEpisodes, seed: int) -> None:
    """Episode `seed` on SLOT: the column's draw and a start uniform over the interval,
    both from the seed."""
    engine.begin(SLOT, [seed])
    start = np.random.default_rng(seed).uniform(-1.0, 1.0)
    engine.misalign(SLOT, np.array([[start]]))


def trace(
    policy_spec: str, instrument: str, episodes: int, seed: int, images: bool = False
) -> list[str]:
    policy, task, column, engine = one_slot(policy_spec, f"instrument:{instrument}", images)
    layout = feature_layout(len(task.knobs), task.extra_features)
    fit = slice(layout["extras"].stop - FIT_FEATURES, None) if task.fit_features else None
    lines: list[str] = []
    for episode in range(episodes):
        begin_episode(engine, seed + episode)
        low, span = engine.low[0, 0], engine.span[0, 0]
        optimum = engine.aligned[0, 0]
        lines.append(
            f"episode {seed + episode}: best {engine.best_width[0]:.2f} px, spec "
            f"{engine.threshold[0]:.2f} px, optimum at {(optimum - low) / span:.3f}"
        )
        while engine.active[0]:
            history = engine.observation(0)
            action = np.asarray(policy.act(history), dtype=np.float64)
            shown = (
                ""
                if fit is None
                else " fit [" + ", ".join(f"{value:+.3f}" for value in history[-1, fit]) + "]"
            )
            lines.append(
                f"  at {(engine.setting[0, 0] - low) / span:.4f} (error "
                f"{(engine.setting[0, 0] - optimum) / span:+.4f}) read {engine.width[0]:.2f} px"
                f"{shown} -> move {action[0]:+.3f} stop {action[1]:+.2f}"
            )
            engine.step(SLOT, action[None])
        # Judged as a session judges: on one more image where the aligner left the column
        # (its narrowest reading, or a fit's optimum where no reading was taken).
        width, _, _ = verify_task(column, task)
        verified = float("nan") if width is None else width
        outcome = "aligned" if verified <= engine.threshold[0] else "missed"
        ended = ", at the fit" if engine.info[0].ended_at_fit else ""
        lines.append(
            f"  left at error {(engine.setting[0, 0] - optimum) / span:+.4f}{ended}, "
            f"verified {verified:.2f} px: {outcome}"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", required=True, help="a run, an export or champion:NAME")
    parser.add_argument("--instrument", required=True, help="a validation instrument's name")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--images", action="store_true", help="rendered frames, not analytic")
    args = parser.parse_args(argv)
    problem = diagnosis_problem(args.instrument, "traces")
    if problem is not None:
        print(problem, file=sys.stderr)
        return 2
    print("\n".join(trace(args.policy, args.instrument, args.episodes, args.seed, args.images)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

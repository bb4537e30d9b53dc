"""Does the adversary earn its place? The league's champion aligner against an aligner of the
same member, trained alone for the same number of env steps against uniform misalignment.

    python -m benchmarks.adversary runs/league-default [--matches 1000] [--out FILE]

Both are judged (deterministic actions) on held-out scenarios in three ways: against the
starts the league's strongest misaligner chooses with its mean action (how a member is
judged), against the starts it samples (how it plays in the league), and in the usual
evaluation session (uniform starts). The solo aligner is trained here with `alignrl train`
machinery, from the champion's own roster entry, in runs/<league>-solo-<steps>/ (reused if
it is already complete).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from alignrl.agents.agent import Agent
from alignrl.config.experiment import parse_experiment
from alignrl.league.backends import InProcessBackend
from alignrl.league.loop import League
from alignrl.training import Trainer


def _solo(league: League, champion: Agent, steps: int, runs_dir: Path) -> Agent:
    """An aligner of the champion's roster entry, trained alone for `steps` env steps."""
    cfg = league.config
    base = champion.id.split("-pbt")[0]
    roster = yaml.safe_load((league.run_dir / "aligners.yaml").read_text())
    learner = next(m["learner"] for m in roster["members"] if m["id"] == base)
    name = f"{cfg.name}-solo-{steps}"
    run_dir = runs_dir / name
    if (run_dir / "checkpoints" / "best.pt").exists():
        trainer = Trainer.resume(run_dir)
    else:
        config = parse_experiment(
            {
                "name": name,
                "seed": cfg.seed,
                "apparatus": cfg.apparatus,
                "apparatus_args": cfg.apparatus_args,
                "eval_apparatus": cfg.eval_apparatus,
                "eval_apparatus_args": cfg.eval_apparatus_args,
                "task": cfg.task,
                "task_options": cfg.task_options.model_dump(exclude_none=True),
                "history": cfg.history,
                "envs": cfg.envs,
                "threads": cfg.threads,
                "learner": learner,
                "budget": {
                    "env_steps": steps,
                    "eval_every": max(steps // 4, 1),
                    "checkpoint_every": max(steps // 4, 1),
                },
            },
            "solo aligner",
        )
        trainer = Trainer.create(config, runs_dir)
    if trainer.env_steps < steps:
        trainer.run(progress=True)
    return trainer.agent


class _MeanActions:
    """An aligner that always acts with its mean action, whatever it is asked."""

    def __init__(self, agent: Agent) -> None:
        self.id, self.agent = agent.id, agent

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        return self.agent.act(observation, deterministic=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("league", help="a league run directory")
    parser.add_argument("--matches", type=int, default=1000, help="matches per judgement")
    parser.add_argument("--runs-dir", default="runs", help="where the solo run goes")
    parser.add_argument("--out", help="also write the Markdown table here")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    league = League.resume(args.league, read_only=True)
    best = json.loads((league.run_dir / "best" / "best.json").read_text())[0]
    champion = Agent.load(league.run_dir / "best" / f"{best['member']}.pt")
    steps = champion.steps_seen  # its lineage's env steps (a PBT copy inherits its parent's)
    solo = _solo(league, champion, steps, Path(args.runs_dir))
    strongest_id = league.ratings.ranking(league.pool.active("misaligner"))[0][0]
    strongest = league.members[strongest_id]

    cfg = league.config
    judged = cfg.model_copy(
        update={"apparatus": cfg.eval_apparatus, "apparatus_args": cfg.eval_apparatus_args}
    )
    rows = []
    for label, agent in (("league champion", champion), ("trained alone", solo)):
        backend = InProcessBackend(judged)
        adversarial = backend.play(
            agent, strongest, args.matches, np.random.default_rng(7), set(), deterministic=True
        )
        sampled = backend.play(
            _MeanActions(agent),  # type: ignore[arg-type]
            strongest,
            args.matches,
            np.random.default_rng(8),
            set(),
            deterministic=False,
        )
        session = league.session(agent, scenarios=100, name=label)
        rows.append(
            f"| {label} ({agent.id}) | {steps:,} | "
            f"{sum(adversarial.successes)}/{adversarial.matches} | "
            f"{np.median(adversarial.acquisitions):g} | "
            f"{sum(sampled.successes)}/{sampled.matches} | "
            f"{np.median(sampled.acquisitions):g} | {session.successes}/100 | "
            f"{session.median_acquisitions:g} |"
        )
    table = "\n".join(
        [
            f"Adversary benchmark: `python -m benchmarks.adversary {args.league}` on "
            f"{platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d')}, "
            f"{time.perf_counter() - started:.0f} s. Strongest misaligner: {strongest_id}.",
            "",
            "| aligner | env steps | vs strongest misaligner (its mean starts) | median "
            "acquisitions | vs strongest misaligner (its sampled starts) | median acquisitions "
            "| held-out session | median acquisitions |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
            *rows,
        ]
    )
    print(table)
    if args.out:
        Path(args.out).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

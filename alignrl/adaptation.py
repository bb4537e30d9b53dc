"""Adaptation on a new instrument (seed section 6.3): a pre-trained aligner trains on.

`alignrl adapt --from SOURCE --apparatus SPEC --steps N` starts a training run whose aligner
is the pre-trained one, critics, optimizers and entropy coefficient included, on another
apparatus. It is an ordinary run directory (`alignrl train --resume`, `alignrl report`,
checkpoints and evaluations work as for `alignrl train`) whose config carries an
`adaptation:` section: where it came from, and the safety shield (site limits, largest step)
that every write to the new apparatus passes. Every acquisition counts as a real one.

The replay buffer starts empty: transitions recorded on the old instrument describe another
focus curve. The aligner's step counter carries over, so it neither acts at random nor waits
for a warm-up; it learns as soon as one batch of new transitions is stored.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from alignrl.apparatus.base import Apparatus
from alignrl.config import AdaptationConfig, ExperimentConfig, LearnerConfig, parse_experiment
from alignrl.deploy.export import PolicySource

__all__ = [
    "adaptation_config",
    "start_adaptation",
    "training_shield",
]


def adaptation_config(
    source: PolicySource,
    *,
    name: str,
    apparatus: str,
    apparatus_args: dict[str, Any],
    steps: int,
    eval_apparatus: str | None = None,
    eval_apparatus_args: dict[str, Any] | None = None,
    eval_every: int | None = None,
    eval_scenarios: int = 100,
    envs: int = 8,
    seed: int = 0,
    limits: dict[str, tuple[float, float]] | None = None,
    max_step: dict[str, float] | None = None,
    spec_px: float | None = None,
    complexity: float = 1.0,
    updates_per_step: float | None = None,
) -> ExperimentConfig:
    """The run config of an adaptation: the source's learner, task and history (from
    `alignrl.deploy.export.resolve_source`, which `export` and `align` use too) on
    `apparatus`. `spec_px`: an absolute success spec (edge width, px) for an apparatus that
    cannot tell its best edge width, as a real column cannot. `updates_per_step` (SAC): more
    gradient updates per acquisition than in pre-training."""
    spec = source.agent.spec
    learner = LearnerConfig(algorithm=spec.algorithm, **spec.hyperparameters)  # type: ignore[arg-type]
    if updates_per_step is not None:  # images are dear on an instrument, updates are cheap
        learner = LearnerConfig(**{**learner.model_dump(), "updates_per_step": updates_per_step})
    every = eval_every or max(steps // 4, 1)
    task_options = source.config.task_options.model_dump(exclude_none=True)
    if spec_px is not None:  # a real column cannot tell its best width: an absolute spec
        task_options["success_absolute_px"] = spec_px
    data = {
        "name": name,
        "seed": seed,
        "apparatus": apparatus,
        "apparatus_args": apparatus_args,
        "eval_apparatus": eval_apparatus or apparatus,
        "eval_apparatus_args": (
            eval_apparatus_args if eval_apparatus_args is not None else apparatus_args
        ),
        "task": source.config.task,
        "task_options": task_options,
        "history": spec.observation_shape[0],
        "envs": envs,
        "complexity": complexity,
        "learner": learner.model_dump(mode="json", exclude_none=True),
        "budget": {
            "env_steps": steps,
            "eval_every": every,
            "eval_scenarios": eval_scenarios,
            "checkpoint_every": min(every, 1000),
        },
        "adaptation": {
            "source": str(source.member_file),
            "source_member": spec.id,
            "source_steps": source.agent.steps_seen,
            "limits": limits or {},
            "max_step": max_step or {},
        },
    }
    return parse_experiment(data, "adaptation")


def start_adaptation(config: ExperimentConfig, source: PolicySource, runs_root: str | Path):
    """A new adaptation run: the Trainer with the source's weights, evaluated zero-shot and
    checkpointed at once, so that a run killed before its first scheduled checkpoint resumes
    from the source."""
    from alignrl.training import Trainer

    if config.adaptation is None:
        raise ValueError(f"{config.name}: not an adaptation config (no `adaptation:` section)")
    trainer = Trainer.create(config, runs_root)
    trainer.agent.load_state_dict(source.agent.state_dict(replay=False))
    # The source's optimizer state carries its own step size; the run's config says which
    # one adaptation uses (by default the source's, copied into the config).
    trainer.agent.set_learning_rate(config.learner.learning_rate)
    # The zero-shot evaluation, at 0 env steps: on record in metrics/evaluations.csv, and the
    # source is best.pt until an adapted aligner does strictly better, so the best an
    # adaptation gives back is never worse than what it started from on that session.
    trainer.evaluate_and_keep_best()
    trainer.checkpoint()
    return trainer


def training_shield(config: AdaptationConfig, audit_path: Path) -> Callable[[Apparatus], Apparatus]:
    """What wraps every apparatus of an adaptation run: a TrainingShield with the run's site
    limits and maximum steps, all writing to one audit log (JSON lines, appended on resume).
    Limits that do not fit the apparatus are a ShieldConfigError on the first one wrapped,
    before anything is written."""
    from alignrl.deploy.align import JsonLinesAudit
    from alignrl.deploy.shield import TrainingShield, resolve_limits

    audit = JsonLinesAudit(audit_path)
    count = 0

    def wrap(apparatus: Apparatus) -> Apparatus:
        nonlocal count
        limits = resolve_limits(apparatus.knobs, config.limits, config.max_step)
        count += 1  # records name their apparatus: 1..envs for training, then evaluations
        return TrainingShield(apparatus, limits, audit, unit=str(count))  # type: ignore[return-value]

    return wrap

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

from pathlib import Path
from typing import Any

from alignrl.apparatus.shield import DEFAULT_CALL_TIMEOUT_S, JsonLinesAudit, ShieldOptions
from alignrl.config.adaptation import AdaptationConfig
from alignrl.config.experiment import ExperimentConfig, parse_experiment
from alignrl.config.learner import LearnerConfig
from alignrl.envs.hindsight import HindsightOptimum
from alignrl.runs.sources import PolicySource, require_learner_state

__all__ = ["adaptation_config", "adaptation_shield", "check_adaptable"]


def check_adaptable(source: PolicySource, named: str) -> None:
    """Refuse a source without a learner's state: an adaptation trains on from the source's
    critics, optimizers and entropy coefficient, which a run, a member file, and an export or
    a shipped champion made with --with-learner-state bring; any other export or champion
    (`named`: as it was given) brings its acting network alone."""
    require_learner_state(
        source,
        named,
        "adapt",
        f"; or run it on the new apparatus as it is: alignrl align --policy {named} "
        "--apparatus SPEC",
    )


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
    call_timeout_s: float = DEFAULT_CALL_TIMEOUT_S,
    spec_px: float | None = None,
    complexity: float = 1.0,
    updates_per_step: float | None = None,
    critic_warmup_steps: int = 0,
    hindsight_secrets: bool = True,
    hindsight_optimum: HindsightOptimum = "posterior",
) -> ExperimentConfig:
    """The run config of an adaptation: the source's learner, task and history (from
    `alignrl.runs.sources.resolve_source`, which `export` and `align` use too) on
    `apparatus`. `spec_px`: an absolute success spec (edge width, px) for an apparatus that
    cannot tell its best edge width, as a real column cannot. `updates_per_step` (SAC): more
    gradient updates per acquisition than in pre-training. `critic_warmup_steps`: the first
    env steps in which only the critics learn. `hindsight_secrets`, `hindsight_optimum`: see
    HindsightSecrets. A source without critics (an export or a champion without its learner
    state) is refused (check_adaptable)."""
    check_adaptable(source, str(source.member_file))
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
            "call_timeout_s": call_timeout_s,
            "critic_warmup_steps": critic_warmup_steps,
            "hindsight_secrets": hindsight_secrets,
            "hindsight_optimum": hindsight_optimum,
        },
    }
    return parse_experiment(data, "adaptation")


def adaptation_shield(config: AdaptationConfig, audit_path: Path) -> ShieldOptions:
    """How every apparatus of an adaptation run is shielded, simulated or not: the run's site
    limits and maximum steps, all writing to one audit log (JSON lines, appended on resume).
    Limits that do not fit the apparatus are a ShieldConfigError when the first one is
    opened, before anything is written."""
    return ShieldOptions(
        site_limits=config.limits,
        max_step=config.max_step,
        call_timeout_s=config.call_timeout_s,
        audit=JsonLinesAudit(audit_path),
        simulators=True,
    )

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

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.config import AdaptationConfig, ExperimentConfig, LearnerConfig, parse_experiment
from alignrl.deploy.export import PolicySource

__all__ = [
    "HindsightSecrets",
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
    critic_warmup_steps: int = 0,
    hindsight_secrets: bool = True,
) -> ExperimentConfig:
    """The run config of an adaptation: the source's learner, task and history (from
    `alignrl.deploy.export.resolve_source`, which `export` and `align` use too) on
    `apparatus`. `spec_px`: an absolute success spec (edge width, px) for an apparatus that
    cannot tell its best edge width, as a real column cannot. `updates_per_step` (SAC): more
    gradient updates per acquisition than in pre-training. `critic_warmup_steps`: the first
    env steps in which only the critics learn. `hindsight_secrets`: see HindsightSecrets."""
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
            "critic_warmup_steps": critic_warmup_steps,
            "hindsight_secrets": hindsight_secrets,
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


Transition = tuple[np.ndarray, ...]  # what Agent.observe takes, secrets included


class HindsightSecrets:
    """The critics' secret on an apparatus that cannot tell its optimum (a real column).

    Pre-trained critics read the secret (optimum - setting, as a fraction of the interval);
    a column cannot tell them, and zeros in its place tell them "at the optimum" at every
    step, which misleads the policy they train. Here each episode's transitions on such a
    slot are held until the episode ends; then the setting of its sharpest reading (the
    lowest edge width, the verification image included) stands in for the optimum, and the
    transitions are stored with the secrets it gives. An aligned episode ends within spec of
    the optimum, so the stand-in is off by less than the spec's width of the focus curve.

    Slots whose apparatus tells its optimum (`blind` false) are not held: their secrets are
    the true ones. Transitions of an episode still in flight when a run is killed are lost
    with it, as the episode itself is.
    """

    def __init__(self, blind: np.ndarray) -> None:
        self.blind = np.asarray(blind, bool)
        n = len(self.blind)
        self._positions: list[list[np.ndarray]] = [[] for _ in range(n)]
        self._widths: list[list[float]] = [[] for _ in range(n)]
        self._held: list[list[tuple[np.ndarray, ...]]] = [[] for _ in range(n)]

    def start(self, infos: dict[str, Any]) -> None:
        """The first reading of every blind slot's episode (the infos of `reset`)."""
        for slot in np.flatnonzero(self.blind):
            self._begin(slot, infos["position"][slot], infos["edge_width_px"][slot])

    def step(
        self,
        observation: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        next_observation: np.ndarray,
        done: np.ndarray,
        infos: dict[str, Any],
    ) -> list[Transition]:
        """Hold this step of every blind slot; returns the transitions of the episodes that
        ended, one batch per episode, with their hindsight secrets. `next_observation` of a
        finished slot is its episode's last history (not the next episode's first)."""
        finished = []
        for slot in np.flatnonzero(self.blind):
            self._held[slot].append(
                (observation[slot], action[slot], reward[slot], next_observation[slot], done[slot])
            )
            self._positions[slot].append(np.asarray(infos["position"][slot], np.float32))
            self._widths[slot].append(float(infos["edge_width_px"][slot]))
            if done[slot]:
                finished.append(self._release(slot))
                self._begin(slot, infos["start_position"][slot], infos["start_edge_width_px"][slot])
        return finished

    def _begin(self, slot: int, position: np.ndarray, width: float) -> None:
        self._positions[slot] = [np.asarray(position, np.float32)]
        self._widths[slot] = [float(width)]
        self._held[slot] = []

    def _release(self, slot: int) -> Transition:
        positions = np.stack(self._positions[slot])  # (steps + 1, k)
        widths = np.array(self._widths[slot])
        best = positions[np.nanargmin(widths)] if np.isfinite(widths).any() else positions[-1]
        secrets = (best - positions).astype(np.float32)
        observation, action, reward, next_observation, done = (
            np.stack(column) for column in zip(*self._held[slot], strict=True)
        )
        return (observation, secrets[:-1], action, reward, next_observation, secrets[1:], done)

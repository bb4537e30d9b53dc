"""alignrl from Python, without YAML: an experiment built in code, trained, evaluated and run on
an apparatus, each step what a command does (docs/python.md).

    experiment(**keys)   the keys of a training YAML (docs/configs.md), checked as strictly
    train(config)        `alignrl train`: the run directory runs/<name>/, its final evaluation
    load_policy(source)  a trained aligner as `align` loads it (a run, a file, champion:NAME)
    evaluate(policy)     `alignrl evaluate`: an evaluation session, or a classical one
    align(policy, ...)   `alignrl align`: one alignment through the safety shield

The environments need nothing of this: `gymnasium.make("alignrl/Focus-v0")` once alignrl.envs
(or this module) is imported (docs/environments.md).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alignrl.animation import alignment_gif, check_gif_path
from alignrl.apparatus.audit import JsonLinesAudit, MemoryAudit
from alignrl.apparatus.filming import Film, FilmedApparatus
from alignrl.apparatus.guard import declared_intervals
from alignrl.apparatus.registry import build_apparatus, make_apparatus
from alignrl.apparatus.shield import resolve_limits
from alignrl.config.experiment import ExperimentConfig, parse_experiment
from alignrl.deploy.align import AlignResult, alignment_scene
from alignrl.deploy.align import align as align_through_shield
from alignrl.deploy.policy import DeployablePolicy, load_deployable
from alignrl.envs.task import Task, get_task
from alignrl.evaluation.baselines import CLASSICAL
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.session import SessionResult, run_session
from alignrl.runs.lock import RunLock
from alignrl.training import EvaluationSummary, Trainer, check_evaluation_apparatus

__all__ = ["TrainedRun", "align", "evaluate", "experiment", "load_policy", "train"]


def experiment(name: str = "experiment", **keys: Any) -> ExperimentConfig:
    """An experiment from the keys of a training YAML (docs/configs.md), nested ones as dicts:
    `experiment("quick", envs=4, budget={"env_steps": 2000})`. Checked as strictly as a file:
    an unknown key or a bad value is a ConfigError that names it."""
    return parse_experiment({"name": name, **keys}, f"experiment {name!r}")


@dataclass(frozen=True)
class TrainedRun:
    """A finished training run: its directory (runs/<name>/, as `alignrl train` writes it:
    config, checkpoints, metrics) and its final evaluation on held-out scenarios."""

    path: Path
    evaluation: SessionResult | EvaluationSummary

    def policy(self) -> DeployablePolicy:
        """Its best checkpoint as a policy (what `--policy RUN` runs)."""
        return load_deployable(str(self.path))


def train(
    config: ExperimentConfig, runs_dir: str | Path = "runs", progress: bool = False
) -> TrainedRun:
    """Train one aligner to the config's budget in `runs_dir`/<name>/ (`alignrl train`). A
    folder that already holds a run is refused (FileExistsError): choose another name, or
    continue it with `alignrl train --resume`. A run another process works on is refused
    (RunLockedError), as the command refuses it; so is an evaluation apparatus that cannot be
    built, before the run's folder exists."""
    check_evaluation_apparatus(config)
    with RunLock(Path(runs_dir) / config.name):
        trainer = Trainer.create(config, runs_dir)
        evaluation = trainer.run(progress=progress)
    return TrainedRun(trainer.run_dir, evaluation)


def load_policy(source: TrainedRun | DeployablePolicy | str | Path) -> DeployablePolicy:
    """A trained aligner: a TrainedRun, a run directory, a checkpoint or member file, an
    exported policy directory, or champion:NAME (`--policy` of `align` and `evaluate`)."""
    if isinstance(source, DeployablePolicy):
        return source
    if isinstance(source, TrainedRun):
        return source.policy()
    return load_deployable(str(source))


def evaluate(
    policy: TrainedRun | DeployablePolicy | str | Path,
    apparatus: str = "csv:default",
    apparatus_args: Mapping[str, Any] | None = None,
    *,
    task: Task | str | None = None,
    scenarios: int = 100,
    seed: int = 0,
    spec_px: float | None = None,
    budget: int | None = None,
) -> SessionResult:
    """An evaluation session of `policy` (anything load_policy takes, or a classical
    controller's name: `hyperbola`, `golden-section`, ...) on `scenarios` seeded alignments of
    `apparatus` (`alignrl evaluate`; docs/evaluation.md). `task`: default the policy's own
    built-in task (a classical controller: focus). ValueError for what cannot be run."""
    if isinstance(policy, str) and policy in CLASSICAL:
        controller: Any = CLASSICAL[policy]()
        judged = task if task is not None else "focus"
    else:
        loaded = load_policy(policy)
        controller = PolicyController(loaded.name, loaded.act, loaded.task, loaded.history)
        judged = task if task is not None else loaded.task.name
    unit = make_apparatus(apparatus, dict(apparatus_args or {}))
    judged_task = get_task(judged) if isinstance(judged, str) else judged
    return run_session(controller, unit, judged_task, scenarios, seed, spec_px, budget)


def align(
    policy: TrainedRun | DeployablePolicy | str | Path,
    apparatus: str = "synthetic",
    apparatus_args: Mapping[str, Any] | None = None,
    *,
    seed: int = 0,
    limits: Mapping[str, tuple[float, float]] | None = None,
    max_step: Mapping[str, float] | None = None,
    spec_px: float | None = None,
    dry_run: bool = False,
    log: str | Path | None = None,
    gif: str | Path | None = None,
) -> AlignResult:
    """One alignment of `apparatus` (a spec; `seed`: which scenario a simulator shows) by
    `policy`, through the safety shield (`alignrl align`; docs/deploy.md): `limits` and
    `max_step` per knob in instrument units, `log` the audit log file (JSON lines), `gif` an
    animated GIF of the alignment. How it ended is the result's `outcome` and `exit_code`."""
    gif_path = check_gif_path(gif, "gif") if gif is not None else None  # before any work
    loaded = load_policy(policy)
    unit = build_apparatus(apparatus, dict(apparatus_args or {}), seed)
    knobs = declared_intervals(unit, apparatus)
    shield_limits = resolve_limits(knobs, dict(limits or {}), dict(max_step or {}))
    film = Film() if gif_path is not None else None
    audit = JsonLinesAudit(str(log)) if log is not None else MemoryAudit()
    try:
        result = align_through_shield(
            loaded,
            unit if film is None else FilmedApparatus(unit, film, knobs),
            shield_limits,
            audit,
            apparatus_spec=apparatus,
            spec_px=spec_px,
            dry_run=dry_run,
            log_path=None if log is None else str(log),
        )
    finally:
        if isinstance(audit, JsonLinesAudit):
            audit.close()
    if film is not None and gif_path is not None and film.readings:
        alignment_gif(film.readings, alignment_scene(result, loaded.task, film.knobs), gif_path)
    return result

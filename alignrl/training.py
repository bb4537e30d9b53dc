"""Training one aligner against the built-in misalignment: the seed's pre-training (4.3).

(It lives beside the league rather than in agents/: it runs evaluation sessions, which sit
above the learners.)

The loop: step N apparatus together, store the transitions, update the learner (a set number
of gradient updates per env step), adjust the curriculum, hold a validation session every so
often (the best one's learner is kept as best.pt), and checkpoint. At the end, best.pt aligns
a test session at another seed (TEST_SEED): the figure to report, since no choice saw it. A
run lives in runs/<name>/:

    config.yaml               the resolved experiment
    .lock                     while a process works on the run (alignrl.runs.lock)
    knobs.json                the knobs' intervals and steps, for export (alignrl.runs.state)
    checkpoints/last.pt       everything needed to continue (atomic writes)
    checkpoints/best.pt       the learner of the best validation session so far
    metrics/updates.csv       losses, entropy, alpha (seed figs. 6.1.2-6.1.7)
    metrics/episodes.csv      return, success, acquisitions, complexity per episode
    metrics/evaluations.csv   the validation sessions: successes and acquisitions
    metrics/test.csv          the test session of best.pt, with its 95 % interval
    tensorboard/              the same as TensorBoard events, and the run's settings
                              (alignrl.runs.training_logs)

A resumed run continues from last.pt: networks, optimizers, replay, counters, curriculum and
random generators; metrics rows and TensorBoard events written after that checkpoint are
dropped and written again, and episodes in flight at the kill start over. A run resumed after
its budget (its final validation and test sessions are in last.pt) writes nothing.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from alignrl.agents.agent import Agent
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.shield import JsonLinesAudit, ShieldOptions
from alignrl.checkpoints import (
    CheckpointError,
    atomic_write_text,
    load_checkpoint,
    remove_partial_writes,
    save_checkpoint,
)
from alignrl.config.experiment import ExperimentConfig, dump_experiment
from alignrl.config.run import RunConfig
from alignrl.config_reading import ConfigError
from alignrl.envs import Curriculum, VectorAlignmentEnv, make_apparatus_copies
from alignrl.envs.task import Task
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.session import TEST_SEED, VALIDATION_SEED, SessionResult, run_session
from alignrl.intervals import success_text, wilson
from alignrl.runs.state import (
    CONFIG_FILE,
    KNOBS_FILE,
    knob_limits,
    read_training_config,
    record_knobs,
    restore_rng,
    rng_state,
)
from alignrl.runs.training_logs import TrainingLogs
from alignrl.runs.training_runs import load_policy, member_spec
from alignrl.transitions import Transition

if TYPE_CHECKING:
    from alignrl.envs.hindsight import HindsightSecrets
    from alignrl.runs.sources import PolicySource

__all__ = [
    "TEST_SEED",
    "VALIDATION_SEED",
    "EvaluationSummary",
    "TestSummary",
    "Trainer",
    "check_evaluation_apparatus",
    "evaluate_policy",
    "start_adaptation",
]

CHECKPOINT_FORMAT = "alignrl-train-2"  # -1: a bare SAC state (policies still load)
EVALUATION_SEED = VALIDATION_SEED  # its name before issue 23 (model cards cite it)
UPDATE_LOG_EVERY = 50  # updates between rows of updates.csv


def with_budget(config: ExperimentConfig, env_steps: int) -> ExperimentConfig:
    """`config` with a budget of `env_steps`, its provenance saying so (an override)."""
    if env_steps < 1:
        raise ValueError(f"a budget is a positive number of env steps, not {env_steps}")
    budget = config.budget.model_copy(update={"env_steps": int(env_steps)})
    from alignrl.config.run import Provenance

    given = config.provenance or Provenance()
    provenance = given.model_copy(
        update={"overrides": [*given.overrides, f"budget.env_steps={env_steps}"]}
    )
    return config.model_copy(update={"budget": budget, "provenance": provenance})


def evaluate_policy(
    act: Callable[[np.ndarray], np.ndarray],
    apparatus: str,
    apparatus_args: dict[str, Any],
    task: Task,
    history: int,
    scenarios: int,
    seed: int = EVALUATION_SEED,
    name: str = "policy",
    shield: ShieldOptions | None = None,
) -> SessionResult:
    """An evaluation session (alignrl/evaluation/session.py) with a deterministic policy:
    `scenarios` seeded scenarios, starts anywhere in the interval, a verification image each,
    on an apparatus opened with `shield` (a driver is always shielded)."""
    controller = PolicyController(name, act, task, history)
    unit = make_apparatus(apparatus, apparatus_args, shield=shield)
    return run_session(controller, unit, task, scenarios, seed)


def check_evaluation_apparatus(config: RunConfig) -> None:
    """Open a run's evaluation apparatus (eval_apparatus, eval_apparatus_args) once and check
    that its sessions can judge the run's task, as a session does before its first alignment:
    a spec, a file or arguments that cannot work are a ConfigError naming the spec before the
    run directory exists, not a failure at the first validation session once training has
    started. (A driver is constructed once more for it, behind the shield its sessions
    have: an adaptation's limits and time limit, the audit in memory.)"""
    from alignrl.apparatus.base import ApparatusError
    from alignrl.evaluation.session import check_session_apparatus

    spec, task = config.eval_apparatus, config.resolved_task()
    shield, adaptation = None, getattr(config, "adaptation", None)
    if adaptation is not None:
        from alignrl.adaptation import adaptation_shield

        shield = adaptation_shield(adaptation, Path(os.devnull))  # a file opened on first use:
        shield = dataclasses.replace(shield, audit=None, unit="evaluation")  # never here
    try:
        check_session_apparatus(
            make_apparatus(spec, config.eval_apparatus_args, shield=shield), task
        )
    except (ApparatusError, ValueError, OSError) as error:
        raise ConfigError(
            f"eval_apparatus {spec!r} (the apparatus of the evaluation sessions) cannot be "
            f"used: {error}"
        ) from None


def _session_row(result: SessionResult) -> dict[str, Any]:
    """A session's figures as a row of metrics/evaluations.csv or test.csv."""
    median_final = result.final_width_stats()["median"]
    return {
        "successes": result.successes,
        "scenarios": result.scenarios,
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": result.p90_acquisitions,
        "median_final_px": round(median_final, 4) if median_final is not None else "",
        "seconds": round(result.seconds, 2),
    }


@dataclass(frozen=True)
class EvaluationSummary:
    """The figures of an evaluation session that a checkpoint keeps: what a finished run,
    resumed, reports without running the session again."""

    successes: int
    scenarios: int
    median_acquisitions: float
    p90_acquisitions: float


@dataclass(frozen=True)
class TestSummary:
    """The test session of a finished run: best.pt (saved at `checkpoint_env_steps`) on
    `scenarios` scenarios of `seed` (TEST_SEED), a session no choice saw."""

    checkpoint_env_steps: int
    seed: int
    successes: int
    scenarios: int
    median_acquisitions: float
    p90_acquisitions: float


class Trainer:
    """One learner, its envs, replay, curriculum and run directory."""

    def __init__(self, config: ExperimentConfig, run_dir: str | Path) -> None:
        self.config = config
        self.run_dir = Path(run_dir)
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        # A driver is always shielded, its calls on record in the run; an adaptation shields
        # whatever it adapts to, with its site limits and maximum steps.
        self.shield = ShieldOptions(audit=JsonLinesAudit(self.run_dir / "audit.jsonl"))
        if config.adaptation is not None:
            from alignrl.adaptation import adaptation_shield

            self.shield = adaptation_shield(config.adaptation, self.run_dir / "audit.jsonl")
        apparatus = make_apparatus_copies(
            config.apparatus, config.apparatus_args, config.envs, self.shield
        )
        self.curriculum = Curriculum.from_config(config.curriculum)
        level = self.curriculum.level if self.curriculum else config.complexity
        self.task = config.resolved_task()
        self.env = VectorAlignmentEnv(apparatus, self.task, config.history, complexity=level)
        self.knob_limits = knob_limits(self.task, apparatus[0].knobs)  # what export scales by
        self.agent = Agent(member_spec(config), config.envs, config.device)
        if self.agent.spec.observation_shape != self.env.single_observation_space.shape:
            raise ValueError(
                f"{config.name}: the env's observations are "
                f"{self.env.single_observation_space.shape}, the aligner expects "
                f"{self.agent.spec.observation_shape}"
            )
        self.hindsight = self._hindsight_secrets()
        self.env_steps = self.episodes = 0
        self.best_successes = -1
        self.starts = 0  # how many times this run was started (resumes change env seeds)
        self.last_evaluation: EvaluationSummary | None = None  # the last validation session
        self.test_result: TestSummary | None = None  # best.pt's test session, at the end
        self.logs = TrainingLogs(self.run_dir, self.agent.metric_names)

    # --- run directory ------------------------------------------------------------------

    @classmethod
    def create(cls, config: ExperimentConfig, runs_root: str | Path = "runs") -> Trainer:
        run_dir = Path(runs_root) / config.name
        if (run_dir / "checkpoints" / "last.pt").exists() or (run_dir / CONFIG_FILE).exists():
            raise FileExistsError(
                f"{run_dir} already holds a run: continue it with `alignrl train --resume "
                f"{run_dir}`, choose another --name, or replace it with --force"
            )
        trainer = cls(config, run_dir)  # bad apparatus or shield settings fail before any file
        # config.yaml last: a start killed before it is no run, and starts afresh.
        record_knobs(run_dir, config.apparatus, trainer.knob_limits)
        atomic_write_text(run_dir / CONFIG_FILE, dump_experiment(config))
        return trainer

    @classmethod
    def resume(cls, run_dir: str | Path, env_steps: int | None = None) -> Trainer:
        """The run in `run_dir` from its last checkpoint. `env_steps` gives it a new budget,
        above the checkpoint's steps (a finished run goes on): config.yaml records it, the
        budget and an override `budget.env_steps=N` in its provenance."""
        run_dir = Path(run_dir)
        config = read_training_config(run_dir)
        if env_steps is not None:
            config = with_budget(config, env_steps)
        trainer = cls(config, run_dir)
        last = run_dir / "checkpoints" / "last.pt"
        if last.exists():
            state = load_checkpoint(last, config.device)
            try:
                trainer._restore(state)
            except CheckpointError:
                raise
            except (ValueError, KeyError, TypeError) as error:  # tensors of another network
                raise CheckpointError(f"{last}: not a checkpoint of this run: {error}") from None
        elif config.adaptation is not None:
            raise FileNotFoundError(
                f"{run_dir}: the adaptation was stopped before its first checkpoint (no "
                f"{last}), so it cannot start from its source again here: remove {run_dir} "
                "and run `alignrl adapt` again"
            )
        if env_steps is not None and trainer.env_steps >= env_steps:
            raise ValueError(
                f"--steps {env_steps}: {run_dir} is at {trainer.env_steps} env steps already; "
                "a new budget must be above that"
            )
        trainer._cut_back_to_checkpoint()
        if env_steps is not None:  # the new budget on record, once it is known to be valid
            atomic_write_text(run_dir / CONFIG_FILE, dump_experiment(config))
        return trainer

    @property
    def finished(self) -> bool:
        """The budget is spent and its final evaluation checkpointed."""
        return self.env_steps >= self.config.budget.env_steps

    def _state(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "agent": self.agent.state_dict(replay=True),
            "env_steps": self.env_steps,
            "episodes": self.episodes,
            "best_successes": self.best_successes,
            "starts": self.starts,
            "evaluation": asdict(self.last_evaluation) if self.last_evaluation else {},
            "test": asdict(self.test_result) if self.test_result else {},
            **rng_state(self.rng),
            "curriculum": self.curriculum.state_dict() if self.curriculum else {},
            "config": dump_experiment(self.config),
        }

    def _restore(self, state: dict[str, Any]) -> None:
        if state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(
                f"checkpoint format {state.get('format')!r} is not {CHECKPOINT_FORMAT}"
            )
        self.agent.load_state_dict(state["agent"])
        self.env_steps, self.episodes = int(state["env_steps"]), int(state["episodes"])
        self.best_successes, self.starts = int(state["best_successes"]), int(state["starts"])
        if state.get("evaluation"):  # (older checkpoints have none)
            self.last_evaluation = EvaluationSummary(**state["evaluation"])
        if state.get("test"):
            self.test_result = TestSummary(**state["test"])
        restore_rng(self.rng, state)
        if self.curriculum and state["curriculum"]:
            self.curriculum.load_state_dict(state["curriculum"])
            self.env.set_complexity(self.curriculum.level)

    def _cut_back_to_checkpoint(self) -> None:
        """Before a resumed run continues: metrics rows and TensorBoard events after its
        checkpoint (or all, where it has none yet) go, and so do writes a kill cut short."""
        for folder in ("checkpoints", "metrics"):
            remove_partial_writes(self.run_dir / folder)
        self.logs.cut_back(self.env_steps)

    def unstart(self) -> None:
        """Undo a start that failed before the run's first checkpoint (an adaptation whose
        instrument failed in its zero-shot session): the run directory is no run again, so
        the same command starts it afresh. Its audit log of what reached the instrument is
        kept (appended to by the next start)."""
        if (self.run_dir / "checkpoints" / "last.pt").exists():
            raise ValueError(f"{self.run_dir} has a checkpoint: resume it instead")
        self.logs.close()
        for name in ("metrics", "tensorboard", "checkpoints"):
            shutil.rmtree(self.run_dir / name, ignore_errors=True)
        (self.run_dir / CONFIG_FILE).unlink(missing_ok=True)
        (self.run_dir / KNOBS_FILE).unlink(missing_ok=True)

    def checkpoint(self) -> None:
        self.logs.flush()  # the events up to this checkpoint are on disk
        save_checkpoint(self.run_dir / "checkpoints" / "last.pt", self._state())

    # --- the loop -----------------------------------------------------------------------

    def evaluate(
        self, agent: Agent | None = None, scenarios: int | None = None, seed: int = VALIDATION_SEED
    ) -> SessionResult:
        """A session of `agent` (default: the one training) on eval_apparatus: by default a
        validation session of budget.eval_scenarios."""
        cfg, agent = self.config, agent or self.agent
        with torch.random.fork_rng(devices=[]):  # evaluating must not move training's stream
            return evaluate_policy(
                lambda observation: agent.act(observation, deterministic=True),
                cfg.eval_apparatus,
                cfg.eval_apparatus_args,
                self.task,
                cfg.history,
                scenarios or cfg.budget.eval_scenarios,
                seed=seed,
                name=cfg.name,
                shield=dataclasses.replace(self.shield, unit="evaluation"),
            )

    def evaluate_and_keep_best(self) -> SessionResult:
        """A validation session: on record, and its learner kept as best.pt where it aligned
        more than any before."""
        result = self.evaluate()
        summary = _session_row(result)
        self.last_evaluation = EvaluationSummary(
            result.successes, result.scenarios, result.median_acquisitions, result.p90_acquisitions
        )
        self.logs.write_validation({"env_steps": self.env_steps, **summary})
        if result.successes > self.best_successes:
            self.best_successes = result.successes
            save_checkpoint(
                self.run_dir / "checkpoints" / "best.pt",
                {
                    "format": CHECKPOINT_FORMAT + "-policy",
                    "agent": self.agent.state_dict(),
                    "env_steps": self.env_steps,
                    "evaluation": {k: v for k, v in summary.items() if k != "seconds"},
                    "config": dump_experiment(self.config),
                },
            )
        return result

    def test_best(self) -> TestSummary | None:
        """The test session of best.pt at TEST_SEED (budget.test_scenarios alignments; None
        where that is 0): on record in metrics/test.csv and kept for the last checkpoint."""
        budget = self.config.budget
        scenarios = (
            budget.eval_scenarios if budget.test_scenarios is None else budget.test_scenarios
        )
        best = self.run_dir / "checkpoints" / "best.pt"
        if not scenarios or not best.exists():
            return None
        with torch.random.fork_rng(devices=[]):  # building the network draws on torch's stream
            agent, _ = load_policy(best, self.config.device)
        result = self.evaluate(agent, scenarios, TEST_SEED)
        chosen_at = int(load_checkpoint(best)["env_steps"])
        low, high = wilson(result.successes, result.scenarios)
        self.logs.write_test(
            {
                "env_steps": self.env_steps,
                "checkpoint_env_steps": chosen_at,
                "seed": TEST_SEED,
                "success_rate_low": round(low, 4),
                "success_rate_high": round(high, 4),
                **_session_row(result),
            }
        )
        self.test_result = TestSummary(
            chosen_at,
            TEST_SEED,
            result.successes,
            result.scenarios,
            result.median_acquisitions,
            result.p90_acquisitions,
        )
        return self.test_result

    def _hindsight_secrets(self) -> HindsightSecrets | None:
        """HindsightSecrets where an adaptation's SAC critics read a secret that some of its
        apparatus cannot tell; None otherwise (every transition is stored as it comes)."""
        from alignrl.envs.hindsight import HindsightSecrets

        adaptation, learner = self.config.adaptation, self.config.learner
        blind = ~self.env.episodes.secrets_known()
        wanted = adaptation is not None and adaptation.hindsight_secrets
        if wanted and self.agent.learner.keeps_replay and learner.secret_critics and blind.any():
            return HindsightSecrets(blind, adaptation.hindsight_optimum, seed=self.config.seed)
        return None

    def _observe(self, step: Transition, infos: dict[str, Any]) -> None:
        """Store the step's transitions: at once, or (blind slots under hindsight secrets)
        when their episodes end."""
        if self.hindsight is None:
            self.agent.observe(step)
            return
        seen = ~self.hindsight.blind
        if seen.any():
            self.agent.observe(step.rows(seen))
        for episode in self.hindsight.step(step, infos):
            self.agent.observe(episode)

    def _policy_learns(self) -> bool:
        """False during an adaptation's critic warm-up (its first critic_warmup_steps)."""
        adaptation = self.config.adaptation
        return adaptation is None or self.env_steps > adaptation.critic_warmup_steps

    def run(
        self, progress: bool = True, log: Callable[[str], None] | None = None
    ) -> SessionResult | EvaluationSummary:
        """Train to the budget, then test best.pt (`test_result`); `log` receives a line per
        session and per checkpoint. Gives back the last validation session; a finished run
        writes nothing and gives back the one its checkpoint keeps."""
        from tqdm import tqdm

        cfg, budget = self.config, self.config.budget
        if self.finished:
            # (An older checkpoint keeps no evaluation: run the deterministic session again.)
            return self.last_evaluation or self.evaluate()
        self.logs.write_hparams(cfg)
        self.starts += 1
        observation, infos = self.env.reset(seed=cfg.seed * 1000 + self.starts)
        secret = infos["secret"]
        if self.hindsight is not None:
            self.hindsight.start(infos)
        returns = np.zeros(self.env.num_envs)
        update_rows: list[dict[str, Any]] = []
        bar = tqdm(
            total=budget.env_steps,
            initial=self.env_steps,
            unit="step",
            disable=not progress,
            desc=cfg.name,
            dynamic_ncols=True,
        )
        result = None
        next_eval = (self.env_steps // budget.eval_every + 1) * budget.eval_every
        next_checkpoint = (self.env_steps // budget.checkpoint_every + 1) * budget.checkpoint_every
        recent: list[bool] = []
        while self.env_steps < budget.env_steps:
            action = self.agent.explore(observation, self.rng)
            next_observation, reward, done, _, infos = self.env.step(action)
            final = np.where(
                done[:, None, None],
                infos.get("final_observation", next_observation),
                next_observation,
            )
            step = Transition(observation, secret, action, reward, final, infos["secret"], done)
            self._observe(step, infos)
            returns += reward
            episode_rows = []
            for index in np.flatnonzero(done):
                self.episodes += 1
                success = bool(infos["success"][index])
                recent.append(success)
                episode_rows.append(
                    {
                        "env_steps": self.env_steps + self.env.num_envs,
                        "episode": self.episodes,
                        "return": round(float(returns[index]), 5),
                        "success": int(success),
                        "acquisitions": int(infos["acquisitions"][index]),
                        "complexity": self.env.episodes.complexity,
                    }
                )
                if self.curriculum:
                    self.env.set_complexity(self.curriculum.record(success))
            returns[done] = 0.0
            self.logs.write_episodes(episode_rows, curriculum=self.curriculum is not None)
            observation, secret = next_observation, infos["secret"]
            self.env_steps += self.env.num_envs
            bar.update(self.env.num_envs)
            learned = self.agent.learn(self.rng, train_policy=self._policy_learns())
            first = self.agent.updates - len(learned) + 1  # the update number of learned[0]
            for number, metrics in enumerate(learned, start=first):
                # SAC logs every UPDATE_LOG_EVERY-th gradient step (counted from the start of
                # the learner, an adaptation's source included); PPO each rollout's update.
                if self.agent.learner.logs_every_update or number % UPDATE_LOG_EVERY == 0:
                    update_rows.append(
                        {
                            "env_steps": self.env_steps,
                            "updates": number,
                            **{k: round(v, 6) for k, v in metrics.items()},
                        }
                    )
            self.logs.write_updates(update_rows)
            update_rows = []
            if recent:
                bar.set_postfix(
                    success=f"{np.mean(recent[-200:]):.2f}",
                    level=f"{self.env.episodes.complexity:.2f}",
                )
            # The final sessions come before the final checkpoint: a run resumed after that
            # checkpoint is finished, with nothing to write again.
            if self.env_steps >= next_eval or self.env_steps >= budget.env_steps:
                best = self.best_successes
                result = self.evaluate_and_keep_best()
                if log:
                    log(validation_line(self.env_steps, result, result.successes > best))
                next_eval += budget.eval_every
            if self.env_steps >= budget.env_steps:
                tested = self.test_best()
                if log and tested:
                    log(test_line(tested))
            if self.env_steps >= next_checkpoint or self.env_steps >= budget.env_steps:
                self.checkpoint()
                if log:
                    log(f"checkpoint at {self.env_steps} env steps")
                next_checkpoint += budget.checkpoint_every
        bar.close()
        self.logs.flush()
        return result


def validation_line(env_steps: int, result: SessionResult, best: bool) -> str:
    """The line a validation session prints as a run trains."""
    aligned = success_text(result.successes, result.scenarios)
    return (
        f"{env_steps} env steps: validation session {aligned} aligned, median "
        f"{result.median_acquisitions:g} acquisitions"
        + ("; the best so far: checkpoints/best.pt" if best else "")
    )


def test_line(test: TestSummary) -> str:
    """The line that reports best.pt on the test session."""
    return (
        f"test session (seed {test.seed}, chose nothing): best.pt of "
        f"{test.checkpoint_env_steps} env steps aligned "
        f"{success_text(test.successes, test.scenarios)}, median "
        f"{test.median_acquisitions:g} acquisitions"
    )


def start_adaptation(
    config: ExperimentConfig, source: PolicySource, runs_root: str | Path
) -> Trainer:
    """A new adaptation run: the Trainer with the source's weights, evaluated zero-shot and
    checkpointed at once, so that a run killed before its first scheduled checkpoint resumes
    from the source."""
    if config.adaptation is None:
        raise ValueError(f"{config.name}: not an adaptation config (no `adaptation:` section)")
    trainer = Trainer.create(config, runs_root)
    try:
        trainer.agent.load_state_dict(source.agent.state_dict(replay=False))
        # The source's optimizer state carries its own step size; the run's config says
        # which one adaptation uses (by default the source's, copied into the config).
        trainer.agent.set_learning_rate(config.learner.learning_rate)
        # The zero-shot evaluation, at 0 env steps: on record in metrics/evaluations.csv,
        # and the source is best.pt until an adapted aligner does strictly better, so the
        # best an adaptation gives back is never worse than what it started from on that
        # session.
        trainer.evaluate_and_keep_best()
        trainer.checkpoint()
    except BaseException:  # an instrument that failed, Ctrl-C, a full disk: no run yet
        trainer.unstart()
        raise
    return trainer

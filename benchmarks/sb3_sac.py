"""Stable-Baselines3 SAC beside our SAC on the focus task: gradient-update speed and learning.

A benchmark only: Stable-Baselines3 is the `bench` extra of pyproject.toml, never a runtime
dependency of alignrl. Both sides get the same AlignmentEnv, built from one experiment file
(apparatus, task, history), and SB3 sees the same (history, features) observation, which its
MlpPolicy flattens as our MLPEncoder does.

* ``--updates``: gradient updates per second for the same network sizes (two hidden layers of
  256 in the actor and in each critic, batch 256), replay sampling included on both sides,
  medians over interleaved repeats.
* ``--learn``: SB3 SAC (MlpPolicy, its own defaults) trained for the step budget and evaluated
  every --eval-every env steps with our held-out evaluation session (the scenarios and starts
  of `alignrl train`'s evaluations); ``--ours CONFIG`` trains our learner beside it the way
  `alignrl train` does, in a temporary run directory.

    python -m benchmarks.sb3_sac --updates
    python -m benchmarks.sb3_sac --learn --steps 30000 --eval-every 5000 [--ours CONFIG]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from alignrl.agents.replay import ReplayBuffer
from alignrl.agents.sac import SAC, SACConfig
from alignrl.config.experiment import ExperimentConfig, load_experiment, parse_experiment
from alignrl.envs.alignment import AlignmentEnv
from alignrl.evaluation.session import SessionResult
from alignrl.training import Trainer, evaluate_policy
from alignrl.transitions import Transition

try:
    from stable_baselines3 import SAC as SB3SAC
    from stable_baselines3.common.logger import configure
except ImportError as error:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        "benchmarks/sb3_sac.py needs Stable-Baselines3, a benchmark-only dependency: "
        "install it with `pip install -e '.[bench]'` (or `make bench`)"
    ) from error

__all__ = [
    "EvaluationRow",
    "UpdateSpeed",
    "learn_ours",
    "learn_sb3",
    "make_env",
    "update_speed",
]

DEFAULT_CONFIG = "benchmarks/configs/focus-sac-mlp-bonus-utd2.yaml"
BATCH_SIZE = 256
WIDTH = 256  # units per hidden layer, both sides
# SB3's net_arch [256, 256] is two hidden layers between the flat history and each output.
# MLPEncoder needs at least one layer of its own, so ours is the encoder's one layer plus one
# head layer: the same depth and widths (our critics' second layer also reads the secret).
OURS_FOR_SPEED = SACConfig(
    encoder="mlp", encoder_kwargs={"hidden": (WIDTH,)}, hidden=(WIDTH,), batch_size=BATCH_SIZE
)
SB3_NET_ARCH = [WIDTH, WIDTH]
# Fields that make up the environment and its evaluation: --ours must agree with --config.
ENVIRONMENT_FIELDS = (
    "apparatus",
    "apparatus_args",
    "task",
    "task_options",
    "history",
    "complexity",
    "curriculum",
    "eval_apparatus",
    "eval_apparatus_args",
)


def make_env(config: ExperimentConfig) -> AlignmentEnv:
    """The env SB3 trains on: one AlignmentEnv with the experiment's apparatus, task and
    history, unwrapped (SB3 adds its own Monitor and vector wrappers)."""
    if config.curriculum.enabled:
        raise ValueError(
            f"{config.name}: the SB3 side has no curriculum; use an experiment with "
            "curriculum.enabled false (a fixed complexity)"
        )
    return AlignmentEnv(
        config.apparatus,
        config.resolved_task(),
        config.history,
        complexity=config.complexity,
        apparatus_args=config.apparatus_args,
    )


# --- update speed -------------------------------------------------------------------------


@dataclass(frozen=True)
class UpdateSpeed:
    """Updates per second of each side, one figure per repeat."""

    ours: list[float]
    sb3: list[float]
    ours_parameters: dict[str, int]  # actor and one Q network
    sb3_parameters: dict[str, int]

    @property
    def ratio(self) -> float:
        """Median of ours over median of SB3's: above 1 means ours updates faster."""
        return statistics.median(self.ours) / statistics.median(self.sb3)


def random_transitions(env: AlignmentEnv, count: int, seed: int) -> Transition:
    """`count` transitions of uniform random actions, episodes restarting as they end."""
    rng = np.random.default_rng(seed)
    shape = env.observation_space.shape
    actions = rng.uniform(-1.0, 1.0, (count, *env.action_space.shape)).astype(np.float32)
    observations = np.zeros((count, *shape), np.float32)
    next_observations = np.zeros((count, *shape), np.float32)
    secrets = np.zeros((count, env.episodes.k), np.float32)
    next_secrets = np.zeros_like(secrets)
    rewards = np.zeros(count, np.float32)
    dones = np.zeros(count, np.float32)
    observation, info = env.reset(seed=seed)
    for index, action in enumerate(actions):
        next_observation, reward, terminated, _, next_info = env.step(action)
        observations[index], next_observations[index] = observation, next_observation
        secrets[index], next_secrets[index] = info["secret"], next_info["secret"]
        rewards[index], dones[index] = reward, terminated
        observation, info = env.reset() if terminated else (next_observation, next_info)
    return Transition(
        observations, secrets, actions, rewards, next_observations, next_secrets, dones
    )


def _parameters(module: torch.nn.Module) -> int:
    return sum(parameter.numel() for parameter in module.parameters())


def update_speed(
    config: ExperimentConfig,
    updates: int = 300,
    repeats: int = 7,
    seed: int = 0,
    transitions: int = 5000,
) -> UpdateSpeed:
    """Our `SAC.update` against SB3's `SAC.train`, same data, same sizes, same threads.

    The two sides alternate which goes first in each repeat, so a load that comes and goes on
    the machine falls on both alike."""
    env = make_env(config)
    stored = random_transitions(env, transitions, seed)
    shape = env.observation_space.shape
    action_dim, secret_dim = env.action_space.shape[0], env.episodes.k

    torch.manual_seed(seed)
    ours = SAC(shape, action_dim, secret_dim, OURS_FOR_SPEED)
    replay = ReplayBuffer(transitions, shape, secret_dim, action_dim)
    replay.add(stored)
    rng = np.random.default_rng(seed)

    sb3 = SB3SAC(
        "MlpPolicy",
        env,
        buffer_size=transitions,
        batch_size=BATCH_SIZE,
        policy_kwargs={"net_arch": SB3_NET_ARCH},
        seed=seed,
        device="cpu",
    )
    sb3.set_logger(configure(folder=None, format_strings=[]))  # train() logs; here to nowhere
    for index in range(transitions):
        row = slice(index, index + 1)
        sb3.replay_buffer.add(
            stored.observation[row],
            stored.next_observation[row],
            stored.action[row],
            stored.reward[row],
            stored.done[row],
            [{}],
        )

    def run_ours(steps: int) -> None:
        for _ in range(steps):
            ours.update(replay.sample(BATCH_SIZE, rng))

    def run_sb3(steps: int) -> None:
        sb3.train(gradient_steps=steps, batch_size=BATCH_SIZE)

    sides = {"ours": run_ours, "sb3": run_sb3}
    for run in sides.values():
        run(updates)  # one untimed round: allocator, optimizer state, caches
    rates: dict[str, list[float]] = {name: [] for name in sides}
    for repeat in range(repeats):
        order = list(sides) if repeat % 2 == 0 else list(reversed(sides))
        for name in order:
            rates[name].append(_updates_per_second(sides[name], updates))
    return UpdateSpeed(
        ours=rates["ours"],
        sb3=rates["sb3"],
        ours_parameters={"actor": _parameters(ours.actor), "q": _parameters(ours.q1)},
        sb3_parameters={
            "actor": _parameters(sb3.actor),
            "q": _parameters(sb3.critic.q_networks[0]),
        },
    )


def _updates_per_second(run: Callable[[int], None], updates: int) -> float:
    start = time.perf_counter()
    run(updates)
    return updates / (time.perf_counter() - start)


def update_speed_lines(speed: UpdateSpeed, threads: int, updates: int) -> list[str]:
    def figures(rates: list[float]) -> str:
        return f"{statistics.median(rates):.0f} (range {min(rates):.0f}-{max(rates):.0f})"

    return [
        f"Gradient updates per second, batch {BATCH_SIZE}, {threads} torch threads, "
        f"{len(speed.ours)} interleaved repeats of {updates} updates (replay sampling included):",
        "",
        "| learner | networks | parameters (actor, one Q) | updates/s, median |",
        "| --- | --- | --- | --- |",
        f"| alignrl SAC | actor, twin Q, V, V target; MLP encoder ({WIDTH}) + head ({WIDTH}) | "
        f"{speed.ours_parameters['actor']:,}, {speed.ours_parameters['q']:,} | "
        f"{figures(speed.ours)} |",
        f"| SB3 SAC | actor, twin Q, twin Q target; net_arch {SB3_NET_ARCH} | "
        f"{speed.sb3_parameters['actor']:,}, {speed.sb3_parameters['q']:,} | "
        f"{figures(speed.sb3)} |",
        "",
        f"Ours / SB3: {speed.ratio:.2f}x",
    ]


# --- learning -----------------------------------------------------------------------------


@dataclass(frozen=True)
class EvaluationRow:
    learner: str
    env_steps: int
    successes: int
    scenarios: int
    median_acquisitions: float
    wall_seconds: float  # since the learner was built, evaluations included


def _row(learner: str, env_steps: int, result: SessionResult, start: float) -> EvaluationRow:
    return EvaluationRow(
        learner,
        env_steps,
        result.successes,
        result.scenarios,
        result.median_acquisitions,
        time.perf_counter() - start,
    )


def evaluate(
    config: ExperimentConfig, act: Callable[[np.ndarray], np.ndarray], scenarios: int
) -> SessionResult:
    """Our held-out session, as `alignrl train` runs it (same scenarios, same starts)."""
    return evaluate_policy(
        act,
        config.eval_apparatus,
        config.eval_apparatus_args,
        config.resolved_task(),
        config.history,
        scenarios,
        name=config.name,
    )


def learn_sb3(
    config: ExperimentConfig,
    steps: int,
    eval_every: int,
    scenarios: int,
    report: Callable[[EvaluationRow], None] | None = None,
) -> list[EvaluationRow]:
    """SB3 SAC with its defaults (one env, one update per env step, 100 steps before
    learning), seeded with the experiment's seed; an evaluation every `eval_every` steps,
    each row also handed to `report` as it comes (long runs show progress)."""
    start = time.perf_counter()
    model = SB3SAC("MlpPolicy", make_env(config), seed=config.seed, device=config.device)

    def act(observation: np.ndarray) -> np.ndarray:
        return model.predict(observation, deterministic=True)[0]

    rows = []
    while model.num_timesteps < steps:
        chunk = min(eval_every, steps - model.num_timesteps)
        # reset_num_timesteps=False: each call goes on from where the last one stopped.
        model.learn(chunk, reset_num_timesteps=False)
        rows.append(_row("SB3 SAC", model.num_timesteps, evaluate(config, act, scenarios), start))
        if report:
            report(rows[-1])
    return rows


class _StopwatchTrainer(Trainer):
    """Our Trainer, noting the result and the wall time of each evaluation session."""

    def __init__(self, config: ExperimentConfig, run_dir: str | Path) -> None:
        self.start = time.perf_counter()
        super().__init__(config, run_dir)
        self.rows: list[EvaluationRow] = []
        self.report: Callable[[EvaluationRow], None] | None = None

    def evaluate(self) -> SessionResult:
        result = super().evaluate()
        self.rows.append(_row("alignrl SAC", self.env_steps, result, self.start))
        if self.report:
            self.report(self.rows[-1])
        return result


def learn_ours(
    config: ExperimentConfig,
    steps: int,
    eval_every: int,
    scenarios: int,
    report: Callable[[EvaluationRow], None] | None = None,
) -> list[EvaluationRow]:
    """`alignrl train` of the experiment with the benchmark's budget and torch threads, in a
    temporary runs directory (deleted afterwards); rows go to `report` as in learn_sb3."""
    settings = config.model_dump()
    settings["threads"] = torch.get_num_threads()  # the benchmark's, as SB3's side runs with
    settings["budget"] = {
        "env_steps": steps,
        "eval_every": eval_every,
        "eval_scenarios": scenarios,
        "checkpoint_every": steps,
    }
    config = parse_experiment(settings, f"{config.name} with the benchmark's budget")
    with tempfile.TemporaryDirectory() as runs_root:
        trainer = _StopwatchTrainer.create(config, runs_root)
        trainer.report = report
        trainer.run(progress=False)
    return trainer.rows


def learning_lines(rows: list[EvaluationRow], command: str) -> list[str]:
    lines = [
        f"`{command}`",
        "",
        "| learner | env steps | successes | median acquisitions | wall seconds |",
        "| --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        lines.append(
            f"| {row.learner} | {row.env_steps:,} | {row.successes}/{row.scenarios} | "
            f"{row.median_acquisitions:g} | {row.wall_seconds:.0f} |"
        )
    return lines


# --- command line -------------------------------------------------------------------------


def _environment_differences(first: ExperimentConfig, second: ExperimentConfig) -> list[str]:
    return [name for name in ENVIRONMENT_FIELDS if getattr(first, name) != getattr(second, name)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--updates", action="store_true", help="compare gradient-update speed")
    parser.add_argument("--learn", action="store_true", help="train SB3 SAC and evaluate it")
    parser.add_argument(
        "--config", default=DEFAULT_CONFIG, help="experiment defining env, evaluation and seed"
    )
    parser.add_argument("--ours", metavar="CONFIG", help="with --learn: train ours from CONFIG too")
    parser.add_argument("--steps", type=int, help="env steps (default: the experiment's budget)")
    parser.add_argument("--eval-every", type=int, help="env steps between evaluations")
    parser.add_argument("--scenarios", type=int, help="held-out scenarios per evaluation")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--repeats", type=int, default=7, help="--updates: timed repeats")
    parser.add_argument("--update-count", type=int, default=300, help="--updates: per repeat")
    parser.add_argument("--out", type=Path, help="also write the tables (Markdown) here")
    args = parser.parse_args(argv)
    if not (args.updates or args.learn):
        parser.error("choose --updates, --learn or both")
    if args.ours and not args.learn:
        parser.error("--ours trains our learner beside SB3's: it needs --learn")
    torch.set_num_threads(args.threads)
    config = load_experiment(args.config)
    ours_config = load_experiment(args.ours) if args.ours else None
    if ours_config is not None and (differences := _environment_differences(config, ours_config)):
        parser.error(
            f"--ours {args.ours} differs from --config {args.config} in "
            f"{', '.join(differences)}; both sides must train on the same environment"
        )
    command = " ".join(["python -m benchmarks.sb3_sac", *(sys.argv[1:] if argv is None else argv)])
    lines: list[str] = []
    if args.updates:
        speed = update_speed(config, args.update_count, args.repeats)
        lines += [*update_speed_lines(speed, args.threads, args.update_count), ""]
        print("\n".join(lines), flush=True)
    if args.learn:
        steps = args.steps or config.budget.env_steps
        eval_every = args.eval_every or config.budget.eval_every
        scenarios = args.scenarios or config.budget.eval_scenarios

        def report(row: EvaluationRow) -> None:
            print(
                f"{row.learner}: {row.env_steps} env steps, {row.successes}/{row.scenarios} "
                f"held-out, median {row.median_acquisitions:g} acquisitions, "
                f"{row.wall_seconds:.0f} s",
                flush=True,
            )

        rows = learn_sb3(config, steps, eval_every, scenarios, report)
        if ours_config is not None:
            rows += learn_ours(ours_config, steps, eval_every, scenarios, report)
        learning = learning_lines(rows, command)
        lines += learning
        print("\n".join(learning), flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The learner registry (alignrl/agents/learners.py): a learner is one class plus one entry.

A toy learner registered here, in the test alone, is built, explores, observes, learns, saves
and loads through `Agent`, and `MemberSpec` and `LearnerConfig` take it by name: nothing else
in alignrl had to change for it. The shipped learners and the config cannot disagree on a
default.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import nn

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.agents.learners import LEARNERS, learner_class, learner_defaults, learner_title
from alignrl.agents.settings import SHIPPED, LearnerSettings
from alignrl.config.experiment import parse_experiment
from alignrl.config.learner import LearnerConfig
from alignrl.config_reading import ConfigError
from alignrl.transitions import Transition

SHAPE = (4, 3)  # history rows, features
TARGET = np.array([0.5, -0.25])  # the toy task: the best action, whatever the history


@dataclass(frozen=True)
class ToyConfig:
    learning_rate: float = 3e-4  # the keys every learner shares default alike
    batch_size: int = 256
    noise: float = 0.3  # std of the exploration noise


class ToyTransitions:
    """The toy's experience: the transitions since its last update."""

    def __init__(self, capacity: int, features: int, action_dim: int) -> None:
        self.features = np.zeros((capacity, features), np.float32)
        self.action = np.zeros((capacity, action_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.size = 0

    def state_dict(self) -> dict[str, Any]:
        used = slice(0, self.size)
        return {
            "features": self.features[used].copy(),
            "action": self.action[used].copy(),
            "reward": self.reward[used].copy(),
            "size": self.size,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.size = int(state["size"])
        for name in ("features", "action", "reward"):
            getattr(self, name)[: self.size] = state[name]


class ToyPolicy(nn.Module):
    """A linear map of the newest history row to the mean of a Gaussian."""

    def __init__(self, features: int, action_dim: int) -> None:
        super().__init__()
        self.head = nn.Linear(features, action_dim)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.head(observation[:, -1])


class ToyLearner:
    """A linear policy that imitates the better half of each batch: its mean steps toward
    the explored actions whose reward was above the batch's median."""

    name = "toy"
    title = "Toy"
    config_type = ToyConfig
    schedule_defaults: Mapping[str, float] = {"learning_starts": 0}
    metric_names = ("imitation_loss", "mean_reward")
    experience_name = "transitions"
    keeps_replay = False
    logs_every_update = True

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: ToyConfig,
        schedule: Mapping[str, float],
        envs: int,
        device: str | torch.device,
    ) -> None:
        self.config, self.schedule = config, dict(schedule)
        self.device = torch.device(device)
        self.action_dim = action_dim
        features = observation_shape[1]
        self.policy = ToyPolicy(features, action_dim).to(self.device)
        self.optimizer = torch.optim.SGD(self.policy.parameters(), lr=config.learning_rate)
        self.experience = ToyTransitions(config.batch_size + envs, features, action_dim)
        self.updates = 0
        self.update_debt = 0.0

    @property
    def optimizers(self) -> list[torch.optim.Optimizer]:
        return [self.optimizer]

    @property
    def acting_network(self) -> nn.Module:
        return self.policy

    @torch.no_grad()
    def _mean(self, observation: np.ndarray) -> np.ndarray:
        batch = torch.as_tensor(observation, dtype=torch.float32, device=self.device)
        return self.policy(batch).cpu().numpy()

    def act(self, observation: np.ndarray, deterministic: bool = False) -> np.ndarray:
        single = observation.ndim == 2
        mean = self._mean(observation[None] if single else observation)
        return np.tanh(mean[0] if single else mean)

    def explore(
        self, observation: np.ndarray, rng: np.random.Generator, steps_seen: int
    ) -> np.ndarray:
        noise = rng.normal(0.0, self.config.noise, (len(observation), self.action_dim))
        return np.tanh(self._mean(observation) + noise)

    def explore_rows(
        self,
        observation: np.ndarray,
        generators: Sequence[np.random.Generator],
        steps_seen: int,
        warm_up: bool,
    ) -> tuple[np.ndarray, None]:
        noise = np.stack([g.normal(0.0, self.config.noise, self.action_dim) for g in generators])
        return np.tanh(self._mean(observation) + noise), None

    def observe(self, transition: Transition, member: str) -> None:
        store, count = self.experience, len(transition)
        rows = slice(store.size, store.size + count)
        store.features[rows] = transition.observation[:, -1]
        store.action[rows] = transition.action
        store.reward[rows] = transition.reward
        store.size += count

    def learn(
        self,
        rng: np.random.Generator,
        steps_seen: int,
        new_steps: int,
        member: str,
        train_policy: bool,
    ) -> list[dict[str, float]]:
        if steps_seen < self.schedule["learning_starts"]:
            return []
        if self.experience.size < self.config.batch_size:
            return []
        metrics = self.learn_from(self.experience.state_dict(), rng, member, train_policy)
        self.experience.size = 0
        return [metrics]

    def learn_from(
        self, batch: Any, rng: np.random.Generator | None, member: str, train_policy: bool
    ) -> dict[str, float]:
        reward = torch.as_tensor(batch["reward"])
        better = (reward > reward.median()).float()  #                                     (B,)
        action = torch.as_tensor(batch["action"]).clamp(-0.999, 0.999)
        mean = self.policy(torch.as_tensor(batch["features"])[:, None])  #                 (B, A)
        # Regress the mean on atanh of the better actions: the policy drifts toward them.
        loss = (better[:, None] * (mean - torch.atanh(action)).square()).mean()
        self.optimizer.zero_grad()
        loss.backward()
        if train_policy:
            self.optimizer.step()
        self.updates += 1
        return {"imitation_loss": float(loss.detach()), "mean_reward": float(reward.mean())}

    def state_dict(self) -> dict[str, Any]:
        return {
            "policy": self.policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "config": dataclasses.asdict(self.config),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])


@pytest.fixture
def toy() -> Iterator[type[ToyLearner]]:
    """The toy learner registered for one test, and gone after it."""
    assert "toy" not in LEARNERS
    LEARNERS["toy"] = ToyLearner  # type: ignore[assignment]
    try:
        yield ToyLearner
    finally:
        del LEARNERS["toy"]


def toy_spec(**hyperparameters: Any) -> MemberSpec:
    return MemberSpec("toy-0", "aligner", "toy", SHAPE, 2, 1, hyperparameters)


def play(agent: Agent, steps: int, seed: int) -> list[dict[str, float]]:
    """Random histories of 4 slots; the reward is how close the action comes to TARGET."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(steps):
        observation = rng.uniform(-1, 1, (4, *SHAPE)).astype(np.float32)
        action = agent.explore(observation, rng)
        reward = -np.square(action - TARGET).sum(-1)
        zeros = np.zeros((4, 1))
        agent.observe(
            Transition(observation, zeros, action, reward, observation, zeros, np.zeros(4, bool))
        )
        rows += agent.learn(rng)
    return rows


def test_a_registered_learner_trains_saves_and_loads_through_the_agent(
    toy: type[ToyLearner], tmp_path: Path
) -> None:
    torch.manual_seed(0)
    agent = Agent(toy_spec(learning_rate=0.5, batch_size=16), envs=4)
    assert isinstance(agent.learner, ToyLearner) and agent.metric_names == toy.metric_names
    probe = np.random.default_rng(9).uniform(-1, 1, (64, *SHAPE)).astype(np.float32)

    def miss() -> float:
        return float(np.square(agent.act(probe) - TARGET).sum(-1).mean())

    before = miss()
    rows = play(agent, 120, seed=0)
    assert len(rows) == agent.updates == 30  # one update per 16 transitions
    assert set(rows[0]) == set(toy.metric_names)
    assert miss() < 0.3 * before  # it learned: the deterministic action nears TARGET
    assert agent.steps_seen == 480 and agent.transitions is agent.experience  # its own name

    play(agent, 2, seed=1)  # 8 transitions wait in the experience
    agent.save(tmp_path / "toy.pt", replay=True)
    loaded = Agent.load(tmp_path / "toy.pt", envs=4)
    assert loaded.spec == agent.spec and loaded.steps_seen == agent.steps_seen
    assert loaded.experience.size == agent.experience.size == 8
    np.testing.assert_array_equal(loaded.act(probe), agent.act(probe))
    assert play(loaded, 6, seed=2) == play(agent, 6, seed=2)  # the same next updates

    copy = Agent.from_policy_state(agent.policy_state())
    np.testing.assert_array_equal(copy.act(probe), agent.act(probe))
    generators = [np.random.default_rng(seed) for seed in range(3)]
    actions, extra = agent.explore_rows(probe[:3], generators)
    assert actions.shape == (3, 2) and extra is None
    agent.set_learning_rate(0.01)
    assert agent.learner.optimizer.param_groups[0]["lr"] == 0.01
    state = agent.state_dict()
    state["learner"]["policy"]["head.weight"] = torch.zeros(3, 2)
    with pytest.raises(
        ValueError, match=r"policy\.head\.weight has shape \(3, 2\), the spec needs"
    ):
        loaded.load_state_dict(state)


def test_member_spec_and_learner_config_take_a_registered_learner_by_name(
    toy: type[ToyLearner],
) -> None:
    spec = toy_spec(noise=0.1, learning_starts=8)
    assert spec.learner_config() == ToyConfig(noise=0.1)
    assert spec.schedule() == {"learning_starts": 8}
    with pytest.raises(ValueError, match="toy has no hyperparameter 'tau'"):
        toy_spec(tau=0.01)

    config = LearnerConfig(algorithm="toy", learning_rate=0.01, learning_starts=4)
    # Only the keys the toy has travel to its member; the others keep their defaults.
    assert config.hyperparameters() == {
        "learning_rate": 0.01,
        "batch_size": 256,
        "learning_starts": 4,
    }
    assert parse_experiment({"learner": {"algorithm": "toy"}}).learner.algorithm == "toy"
    with pytest.raises(ValueError, match="encoder, tau do not apply to algorithm toy"):
        LearnerConfig(algorithm="toy", tau=0.01, encoder="gru")


def test_an_unregistered_learner_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="algorithm 'toy' is not one of sac, ppo"):
        toy_spec()
    with pytest.raises(ConfigError, match=r"learner\.algorithm.*'sac' or 'ppo'"):
        parse_experiment({"learner": {"algorithm": "toy"}})
    with pytest.raises(ValueError, match="unknown learner 'toy'; known learners: sac, ppo"):
        learner_class("toy")


def test_a_learner_whose_defaults_disagree_with_the_config_is_refused() -> None:
    @dataclass(frozen=True)
    class EagerConfig(ToyConfig):
        learning_rate: float = 0.1

    class Eager(ToyLearner):
        name = "eager"
        config_type = EagerConfig

    LEARNERS["eager"] = Eager  # type: ignore[assignment]
    try:
        with pytest.raises(ValueError, match=r"learner eager defaults learning_rate=0\.1"):
            LearnerConfig(algorithm="eager")
    finally:
        del LEARNERS["eager"]


@pytest.mark.parametrize("name", ["sac", "ppo"])
def test_a_shipped_learner_and_the_config_agree_on_every_default(name: str) -> None:
    """A config that names only the algorithm builds the learner's own defaults."""
    learner = learner_class(name)
    config = LearnerConfig(algorithm=name)
    spec = MemberSpec("m", "aligner", name, (8, 7), 2, 1, config.hyperparameters())
    assert spec.learner_config() == learner.config_type()
    assert spec.schedule() == dict(learner.schedule_defaults)
    fields = LearnerConfig.model_fields
    for key, default in learner_defaults(name).items():
        if key in fields:  # null for a learner's own key: its default, quoted in the doc
            declared = fields[key].get_default(call_default_factory=True)
            assert declared == default or declared is None, key
            if declared is None:
                assert str(fields[key].description).startswith(f"({learner.title})"), key


@pytest.mark.parametrize("name", ["sac", "ppo"])
def test_a_shipped_learner_provides_all_the_agent_asks(name: str) -> None:
    learner = learner_class(name)
    assert learner.name == name and learner.title == name.upper()
    agent = Agent(MemberSpec("m", "aligner", name, (8, 7), 2, 1, {"hidden": [8]}), envs=2)
    assert getattr(agent, learner.experience_name) is agent.experience
    network = agent.learner.acting_network
    assert hasattr(network, "encoder") and hasattr(network, "head")  # what export reads
    parameters = {
        id(p)
        for optimizer in agent.learner.optimizers
        for group in optimizer.param_groups
        for p in group["params"]
    }
    assert {id(p) for p in network.parameters()} <= parameters


@pytest.mark.parametrize("name", ["sac", "ppo"])
def test_a_learner_that_only_acts_makes_no_optimizer(name: str) -> None:
    """A shipped learner makes its optimizers when an update or a state first asks for them:
    a policy loaded to act (`alignrl align`, `evaluate`) makes none, and so never imports
    what torch's first optimizer needs (1.5-2 s a command)."""
    agent = Agent(MemberSpec("m", "aligner", name, (8, 7), 2, 1, {"hidden": [8]}), envs=2)
    agent.load_policy_state(agent.policy_state())
    action = agent.act(np.zeros((8, 7), np.float32), deterministic=True)
    assert action.shape == (2,) and np.all(np.isfinite(action))
    names = ("optimizer", "actor_optimizer", "critic_optimizer", "alpha_optimizer")
    assert not [key for key in names if key in vars(agent.learner)]
    optimizers = agent.learner.optimizers
    made = [key for key in names if key in vars(agent.learner)]
    assert len(made) == len(optimizers)  # made now, and once
    assert list(map(id, agent.learner.optimizers)) == list(map(id, optimizers))
    assert set(made) <= set(agent.learner.state_dict())  # what a checkpoint keeps


@pytest.mark.parametrize("name", ["sac", "ppo"])
def test_a_shipped_learners_settings_are_its_class_attributes(name: str) -> None:
    """What the registry tells before the class is imported is what the class says."""
    where, settings = SHIPPED[name]
    learner = learner_class(name)
    assert f"{learner.__module__}:{learner.__qualname__}" == where
    assert settings == LearnerSettings(
        learner.title, learner.config_type, learner.schedule_defaults
    )
    assert LEARNERS.settings(name) == settings and learner_title(name) == learner.title


def test_reading_a_config_and_building_the_cli_import_no_torch() -> None:
    """`alignrl baselines`, `record`, `scenarios` and `--help` start without torch (seconds
    a call): the config checks a learner's settings from alignrl/agents/settings.py. A
    learner's class is imported where one is built, and torch with it."""
    script = (
        "import sys\n"
        "from alignrl.cli.main import build_parser\n"
        "from alignrl.config.experiment import load_experiment\n"
        "build_parser()\n"
        "config = load_experiment('experiments/focus-v2.yaml')\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "from alignrl.agents.learners import learner_class\n"
        "assert learner_class(config.learner.algorithm).title == 'SAC'\n"
        "assert 'torch' in sys.modules\n"
    )
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]

"""Members: the record, both learners behind one interface, safe save/load, the NaN guard,
and PPO learning the focus task through the trainer."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.agents.sac import NonFiniteError
from alignrl.checkpoints import CheckpointError
from alignrl.config.experiment import parse_experiment
from alignrl.config_reading import ConfigError
from alignrl.training import Trainer
from alignrl.transitions import Transition

SHAPE = (8, 7)
SAC_SMALL = {
    "encoder_kwargs": {"hidden": [32]},
    "hidden": [32, 32],
    "batch_size": 16,
    "learning_starts": 16,
    "random_steps": 8,
}
PPO_SMALL = {
    "encoder": "gru",
    "encoder_kwargs": {"hidden": 16},
    "hidden": [32],
    "batch_size": 16,
    "rollout_steps": 4,
    "epochs": 2,
}


def spec(algorithm: str = "sac", **changes: object) -> MemberSpec:
    settings = {
        "id": f"aligner-{algorithm}",
        "team": "aligner",
        "algorithm": algorithm,
        "observation_shape": SHAPE,
        "action_dim": 2,
        "secret_dim": 1,
        "hyperparameters": SAC_SMALL if algorithm == "sac" else PPO_SMALL,
        **changes,
    }
    return MemberSpec(**settings)  # type: ignore[arg-type]


def play(agent: Agent, steps: int, seed: int) -> None:
    """Feed the member random transitions of 4 slots and let it learn as it goes."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        observation = rng.uniform(-1, 1, (4, *SHAPE)).astype(np.float32)
        observation[..., 0] = 1.0
        action = agent.explore(observation, rng)
        agent.observe(
            Transition(
                observation,
                rng.uniform(-1, 1, (4, 1)),
                action,
                rng.normal(size=4),
                observation[::-1].copy(),
                rng.uniform(-1, 1, (4, 1)),
                rng.random(4) < 0.2,
            )
        )
        agent.learn(rng)


def test_the_member_record_names_its_architecture_and_refuses_nonsense() -> None:
    gtrxl = spec(hyperparameters={"encoder": "gtrxl", "encoder_kwargs": {"d_model": 32}})
    assert gtrxl.architecture == "gtrxl(d_model=32)"
    assert spec("ppo").architecture == "gru(hidden=16)"
    assert MemberSpec.from_dict(gtrxl.to_dict()) == gtrxl
    with pytest.raises(ValueError, match="member 'x': team 'referee'"):
        spec(id="x", team="referee")
    with pytest.raises(ValueError, match="algorithm 'dqn'"):
        spec(algorithm="dqn", hyperparameters={})
    with pytest.raises(ValueError, match="sac has no hyperparameter 'epochs'"):
        spec(hyperparameters={"epochs": 3})
    with pytest.raises(ValueError, match="unknown fields rating"):
        MemberSpec.from_dict({**gtrxl.to_dict(), "rating": 1200})


@pytest.mark.parametrize("algorithm", ["sac", "ppo"])
def test_save_load_gives_identical_actions_and_identical_next_update(
    algorithm: str, tmp_path: Path
) -> None:
    torch.manual_seed(0)
    agent = Agent(spec(algorithm), envs=4)
    play(agent, 12, seed=0)
    assert agent.updates > 0
    agent.save(tmp_path / "member.pt", replay=True)
    torch.manual_seed(123)  # the loaded member must not depend on the fresh initialisation
    loaded = Agent.load(tmp_path / "member.pt", envs=4)
    assert loaded.spec == agent.spec and loaded.steps_seen == agent.steps_seen
    observation = np.random.default_rng(5).uniform(-1, 1, SHAPE).astype(np.float32)
    np.testing.assert_array_equal(agent.act(observation), loaded.act(observation))
    # The same experience afterwards gives the same next updates, weight for weight.
    torch.manual_seed(9)
    play(agent, 8, seed=1)
    torch.manual_seed(9)
    play(loaded, 8, seed=1)
    assert loaded.updates == agent.updates
    for (name, a), (_, b) in zip(
        agent.learner.state_dict()["actor" if algorithm == "sac" else "policy"].items(),
        loaded.learner.state_dict()["actor" if algorithm == "sac" else "policy"].items(),
        strict=True,
    ):
        assert torch.equal(a, b), name


def test_replay_travels_only_when_asked(tmp_path: Path) -> None:
    agent = Agent(spec("sac"), envs=4)
    play(agent, 6, seed=0)
    agent.save(tmp_path / "weights.pt")
    agent.save(tmp_path / "full.pt", replay=True)
    assert Agent.load(tmp_path / "weights.pt").replay.size == 0
    assert Agent.load(tmp_path / "full.pt").replay.size == agent.replay.size == 24


def test_a_corrupt_or_foreign_member_file_is_refused_clearly(tmp_path: Path) -> None:
    agent = Agent(spec("sac"))
    path = tmp_path / "member.pt"
    agent.save(path)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(CheckpointError, match="cannot be read"):
        Agent.load(path)
    other = Agent(spec("ppo"))
    with pytest.raises(ValueError, match="saved state is of ppo"):
        agent.load_state_dict(other.state_dict())


def test_a_nan_stops_training_names_the_member_and_keeps_the_last_checkpoint(
    tmp_path: Path,
) -> None:
    settings = {
        "name": "diverges",
        "envs": 2,
        "learner": {**SAC_SMALL, "batch_size": 32, "learning_starts": 32, "random_steps": 32},
        "budget": {"env_steps": 40, "eval_every": 40, "eval_scenarios": 2, "checkpoint_every": 40},
    }
    trainer = Trainer.create(parse_experiment(settings), tmp_path)
    trainer.run(progress=False)
    last = tmp_path / "diverges" / "checkpoints" / "last.pt"
    saved = last.read_bytes()
    resumed = Trainer.resume(tmp_path / "diverges")
    resumed.config = resumed.config.model_copy(
        update={"budget": resumed.config.budget.model_copy(update={"env_steps": 200})}
    )
    with torch.no_grad():
        next(resumed.agent.learner.q1.parameters()).fill_(float("nan"))
    with pytest.raises(NonFiniteError, match=r"member diverges: the \w+ loss is nan"):
        resumed.run(progress=False)
    assert last.read_bytes() == saved


def test_ppo_settings_belong_to_ppo() -> None:
    with pytest.raises(ConfigError, match=r"learner: .*epochs does not apply to algorithm sac"):
        parse_experiment({"learner": {"epochs": 4}})
    with pytest.raises(ConfigError, match="tau, buffer_size do not apply to algorithm ppo"):
        parse_experiment({"learner": {"algorithm": "ppo", "tau": 0.01, "buffer_size": 5000}})


def test_ppo_with_a_gru_lifts_its_success_rate_well_above_an_untrained_one(
    tmp_path: Path,
) -> None:
    """The tiny focus problem of test_training (starts within 20 % of the interval): 6000 env
    steps of PPO take a GRU policy from chance to aligning most held-out scenarios (of 40,
    untrained -> trained: seed 3 8 -> 31, seed 4 4 -> 32, seed 5 8 -> 19)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from test_training import _near_focus_successes

    settings = {
        "name": "ppo-learns",
        "seed": 3,
        "envs": 8,
        "complexity": 0.2,
        "learner": {
            "algorithm": "ppo",
            "encoder": "gru",
            "encoder_kwargs": {"hidden": 32},
            "hidden": [64, 64],
            "learning_rate": 2e-3,
            "batch_size": 128,
            "rollout_steps": 32,
            "epochs": 8,
        },
        "budget": {"env_steps": 6000, "eval_every": 6000, "eval_scenarios": 10},
    }
    trainer = Trainer.create(parse_experiment(settings), tmp_path / "runs")
    before = _near_focus_successes(trainer, 40)
    trainer.run(progress=False)
    after = _near_focus_successes(trainer, 40)
    assert before <= 12, before
    assert after >= 20 and after >= before + 12, (before, after)


@pytest.mark.parametrize("algorithm", ["sac", "ppo"])
def test_an_acting_copy_acts_as_the_member_each_row_on_its_own_noise(algorithm: str) -> None:
    agent = Agent(spec(algorithm), envs=4)
    play(agent, 3, seed=0)  # past SAC's random warm-up of 8 steps
    state = agent.policy_state()
    assert set(state) == {"format", "spec", "policy", "steps_seen"}  # no critics, no optimizer
    copy = Agent.from_policy_state(state)
    assert copy.steps_seen == agent.steps_seen == 12
    observation = np.random.default_rng(1).uniform(-1, 1, (5, *SHAPE)).astype(np.float32)
    np.testing.assert_array_equal(copy.act(observation), agent.act(observation))

    def generators(count: int) -> list[np.random.Generator]:
        return [np.random.default_rng([seed, 1]) for seed in range(count)]

    actions, pre_tanh = agent.explore_rows(observation, generators(5))
    again, _ = copy.explore_rows(observation, generators(5))
    np.testing.assert_allclose(actions, again, rtol=0, atol=1e-6)
    # Row 2 drew from its own generator: alone, it gets the same action.
    alone, _ = agent.explore_rows(observation[2:3], generators(5)[2:3])
    np.testing.assert_allclose(alone[0], actions[2], rtol=0, atol=1e-6)
    assert not np.allclose(actions, agent.act(observation))  # a sample, not the mean
    assert (pre_tanh is None) == (algorithm == "sac")
    if pre_tanh is not None:
        np.testing.assert_allclose(np.tanh(pre_tanh), actions)


def test_sac_warm_up_and_ppo_samples_from_elsewhere() -> None:
    fresh = Agent(spec("sac"))
    observation = np.zeros((3, *SHAPE), np.float32)
    generators = [np.random.default_rng(seed) for seed in range(3)]
    uniform, _ = fresh.explore_rows(observation, generators)
    expected = np.stack([np.random.default_rng(seed).uniform(-1, 1, 2) for seed in range(3)])
    np.testing.assert_array_equal(uniform, expected)  # still in its random warm-up
    ppo = Agent(spec("ppo"), envs=3)
    actions, pre_tanh = ppo.explore_rows(observation, generators)
    step = Transition(
        observation,
        np.zeros((3, 1)),
        actions,
        np.zeros(3),
        observation,
        np.zeros((3, 1)),
        np.zeros(3, bool),
    )
    with pytest.raises(RuntimeError, match="needs the explore"):
        ppo.observe(step)
    ppo.observe(dataclasses.replace(step, pre_tanh=pre_tanh))
    np.testing.assert_array_equal(ppo.rollout.pre_tanh[:3], pre_tanh)
    assert ppo.steps_seen == 3
    with pytest.raises(ValueError, match="another member"):
        ppo.load_policy_state(fresh.policy_state())

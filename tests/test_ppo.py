"""PPO: GAE, the clipped update, the value network's secret, exact save/load, the NaN guard."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from alignrl.agents.ppo import PPO, PPOConfig, Rollout, RolloutBuffer, generalized_advantages
from alignrl.agents.sac import NonFiniteError
from alignrl.transitions import Transition

SHAPE = (8, 7)
SMALL = PPOConfig(
    encoder="gru", encoder_kwargs={"hidden": 16}, hidden=(32,), batch_size=32, epochs=2
)


def learner(seed: int = 0, config: PPOConfig = SMALL) -> PPO:
    torch.manual_seed(seed)
    return PPO(SHAPE, 2, 1, config)


def random_rollout(steps: int = 16, envs: int = 4, seed: int = 0) -> Rollout:
    """`steps` steps of `envs` slots through the buffer, as the trainer stores them."""
    rng = np.random.default_rng(seed)
    buffer = RolloutBuffer(steps, envs, SHAPE, 1, 2)
    observation = rng.uniform(-1, 1, (envs, *SHAPE)).astype(np.float32)
    for _ in range(steps):
        observation[..., 0] = 1.0  # every row valid
        following = rng.uniform(-1, 1, (envs, *SHAPE)).astype(np.float32)
        secret = rng.uniform(-1, 1, (envs, 1))
        pre_tanh = rng.normal(size=(envs, 2))
        step = Transition(
            observation,
            secret,
            np.tanh(pre_tanh),
            rng.normal(size=envs),
            following,
            rng.uniform(-1, 1, (envs, 1)),
            (rng.random(envs) < 0.2).astype(np.float32),
            pre_tanh=pre_tanh,
        )
        buffer.add(step)
        observation = following
    return buffer.rollout()


def test_generalized_advantages_match_the_recursion_by_hand() -> None:
    # One slot: transitions 0 -> 1 (episode ends at 1), then 2, whose episode goes on past
    # the rollout (bootstrapped from V of its next history).
    reward = np.array([1.0, 0.0, 2.0])
    done = np.array([0.0, 1.0, 0.0])
    value = np.array([0.5, 0.2, 0.1])
    next_value = np.array([0.2, 9.9, 0.3])  # V(next) of a done transition must not count
    follows = np.array([1, -1, -1])
    gamma, lam = 0.9, 0.8
    a2 = 2.0 + gamma * 0.3 - 0.1
    a1 = 0.0 - 0.2
    a0 = (1.0 + gamma * 0.2 - 0.5) + gamma * lam * a1
    got = generalized_advantages(reward, done, value, next_value, follows, gamma, lam)
    np.testing.assert_allclose(got, [a0, a1, a2])


def test_the_buffer_links_each_slot_to_its_next_step_also_when_slots_wait() -> None:
    buffer = RolloutBuffer(steps=3, envs=2, observation_shape=SHAPE, secret_dim=1, action_dim=2)
    zeros = np.zeros((2, *SHAPE), np.float32)

    def step(slots: list[int], done: list[float]) -> None:
        n = len(slots)
        secret, action = np.zeros((n, 1)), np.zeros((n, 2))
        step = Transition(zeros[:n], secret, action, np.ones(n), zeros[:n], secret, np.array(done))
        buffer.add(dataclasses.replace(step, slots=np.array(slots), pre_tanh=action))

    step([0, 1], [0.0, 1.0])  # transitions 0 (slot 0) and 1 (slot 1, its episode ends)
    step([0], [0.0])  # 2: slot 0 alone (slot 1 waits for the round to finish)
    step([1, 0], [0.0, 1.0])  # 3: slot 1's new episode, 4: slot 0 ends
    rollout = buffer.rollout()
    assert rollout.follows.tolist() == [2, -1, 4, -1, -1]
    step([1], [0.0])
    assert buffer.full and buffer.rollout().follows.tolist() == [2, -1, 4, 5, -1, -1]
    with pytest.raises(ValueError, match="full"):
        step([0], [0.0])
    buffer.clear()
    with pytest.raises(ValueError, match="0 of 6"):
        buffer.rollout()
    with pytest.raises(ValueError, match="slot numbers below 2"):
        step([2], [0.0])


def test_the_value_network_reads_the_secret_and_the_policy_cannot() -> None:
    ppo = learner()
    observation = torch.as_tensor(random_rollout().observation[:4])
    v_a = ppo.value(observation, torch.zeros(4, 1))
    v_b = ppo.value(observation, torch.ones(4, 1))
    assert not torch.allclose(v_a, v_b)
    # The policy's GRU takes the history rows alone: its input width is the row width.
    assert ppo.policy.encoder.cell.input_size == SHAPE[1]
    assert ppo.policy.head[0].in_features == ppo.policy.encoder.output_dim
    blind = learner(config=dataclasses.replace(SMALL, secret_critics=False))
    assert blind.value.head[0].in_features == ppo.value.head[0].in_features - 1


def test_an_update_moves_the_policy_within_the_clip_and_reports_its_metrics() -> None:
    ppo = learner()
    before = copy.deepcopy(ppo.policy.state_dict())
    metrics = ppo.update(random_rollout(), np.random.default_rng(0))
    assert set(metrics) == {"policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction"}
    assert all(np.isfinite(value) for value in metrics.values())
    assert 0.0 <= metrics["clip_fraction"] <= 1.0 and metrics["approx_kl"] >= 0.0
    assert ppo.updates == 1
    changed = [not torch.equal(before[k], v) for k, v in ppo.policy.state_dict().items()]
    assert all(changed)


def test_a_critic_warm_up_update_moves_the_value_network_only() -> None:
    ppo = learner()
    policy = copy.deepcopy(ppo.policy.state_dict())
    value = copy.deepcopy(ppo.value.state_dict())
    ppo.update(random_rollout(), np.random.default_rng(0), train_policy=False)
    for key, tensor in ppo.policy.state_dict().items():
        assert torch.equal(policy[key], tensor), key
    assert any(not torch.equal(value[k], v) for k, v in ppo.value.state_dict().items())


def test_save_load_gives_identical_actions_and_identical_next_update() -> None:
    ppo = learner(seed=1)
    ppo.update(random_rollout(seed=1), np.random.default_rng(1))
    state = copy.deepcopy(ppo.state_dict())
    restored = learner(seed=99)
    restored.load_state_dict(state)
    observation = random_rollout(seed=2).observation[:4]
    np.testing.assert_array_equal(
        ppo.act(observation, deterministic=True), restored.act(observation, deterministic=True)
    )
    rollout = random_rollout(seed=3)
    first = ppo.update(rollout, np.random.default_rng(7))
    second = restored.update(rollout, np.random.default_rng(7))
    assert first == second
    for key, value in ppo.policy.state_dict().items():
        torch.testing.assert_close(value, restored.policy.state_dict()[key], rtol=0, atol=0)


def test_a_nan_stops_the_update_names_the_member_and_changes_nothing() -> None:
    ppo = learner()
    before = copy.deepcopy(ppo.state_dict())
    broken = random_rollout()
    broken.reward[13] = np.nan
    with pytest.raises(NonFiniteError, match=r"member aligner-7: the advantage"):
        ppo.update(broken, np.random.default_rng(0), member="aligner-7")
    after = ppo.state_dict()
    for key in ("policy", "value"):
        for name, value in before[key].items():
            assert torch.equal(value, after[key][name]), name
    assert after["updates"] == 0
    # A loss that turns non-finite after some minibatch steps: those steps are rolled back.
    calls = {"n": 0}
    forward = ppo.value.forward

    def fails_later(*args: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        out = forward(*args)
        return out * float("nan") if calls["n"] > 4 else out

    ppo.value.forward = fails_later  # type: ignore[method-assign]
    with pytest.raises(NonFiniteError, match="member m: the value"):
        ppo.update(random_rollout(), np.random.default_rng(0), member="m")
    ppo.value.forward = forward  # type: ignore[method-assign]
    assert calls["n"] > 4  # minibatch steps were taken before the NaN
    after = ppo.state_dict()
    for key in ("policy", "value"):
        for name, value in before[key].items():
            assert torch.equal(value, after[key][name]), name
    assert after["optimizer"]["state"] == {}  # Adam never stepped: its moments are gone


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_ppo_runs_on_cuda_where_available() -> None:
    torch.manual_seed(0)
    ppo = PPO(SHAPE, 2, 1, SMALL, device="cuda")
    metrics = ppo.update(random_rollout(), np.random.default_rng(0))
    assert all(np.isfinite(value) for value in metrics.values())
    assert next(ppo.policy.parameters()).is_cuda
    assert ppo.act(random_rollout().observation[:4]).shape == (4, 2)

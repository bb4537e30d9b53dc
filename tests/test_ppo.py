"""PPO: GAE, the clipped update, the value network's secret, exact save/load, the NaN guard."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from alignrl.agents.ppo import PPO, PPOConfig, Rollout, RolloutBuffer, generalized_advantages
from alignrl.agents.sac import NonFiniteError

SHAPE = (8, 7)
SMALL = PPOConfig(encoder_kwargs={"hidden": 16}, hidden=(32,), batch_size=32, epochs=2)


def learner(seed: int = 0, config: PPOConfig = SMALL) -> PPO:
    torch.manual_seed(seed)
    return PPO(SHAPE, 2, 1, config)


def random_rollout(steps: int = 16, envs: int = 4, seed: int = 0) -> Rollout:
    rng = np.random.default_rng(seed)
    observation = rng.uniform(-1, 1, (steps, envs, *SHAPE)).astype(np.float32)
    observation[..., 0] = 1.0  # every row valid
    return Rollout(
        observation=observation,
        secret=rng.uniform(-1, 1, (steps, envs, 1)).astype(np.float32),
        pre_tanh=rng.normal(size=(steps, envs, 2)).astype(np.float32),
        reward=rng.normal(size=(steps, envs)).astype(np.float32),
        done=(rng.random((steps, envs)) < 0.2).astype(np.float32),
        last_observation=observation[-1],
        last_secret=rng.uniform(-1, 1, (envs, 1)).astype(np.float32),
    )


def test_generalized_advantages_match_the_recursion_by_hand() -> None:
    reward = torch.tensor([[1.0], [0.0], [2.0]])
    done = torch.tensor([[0.0], [1.0], [0.0]])
    value = torch.tensor([[0.5], [0.2], [0.1]])
    last = torch.tensor([0.3])
    gamma, lam = 0.9, 0.8
    # t=2 bootstraps from `last`; t=1 ends its episode (no bootstrap, no carry-over);
    # t=0 bootstraps from V(t=1) and carries t=1's advantage.
    a2 = 2.0 + gamma * 0.3 - 0.1
    a1 = 0.0 - 0.2
    a0 = (1.0 + gamma * 0.2 - 0.5) + gamma * lam * a1
    got = generalized_advantages(reward, done, value, last, gamma, lam)
    torch.testing.assert_close(got, torch.tensor([[a0], [a1], [a2]]))


def test_the_value_network_reads_the_secret_and_the_policy_cannot() -> None:
    ppo = learner()
    observation = torch.as_tensor(random_rollout().observation[0])
    v_a = ppo.value(observation, torch.zeros(4, 1))
    v_b = ppo.value(observation, torch.ones(4, 1))
    assert not torch.allclose(v_a, v_b)
    # The policy's GRU takes the history rows alone: its input width is the row width.
    assert ppo.policy.encoder.cell.input_size == SHAPE[1]
    assert ppo.policy.head[0].in_features == ppo.policy.encoder.output_dim
    blind = learner(config=PPOConfig(encoder_kwargs={"hidden": 16}, secret_critics=False))
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


def test_save_load_gives_identical_actions_and_identical_next_update() -> None:
    ppo = learner(seed=1)
    ppo.update(random_rollout(seed=1), np.random.default_rng(1))
    state = copy.deepcopy(ppo.state_dict())
    restored = learner(seed=99)
    restored.load_state_dict(state)
    observation = random_rollout(seed=2).observation[0]
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
    broken.reward[3, 1] = np.nan
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


def test_the_rollout_buffer_fills_in_order_and_refuses_overflow() -> None:
    buffer = RolloutBuffer(steps=2, envs=3, observation_shape=SHAPE, secret_dim=1, action_dim=2)
    zeros = np.zeros((3, *SHAPE), np.float32)
    for step in range(2):
        buffer.add(
            zeros + step, np.zeros((3, 1)), np.zeros((3, 2)), np.full(3, step), zeros + step + 1,
            np.ones((3, 1)), np.zeros(3),
        )  # fmt: skip
    rollout = buffer.rollout()
    assert rollout.reward.tolist() == [[0, 0, 0], [1, 1, 1]]
    assert rollout.last_observation.max() == 2.0  # the history after the last step
    with pytest.raises(ValueError, match="full"):
        buffer.add(zeros, np.zeros((3, 1)), np.zeros((3, 2)), np.zeros(3), zeros, np.ones((3, 1)),
                   np.zeros(3))  # fmt: skip
    buffer.clear()
    with pytest.raises(ValueError, match="0 of 2"):
        buffer.rollout()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_ppo_runs_on_cuda_where_available() -> None:
    torch.manual_seed(0)
    ppo = PPO(SHAPE, 2, 1, SMALL, device="cuda")
    metrics = ppo.update(random_rollout(), np.random.default_rng(0))
    assert all(np.isfinite(value) for value in metrics.values())
    assert next(ppo.policy.parameters()).is_cuda
    assert ppo.act(random_rollout().observation[0]).shape == (4, 2)

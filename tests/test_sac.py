"""SAC: asymmetric critics, exact save/load, the NaN guard, safe checkpoints, CUDA."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from alignrl.agents.replay import ReplayBuffer
from alignrl.agents.sac import SAC, NonFiniteError, SACConfig
from alignrl.checkpoints import CheckpointError, load_checkpoint, save_checkpoint
from alignrl.transitions import Transition

SHAPE = (8, 7)
SMALL = SACConfig(encoder_kwargs={"hidden": (32, 32)}, batch_size=16)


def random_batch(size: int = 16, seed: int = 0) -> Transition:
    rng = np.random.default_rng(seed)
    observation = rng.uniform(-1, 1, (size, *SHAPE)).astype(np.float32)
    observation[:, :, 0] = 1.0
    return Transition(
        observation=observation,
        secret=rng.uniform(-1, 1, (size, 1)).astype(np.float32),
        action=rng.uniform(-1, 1, (size, 2)).astype(np.float32),
        reward=rng.normal(size=size).astype(np.float32),
        next_observation=observation[::-1].copy(),
        next_secret=rng.uniform(-1, 1, (size, 1)).astype(np.float32),
        done=(rng.random(size) < 0.3).astype(np.float32),
    )


def agent(seed: int = 0, config: SACConfig = SMALL, device: str = "cpu") -> SAC:
    torch.manual_seed(seed)
    return SAC(SHAPE, 2, 1, config, device)


def test_critics_read_the_secret_and_the_policy_cannot() -> None:
    learner = agent()
    batch = random_batch()
    observation = torch.as_tensor(batch.observation)
    action = torch.as_tensor(batch.action)
    q_a = learner.q1(observation, torch.zeros(16, 1), action)
    q_b = learner.q1(observation, torch.ones(16, 1), action)
    assert not torch.allclose(q_a, q_b)  # the secret is an input of every critic
    # The actor has no input for it: its first layer sees exactly the history.
    first_layer = next(learner.actor.encoder.parameters())
    assert first_layer.shape[1] == SHAPE[0] * SHAPE[1]
    blind = agent(config=SACConfig(encoder_kwargs={"hidden": (32, 32)}, secret_critics=False))
    assert blind.q1.head[0].in_features == learner.q1.head[0].in_features - 1


def test_an_update_changes_every_network_and_reports_the_seed_losses() -> None:
    learner = agent()
    before = copy.deepcopy(learner.state_dict())
    metrics = learner.update(random_batch())
    assert set(metrics) == {"policy_loss", "q1_loss", "q2_loss", "v_loss", "entropy", "alpha"}
    assert all(np.isfinite(value) for value in metrics.values())
    after = learner.state_dict()
    for name in ("actor", "q1", "q2", "v", "v_target"):
        changed = any(not torch.equal(before[name][key], after[name][key]) for key in before[name])
        assert changed, name


def test_a_critic_warm_up_update_leaves_the_policy_and_alpha_as_they_were() -> None:
    learner = agent()
    before = copy.deepcopy(learner.state_dict())
    for seed in range(3):
        learner.update(random_batch(seed=seed), train_policy=False)
    after = learner.state_dict()
    for key in before["actor"]:
        assert torch.equal(before["actor"][key], after["actor"][key]), key
    assert torch.equal(before["log_alpha"], after["log_alpha"])
    for name in ("q1", "q2", "v", "v_target"):
        assert any(not torch.equal(before[name][k], after[name][k]) for k in before[name]), name
    learner.update(random_batch(seed=9))  # and the next full update moves the policy again
    assert any(
        not torch.equal(before["actor"][k], learner.state_dict()["actor"][k])
        for k in before["actor"]
    )


def test_each_network_learns_from_its_own_loss_alone() -> None:
    """update() takes one backward pass of all losses together: the gradients must be those
    of the seed's separate passes (critics: their regression losses; policy: the policy loss
    through min Q; alpha: its own loss)."""
    # lr 0 keeps the networks as they were; the gradients stay in .grad after the update.
    config = SACConfig(encoder_kwargs={"hidden": (32,)}, learning_rate=0.0, max_grad_norm=1e9)
    learner = agent(config=config)
    batch = random_batch()
    torch.manual_seed(3)
    learner.update(batch)

    given = {
        name: torch.as_tensor(array) for name, array in vars(batch).items() if array is not None
    }
    observation, secret, action = given["observation"], given["secret"], given["action"]
    torch.manual_seed(3)  # the same policy noise as inside update()
    new_action, log_prob, _ = learner.actor.sample(observation)
    alpha = learner.log_alpha.detach().exp()
    with torch.no_grad():
        v_next = learner.v_target(given["next_observation"], given["next_secret"])
        q_target = given["reward"] + config.gamma * (1 - given["done"]) * v_next
    min_q_new = torch.min(
        learner.q1(observation, secret, new_action), learner.q2(observation, secret, new_action)
    )
    v_target = (min_q_new - alpha * log_prob).detach()
    critic_loss = sum(
        0.5 * (prediction - target).pow(2).mean()
        for prediction, target in (
            (learner.q1(observation, secret, action), q_target),
            (learner.q2(observation, secret, action), q_target),
            (learner.v(observation, secret), v_target),
        )
    )
    policy_loss = (alpha * log_prob - min_q_new).mean()
    critics = [*learner.q1.parameters(), *learner.q2.parameters(), *learner.v.parameters()]
    actor = list(learner.actor.parameters())
    expected = [
        *torch.autograd.grad(critic_loss, critics),
        *torch.autograd.grad(policy_loss, actor),
        -(log_prob.detach() + learner.target_entropy).mean(),
    ]
    for parameter, gradient in zip([*critics, *actor, learner.log_alpha], expected, strict=True):
        torch.testing.assert_close(parameter.grad, gradient, rtol=1e-4, atol=1e-6)


def test_save_load_gives_identical_actions_and_identical_next_update(tmp_path: Path) -> None:
    learner = agent(seed=1)
    for seed in range(3):
        learner.update(random_batch(seed=seed))
    path = tmp_path / "sac.pt"
    save_checkpoint(path, {"format": "test", "agent": learner.state_dict()})
    restored = agent(seed=99)
    restored.load_state_dict(load_checkpoint(path)["agent"])
    histories = random_batch(seed=5).observation
    np.testing.assert_array_equal(
        learner.act(histories, deterministic=True), restored.act(histories, deterministic=True)
    )
    torch.manual_seed(7)
    first = learner.update(random_batch(seed=9))
    torch.manual_seed(7)
    second = restored.update(random_batch(seed=9))
    assert first == second
    for name in ("actor", "q1", "v"):
        for key, value in learner.state_dict()[name].items():
            assert torch.equal(value, restored.state_dict()[name][key])


def test_a_nan_loss_stops_the_update_and_changes_nothing() -> None:
    learner = agent()
    learner.update(random_batch())
    before = copy.deepcopy(learner.state_dict())
    poisoned = random_batch(seed=3)
    poisoned.reward[4] = np.nan
    with pytest.raises(NonFiniteError, match=r"member aligner-7: the q1 loss is nan"):
        learner.update(poisoned, member="aligner-7")
    after = learner.state_dict()
    for name in ("actor", "q1", "q2", "v", "v_target"):
        for key, value in before[name].items():
            assert torch.equal(value, after[name][key])
    assert learner.updates == before["updates"]


def test_checkpoints_refuse_garbage_with_a_clear_error(tmp_path: Path) -> None:
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_checkpoint(broken)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    truncated = tmp_path / "truncated.pt"
    save_checkpoint(truncated, {"format": "x", "weights": torch.ones(1000)})
    truncated.write_bytes(truncated.read_bytes()[:500])
    with pytest.raises(CheckpointError):
        load_checkpoint(truncated)


def test_replay_round_trips_and_samples_reproducibly() -> None:
    replay = ReplayBuffer(10, SHAPE, 1, 2)
    for seed in range(3):
        batch = random_batch(size=4, seed=seed)
        replay.add(batch)
    assert replay.size == 10 and replay.position == 2  # 12 added into a ring of 10
    copy_of = ReplayBuffer(10, SHAPE, 1, 2)
    copy_of.load_state_dict(replay.state_dict())
    first = replay.sample(5, np.random.default_rng(3))
    second = copy_of.sample(5, np.random.default_rng(3))
    np.testing.assert_array_equal(first.observation, second.observation)
    np.testing.assert_array_equal(first.reward, second.reward)


@pytest.mark.parametrize("encoder", ["gru", "gtrxl"])
def test_sequence_encoders_train_too(encoder: str) -> None:
    learner = agent(config=SACConfig(encoder=encoder, hidden=(32,), batch_size=16))
    metrics = learner.update(random_batch())
    assert all(np.isfinite(value) for value in metrics.values())
    assert learner.act(random_batch().observation[0]).shape == (2,)


def test_sac_runs_on_cuda_where_available() -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device on this machine")
    learner = agent(device="cuda")
    metrics = learner.update(random_batch())
    assert all(np.isfinite(value) for value in metrics.values())
    assert next(learner.actor.parameters()).is_cuda
    action = learner.act(random_batch().observation, deterministic=True)
    assert action.shape == (16, 2) and np.all(np.abs(action) <= 1)
    # A critic warm-up update (an adaptation's first steps) leaves the policy as it was.
    policy = copy.deepcopy(learner.actor.state_dict())
    critic = copy.deepcopy(learner.q1.state_dict())
    learner.update(random_batch(), train_policy=False)
    assert all(torch.equal(policy[k], v) for k, v in learner.actor.state_dict().items())
    assert not all(torch.equal(critic[k], v) for k, v in learner.q1.state_dict().items())


def test_a_shared_critic_encoder_is_one_module_trained_by_all_critics(tmp_path: Path) -> None:
    shared = agent(config=dataclasses.replace(SMALL, shared_critic_encoder=True))
    assert shared.q1.encoder is shared.q2.encoder is shared.v.encoder
    assert shared.v_target.encoder is not shared.v.encoder  # the target keeps its own copy
    assert shared.actor.encoder is not shared.q1.encoder  # the policy never shares
    separate = agent()
    count = lambda sac: sum(p.numel() for p in sac._critic_parameters)  # noqa: E731
    assert count(shared) == count(separate) - 2 * sum(
        p.numel() for p in separate.q1.encoder.parameters()
    )
    before = copy.deepcopy(shared.q1.encoder.state_dict())
    metrics = shared.update(random_batch())
    assert all(np.isfinite(value) for value in metrics.values())
    changed = [not torch.equal(before[k], v) for k, v in shared.q1.encoder.state_dict().items()]
    assert all(changed)
    # Saved and loaded, the encoder is still one module, with the trained weights.
    path = tmp_path / "shared.pt"
    save_checkpoint(path, {"format": "test", "agent": shared.state_dict()})
    restored = agent(seed=5, config=dataclasses.replace(SMALL, shared_critic_encoder=True))
    restored.load_state_dict(load_checkpoint(path)["agent"])
    assert restored.q1.encoder is restored.v.encoder
    batch = random_batch(seed=4)
    torch.manual_seed(3)
    first = shared.update(batch)
    torch.manual_seed(3)
    assert restored.update(batch) == first

"""Proximal Policy Optimization (Schulman et al. 2017) with the same history encoders as SAC.

* Policy: a Gaussian over pre-squash actions u with a learned, state-independent log-std;
  the env receives tanh(u), in (-1, 1). Ratios are taken on u, where the tanh correction of
  the two log-probabilities cancels, so the stored u (never atanh of a clipped action) is the
  sample of record.
* Value: V(history, secret) with its own encoder; the secret (optimum - setting) is an extra
  input at training time, as in SAC's critics. The policy never reads it.
* Update: generalized advantage estimation over a rollout of whole env steps, the clipped
  surrogate objective, an entropy bonus, minibatch epochs, gradient clipping.

An update that meets a NaN/inf loss or gradient raises NonFiniteError and leaves the networks
and the optimizer exactly as they were before the update began. `PPO` is the algorithm (the
epochs on one rollout); `PPOLearner` is PPO as a member trains with it
(alignrl/agents/learners.py): it collects a rollout and updates when the rollout is full.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from alignrl.agents.exploration import gaussian_rows
from alignrl.agents.networks import make_encoder, mlp
from alignrl.agents.sac import NonFiniteError
from alignrl.agents.settings import SHIPPED, PPOConfig
from alignrl.transitions import Transition

__all__ = ["PPO", "PPOConfig", "PPOLearner", "Rollout", "RolloutBuffer"]

# What a rollout keeps of a Transition, each in an array of its own name: the pre-squash
# sample in place of the action; which env slot a row came from links it (`follows`).
STORED = ("observation", "secret", "pre_tanh", "reward", "next_observation", "next_secret", "done")
# The arrays of a rollout's state (`state_dict`), in their order there.
SAVED = (
    "observation",
    "next_observation",
    "secret",
    "next_secret",
    "pre_tanh",
    "reward",
    "done",
    "follows",
)


@dataclass(frozen=True)
class Rollout:
    """Transitions in the order they happened, each linked to the next one of its episode.

    `follows[i]` is the index of the transition that came after transition i in the same env
    slot (-1: the episode ended there, or its continuation is not in this rollout, in which
    case V(next_observation) bootstraps it)."""

    observation: np.ndarray  # (M, H, F)
    secret: np.ndarray  # (M, k)
    pre_tanh: np.ndarray  # (M, A) the Gaussian sample u; the env got tanh(u)
    reward: np.ndarray  # (M,)
    done: np.ndarray  # (M,) 1.0 where the episode ended with this transition
    next_observation: np.ndarray  # (M, H, F)
    next_secret: np.ndarray  # (M, k)
    follows: np.ndarray  # (M,) int64


class RolloutBuffer:
    """Collects `steps x envs` transitions for an on-policy update. A step may bring every
    env slot or only some (`slots`): in a league, finished matches wait for the others."""

    def __init__(
        self,
        steps: int,
        envs: int,
        observation_shape: tuple[int, ...],
        secret_dim: int,
        action_dim: int,
    ) -> None:
        if steps < 1 or envs < 1:
            raise ValueError(f"a rollout needs steps >= 1 and envs >= 1, got {steps}, {envs}")
        self.steps, self.envs = steps, envs
        self.capacity = steps * envs  # full from here on
        capacity = self.capacity + envs  # a partial step may end just past `capacity`
        self.observation = np.zeros((capacity, *observation_shape), np.float32)
        self.next_observation = np.zeros((capacity, *observation_shape), np.float32)
        self.secret = np.zeros((capacity, secret_dim), np.float32)
        self.next_secret = np.zeros((capacity, secret_dim), np.float32)
        self.pre_tanh = np.zeros((capacity, action_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.done = np.zeros(capacity, np.float32)
        self.follows = np.full(capacity, -1, np.int64)
        self._last = np.full(envs, -1, np.int64)  # latest transition of each slot
        self.size = 0

    @property
    def full(self) -> bool:
        return self.size >= self.capacity

    def add(self, transition: Transition) -> None:
        """One step of the env slots `transition.slots` (None: all, in order), with its
        pre-squash sample `transition.pre_tanh`."""
        count = len(transition)
        slots = transition.slots
        slots = np.arange(count) if slots is None else np.asarray(slots, np.int64)
        if len(slots) != count or (count and (slots.min() < 0 or slots.max() >= self.envs)):
            raise ValueError(f"a rollout step needs slot numbers below {self.envs} per row")
        if self.full:
            raise ValueError("the rollout is full: update on it, then clear it")
        index = np.arange(self.size, self.size + count)
        for name in STORED:
            getattr(self, name)[index] = getattr(transition, name)
        self.follows[index] = -1
        previous = self._last[slots]
        linked = previous >= 0
        self.follows[previous[linked]] = index[linked]
        self._last[slots] = np.where(np.asarray(transition.done, bool), -1, index)
        self.size += count

    def rollout(self) -> Rollout:
        if self.size == 0:
            raise ValueError(f"the rollout holds 0 of {self.capacity} transitions")
        used = slice(0, self.size)
        return Rollout(
            self.observation[used].copy(),
            self.secret[used].copy(),
            self.pre_tanh[used].copy(),
            self.reward[used].copy(),
            self.done[used].copy(),
            self.next_observation[used].copy(),
            self.next_secret[used].copy(),
            self.follows[used].copy(),
        )

    def state_dict(self) -> dict[str, np.ndarray | int]:
        """The transitions so far and each slot's latest (numpy and ints: safe to store)."""
        used = slice(0, self.size)
        return {
            **{name: getattr(self, name)[used].copy() for name in SAVED},
            "last": self._last.copy(),
            "size": self.size,
        }

    def load_state_dict(self, state: dict[str, np.ndarray | int]) -> None:
        size = int(state["size"])
        if size > len(self.reward) or len(state["last"]) != self.envs:
            raise ValueError(
                f"saved rollout of {size} transitions over {len(state['last'])} slots does not "
                f"fit a rollout of {self.capacity} over {self.envs}"
            )
        for name in SAVED:
            getattr(self, name)[:size] = state[name]
        self._last[:] = state["last"]
        self.size = size

    def clear(self) -> None:
        """Empty the buffer; episodes in flight continue into the next rollout unlinked
        (their last transition here bootstraps from V)."""
        self.size = 0
        self._last[:] = -1


def generalized_advantages(
    reward: np.ndarray,
    done: np.ndarray,
    value: np.ndarray,
    next_value: np.ndarray,
    follows: np.ndarray,
    gamma: float,
    lam: float,
) -> np.ndarray:
    """GAE over linked transitions (Rollout.follows): delta_i = r_i + gamma (1 - done_i)
    V(next_i) - V(obs_i), and A_i = delta_i + gamma lam A_(follows_i) where the episode goes
    on inside the rollout. A later transition always has a higher index."""
    keep = 1.0 - done
    delta = reward + gamma * keep * next_value - value
    advantage = np.zeros_like(delta)
    for i in range(len(delta) - 1, -1, -1):
        after = follows[i]
        advantage[i] = delta[i] + (gamma * lam * keep[i] * advantage[after] if after >= 0 else 0.0)
    return advantage


class PolicyNet(nn.Module):
    def __init__(self, history: int, features: int, action_dim: int, config: PPOConfig) -> None:
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = mlp(self.encoder.output_dim, config.hidden, action_dim)
        self.log_std = nn.Parameter(torch.full((action_dim,), float(config.initial_log_std)))

    def forward(self, observation: Tensor) -> torch.distributions.Normal:
        encoded, _ = self.encoder(observation)
        std = self.log_std.clamp(-5.0, 1.0).exp().expand(encoded.shape[0], -1)
        return torch.distributions.Normal(self.head(encoded), std)


class ValueNet(nn.Module):
    def __init__(self, history: int, features: int, secret_in: int, config: PPOConfig) -> None:
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = mlp(self.encoder.output_dim + secret_in, config.hidden, 1)

    def forward(self, observation: Tensor, *extra: Tensor) -> Tensor:
        encoded, _ = self.encoder(observation)
        return self.head(torch.cat([encoded, *extra], dim=-1)).squeeze(-1)


class PPO:
    """One PPO learner: policy and value networks and their optimizer."""

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: PPOConfig | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config = config or PPOConfig()
        cfg = self.config
        self.device = torch.device(device)
        history, features = observation_shape
        self.action_dim, self.secret_dim = action_dim, secret_dim
        self.policy = PolicyNet(history, features, action_dim, cfg).to(self.device)
        secret_in = secret_dim if cfg.secret_critics else 0
        self.value = ValueNet(history, features, secret_in, cfg).to(self.device)
        self.updates = 0  # rollouts learned from

    @functools.cached_property
    def optimizer(self) -> torch.optim.Adam:
        """Made when first asked for (an update, a state): a policy that only acts never
        makes one (as SAC's, alignrl/agents/sac.py)."""
        parameters = [*self.policy.parameters(), *self.value.parameters()]
        return torch.optim.Adam(parameters, lr=self.config.learning_rate)

    # --- acting -------------------------------------------------------------------------

    def _tensor(self, array: np.ndarray) -> Tensor:
        return torch.as_tensor(array, dtype=torch.float32, device=self.device)

    @torch.no_grad()
    def act(self, observation: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Actions in (-1, 1) for a batch of histories (B, H, F) or one history (H, F)."""
        return np.tanh(self.sample(observation, deterministic))

    @torch.no_grad()
    def sample(self, observation: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Pre-squash actions u (the env takes tanh(u)); the mean when deterministic."""
        single = observation.ndim == 2
        batch = self._tensor(observation)
        if single:
            batch = batch[None]
        distribution = self.policy(batch)
        u = distribution.mean if deterministic else distribution.sample()
        result = u.cpu().numpy()
        return result[0] if single else result

    # --- learning -----------------------------------------------------------------------

    def _extra(self, secret: Tensor) -> list[Tensor]:
        return [secret] if self.config.secret_critics else []

    def update(
        self,
        rollout: Rollout,
        rng: np.random.Generator,
        member: str = "ppo",
        train_policy: bool = True,
    ) -> dict[str, float]:
        """Epochs of clipped-surrogate minibatch steps on one rollout; returns their means.
        `train_policy=False` steps the value network only (a critic warm-up)."""
        snapshot = (
            copy.deepcopy(self.policy.state_dict()),
            copy.deepcopy(self.value.state_dict()),
            copy.deepcopy(self.optimizer.state_dict()),
        )
        try:
            return self._update(rollout, rng, member, train_policy)
        except NonFiniteError:
            self.policy.load_state_dict(snapshot[0])
            self.value.load_state_dict(snapshot[1])
            self.optimizer.load_state_dict(snapshot[2])
            raise

    def _update(
        self, rollout: Rollout, rng: np.random.Generator, member: str, train_policy: bool
    ) -> dict[str, float]:
        cfg = self.config
        observation = self._tensor(rollout.observation)  # (M, H, F)
        secret = self._tensor(rollout.secret)  # (M, k)
        pre_tanh = self._tensor(rollout.pre_tanh)  # (M, A)
        with torch.no_grad():
            old_log_prob = self.policy(observation).log_prob(pre_tanh).sum(-1)
            value = self.value(observation, *self._extra(secret))
            next_value = self.value(
                self._tensor(rollout.next_observation),
                *self._extra(self._tensor(rollout.next_secret)),
            )
        advantage_np = generalized_advantages(
            rollout.reward.astype(np.float64),
            rollout.done.astype(np.float64),
            value.double().cpu().numpy(),
            next_value.double().cpu().numpy(),
            rollout.follows,
            cfg.gamma,
            cfg.gae_lambda,
        )
        advantage = self._tensor(advantage_np)
        returns = advantage + value
        self._check_finite(member, {"value": value, "advantage": advantage})

        count = len(rollout.reward)
        batch = min(cfg.batch_size, count)
        sums = dict.fromkeys(
            ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction"), 0.0
        )
        minibatches = 0
        parameters = [*self.policy.parameters(), *self.value.parameters()]
        for _ in range(cfg.epochs):
            order = torch.as_tensor(rng.permutation(count), device=self.device)
            for start in range(0, count - batch + 1, batch):
                index = order[start : start + batch]
                distribution = self.policy(observation[index])
                log_prob = distribution.log_prob(pre_tanh[index]).sum(-1)
                log_ratio = log_prob - old_log_prob[index]
                ratio = log_ratio.exp()
                adv = advantage[index]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                surrogate = torch.min(
                    ratio * adv, ratio.clamp(1 - cfg.clip_range, 1 + cfg.clip_range) * adv
                )
                policy_loss = -surrogate.mean()
                value_loss = (
                    0.5
                    * (self.value(observation[index], *self._extra(secret[index])) - returns[index])
                    .pow(2)
                    .mean()
                )
                entropy = distribution.entropy().sum(-1).mean()
                self._check_finite(
                    member, {"policy": policy_loss, "value": value_loss, "entropy": entropy}
                )
                loss = cfg.value_coef * value_loss
                if train_policy:  # otherwise the policy gets no gradient: Adam leaves it be
                    loss = loss + policy_loss - cfg.entropy_coef * entropy
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                norm = nn.utils.clip_grad_norm_(parameters, cfg.max_grad_norm)
                self._check_finite(member, {"gradient": norm})
                self.optimizer.step()
                with torch.no_grad():
                    sums["policy_loss"] += policy_loss.item()
                    sums["value_loss"] += value_loss.item()
                    sums["entropy"] += entropy.item()
                    # The (r - 1) - log r estimator of KL(old || new): unbiased, never negative.
                    sums["approx_kl"] += ((ratio - 1) - log_ratio).mean().item()
                    sums["clip_fraction"] += (
                        ((ratio - 1).abs() > cfg.clip_range).float().mean().item()
                    )
                minibatches += 1
        self.updates += 1
        return {name: total / max(minibatches, 1) for name, total in sums.items()}

    def _check_finite(self, member: str, values: dict[str, Tensor]) -> None:
        for name, value in values.items():
            if not torch.isfinite(value).all():
                raise NonFiniteError(
                    f"member {member}: the {name} {'is' if value.numel() == 1 else 'holds'} "
                    f"non-finite values at update {self.updates}; the update was refused and "
                    "the networks are unchanged"
                )

    # --- state --------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain numbers only: loadable with torch.load(weights_only=True)."""
        return {
            "policy": self.policy.state_dict(),
            "value": self.value.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "config": asdict(self.config),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.value.load_state_dict(state["value"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])


class PPOLearner(PPO):
    """PPO as a member trains with it: each explored action's pre-squash sample kept for
    `observe`, a rollout of `rollout_steps` steps of every env slot, and an update (then a
    fresh rollout) whenever the rollout is full."""

    name = "ppo"
    title, config_type, schedule_defaults = SHIPPED["ppo"][1]  # "PPO", PPOConfig, no schedule
    metric_names = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction")
    experience_name = "rollout"
    keeps_replay = False  # on-policy: a rollout holds this policy's steps, in order
    logs_every_update = True  # one update per rollout

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: PPOConfig,
        schedule: Mapping[str, float],
        envs: int,
        device: str | torch.device,
    ) -> None:
        super().__init__(observation_shape, action_dim, secret_dim, config, device)
        steps = config.rollout_steps
        self.experience = RolloutBuffer(steps, envs, observation_shape, secret_dim, action_dim)
        self.update_debt = 0.0  # PPO is paced by its rollout, not by a debt of updates
        self._pending_pre_tanh: np.ndarray | None = None  # of the last explore(), for observe()

    @property
    def optimizers(self) -> list[torch.optim.Optimizer]:
        return [self.optimizer]

    @property
    def acting_network(self) -> nn.Module:
        return self.policy

    def explore(
        self, observation: np.ndarray, rng: np.random.Generator, steps_seen: int
    ) -> np.ndarray:
        pre_tanh = self.sample(observation)
        self._pending_pre_tanh = pre_tanh
        return np.tanh(pre_tanh)

    @torch.no_grad()
    def explore_rows(
        self,
        observation: np.ndarray,
        generators: Sequence[np.random.Generator],
        steps_seen: int,
        warm_up: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        distribution = self.policy(self._tensor(observation))
        mean, std = distribution.mean.cpu().numpy(), distribution.stddev.cpu().numpy()
        return gaussian_rows(generators, mean, std)

    def observe(self, transition: Transition, member: str) -> None:
        # The ratio is taken on the sample u, never on atanh of the action the env got.
        if transition.pre_tanh is None:
            if self._pending_pre_tanh is None:
                raise RuntimeError(
                    f"member {member}: observe() needs the explore() before it, or pre_tanh"
                )
            transition = replace(transition, pre_tanh=self._pending_pre_tanh)
        self.experience.add(transition)
        self._pending_pre_tanh = None

    def learn(
        self,
        rng: np.random.Generator,
        steps_seen: int,
        new_steps: int,
        member: str,
        train_policy: bool,
    ) -> list[dict[str, float]]:
        if not self.experience.full:
            return []
        metrics = self.update(self.experience.rollout(), rng, member, train_policy)
        self.experience.clear()
        return [metrics]

    def learn_from(
        self, batch: Any, rng: np.random.Generator | None, member: str, train_policy: bool
    ) -> dict[str, float]:
        rng = rng or np.random.default_rng(self.updates)
        return self.update(batch, rng, member, train_policy)

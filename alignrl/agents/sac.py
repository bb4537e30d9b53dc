"""Soft Actor-Critic as the seed trains its aligners (sections 4.3 and 6.1; Haarnoja et al. 2018).

* Policy: a tanh-squashed Gaussian over actions in (-1, 1), reading only the history.
* Critics: twin Q networks and a V network with a slowly following target copy; the critics
  also read the secret (optimum - setting) at training time: an asymmetric actor-critic.
  Only the policy runs on an instrument.
* The policy loss uses the minimum of the two Qs (seed section 6.1, against the optimistic
  critic it describes); the entropy coefficient alpha is tuned toward a target entropy.

Each network has its own history encoder (alignrl/agents/networks.py); parameters are never
shared between members of a league. `SAC` is the algorithm (one gradient step on a batch);
`SACLearner` is SAC as a member trains with it (alignrl/agents/learners.py): a replay, a
random warm-up, and a number of updates per env step.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from alignrl.agents.exploration import gaussian_rows, uniform_rows
from alignrl.agents.networks import make_encoder, mlp
from alignrl.agents.replay import ReplayBuffer
from alignrl.agents.settings import SAC_SCHEDULE, SHIPPED, SACConfig
from alignrl.transitions import Transition

__all__ = ["SAC", "SAC_SCHEDULE", "NonFiniteError", "SACConfig", "SACLearner"]

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0  # keeps exp(log_std) in a range float32 handles well
HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)  # normalising constant of log N(x; mean, std)
LOSS_NAMES = ("policy", "q1", "q2", "v", "alpha")  # checked in this order: the first is named


class NonFiniteError(FloatingPointError):
    """A loss or parameter became NaN/inf: the update is refused, nothing is changed."""


class Actor(nn.Module):
    def __init__(self, history: int, features: int, action_dim: int, config: SACConfig):
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = mlp(self.encoder.output_dim, config.hidden, 2 * action_dim)

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        encoded, _ = self.encoder(observation)  # (B, D)
        mean, log_std = self.head(encoded).chunk(2, dim=-1)  # (B, A) each
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def sample(self, observation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """A reparameterised action, its log-probability and the deterministic action."""
        mean, log_std = self(observation)
        noise = torch.randn_like(mean)
        pre_tanh = mean + log_std.exp() * noise
        action = torch.tanh(pre_tanh)
        # log N(pre_tanh; mean, std) written with the noise: (pre_tanh - mean) / std = noise.
        # Then the change of variables for tanh, in the stable form
        # log(1 - tanh(x)^2) = 2 (log 2 - x - softplus(-2x)).
        log_prob = (-0.5 * noise.square() - log_std - HALF_LOG_2PI) - 2.0 * (
            math.log(2.0) - pre_tanh - F.softplus(-2.0 * pre_tanh)
        )
        return action, log_prob.sum(-1), torch.tanh(mean)


class Critic(nn.Module):
    """Q(history, secret, action) or, without an action, V(history, secret)."""

    def __init__(self, history: int, features: int, extra_inputs: int, config: SACConfig) -> None:
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = mlp(self.encoder.output_dim + extra_inputs, config.hidden, 1)

    def forward(self, observation: Tensor, *extra: Tensor) -> Tensor:
        return self.from_encoding(self.encoder(observation)[0], *extra)

    def from_encoding(self, encoded: Tensor, *extra: Tensor) -> Tensor:
        return self.head(torch.cat([encoded, *extra], dim=-1)).squeeze(-1)  # (B,)

    def stored_and_new(
        self,
        observation: Tensor,
        extra: list[Tensor],
        action: Tensor,
        new_action: Tensor,
        encoded: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Q of the stored action, which trains this critic, and Q of the policy's new action,
        which must train the policy alone: for it the critic is read without gradient to its
        weights, and the gradient reaches new_action only.

        The first head layer is linear in its input, layer([e, s, a']) = layer([e, s, a]) +
        W_a (a' - a), so the new action reuses the stored action's first layer (and the
        policy's backward pass crosses W_a only)."""
        first, rest = self.head[0], self.head[1:]
        if encoded is None:  # else: the shared critic encoding, computed once per update
            encoded, _ = self.encoder(observation)
        stored_input = first(torch.cat([encoded, *extra, action], dim=-1))  #       (B, hidden)
        q_stored = rest(stored_input).squeeze(-1)  #                                         (B,)
        action_weight = first.weight[:, -action.shape[-1] :].detach()  #               (hidden, A)
        with _frozen(list(rest.parameters())):
            new_input = torch.addmm(stored_input.detach(), new_action - action, action_weight.t())
            q_new = rest(new_input).squeeze(-1)  #                                           (B,)
        return q_stored, q_new


def _gradients(parameters: list[nn.Parameter]) -> list[Tensor]:
    return [parameter.grad for parameter in parameters if parameter.grad is not None]


@contextmanager
def _frozen(parameters: list[nn.Parameter]) -> Iterator[None]:
    """Parameters that what is computed inside must not train (they still pass gradients on
    to their inputs)."""
    for parameter in parameters:
        parameter.requires_grad_(False)
    try:
        yield
    finally:
        for parameter in parameters:
            parameter.requires_grad_(True)


class SAC:
    """One SAC learner: its networks, optimizers and entropy coefficient."""

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: SACConfig | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config = config or SACConfig()
        cfg = self.config
        self.device = torch.device(device)
        history, features = observation_shape
        secret_in = secret_dim if cfg.secret_critics else 0
        self.secret_dim = secret_dim
        self.action_dim = action_dim
        self.actor = Actor(history, features, action_dim, cfg).to(self.device)
        self.q1 = Critic(history, features, secret_in + action_dim, cfg).to(self.device)
        self.q2 = Critic(history, features, secret_in + action_dim, cfg).to(self.device)
        self.v = Critic(history, features, secret_in, cfg).to(self.device)
        if cfg.shared_critic_encoder:
            self.q2.encoder = self.v.encoder = self.q1.encoder
        # The target is a copy of V, encoder included: with a shared encoder it follows that.
        self.v_target = Critic(history, features, secret_in, cfg).to(self.device)
        self.v_target.load_state_dict(self.v.state_dict())
        self.v_target.requires_grad_(False)
        self.log_alpha = torch.tensor(
            math.log(cfg.initial_alpha), device=self.device, requires_grad=True
        )
        self.target_entropy = (
            cfg.target_entropy if cfg.target_entropy is not None else -float(action_dim)
        )
        self._actor_parameters = list(self.actor.parameters())
        # Each parameter once, also where the critics share their encoder.
        self._critic_parameters = list(
            {
                id(parameter): parameter
                for network in (self.q1, self.q2, self.v)
                for parameter in network.parameters()
            }.values()
        )
        self._v_parameters = list(self.v.parameters())
        self._v_target_parameters = list(self.v_target.parameters())
        self.updates = 0

    # The optimizers are made when first asked for (an update, a state): a policy that only
    # acts (`alignrl align`, `evaluate`) never makes one, and never waits the 1.5 s torch takes
    # to import what its first optimizer needs. Fused Adam: one kernel per step instead of a
    # dozen small ops per parameter tensor, the largest share of an update's time on a CPU
    # (benchmarks/sb3_sac.py).

    def _adam(self, parameters: list[Tensor]) -> torch.optim.Adam:
        return torch.optim.Adam(parameters, lr=self.config.learning_rate, fused=True)

    @functools.cached_property
    def actor_optimizer(self) -> torch.optim.Adam:
        return self._adam(self._actor_parameters)

    @functools.cached_property
    def critic_optimizer(self) -> torch.optim.Adam:
        return self._adam(self._critic_parameters)

    @functools.cached_property
    def alpha_optimizer(self) -> torch.optim.Adam:
        return self._adam([self.log_alpha])

    # --- acting -------------------------------------------------------------------------

    @torch.no_grad()
    def act(self, observation: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Actions for a batch of histories (B, H, F) or one history (H, F)."""
        single = observation.ndim == 2
        batch = torch.as_tensor(observation, dtype=torch.float32, device=self.device)
        if single:
            batch = batch[None]
        action, _, mean_action = self.actor.sample(batch)
        chosen = mean_action if deterministic else action
        result = chosen.cpu().numpy()
        return result[0] if single else result

    # --- learning -----------------------------------------------------------------------

    def _critic_inputs(self, secret: Tensor) -> list[Tensor]:
        return [secret] if self.config.secret_critics else []

    def update(
        self, batch: Transition, member: str = "sac", train_policy: bool = True
    ) -> dict[str, float]:
        """One gradient step of every network; returns the losses of seed figs. 6.1.2-6.1.7.
        `train_policy=False` steps the critics only: the policy and alpha stay as they are
        (a critic warm-up, e.g. on an instrument that cannot tell the critics its secret)."""
        cfg = self.config
        tensor = lambda array: torch.as_tensor(array, dtype=torch.float32, device=self.device)  # noqa: E731
        observation, secret = tensor(batch.observation), tensor(batch.secret)
        action, reward = tensor(batch.action), tensor(batch.reward)
        next_observation, next_secret = tensor(batch.next_observation), tensor(batch.next_secret)
        done = tensor(batch.done)
        alpha = self.log_alpha.detach().exp()
        extra, next_extra = self._critic_inputs(secret), self._critic_inputs(next_secret)

        # Q targets bootstrap from the slow V target at the next history.
        with torch.no_grad():
            v_next = self.v_target(next_observation, *next_extra)
            q_target = reward + cfg.gamma * (1.0 - done) * v_next
        # A fresh action from the *current* policy serves both V's target and the policy loss.
        new_action, log_prob, _ = self.actor.sample(observation)
        # Each Q reads the stored action (for its own loss) and the new action (for the policy
        # loss, which must not train the critics: see Critic.stored_and_new).
        encoded = self.q1.encoder(observation)[0] if cfg.shared_critic_encoder else None
        q1_pred, q1_new = self.q1.stored_and_new(observation, extra, action, new_action, encoded)
        q2_pred, q2_new = self.q2.stored_and_new(observation, extra, action, new_action, encoded)
        q1_loss = 0.5 * (q1_pred - q_target).pow(2).mean()
        q2_loss = 0.5 * (q2_pred - q_target).pow(2).mean()
        # The policy follows the minimum of the two Qs (against optimistic critics).
        min_q_new = torch.min(q1_new, q2_new)
        # V regresses on the soft value of the current policy: min Q minus alpha log pi.
        v_target = (min_q_new - alpha * log_prob).detach()
        v_pred = (
            self.v.from_encoding(encoded, *extra)
            if encoded is not None
            else self.v(observation, *extra)
        )
        v_loss = 0.5 * (v_pred - v_target).pow(2).mean()
        policy_loss = (alpha * log_prob - min_q_new).mean()
        alpha_loss = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()

        # Each loss reaches only its own networks (targets detached, the critics read without
        # weight gradients for the policy, alpha detached outside its loss), so one backward
        # of the sum gives every network exactly the gradient of its own loss.
        for optimizer in (self.critic_optimizer, self.actor_optimizer, self.alpha_optimizer):
            optimizer.zero_grad(set_to_none=True)
        losses = (policy_loss, q1_loss, q2_loss, v_loss, alpha_loss)
        sum(losses).backward()
        critic_norm = nn.utils.get_total_norm(_gradients(self._critic_parameters))
        actor_norm = nn.utils.get_total_norm(_gradients(self._actor_parameters))
        # One read of every figure: the guard below and the report share it.
        with torch.no_grad():
            figures = torch.stack(
                [*losses, critic_norm, actor_norm, -log_prob.mean(), alpha]
            ).tolist()
        *checked, entropy, alpha_value = figures
        self._refuse_non_finite(member, checked)
        # clip_grad_norm_ in two halves: it scales by min(max / (norm + 1e-6), 1), so below
        # the limit (the usual case) the scaling is skipped, not done with a factor of 1.
        for parameters, norm, norm_value in (
            (self._critic_parameters, critic_norm, checked[-2]),
            (self._actor_parameters, actor_norm, checked[-1]),
        ):
            if cfg.max_grad_norm / (norm_value + 1e-6) < 1.0:
                nn.utils.clip_grads_with_norm_(parameters, cfg.max_grad_norm, norm)
        self.critic_optimizer.step()
        if train_policy:
            self.actor_optimizer.step()
            self.alpha_optimizer.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._v_target_parameters, self._v_parameters, cfg.tau)
        self.updates += 1
        policy, q1, q2, v = checked[:4]
        return {
            "policy_loss": policy,
            "q1_loss": q1,
            "q2_loss": q2,
            "v_loss": v,
            "entropy": entropy,
            "alpha": alpha_value,
        }

    def _refuse_non_finite(self, member: str, figures: list[float]) -> None:
        """Raise before any optimizer step if a loss or gradient norm is NaN/inf: the
        networks, the optimizers and the update count stay as they were."""
        names = [*(f"{name} loss" for name in LOSS_NAMES), "critic gradient", "policy gradient"]
        for name, value in zip(names, figures, strict=True):
            if not math.isfinite(value):
                raise NonFiniteError(
                    f"member {member}: the {name} is {value} at update {self.updates}; "
                    "the update was refused and the networks are unchanged"
                )

    # --- state --------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain numbers only: loadable with torch.load(weights_only=True)."""
        return {
            "actor": self.actor.state_dict(),
            "q1": self.q1.state_dict(),
            "q2": self.q2.state_dict(),
            "v": self.v.state_dict(),
            "v_target": self.v_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "alpha_optimizer": self.alpha_optimizer.state_dict(),
            "updates": self.updates,
            "config": asdict(self.config),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("actor", "q1", "q2", "v", "v_target"):
            getattr(self, name).load_state_dict(state[name])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        for name in ("actor_optimizer", "critic_optimizer", "alpha_optimizer"):
            optimizer = getattr(self, name)
            optimizer.load_state_dict(state[name])
            # The saved settings replace ours; checkpoints from before fused Adam say
            # fused=None, which would quietly bring back the slow per-tensor loop.
            for group in optimizer.param_groups:
                group["fused"], group["foreach"] = True, None
        self.updates = int(state["updates"])


class SACLearner(SAC):
    """SAC as a member trains with it: the replay it stores every transition in, uniform
    random actions for its first `random_steps` transitions, then `updates_per_step`
    gradient steps per new transition once `learning_starts` have been seen."""

    name = "sac"
    title, config_type, schedule_defaults = SHIPPED["sac"][1]  # "SAC", SACConfig, SAC_SCHEDULE
    metric_names = ("policy_loss", "q1_loss", "q2_loss", "v_loss", "entropy", "alpha")
    experience_name = "replay"
    keeps_replay = True
    logs_every_update = False  # thousands of gradient steps: every UPDATE_LOG_EVERY-th

    def __init__(
        self,
        observation_shape: tuple[int, int],
        action_dim: int,
        secret_dim: int,
        config: SACConfig,
        schedule: Mapping[str, float],
        envs: int,
        device: str | torch.device,
    ) -> None:
        super().__init__(observation_shape, action_dim, secret_dim, config, device)
        self.schedule = dict(schedule)
        capacity = int(self.schedule["buffer_size"])
        self.experience = ReplayBuffer(capacity, observation_shape, secret_dim, action_dim)
        self.update_debt = 0.0  # gradient steps owed: updates_per_step may be fractional

    @property
    def optimizers(self) -> list[torch.optim.Optimizer]:
        return [self.actor_optimizer, self.critic_optimizer, self.alpha_optimizer]

    @property
    def acting_network(self) -> nn.Module:
        return self.actor

    def _warming_up(self, steps_seen: int) -> bool:
        return steps_seen < self.schedule["random_steps"]

    def explore(
        self, observation: np.ndarray, rng: np.random.Generator, steps_seen: int
    ) -> np.ndarray:
        if self._warming_up(steps_seen):
            return rng.uniform(-1.0, 1.0, (len(observation), self.action_dim))
        return self.act(observation, deterministic=False)

    @torch.no_grad()
    def explore_rows(
        self,
        observation: np.ndarray,
        generators: Sequence[np.random.Generator],
        steps_seen: int,
        warm_up: bool,
    ) -> tuple[np.ndarray, None]:
        if warm_up and self._warming_up(steps_seen):
            return uniform_rows(generators, self.action_dim), None
        batch = torch.as_tensor(observation, dtype=torch.float32, device=self.device)
        mean, log_std = self.actor(batch)
        actions, _ = gaussian_rows(generators, mean.cpu().numpy(), log_std.exp().cpu().numpy())
        return actions, None

    def observe(self, transition: Transition, member: str) -> None:
        # A replay keeps transitions, not episodes: which slot a row came from does not matter.
        self.experience.add(transition)

    def learn(
        self,
        rng: np.random.Generator,
        steps_seen: int,
        new_steps: int,
        member: str,
        train_policy: bool,
    ) -> list[dict[str, float]]:
        rows: list[dict[str, float]] = []
        batch = self.config.batch_size
        if steps_seen < self.schedule["learning_starts"] or self.experience.size < batch:
            return rows
        self.update_debt += new_steps * self.schedule["updates_per_step"]
        while self.update_debt >= 1.0:
            rows.append(
                self.learn_from(self.experience.sample(batch, rng), rng, member, train_policy)
            )
            self.update_debt -= 1.0
        return rows

    def learn_from(
        self, batch: Any, rng: np.random.Generator | None, member: str, train_policy: bool
    ) -> dict[str, float]:
        if not isinstance(batch, Transition):
            raise TypeError(f"member {member}: SAC updates on a Transition batch of its replay")
        return self.update(batch, member, train_policy)

"""Soft Actor-Critic as the seed trains its aligners (sections 4.3 and 6.1; Haarnoja et al. 2018).

* Policy: a tanh-squashed Gaussian over actions in (-1, 1), reading only the history.
* Critics: twin Q networks and a V network with a slowly following target copy; the critics
  also read the secret (optimum - setting) at training time: an asymmetric actor-critic.
  Only the policy runs on an instrument.
* The policy loss uses the minimum of the two Qs (seed section 6.1, against the optimistic
  critic it describes); the entropy coefficient alpha is tuned toward a target entropy.

Each network has its own history encoder (alignrl/agents/networks.py); parameters are never
shared between members of a league.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from alignrl.agents.networks import make_encoder
from alignrl.agents.replay import Batch

__all__ = ["SAC", "NonFiniteError", "SACConfig"]

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0  # keeps exp(log_std) in a range float32 handles well


class NonFiniteError(FloatingPointError):
    """A loss or parameter became NaN/inf: the update is refused, nothing is changed."""


@dataclass(frozen=True)
class SACConfig:
    encoder: str = "mlp"  # history encoder of every network: mlp, gru or gtrxl
    encoder_kwargs: dict[str, Any] = field(default_factory=dict)
    # Hidden layers of the heads. The critics' action and secret join the encoding here, so
    # they need hidden layers: a linear head makes Q linear in the action, and the policy
    # is then pushed to the bounds of the action box.
    hidden: tuple[int, ...] = (256, 256)
    learning_rate: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005  # target V follows at this rate per update
    batch_size: int = 256
    initial_alpha: float = 0.2
    target_entropy: float | None = None  # default: -(action dimensions)
    secret_critics: bool = True  # critics see optimum - setting (training only)
    max_grad_norm: float = 10.0


def _mlp(inputs: int, hidden: tuple[int, ...], outputs: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), nn.ReLU()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    def __init__(self, history: int, features: int, action_dim: int, config: SACConfig):
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = _mlp(self.encoder.output_dim, config.hidden, 2 * action_dim)

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        encoded, _ = self.encoder(observation)  # (B, D)
        mean, log_std = self.head(encoded).chunk(2, dim=-1)  # (B, A) each
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def sample(self, observation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """A reparameterised action, its log-probability and the deterministic action."""
        mean, log_std = self(observation)
        normal = torch.distributions.Normal(mean, log_std.exp())
        pre_tanh = normal.rsample()
        action = torch.tanh(pre_tanh)
        # Change of variables for tanh, written in the stable form
        # log(1 - tanh(x)^2) = 2 (log 2 - x - softplus(-2x)).
        log_prob = normal.log_prob(pre_tanh) - 2.0 * (
            math.log(2.0) - pre_tanh - nn.functional.softplus(-2.0 * pre_tanh)
        )
        return action, log_prob.sum(-1), torch.tanh(mean)


class Critic(nn.Module):
    """Q(history, secret, action) or, without an action, V(history, secret)."""

    def __init__(self, history: int, features: int, extra_inputs: int, config: SACConfig) -> None:
        super().__init__()
        self.encoder = make_encoder(config.encoder, history, features, **config.encoder_kwargs)
        self.head = _mlp(self.encoder.output_dim + extra_inputs, config.hidden, 1)

    def forward(self, observation: Tensor, *extra: Tensor) -> Tensor:
        encoded, _ = self.encoder(observation)
        return self.head(torch.cat([encoded, *extra], dim=-1)).squeeze(-1)  # (B,)


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
        self.v_target = Critic(history, features, secret_in, cfg).to(self.device)
        self.v_target.load_state_dict(self.v.state_dict())
        self.v_target.requires_grad_(False)
        self.log_alpha = torch.tensor(
            math.log(cfg.initial_alpha), device=self.device, requires_grad=True
        )
        self.target_entropy = (
            cfg.target_entropy if cfg.target_entropy is not None else -float(action_dim)
        )
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.learning_rate)
        self.critic_optimizer = torch.optim.Adam(
            [*self.q1.parameters(), *self.q2.parameters(), *self.v.parameters()],
            lr=cfg.learning_rate,
        )
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.learning_rate)
        self.updates = 0

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

    def update(self, batch: Batch, member: str = "sac") -> dict[str, float]:
        """One gradient step of every network; returns the losses of seed figs. 6.1.2-6.1.7."""
        cfg = self.config
        tensor = lambda array: torch.as_tensor(array, dtype=torch.float32, device=self.device)  # noqa: E731
        observation, secret = tensor(batch.observation), tensor(batch.secret)
        action, reward = tensor(batch.action), tensor(batch.reward)
        next_observation, next_secret = tensor(batch.next_observation), tensor(batch.next_secret)
        done = tensor(batch.done)
        alpha = self.log_alpha.exp().detach()
        extra, next_extra = self._critic_inputs(secret), self._critic_inputs(next_secret)

        # Q targets bootstrap from the slow V target at the next history.
        with torch.no_grad():
            v_next = self.v_target(next_observation, *next_extra)
            q_target = reward + cfg.gamma * (1.0 - done) * v_next
        q1_pred = self.q1(observation, *extra, action)
        q2_pred = self.q2(observation, *extra, action)
        q1_loss = 0.5 * (q1_pred - q_target).pow(2).mean()
        q2_loss = 0.5 * (q2_pred - q_target).pow(2).mean()

        # A fresh action from the *current* policy serves both V's target and the policy loss.
        new_action, log_prob, _ = self.actor.sample(observation)
        # The policy follows the minimum of the two Qs (against optimistic critics).
        min_q_new = torch.min(
            self.q1(observation, *extra, new_action), self.q2(observation, *extra, new_action)
        )
        # V regresses on the soft value of the current policy: min Q minus alpha log pi.
        v_target = (min_q_new - alpha * log_prob).detach()
        v_pred = self.v(observation, *extra)
        v_loss = 0.5 * (v_pred - v_target).pow(2).mean()
        policy_loss = (alpha * log_prob - min_q_new).mean()
        alpha_loss = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()

        losses = {
            "policy": policy_loss,
            "q1": q1_loss,
            "q2": q2_loss,
            "v": v_loss,
            "alpha": alpha_loss,
        }
        for name, loss in losses.items():
            if not torch.isfinite(loss):
                raise NonFiniteError(
                    f"member {member}: the {name} loss is {loss.item()} at update "
                    f"{self.updates}; the update was refused and the networks are unchanged"
                )

        # The critics learn from their losses only: policy_loss also reaches them through
        # min_q_new, so each backward names the parameters it may touch.
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_params = [*self.q1.parameters(), *self.q2.parameters(), *self.v.parameters()]
        (q1_loss + q2_loss + v_loss).backward(inputs=critic_params)
        critic_norm = nn.utils.clip_grad_norm_(critic_params, cfg.max_grad_norm)
        self.actor_optimizer.zero_grad(set_to_none=True)
        policy_loss.backward(inputs=list(self.actor.parameters()))
        actor_norm = nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        for name, norm in (("critic", critic_norm), ("policy", actor_norm)):
            if not torch.isfinite(norm):
                raise NonFiniteError(
                    f"member {member}: the {name} gradient is {norm.item()} at update "
                    f"{self.updates}; the update was refused and the networks are unchanged"
                )
        self.critic_optimizer.step()
        self.actor_optimizer.step()
        self.alpha_optimizer.step()
        with torch.no_grad():
            for target, source in zip(self.v_target.parameters(), self.v.parameters(), strict=True):
                target.lerp_(source, cfg.tau)
        self.updates += 1
        return {
            "policy_loss": policy_loss.item(),
            "q1_loss": q1_loss.item(),
            "q2_loss": q2_loss.item(),
            "v_loss": v_loss.item(),
            "entropy": -log_prob.mean().item(),
            "alpha": alpha.item(),
        }

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
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        self.updates = int(state["updates"])

"""Replay memory for off-policy learners: transitions of whole episodes, sampled as histories.

Each stored observation already is the history window the policy saw (H rows), so a sampled
transition carries its history; the critics' secret (optimum - setting) travels alongside
and never enters the policy's input. Storage is a fixed ring of numpy arrays; sampling takes
a `numpy.random.Generator`, so runs reproduce.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Batch", "ReplayBuffer"]


@dataclass(frozen=True)
class Batch:
    observation: np.ndarray  # (B, H, F)
    secret: np.ndarray  # (B, k)
    action: np.ndarray  # (B, A)
    reward: np.ndarray  # (B,)
    next_observation: np.ndarray  # (B, H, F)
    next_secret: np.ndarray  # (B, k)
    done: np.ndarray  # (B,) 1.0 where the episode ended with this transition


class ReplayBuffer:
    """A ring of the most recent `capacity` transitions."""

    def __init__(
        self, capacity: int, observation_shape: tuple[int, ...], secret_dim: int, action_dim: int
    ) -> None:
        if capacity < 1:
            raise ValueError(f"replay capacity must be positive, got {capacity}")
        self.capacity = capacity
        self.observation = np.zeros((capacity, *observation_shape), np.float32)
        self.next_observation = np.zeros((capacity, *observation_shape), np.float32)
        self.secret = np.zeros((capacity, secret_dim), np.float32)
        self.next_secret = np.zeros((capacity, secret_dim), np.float32)
        self.action = np.zeros((capacity, action_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.done = np.zeros(capacity, np.float32)
        self.position = 0
        self.size = 0

    def add(
        self,
        observation: np.ndarray,
        secret: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        next_observation: np.ndarray,
        next_secret: np.ndarray,
        done: np.ndarray,
    ) -> None:
        """Store a batch of transitions (one per env slot)."""
        count = len(reward)
        slots = (self.position + np.arange(count)) % self.capacity
        self.observation[slots] = observation
        self.secret[slots] = secret
        self.action[slots] = action
        self.reward[slots] = reward
        self.next_observation[slots] = next_observation
        self.next_secret[slots] = next_secret
        self.done[slots] = done
        self.position = int((self.position + count) % self.capacity)
        self.size = int(min(self.capacity, self.size + count))

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        index = rng.integers(0, self.size, batch_size)
        return Batch(
            observation=self.observation[index],
            secret=self.secret[index],
            action=self.action[index],
            reward=self.reward[index],
            next_observation=self.next_observation[index],
            next_secret=self.next_secret[index],
            done=self.done[index],
        )

    def state_dict(self) -> dict[str, np.ndarray | int]:
        """Arrays and counters (numpy only: safe to store without pickling)."""
        used = slice(0, self.size)
        return {
            "observation": self.observation[used],
            "next_observation": self.next_observation[used],
            "secret": self.secret[used],
            "next_secret": self.next_secret[used],
            "action": self.action[used],
            "reward": self.reward[used],
            "done": self.done[used],
            "position": self.position,
            "size": self.size,
        }

    def load_state_dict(self, state: dict[str, np.ndarray | int]) -> None:
        size = int(state["size"])
        if size > self.capacity:
            raise ValueError(f"saved replay holds {size} transitions, capacity is {self.capacity}")
        for name in ("observation", "next_observation", "secret", "next_secret", "action"):
            getattr(self, name)[:size] = state[name]
        self.reward[:size] = state["reward"]
        self.done[:size] = state["done"]
        self.position, self.size = int(state["position"]), size

"""Replay memory for off-policy learners: transitions of whole episodes, sampled as histories.

Each stored observation already is the history window the policy saw (H rows), so a sampled
transition carries its history; the critics' secret (optimum - setting) travels alongside
and never enters the policy's input. Storage is a fixed ring of numpy arrays; sampling takes
a `numpy.random.Generator`, so runs reproduce.
"""

from __future__ import annotations

import numpy as np

from alignrl.transitions import Transition

__all__ = ["ReplayBuffer"]

# What a replay keeps of a Transition, each in an array of its own name (not which env slot a
# row came from, nor PPO's pre-squash sample).
STORED = ("observation", "secret", "action", "reward", "next_observation", "next_secret", "done")


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

    def add(self, transition: Transition) -> None:
        """Store a batch of transitions (one per env slot; which slot does not matter here)."""
        count = len(transition)
        slots = (self.position + np.arange(count)) % self.capacity
        for name in STORED:
            getattr(self, name)[slots] = getattr(transition, name)
        self.position = int((self.position + count) % self.capacity)
        self.size = int(min(self.capacity, self.size + count))

    def sample(self, batch_size: int, rng: np.random.Generator) -> Transition:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        index = rng.integers(0, self.size, batch_size)
        return Transition(**{name: getattr(self, name)[index] for name in STORED})

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

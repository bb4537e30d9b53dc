"""The transition: what a learner stores of an env step and learns from, one record.

A Transition holds rows of transitions side by side: those of the env slots that stepped
together, those of one episode from its first step to its last, or a batch drawn from a
replay. The trainer, the league and the hindsight secrets build one; `Agent.observe`,
the learners' `observe` and the replay's `add` take it whole, and a replay's `sample` gives
one back. numpy only: the record is below the envs that fill it and the learners that read
it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Transition"]


@dataclass(frozen=True)
class Transition:
    """Transitions, one row each (B rows); the critics' secret (optimum - setting) travels
    alongside and never enters the policy's input."""

    observation: np.ndarray  # (B, H, F) the history the policy read
    secret: np.ndarray  # (B, k) optimum - setting, for the critics
    action: np.ndarray  # (B, A) what the policy did, in (-1, 1)
    reward: np.ndarray  # (B,)
    next_observation: np.ndarray  # (B, H, F) of a finished episode: its last history
    next_secret: np.ndarray  # (B, k)
    done: np.ndarray  # (B,) true (1.0) where the episode ended with this transition
    slots: np.ndarray | None = None  # (B,) the env slot of each row; None: slots 0 .. B-1
    pre_tanh: np.ndarray | None = None  # (B, A) PPO's pre-squash sample, where it travels along

    def __len__(self) -> int:
        return len(self.reward)

    def rows(self, index: Any) -> Transition:
        """These rows of every array (a mask, indices or a slice); what is None stays None."""
        arrays = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        return Transition(
            **{name: None if array is None else array[index] for name, array in arrays.items()}
        )

    @classmethod
    def joined(cls, parts: Sequence[Transition]) -> Transition:
        """The rows of `parts`, one part after the other; an array that a part lacks (None)
        is None in the whole."""

        def column(name: str) -> np.ndarray | None:
            arrays = [getattr(part, name) for part in parts]
            return None if any(array is None for array in arrays) else np.concatenate(arrays)

        return cls(**{field.name: column(field.name) for field in dataclasses.fields(cls)})

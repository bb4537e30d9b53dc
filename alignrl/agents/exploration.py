"""Exploration one row at a time, for actions sampled away from the learner (a Ray worker).

Row i of a batch draws its randomness from `generators[i]` alone (one generator per match),
so a row's action depends neither on the rows beside it nor on the process that computed
it. The learners' `explore_rows` build on these two draws.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["gaussian_rows", "uniform_rows"]


def uniform_rows(generators: Sequence[np.random.Generator], action_dim: int) -> np.ndarray:
    """Uniform actions in (-1, 1): (rows, action_dim), row i from generators[i]."""
    return np.stack([generator.uniform(-1.0, 1.0, action_dim) for generator in generators])


def gaussian_rows(
    generators: Sequence[np.random.Generator], mean: np.ndarray, std: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """tanh-squashed samples of the Gaussians N(mean, std) (each (rows, action_dim), float32)
    and the pre-squash samples: the same reparameterised draw as SAC's Actor.sample and
    PPO's Normal.sample, with row i's noise from generators[i]."""
    action_dim = mean.shape[-1]
    noise = np.stack([generator.standard_normal(action_dim) for generator in generators])
    pre_tanh = mean + std * noise.astype(np.float32)
    return np.tanh(pre_tanh), pre_tanh

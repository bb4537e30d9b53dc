"""What a posterior's states would read, for its probe and its stop (FamilyPosterior's
`_next_probe` and `_final`): the reading model gathered per state (`StateReadings`), the
chance of each outcome of a reading in bins (`outcome_chances`), and the optimum's expected
entropy after one (`expected_entropy`), into scratch buffers (alignrl/posterior/workspace.py).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import ndtr

from alignrl.posterior.models import ColumnModels, ReadingConstants, reading_into, reading_work
from alignrl.posterior.workspace import scratch

__all__ = ["StateReadings", "expected_entropy", "outcome_chances"]


class StateReadings(NamedTuple):
    """The reading model of a posterior's states (S,): their columns' `constants` (of
    states), lags and optima (fractions), their specimen's factor (None: 1) and the width
    each must read to pass (px)."""

    constants: ReadingConstants
    lag: np.ndarray
    optimum: np.ndarray
    factor: np.ndarray | None
    spec: np.ndarray

    @classmethod
    def of(
        cls,
        models: ColumnModels,
        k: np.ndarray,
        optimum: np.ndarray,
        scale: np.ndarray,
        spec_relative: float,
    ) -> StateReadings:
        """States of columns `k` at optima `optimum`, their specimen's log scale `scale` x
        specimen_rel, passing within `spec_relative` x the in-focus width."""
        factor = np.exp(models.specimen_rel[k, 0, 0] * scale)
        return cls(
            models.constants.of_states(k),
            models.lag[k, 0, 0],
            optimum,
            None if np.all(factor == 1.0) else factor,  # x 1: the same numbers
            spec_relative * models.constants.best[k, 0, 0],
        )

    def reading(
        self, settings: np.ndarray | None, shift: tuple[np.ndarray, np.ndarray] | None = None
    ) -> tuple[np.ndarray, ...]:
        """ColumnModels.reading (of states) at `settings` (M,) approached from below:
        (M, S) each, or (1, S) at each state's optimum (`settings` None); with `shift`,
        each state's log scale and its variance (ScaleSums.estimate), in the readings'
        pixels. Buffers (`scratch`) the next call overwrites."""
        shape = (1 if settings is None else settings.size, self.lag.size)
        error = scratch("state error", shape)
        if settings is None:  # each state's own optimum
            error.fill(0.0)
        else:
            np.subtract(settings[:, None], self.lag[None, :], out=error)
            np.subtract(error, self.optimum[None, :], out=error)
        work = reading_work(shape, shape)
        none, mean, spread = reading_into(self.constants, error, self.factor, work)
        if shift is not None:  # spread = mean sqrt((spread / mean)^2 + variance) exp(shift)
            grown = np.exp(shift[0])
            np.square(np.divide(spread, mean, out=spread), out=spread)
            np.sqrt(np.add(spread, shift[1], out=spread), out=spread)
            np.multiply(np.multiply(mean, spread, out=spread), grown, out=spread)
            mean = np.multiply(mean, grown, out=mean)
        return none, mean, spread

    def passing(self, settings: np.ndarray | None) -> np.ndarray:
        """Each state's chance of reading within its spec at `settings` (`reading`): (M, S),
        a buffer the next call overwrites."""
        none, mean, spread = self.reading(settings)
        chance = np.subtract(self.spec[None, :], mean, out=mean)
        ndtr(np.divide(chance, spread, out=chance), out=chance)
        return np.multiply(np.subtract(1.0, none, out=none), chance, out=chance)


def outcome_chances(
    none: np.ndarray, mean: np.ndarray, spread: np.ndarray, edges: np.ndarray, weight: np.ndarray
) -> np.ndarray:
    """Per setting and state (M, S) of `StateReadings.reading`, the chance of each bin of
    readings between `edges` (B), and last of no edges, x each state's `weight`:
    (M, S, B + 2), a buffer the next call overwrites."""
    bins = edges.size
    below = scratch("below", (*mean.shape, bins))
    np.subtract(edges[None, None, :], mean[..., None], out=below)
    ndtr(np.divide(below, spread[..., None], out=below), out=below)
    joint = scratch("joint", (*mean.shape, bins + 2))  # np.diff(prepend 0, append 1)
    np.subtract(below[..., :1], 0.0, out=joint[..., :1])
    np.subtract(below[..., 1:], below[..., :-1], out=joint[..., 1:bins])
    np.subtract(1.0, below[..., -1:], out=joint[..., bins : bins + 1])
    measured = np.subtract(1.0, none, out=scratch("measured", none.shape))
    np.multiply(joint[..., : bins + 1], measured[..., None], out=joint[..., : bins + 1])
    joint[..., bins + 1] = none
    return np.multiply(joint, weight[None, :, None], out=joint)


def expected_entropy(joint: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Per setting, the expected entropy of the optimum over its grid points after the
    reading: `joint` (M, S, B) of `outcome_chances`, the states sorted by their grid point,
    `cells` where each point's states begin."""
    settings, _, outcomes = joint.shape
    mass = scratch("mass", (settings, cells.size, outcomes))
    np.add.reduceat(joint, cells, axis=1, out=mass)
    outcome = mass.sum(axis=1)
    spent = scratch("spent", mass.shape)
    np.multiply(mass, np.log(np.maximum(mass, 1e-300, out=spent), out=spent), out=spent)
    known = np.sum(outcome * np.log(np.maximum(outcome, 1e-300)), axis=1)
    return known - np.sum(spent, axis=(1, 2))

"""An unknown pixel scale marginalised in closed form, per state of a posterior
(alignrl/posterior/inference.py, `scale_free`): every reading is the model's times a
factor of the episode, flat on a log scale, so that the readings tell only their ratios and
the curve's shape."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ScaleSums"]


@dataclass
class ScaleSums:
    """Per state, the precision-weighted sums of log residuals that marginalise an unknown
    log scale with a flat prior: the scale's estimate is sum1 / sum0 with variance 1 / sum0,
    and a new residual's predictive is normal around it."""

    sum0: np.ndarray  # sum of 1 / variance
    sum1: np.ndarray  # sum of residual / variance
    readings: int = 0  # every measured reading adds to every state

    UNKNOWN = 1.0  # the log scale's spread before any reading (for probe choices only)

    @classmethod
    def empty(cls, shape: tuple[int, ...]) -> ScaleSums:
        return cls(np.zeros(shape), np.zeros(shape))

    def add(self, residual: np.ndarray, variance: np.ndarray) -> None:
        self.sum0 = self.sum0 + 1.0 / variance
        self.sum1 = self.sum1 + residual / variance
        self.readings += 1

    def predictive(self, residual: np.ndarray, variance: np.ndarray) -> np.ndarray:
        """The density of a new log residual given the earlier ones (a constant before any:
        the first reading's pixels say nothing of the column)."""
        if not self.readings:
            return np.ones_like(residual)
        total = variance + 1.0 / self.sum0
        return np.exp(-0.5 * (residual - self.sum1 / self.sum0) ** 2 / total) / np.sqrt(total)

    def add_either(
        self, residuals: list[np.ndarray], variances: list[np.ndarray], chances: list[np.ndarray]
    ) -> np.ndarray:
        """A reading that is one of several alike likely (its log residual and variance on
        each, each with the `chances` of being measured at all): the mean of their
        predictives; it joins the sums as one normal matched to the mixture's moments (the
        residuals' mean, their spread added to the mean variance), so the sums stay one per
        state."""
        count = len(residuals)
        density = sum(
            chance * self.predictive(residual, variance)
            for residual, variance, chance in zip(residuals, variances, chances, strict=True)
        )
        centre = sum(residuals) / count
        spread = sum((residual - centre) ** 2 for residual in residuals) / count
        self.add(centre, sum(variances) / count + spread)
        return density / count

    def predictive_into(
        self, rows: slice, residual: np.ndarray, variance: np.ndarray, work: list[np.ndarray]
    ) -> np.ndarray | None:
        """`predictive` of the states of columns `rows` (the same numbers, into `work`: two
        buffers of `residual`'s shape); None before any reading (the constant 1)."""
        if not self.readings:
            return None
        sum0, total, density = self.sum0[rows], work[0], work[1]
        np.divide(1.0, sum0, out=total)
        np.add(variance, total, out=total)
        np.divide(self.sum1[rows], sum0, out=density)
        np.subtract(residual, density, out=density)
        np.square(density, out=density)
        np.multiply(-0.5, density, out=density)
        np.divide(density, total, out=density)
        np.exp(density, out=density)
        np.sqrt(total, out=total)
        return np.divide(density, total, out=density)

    def add_into(
        self, rows: slice, residual: np.ndarray, variance: np.ndarray, work: np.ndarray
    ) -> None:
        """`add` for the states of columns `rows` alone, in place (the same numbers; `work`:
        a buffer of `residual`'s shape); `counted` once every row has its reading."""
        sum0, sum1 = self.sum0[rows], self.sum1[rows]
        np.add(sum0, np.divide(1.0, variance, out=work), out=sum0)
        np.add(sum1, np.divide(residual, variance, out=work), out=sum1)

    def counted(self) -> None:
        """A reading `add_into` gave every state joins the count."""
        self.readings += 1

    def estimate(self, k: np.ndarray, z: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, ...]:
        """(log scale, its variance) of states (S,)."""
        if not self.readings:
            return np.zeros(k.shape), np.full(k.shape, self.UNKNOWN**2)
        sum0 = self.sum0[k, z, n]
        return self.sum1[k, z, n] / sum0, 1.0 / sum0

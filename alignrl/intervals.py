"""How sure a figure is: 95 % intervals for success counts, and the interquartile mean of
several seeds with its bootstrap interval (issue 23, "Honest figures").

* `wilson(successes, n)`: the Wilson score interval of a success rate. 30/50 is 0.60 with an
  interval of 0.46-0.72: about +-14 points, which a bare "30/50" hides. Wilson rather than the
  normal approximation because it stays inside [0, 1] and holds at 0/n and n/n, where
  evaluation sessions often land.
* `iqm(values)`: the interquartile mean (the mean of the middle half), the aggregate rliable
  recommends over the mean (outlier runs) and the median (too coarse with few runs)
  (Agarwal et al., "Deep RL at the edge of the statistical precipice", NeurIPS 2021).
* `bootstrap_interval(values, statistic)`: scipy's bootstrap (percentile method, a seeded
  generator) of any statistic of the runs; with fewer than two distinct values there is no
  spread to resample and the interval is the point itself.

Every function takes plain numbers and returns plain floats, so that tables, `--json`, model
cards and reports all print the same interval the same way (`success_text`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

__all__ = [
    "CONFIDENCE",
    "bootstrap_interval",
    "iqm",
    "success_interval",
    "success_text",
    "wilson",
]

CONFIDENCE = 0.95
BOOTSTRAP_RESAMPLES = 2000


def _z(confidence: float) -> float:
    from statistics import NormalDist

    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    return NormalDist().inv_cdf(0.5 + confidence / 2.0)


def wilson(successes: int, total: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Wilson score interval (low, high) of the rate successes / total, in [0, 1].
    ValueError for a total below 1 or successes outside [0, total]."""
    successes, total = int(successes), int(total)
    if total < 1:
        raise ValueError(f"an interval needs at least one trial, got {total}")
    if not 0 <= successes <= total:
        raise ValueError(f"successes must be in [0, {total}], got {successes}")
    z = _z(confidence)
    rate = successes / total
    denominator = 1.0 + z * z / total
    centre = (rate + z * z / (2 * total)) / denominator
    half = z * math.sqrt(rate * (1 - rate) / total + z * z / (4 * total * total)) / denominator
    # At 0/n and n/n the bound on that side is exactly 0 or 1 (the formula leaves rounding).
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == total else min(1.0, centre + half)
    return low, high


def success_interval(
    successes: int, total: int, confidence: float = CONFIDENCE
) -> dict[str, float | int]:
    """A success figure as `--json` and cards give it: successes, total, rate and the
    interval's ends (rates), with the confidence they hold at."""
    low, high = wilson(successes, total, confidence)
    return {
        "successes": int(successes),
        "total": int(total),
        "rate": int(successes) / int(total),
        "low": low,
        "high": high,
        "confidence": confidence,
    }


def success_text(successes: int, total: int, confidence: float = CONFIDENCE) -> str:
    """`30/50 (46-72 %)`: the count and its interval in whole percent, or in tenths where
    whole percent would show both ends alike (`3830/3840 (99.5-99.9 %)`)."""
    low, high = wilson(successes, total, confidence)
    digits = 0 if round(100 * low) != round(100 * high) else 1
    return f"{int(successes)}/{int(total)} ({100 * low:.{digits}f}-{100 * high:.{digits}f} %)"


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """The interquartile mean: the mean of the middle 50 % of `values` (25 % trimmed at each
    end, scipy.stats.trim_mean). ValueError for no values or a value that is not finite."""
    from scipy.stats import trim_mean

    array = np.asarray(values, float).reshape(-1)
    if array.size == 0:
        raise ValueError("the interquartile mean of no values")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"the interquartile mean needs finite values, got {array.tolist()}")
    return float(trim_mean(array, 0.25))


def bootstrap_interval(
    values: Sequence[float] | np.ndarray,
    statistic: Callable[[np.ndarray], float] = iqm,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """The percentile bootstrap interval (low, high) of `statistic` over `values` (one per
    run or seed), by scipy.stats.bootstrap with a generator of `seed`: the same values give
    the same interval. Fewer than two distinct values: (point, point)."""
    from scipy.stats import bootstrap

    array = np.asarray(values, float).reshape(-1)
    point = float(statistic(array))
    if np.unique(array).size < 2:
        return point, point
    result = bootstrap(
        (array,),
        lambda sample, axis=-1: np.apply_along_axis(statistic, axis, sample),
        confidence_level=confidence,
        n_resamples=int(resamples),
        method="percentile",
        vectorized=True,
        random_state=np.random.default_rng(seed),
    )
    low, high = result.confidence_interval
    return float(min(low, point)), float(max(high, point))

"""A box's values, shared by the focus family (family_box.py, family.py) and the whole
columns' (column_box.py, column_family.py): a parameter is a point or [low, high] within its
physical range, a column lies at a fraction of each range (uniform, or at the box's edges
by the arcsine law), and a list (specimens, mirrors) is picked by a fraction too."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np

__all__ = [
    "SAMPLINGS",
    "SHOWN_PROBLEMS",
    "at_fraction",
    "check_sampling",
    "pair",
    "pick",
    "range_problem",
    "shown_problems",
    "span",
    "unit_fractions",
]

SAMPLINGS = ("uniform", "edges")  # how a family column draws from its box
SHOWN_PROBLEMS = 8  # problems of a bad box listed in one message
Chosen = TypeVar("Chosen")


def pair(value: Any) -> Any:
    """A point x means the range [x, x]."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        try:
            return (float(value), float(value))
        except OverflowError:  # an integer of hundreds of digits
            raise ValueError(f"a number of {len(str(value))} digits is beyond any range") from None
    return value


def span(low: float, high: float) -> str:
    return f"{low:g}" if low == high else f"[{low:g}, {high:g}]"


def range_problem(
    name: str, low: float, high: float, lowest: float, highest: float, unit: str
) -> str | None:
    """What is wrong with `name` = [low, high] against its physical range [lowest, highest]
    (in `unit`), in words; None where nothing is."""
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        return f"{name}: need finite low <= high, got {span(low, high)}"
    if low < lowest or high > highest:
        return (
            f"{name} {span(low, high)} lies outside its physical range "
            f"[{lowest:g}, {highest:g}] {unit}"
        ).rstrip()
    return None


def shown_problems(problems: list[str]) -> list[str]:
    """The first SHOWN_PROBLEMS of `problems`, and how many more there are."""
    if len(problems) > SHOWN_PROBLEMS:
        return [*problems[:SHOWN_PROBLEMS], f"and {len(problems) - SHOWN_PROBLEMS} more"]
    return problems


def check_sampling(sampling: str) -> None:
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {', '.join(SAMPLINGS)}, got {sampling!r}")


def unit_fractions(
    names: Sequence[str], rng: np.random.Generator, sampling: str = "uniform"
) -> dict[str, float]:
    """One fraction of [0, 1] per name, in order: uniform, or "edges", from the arcsine law
    Beta(1/2, 1/2), which puts 29 % of a parameter's draws in the outer tenth of its range
    (uniform: 10 %) and still a third in its middle half."""
    check_sampling(sampling)
    if sampling == "edges":
        return {name: float(rng.beta(0.5, 0.5)) for name in names}
    return {name: float(rng.random()) for name in names}


def at_fraction(low: float, high: float, fraction: float, log: bool) -> float:
    """The value `fraction` of the way from `low` to `high`, on a log scale where `log`."""
    if log:
        return float(math.exp(math.log(low) + fraction * (math.log(high) - math.log(low))))
    return low + fraction * (high - low)


def pick(options: Sequence[Chosen], fraction: float) -> Chosen:
    """The option at `fraction` (clipped to [0, 1]) of the list: each an equal share."""
    index = int(min(max(float(fraction), 0.0), 1.0) * len(options))
    return options[min(index, len(options) - 1)]

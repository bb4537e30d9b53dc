"""How a knob arrives at a setting so that backlash leaves it where it was meant to be.

A lens field lags the voltage written to it (hysteresis), and a mechanical stage lags the
way it last moved (backlash): the same setting reached from below and from above puts the
focus in two places. Whoever writes a setting that must lie on one branch of that lag
(every probe of the classical autofocus, alignrl/evaluation/controllers.py; every reading
and the way back of an episode, alignrl/envs/ending.py) asks `arrival` for the writes:
one, or a pass beyond the target on the near side first.
"""

from __future__ import annotations

import numpy as np

__all__ = ["arrival"]


def arrival(
    target: np.ndarray,
    start: np.ndarray,
    side: np.ndarray,
    overshoot: np.ndarray | float,
    low: np.ndarray,
    high: np.ndarray,
    arrived: np.ndarray | None = None,
) -> list[np.ndarray]:
    """The writes that take knobs from `start` (NaN: unknown) to `target`, each arriving
    from its `side` (+1 from below, -1 from above, 0 either way): a knob that would come
    from the other side goes past the target by `overshoot` first, kept inside
    [low, high]. A knob that already sits at its target goes past and back too where it
    `arrived` there from the other side (-side; 0 or None: not known, and it stays as it
    was found). Where the pass would be clipped onto the target itself (the target at a
    bound) it is left out."""
    target = np.asarray(target, float)
    start, side = np.asarray(start, float), np.asarray(side, float)
    known = np.zeros_like(side) if arrived is None else np.asarray(arrived, float)
    with np.errstate(invalid="ignore"):
        towards = np.sign(target - start)  # NaN where the start is unknown
        reverse = (side != 0) & ((towards == -side) | ((towards == 0) & (known == -side)))
    reverse &= np.asarray(overshoot) > 0
    if not np.any(reverse):
        return [target]
    past = np.clip(np.where(reverse, target - side * overshoot, target), low, high)
    if np.array_equal(past, target):
        return [target]
    return [past, target]

"""Rewards of an alignment episode, exactly as the seed gives them (section 4.3).

* 0 for a step that keeps every knob inside its allowed interval;
* -penalty for a step that would leave it (the knob stays clipped at the bound);
* at the final step, scale x (edge width before - edge width after), widths in pixels.

The misaligner receives the negative of every aligner reward, so each episode sums to zero.
No shaping is hidden here; an optional per-acquisition cost and an optional success bonus
(both 0 by default) are named task fields.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bound_penalty", "final_reward", "success_bonus"]


def bound_penalty(hit_bound: np.ndarray, penalty: float) -> np.ndarray:
    """-penalty where a step would have left the interval, else 0."""
    return np.where(hit_bound, -float(penalty), 0.0)


def final_reward(
    width_before_px: np.ndarray, width_after_px: np.ndarray, scale: float
) -> np.ndarray:
    """scale x (before - after): positive when the alignment sharpened the image."""
    return float(scale) * (np.asarray(width_before_px) - np.asarray(width_after_px))


def success_bonus(succeeded: np.ndarray, bonus: float) -> np.ndarray:
    """Optional shaping: +bonus for an alignment that ends within spec (off by default)."""
    return np.where(succeeded, float(bonus), 0.0)

"""Rewards of an alignment episode, exactly as the seed gives them (section 4.3).

* 0 for a step that keeps every knob inside its allowed interval;
* -penalty for a step that would leave it (the knob stays clipped at the bound);
* at the final step, scale x (edge width before - edge width after), widths in pixels.

The game between the two teams is zero-sum step by step. When the misaligner places the start
it scores the misalignment it created, scale x (edge width at the start - best edge width), and
the aligner is charged the same (`misalignment_score`); from then on the misaligner receives
the negative of every aligner reward. Its total is what the aligner failed to recover: scale x
(final width - best width), minus any success bonus, plus any penalties and costs. (Were it
paid only the negative of the aligner's improvement, its best move would be a start at focus,
where there is nothing to improve.) The charge comes before the aligner's first action, so the
aligner's learning reward, and with it its best policy, is the seed's.
No shaping is hidden here; an optional per-acquisition cost and an optional success bonus
(both 0 by default) are named task fields.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bound_penalty", "final_reward", "misalignment_score", "success_bonus"]


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


def misalignment_score(
    width_start_px: np.ndarray, best_width_px: np.ndarray, scale: float
) -> np.ndarray:
    """scale x (start - best): what a misaligner's start is worth before the aligner acts.
    Where the best width is unknown (a real column) it counts as 0 px."""
    best = np.nan_to_num(np.asarray(best_width_px, float), nan=0.0)
    return float(scale) * (np.asarray(width_start_px) - best)

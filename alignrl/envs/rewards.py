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
With the task's `final_reward_form: log_ratio` the widths enter as logarithms instead,
scale x log(before / after) and scale x log(start / best): the same game in a unit-free
measure, so that columns of every pixel scale pay alike (the instrument family). No shaping
is hidden here; an optional per-acquisition cost and an optional success bonus
(both 0 by default) are named task fields.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bound_penalty", "final_reward", "misalignment_score", "success_bonus"]


def bound_penalty(hit_bound: np.ndarray, penalty: float) -> np.ndarray:
    """-penalty where a step would have left the interval, else 0."""
    return np.where(hit_bound, -float(penalty), 0.0)


FORMS = ("difference", "log_ratio")


def _measure(width_px: np.ndarray, form: str) -> np.ndarray:
    """A width as the final reward counts it: px, or log px (log_ratio)."""
    width = np.asarray(width_px, float)
    return np.log(width) if form == "log_ratio" else width


def final_reward(
    width_before_px: np.ndarray,
    width_after_px: np.ndarray,
    scale: float,
    form: str = "difference",
) -> np.ndarray:
    """scale x (before - after), or scale x log(before / after): positive when the alignment
    sharpened the image."""
    return float(scale) * (_measure(width_before_px, form) - _measure(width_after_px, form))


def success_bonus(succeeded: np.ndarray, bonus: float) -> np.ndarray:
    """Optional shaping: +bonus for an alignment that ends within spec (off by default)."""
    return np.where(succeeded, float(bonus), 0.0)


def misalignment_score(
    width_start_px: np.ndarray,
    best_width_px: np.ndarray,
    scale: float,
    form: str = "difference",
) -> np.ndarray:
    """scale x (start - best), or x log(start / best): what a misaligner's start is worth
    before the aligner acts. Where the best width is unknown (a real column) it counts as
    0 px (difference), or as the start itself (log_ratio: a score of 0)."""
    start = np.asarray(width_start_px, float)
    best = np.asarray(best_width_px, float)
    if form == "log_ratio":
        best = np.where(np.isfinite(best), best, start)
        return float(scale) * (np.log(start) - np.log(best))
    return float(scale) * (start - np.nan_to_num(best, nan=0.0))

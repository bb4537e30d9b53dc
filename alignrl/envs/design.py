"""Misaligners that design the instrument, and the regret payoff (issue 22; design.md,
"Misaligners design the instrument").

A designing misaligner acts once, as before, but its action is [start (k), design (d)] in
(-1, 1)^(k + d):
* the start: where in the complexity window around the aligned state each knob starts;
* the design: one value per parameter of the instrument family's box that the column's
  reading path uses (FamilyColumn.design_names: interval, gain, floor, curve shape, noise,
  drift, hysteresis, and on the image path specimen and dose), each put (a + 1) / 2 of the
  way from its range's low end to its high end (on a log scale where the box draws
  log-uniformly). Any action is a column inside the box: the action is bounded by
  construction.
It reads [valid, the episode's uniform draw of the design as 2u - 1 (d), complexity]: a
noise vector, as PAIRED's adversary is given one (Dennis et al. 2020), so that even a
deterministic designer can vary its columns; it is also what a uniform designer (domain
randomization) picks.

What the misaligner's move scores (the aligner is charged the same, before its first action;
from then on the misaligner receives the negative of every aligner reward, so the teams'
totals sum to zero in every episode):
* `improvement` (the seed's, alignrl.envs.rewards.misalignment_score): what the start is worth,
  scale x (start - best). Its total is what the aligner did not recover: a designer paid so
  wins with columns nobody can align.
* `regret`: what a reference earns under the same task rewards (bound penalties aside, which
  a reference never incurs; the acquisition cost and the final reward alike) on the same
  column from the same start, with common random numbers: the reference plays a twin of the
  apparatus in its very state, noise stream included (`twin_of`). The misaligner's total is
  then the reference's return minus the aligner's: the aligner's regret. A column nobody can
  align pays nothing (the reference fails as well), nor does a trivial one (both succeed);
  what pays is a column the reference aligns and the aligner does not. The reference's
  return does not depend on the aligner's actions, so to the aligner it is a start-dependent
  baseline: its learning reward, and the gradient of it, stay the seed's.

PAIRED pays the regret of a learned antagonist, max(antagonist return - protagonist return,
0); here the reference is a classical controller (the hyperbola fit, or golden-section), so
it needs no training and cannot collude, and the payoff is not clipped at zero, so the game
stays zero-sum. ACCEL (Parker-Holder et al. 2022) edits and replays high-regret levels;
nothing of that is taken here.

The rated score of a match (Elo, PFSP): under `improvement` the aligner's success; under
`regret` whether it did better than the reference: 1 where it met the spec and the reference
did not, 0 the other way round, 1/2 where both or neither did.
"""

from __future__ import annotations

import copy
from typing import Protocol, TypeGuard, runtime_checkable

import numpy as np

from alignrl.apparatus.base import Apparatus, knows_optimum
from alignrl.envs import rewards
from alignrl.envs.task import Task

__all__ = [
    "PAYOFFS",
    "Designable",
    "Reference",
    "can_twin",
    "designer_input_shape",
    "designs_columns",
    "fractions_of",
    "rated_scores",
    "reference_returns",
    "twin_of",
]

PAYOFFS = ("improvement", "regret")


@runtime_checkable
class Designable(Protocol):
    """An apparatus whose column a misaligner may choose (alignrl.apparatus.family)."""

    def design_names(self) -> tuple[str, ...]: ...
    def design_draw(self) -> np.ndarray: ...
    def design(self, fractions: np.ndarray) -> None: ...


def designs_columns(unit: object) -> TypeGuard[Designable]:
    """Whether a misaligner may design `unit`'s column (and it has parameters to design)."""
    names = getattr(unit, "design_names", None)
    return callable(names) and callable(getattr(unit, "design", None)) and bool(names())


def designer_input_shape(n_design: int) -> tuple[int, int]:
    """What a designing misaligner member reads: one row [valid, draw (d), complexity]."""
    return (1, n_design + 2)


def fractions_of(actions: np.ndarray) -> np.ndarray:
    """Design actions in (-1, 1) as fractions of the box's ranges, in [0, 1]."""
    return 0.5 * (np.clip(np.asarray(actions, float), -1.0, 1.0) + 1.0)


def can_twin(unit: Apparatus) -> bool:
    """Whether `unit` can give a twin of its column: a simulator that knows its optimum and
    either offers `twin` or is a plain object to copy. A unit behind the safety shield never
    can: a driver (loaded by import path, so always shielded) may be a microscope, and a copy
    of it would reach the same instrument around the shield."""
    from alignrl.apparatus.shield import ShieldedApparatus

    if not knows_optimum(unit):
        return False
    return callable(getattr(unit, "twin", None)) or not isinstance(unit, ShieldedApparatus)


def twin_of(unit: Apparatus) -> Apparatus:
    """An independent copy of `unit` in its present state, noise stream included (the
    apparatus's own `twin`, else a deep copy): the same column and the same random numbers.
    ValueError where `unit` cannot give one (`can_twin`)."""
    if not can_twin(unit):
        raise ValueError(
            f"{type(unit).__name__} cannot give a twin of its column: only a simulator that "
            "knows its optimum can, never a driver behind the shield"
        )
    twin = getattr(unit, "twin", None)
    return twin() if callable(twin) else copy.deepcopy(unit)


class Reference(Protocol):
    """What the regret is measured against: aligns a twin of the column from its start by
    its own rule and tells where it left it."""

    name: str

    def align(self, twin: Apparatus, task: Task) -> tuple[float, int]:
        """(the task's cost of one image at the final setting, px, NaN where it failed;
        images acquired before it)."""
        ...


def reference_returns(
    cost_before_px: np.ndarray,
    final_cost_px: np.ndarray,
    acquisitions: np.ndarray,
    task: Task,
) -> np.ndarray:
    """A reference's return under the task's rewards: the final reward from the start's
    cost to its final cost (a failed image counts as the task's no-edges width), less the
    acquisition cost of every image it took."""
    final = np.where(np.isfinite(final_cost_px), final_cost_px, task.no_edges_px)
    earned = rewards.final_reward(
        cost_before_px, final, task.final_reward_scale, task.final_reward_form
    )
    return earned - task.acquisition_cost * np.asarray(acquisitions, float)


def rated_scores(aligner_success: np.ndarray, reference_success: np.ndarray | None) -> np.ndarray:
    """The aligner's rated score per match: its success (no reference), or 1/2 + (its
    success - the reference's) / 2."""
    mine = np.asarray(aligner_success, float)
    if reference_success is None:
        return mine
    return 0.5 + 0.5 * (mine - np.asarray(reference_success, float))

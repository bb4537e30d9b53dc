"""Population-based training (Jaderberg et al. 2017): exploit, then explore, per team.

Exploit: ranked by rating, the weakest members are replaced by copies of the strongest (the
n-th strongest copied over the n-th weakest), a share `fraction` of the team at a time, at
least one and at most half of it, and only where the source leads by `min_gap` rating points.
Explore: each copy's learning rate is its source's times a factor drawn from `perturb`.
`choose_replacements` is the decision, a pure function of the ranking and the league's
generator; `copy_member` makes the copy, which records its source as `parent` (lineage).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from copy import deepcopy
from dataclasses import dataclass

import numpy as np

from alignrl.agents.agent import Agent, MemberSpec

__all__ = [
    "DEFAULT_LEARNING_RATE",
    "Replacement",
    "choose_replacements",
    "copy_id",
    "copy_member",
    "learning_rate",
    "replacement_count",
]

DEFAULT_LEARNING_RATE = 3e-4  # a member whose hyperparameters name none


@dataclass(frozen=True)
class Replacement:
    """One PBT copy: `parent` is copied over `replaced`, at `learning_rate`; `position` is
    the pair's place in the ranking (0: the strongest over the weakest)."""

    position: int
    parent: str
    replaced: str
    learning_rate: float


def replacement_count(team_size: int, fraction: float) -> int:
    """How many of a team's weakest may be replaced: `fraction` of it rounded down, at least
    one, and never more than half (a source is never itself replaced)."""
    return min(max(1, math.floor(team_size * fraction)), team_size // 2)


def choose_replacements(
    ranking: Sequence[tuple[str, float]],
    learning_rates: Mapping[str, float],
    fraction: float,
    min_gap: float,
    perturb: Sequence[float],
    rng: np.random.Generator,
) -> list[Replacement]:
    """The copies one team makes, from its `ranking` (member, rating; best first) and each
    member's learning rate. One factor is drawn from `perturb` per copy, in ranking order;
    a pair within `min_gap` draws nothing."""
    replacements = []
    for position in range(replacement_count(len(ranking), fraction)):
        (parent, strong), (replaced, weak) = ranking[position], ranking[-1 - position]
        if strong - weak < min_gap:
            continue  # not clearly weaker: a copy would only lose diversity
        factor = float(rng.choice(perturb))
        replacements.append(
            Replacement(position, parent, replaced, learning_rates[parent] * factor)
        )
    return replacements


def learning_rate(spec: MemberSpec) -> float:
    """The learning rate a member was built with."""
    return float(spec.hyperparameters.get("learning_rate", DEFAULT_LEARNING_RATE))


def copy_id(parent: str, iteration: int, position: int) -> str:
    """`<original member>-pbt<iteration>.<position>`: a copy of a copy names the original."""
    return f"{parent.split('-pbt')[0]}-pbt{iteration}.{position}"


def copy_member(source: Agent, member_id: str, rate: float, envs: int, device: str) -> Agent:
    """A new member `member_id`: `source`'s spec, weights, optimizer state and replay, with
    learning rate `rate`, and `source` as its parent."""
    hyperparameters = {**source.spec.hyperparameters, "learning_rate": rate}
    spec = MemberSpec(
        **{
            **source.spec.to_dict(),
            "id": member_id,
            "hyperparameters": hyperparameters,
            "parent": source.id,
        }
    )
    copy = Agent(spec, envs, device)
    # A deep copy: Optimizer.load_state_dict keeps the tensors it is given, and a copy
    # sharing its source's Adam moments would move them as it learns (and a resumed league,
    # loading each from its own file, would not).
    state = deepcopy(source.state_dict(replay=True))
    state["spec"] = spec.to_dict()
    copy.load_state_dict(state)
    copy.set_learning_rate(rate)
    return copy

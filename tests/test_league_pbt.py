"""Population-based training's decision, checked against answers worked out by hand from the
rule: the n-th strongest copies over the n-th weakest, a share of the team at a time, only
with a lead of min_gap, one perturbation factor drawn per copy."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.league.pbt import Replacement, choose_replacements, copy_id, replacement_count

# Five aligners, best first; a's and b's learning rates are the only ones a copy can take.
RANKING = [("a", 1300.0), ("b", 1250.0), ("c", 1200.0), ("d", 1190.0), ("e", 1100.0)]
RATES = {"a": 1e-3, "b": 4e-4, "c": 3e-4, "d": 3e-4, "e": 3e-4}


@pytest.mark.parametrize(
    ("team_size", "fraction", "count"),
    [
        (5, 0.5, 2),  # floor(2.5) = 2, at most 5 // 2 = 2
        (6, 0.34, 2),  # floor(2.04) = 2
        (3, 0.1, 1),  # floor(0.3) = 0, but at least one
        (4, 0.9, 2),  # floor(3.6) = 3, but never more than half
        (1, 0.34, 0),  # a team of one has nobody to copy
    ],
)
def test_replacement_count_is_a_share_at_least_one_at_most_half(
    team_size: int, fraction: float, count: int
) -> None:
    assert replacement_count(team_size, fraction) == count


def test_the_strongest_copy_over_the_weakest_with_their_learning_rate_perturbed() -> None:
    # Both factors 2: whatever the draw, a copy learns twice as fast as its parent.
    replacements = choose_replacements(
        RANKING, RATES, 0.5, 50.0, (2.0, 2.0), np.random.default_rng(0)
    )
    # Two pairs: a (1300) over e (1100), lead 200; b (1250) over d (1190), lead 60 >= 50.
    assert replacements == [
        Replacement(position=0, parent="a", replaced="e", learning_rate=pytest.approx(2e-3)),
        Replacement(position=1, parent="b", replaced="d", learning_rate=pytest.approx(8e-4)),
    ]


def test_a_pair_within_min_gap_is_left_alone_and_draws_nothing() -> None:
    perturb = (0.5, 2.0)
    rng, twin = np.random.default_rng(3), np.random.default_rng(3)
    # min_gap 100: a over e (lead 200) copies; b over d (lead 60) does not.
    replacements = choose_replacements(RANKING, RATES, 0.5, 100.0, perturb, rng)
    factor = float(twin.choice(perturb))  # the one draw the one copy makes
    assert replacements == [
        Replacement(
            position=0, parent="a", replaced="e", learning_rate=pytest.approx(1e-3 * factor)
        )
    ]
    # Exactly one draw was made: the league's generator goes on where the twin does.
    assert rng.bit_generator.state == twin.bit_generator.state


def test_a_lead_of_exactly_min_gap_is_enough() -> None:
    ranking = [("x", 1250.0), ("y", 1200.0)]
    rates = {"x": 3e-4, "y": 3e-4}
    replacements = choose_replacements(
        ranking, rates, 0.34, 50.0, (1.25, 1.25), np.random.default_rng(1)
    )
    assert replacements == [Replacement(0, "x", "y", pytest.approx(3.75e-4))]
    assert (
        choose_replacements(ranking, rates, 0.34, 50.1, (1.25, 1.25), np.random.default_rng(1))
        == []
    )


def test_a_copy_is_named_after_the_original_member() -> None:
    assert copy_id("a-sac", 4, 0) == "a-sac-pbt4.0"
    assert copy_id("a-sac-pbt4.0", 8, 1) == "a-sac-pbt8.1"  # a copy of a copy

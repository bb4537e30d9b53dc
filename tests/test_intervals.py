"""alignrl/intervals.py: Wilson intervals of success counts, the interquartile mean and its
bootstrap interval."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.intervals import bootstrap_interval, iqm, success_interval, success_text, wilson


def test_wilson_matches_the_closed_form_and_holds_at_the_ends():
    low, high = wilson(30, 50)
    assert (round(low, 3), round(high, 3)) == (0.462, 0.724)
    assert wilson(0, 100)[0] == 0.0 and 0.0 < wilson(0, 100)[1] < 0.05
    assert wilson(0, 5)[0] == 0.0 and wilson(5, 5)[1] == 1.0  # exactly, not 3e-17
    assert wilson(100, 100)[1] == 1.0 and 0.95 < wilson(100, 100)[0] < 1.0
    # More alignments, a narrower interval around the same rate.
    assert np.diff(wilson(300, 500)) < np.diff(wilson(30, 50))


def test_wilson_covers_the_true_rate_about_95_percent_of_the_time():
    rng = np.random.default_rng(0)
    rate, n = 0.8, 100
    covered = 0
    for _ in range(2000):
        low, high = wilson(int(rng.binomial(n, rate)), n)
        covered += low <= rate <= high
    assert 0.92 <= covered / 2000 <= 0.98


def test_success_text_and_json_agree():
    assert success_text(30, 50) == "30/50 (46-72 %)"
    assert success_text(3830, 3840) == "3830/3840 (99.5-99.9 %)"  # whole percent: 100-100
    figure = success_interval(30, 50)
    assert figure["successes"] == 30 and figure["total"] == 50 and figure["rate"] == 0.6
    assert (figure["low"], figure["high"]) == wilson(30, 50)


@pytest.mark.parametrize("successes, total", [(5, 0), (-1, 10), (11, 10)])
def test_impossible_counts_are_refused(successes, total):
    with pytest.raises(ValueError):
        wilson(successes, total)


def test_iqm_ignores_the_outer_quarters():
    assert iqm([1, 2, 3, 4, 100, -100, 2.5, 3.5]) == pytest.approx(np.mean([2, 2.5, 3, 3.5]))
    with pytest.raises(ValueError):
        iqm([])
    with pytest.raises(ValueError):
        iqm([1.0, float("nan")])


def test_bootstrap_interval_is_seeded_and_holds_the_point():
    values = [0.61, 0.7, 0.74, 0.55, 0.8]
    first = bootstrap_interval(values, seed=3)
    assert first == bootstrap_interval(values, seed=3)
    assert first[0] <= iqm(values) <= first[1]
    assert first[0] >= min(values) and first[1] <= max(values)
    assert bootstrap_interval([0.5, 0.5, 0.5]) == (0.5, 0.5)

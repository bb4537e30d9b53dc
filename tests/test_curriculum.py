"""The curriculum raises the misalignment complexity on success and lowers it on collapse."""

from __future__ import annotations

import pytest

from alignrl.envs.curriculum import Curriculum


def test_level_rises_after_a_window_of_successes() -> None:
    curriculum = Curriculum(level=0.2, step=0.1, window=10, raise_at=0.8)
    for _ in range(9):
        assert curriculum.record(True) == 0.2  # the window is not full yet
    assert curriculum.record(True) == pytest.approx(0.3)
    assert curriculum.success_rate is None  # a new level is judged on its own episodes


def test_level_holds_between_the_thresholds() -> None:
    curriculum = Curriculum(level=0.5, window=10, raise_at=0.8, lower_at=0.3)
    for episode in range(50):
        curriculum.record(episode % 2 == 0)  # 50 % success
    assert curriculum.level == 0.5


def test_level_falls_on_a_collapse_but_not_below_the_minimum() -> None:
    curriculum = Curriculum(level=0.3, minimum=0.2, step=0.1, window=5, lower_at=0.3)
    for _ in range(5):
        curriculum.record(False)
    assert curriculum.level == pytest.approx(0.2)
    for _ in range(20):
        curriculum.record(False)
    assert curriculum.level == pytest.approx(0.2)


def test_level_stops_at_the_maximum() -> None:
    curriculum = Curriculum(level=0.9, step=0.25, window=2)
    for _ in range(10):
        curriculum.record(True)
    assert curriculum.level == 1.0


def test_state_is_saved_and_restored() -> None:
    curriculum = Curriculum(level=0.4, window=4)
    for outcome in (True, False, True):
        curriculum.record(outcome)
    restored = Curriculum(level=0.1, window=4)
    restored.load_state_dict(curriculum.state_dict())
    assert restored.level == 0.4
    assert restored.record(True) == curriculum.record(True)
    assert restored.state_dict() == curriculum.state_dict()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"level": 0.0},
        {"level": 1.5},
        {"step": 0.0},
        {"window": 0},
        {"raise_at": 0.2, "lower_at": 0.3},
    ],
)
def test_impossible_settings_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="curriculum"):
        Curriculum(**kwargs)


def test_a_saved_level_outside_the_range_is_refused() -> None:
    with pytest.raises(ValueError, match="outside"):
        Curriculum(level=0.5, minimum=0.5).load_state_dict({"level": 0.1, "recent": []})

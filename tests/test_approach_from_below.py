"""The task option `approach_from_below`: every setting a reading is taken at is reached from
below, so that backlash puts every reading on one branch of the focus curve."""

from __future__ import annotations

import numpy as np
import pytest
from test_stop_at_best import _hysteretic, _Recorder  # a column with 2 % backlash, no drift

from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task

MOVES = [0.5, 0.5, -0.5, -0.5, 0.3]  # up past focus, back down, up again (maximum steps)


def _walk(**options):
    """Each reading's setting, the column's backlash offset there (effective setting minus
    setting), the writes it took to get there; the episode."""
    task = TaskOptions(**options).apply(get_task("focus"))
    unit = _Recorder(_hysteretic())
    episodes = AlignmentEpisodes([unit], task, history=8)
    slot = np.array([0])
    episodes.begin(slot, [21])
    episodes.misalign(slot, np.array([0.0]))
    steps = []
    for move in MOVES:
        before = len(unit.writes)
        episodes.step(slot, np.array([[move, -1.0]]))
        setting = float(episodes.setting[0, 0])
        offset = unit.focus_error() + unit.optimum()["defocus"] - setting
        steps.append((setting, offset, unit.writes[before:]))
    return steps, episodes


def test_every_reading_is_taken_on_one_branch_of_the_backlash() -> None:
    steps, episodes = _walk(approach_from_below=True)
    offsets = [offset for _, offset, _ in steps]
    assert np.ptp(offsets) == pytest.approx(0.0, abs=1e-9)  # the up branch, every reading
    width = episodes.high[0, 0] - episodes.low[0, 0]
    for (setting, _, writes), move in zip(steps, MOVES, strict=True):
        if move < 0:  # down: past the target by the overshoot (2 %), then up to it
            assert writes == pytest.approx([setting - 0.02 * width, setting])
        else:
            assert writes == pytest.approx([setting])
    assert episodes.acquisitions[0] == 1 + len(MOVES)  # the way there acquires nothing
    # Without the option the moves down read the other branch: 2 h W away.
    plain, _ = _walk()
    offsets = [offset for _, offset, _ in plain]
    assert np.ptp(offsets) == pytest.approx(2 * 0.02 * width, rel=1e-6)
    assert [setting for setting, _, _ in plain] == pytest.approx([s for s, _, _ in steps])


def test_the_approach_stays_inside_the_interval() -> None:
    """An overshoot larger than the room below the target stops at the interval's bound."""
    steps, episodes = _walk(approach_from_below=True, backlash_overshoot=0.5)
    low, high = episodes.low[0, 0], episodes.high[0, 0]
    for setting, _, writes in steps:
        assert all(low <= value <= high for value in writes)
        assert writes[-1] == pytest.approx(setting)
    down = [writes for (_, _, writes), move in zip(steps, MOVES, strict=True) if move < 0]
    assert all(w[0] == pytest.approx(max(low, w[1] - 0.5 * (high - low))) for w in down)

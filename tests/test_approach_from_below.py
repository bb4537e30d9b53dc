"""The task option `approach_from_below`: every setting a reading is taken at is reached from
below, so that backlash puts every reading on one branch of the focus curve."""

from __future__ import annotations

import numpy as np
import pytest
from test_stop_at_best import _hysteretic, _Recorder  # a column with 2 % backlash, no drift

from alignrl.apparatus.backlash import arrival
from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task
from alignrl.evaluation.controllers import approach_from_below

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


# --- the one mechanism: alignrl/apparatus/backlash.py, `arrival` ------------------------------

LOW, HIGH = np.array([0.0]), np.array([10.0])


@pytest.mark.parametrize(
    ("start", "target", "arrived", "writes"),
    [
        (2.0, 5.0, None, [[5.0]]),  # up from below: one write
        (8.0, 5.0, None, [[4.0], [5.0]]),  # down: past the target underneath, then up
        (np.nan, 5.0, None, [[5.0]]),  # where it stands is not known: one write
        (5.0, 5.0, None, [[5.0]]),  # at the target, arrival unknown: left as found
        (5.0, 5.0, 1.0, [[5.0]]),  # at the target from below already
        (5.0, 5.0, -1.0, [[4.0], [5.0]]),  # at the target from above: past and back
        (3.0, 0.5, None, [[0.0], [0.5]]),  # the pass kept inside the interval
        (3.0, 0.0, -1.0, [[0.0]]),  # at the lower bound: no pass onto the target itself
    ],
)
def test_arrival_writes(start, target, arrived, writes) -> None:
    got = arrival(np.array([target]), np.array([start]), np.ones(1), 1.0, LOW, HIGH, arrived)
    assert [write.tolist() for write in got] == writes


def test_arrival_from_above_and_either_side() -> None:
    target, start = np.array([5.0, 5.0]), np.array([2.0, 2.0])
    got = arrival(target, start, np.array([-1.0, 0.0]), 1.0, LOW, HIGH)
    assert [write.tolist() for write in got] == [[6.0, 5.0], [5.0, 5.0]]  # only the first
    none = arrival(target, start, np.array([-1.0, 0.0]), 0.0, LOW, HIGH)  # no overshoot
    assert [write.tolist() for write in none] == [[5.0, 5.0]]


def test_a_controller_takes_the_knob_as_arrived_from_above() -> None:
    """The classical controllers cannot know how the knob got where it is: at the target they
    pass underneath and come back, as they always did."""

    class Column:
        def __init__(self, at: float) -> None:
            self.knobs = {"defocus": (0.0, 10.0)}
            self.at, self.writes = at, []

        def read(self):
            return {"defocus": self.at}

        def write(self, values):
            self.writes.append(values["defocus"])
            self.at = values["defocus"]

    for at, target, writes in [(5.0, 5.0, [4.0, 5.0]), (2.0, 5.0, [5.0]), (0.0, 0.0, [0.0])]:
        column = Column(at)
        approach_from_below(column, "defocus", target, 1.0)
        assert column.writes == writes

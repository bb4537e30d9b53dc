"""The task option `final_move`: the stopping action's knob components move the knobs one last
time, without the floor and without an acquisition, so that a policy ends its episode between
its readings; refused with stop_at_best; through a driver that refuses the write."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus.base import ApparatusError
from alignrl.apparatus.registry import make_apparatus
from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task


def _episode(task, unit=None):
    unit = unit or make_apparatus("family:focus", {"analytic": True}, seed=3)
    episodes = AlignmentEpisodes([unit], task, history=8)
    slot = np.array([0])
    episodes.begin(slot, [21])
    episodes.misalign(slot, np.array([0.0]))
    return episodes, slot, unit


def _task(**options):
    return TaskOptions(final_move=True, action_power=2.0, move_floor=0.02, **options).apply(
        get_task("focus")
    )


def test_a_stop_moves_by_its_knob_action_without_the_floor_or_an_image() -> None:
    episodes, slot, unit = _episode(_task())
    start, span = float(episodes.setting[0, 0]), float(episodes.span[0, 0])
    max_step = float(episodes.max_step[0, 0])
    acquired = int(episodes.acquisitions[0])
    before = episodes.history.copy()
    _reward, done = episodes.step(slot, np.array([[-0.1, 1.0]]))
    assert done[0]
    # -0.1 squared x the maximum step: well under the 2 % floor every probe move goes.
    expected = start - 0.01 * max_step
    assert 0.01 * max_step < 0.02 * span
    assert episodes.setting[0, 0] == pytest.approx(expected)
    assert unit.read()["defocus"] == pytest.approx(expected)
    assert episodes.acquisitions[0] == acquired  # no image on the way
    np.testing.assert_array_equal(episodes.history, before)  # the history is over
    # Without the option the same stop leaves the knob where it was.
    plain, slot, plain_unit = _episode(get_task("focus"))
    plain.step(slot, np.array([[-0.1, 1.0]]))
    assert plain.setting[0, 0] == pytest.approx(start)
    assert plain_unit.read()["defocus"] == pytest.approx(start)


def test_the_verification_is_taken_where_the_final_move_went() -> None:
    episodes, slot, _ = _episode(_task(verify_final=True))
    acquired = int(episodes.acquisitions[0])
    optimum, setting = float(episodes.aligned[0, 0]), float(episodes.setting[0, 0])
    max_step = float(episodes.max_step[0, 0])
    move = optimum - setting
    if abs(move) > max_step:  # bring the column within one move first
        episodes.setting[0, 0] = optimum - 0.5 * max_step
        move = 0.5 * max_step
    action = np.sign(move) * np.sqrt(abs(move) / max_step)
    _reward, done = episodes.step(slot, np.array([[action, 1.0]]))
    assert done[0] and episodes.acquisitions[0] == acquired + 1  # the verification alone
    assert episodes.setting[0, 0] == pytest.approx(optimum, abs=1e-6 * episodes.span[0, 0])
    assert episodes.successes()[0]  # judged on the image at the final setting


def test_a_final_move_past_a_bound_is_clipped_and_penalised() -> None:
    rewards = {}
    for penalty in (0.0, 0.7):
        episodes, slot, _ = _episode(_task(out_of_bounds_penalty=penalty))
        episodes.setting[0, 0] = episodes.low[0, 0] + 0.01 * episodes.span[0, 0]
        reward, done = episodes.step(slot, np.array([[-1.0, 1.0]]))
        assert done[0]
        assert episodes.setting[0, 0] == pytest.approx(episodes.low[0, 0])
        assert episodes.info[0].out_of_bounds == 1
        rewards[penalty] = float(reward[0])
    assert rewards[0.7] == pytest.approx(rewards[0.0] - 0.7)
    # A final move inside the interval pays no penalty.
    inside, slot, _ = _episode(_task(out_of_bounds_penalty=0.7))
    inside.setting[0, 0] = inside.low[0, 0] + 0.5 * inside.span[0, 0]
    inside.step(slot, np.array([[-0.1, 1.0]]))
    assert inside.info[0].out_of_bounds == 0


class _Refusing:
    """A focus column whose driver refuses every write after the first `allowed`."""

    def __init__(self, unit, allowed):
        self._unit, self._allowed = unit, allowed

    def __getattr__(self, name):
        return getattr(self._unit, name)

    def write(self, settings):
        if self._allowed <= 0:
            raise ApparatusError("the lens supply refused the write")
        self._allowed -= 1
        self._unit.write(settings)


def test_a_refused_final_move_ends_the_episode_with_the_error_on_record() -> None:
    base = make_apparatus("family:focus", {"analytic": True}, seed=3)
    episodes, slot, _ = _episode(_task(), _Refusing(base, allowed=1))
    setting = float(episodes.setting[0, 0])
    reward, done = episodes.step(slot, np.array([[0.5, 1.0]]))
    assert done[0] and np.isfinite(reward[0])
    assert "refused" in episodes.info[0].last_error
    assert episodes.setting[0, 0] == pytest.approx(setting)  # where the column still is


def test_final_move_and_stop_at_best_are_refused_together() -> None:
    with pytest.raises(ValueError, match="final_move"):
        TaskOptions(final_move=True, stop_at_best=True).apply(get_task("focus"))


def test_a_final_move_reach_scales_the_last_move_alone() -> None:
    """final_move_reach 0.2: the stopping move is a fifth of what the same action asks for
    without it; probes keep their reach."""
    episodes, slot, _ = _episode(_task(final_move_reach=0.2))
    start, max_step = float(episodes.setting[0, 0]), float(episodes.max_step[0, 0])
    span = float(episodes.span[0, 0])
    episodes.step(slot, np.array([[0.5, -1.0]]))  # a probe: 0.25 x max_step and the floor
    probed = float(episodes.setting[0, 0])
    assert probed == pytest.approx(start + 0.25 * max_step + 0.02 * span)
    episodes.step(slot, np.array([[-0.5, 1.0]]))
    assert episodes.setting[0, 0] == pytest.approx(probed - 0.2 * 0.25 * max_step)


def test_a_last_move_from_the_fit_starts_at_the_bracketed_optimum() -> None:
    """finish_at_fit with final_move: a stopping action of 0 ends at the fit's optimum of
    readings that bracket it; before a fit exists, at the present setting."""
    task = _task(finish_at_fit=True)
    episodes, slot, _ = _episode(task)
    assert episodes.stop_origins(slot)[0, 0] == episodes.setting[0, 0]  # one reading: no fit
    optimum, span = float(episodes.aligned[0, 0]), float(episodes.span[0, 0])
    for offset in (-0.06, 0.05, -0.01):  # readings on both sides of the optimum
        move = optimum + offset * span - float(episodes.setting[0, 0])
        action = np.sign(move) * np.sqrt(max(abs(move) - 0.02 * span, 0) / episodes.max_step[0, 0])
        episodes.step(slot, np.array([[float(action[()]), -1.0]]))
    origin = float(episodes.stop_origins(slot)[0, 0])
    assert origin != float(episodes.setting[0, 0])
    assert abs(origin - optimum) < 0.02 * span  # the fit lands near the column's optimum
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert episodes.setting[0, 0] == pytest.approx(origin)


@pytest.mark.parametrize("options", [{"final_move_reach": 0.0}, {"final_move_reach": 1.5}])
def test_a_final_move_reach_outside_its_range_is_refused(options) -> None:
    with pytest.raises(ValueError, match="final_move_reach"):
        _task(**options)
    with pytest.raises(ValueError, match="final_move_reach"):
        TaskOptions(final_move_reach=0.5).apply(get_task("focus"))  # without final_move

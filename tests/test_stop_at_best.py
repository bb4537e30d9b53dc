"""The task option `stop_at_best`: an episode ends where its narrowest reading was taken, as a
classical autofocus does, in training (with and without the verification image), in an
evaluation session and through a driver that refuses the write back."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from alignrl.apparatus.base import ApparatusError
from alignrl.apparatus.registry import make_apparatus
from alignrl.config import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task

WALK = [0.5, 0.5, 0.5, 0.5]  # four moves of half a maximum step upwards, then stop


def _episode(task, unit=None):
    unit = unit or make_apparatus("family:focus", {"analytic": True}, seed=3)
    episodes = AlignmentEpisodes([unit], task, history=8)
    slot = np.array([0])
    episodes.begin(slot, [21])
    # Start below the optimum by about one maximum step: the walk passes focus and goes on.
    optimum = episodes.aligned[0, 0]
    span = episodes.span[0, 0]
    episodes.misalign(slot, np.array([0.0]))
    episodes.setting[0, 0] = optimum - 0.2 * span
    return episodes, slot, unit


def _walk(episodes, slot):
    readings = []
    for change in WALK:
        episodes.step(slot, np.array([[change, -1.0]]))
        readings.append((float(episodes.setting[0, 0]), float(episodes.width[0])))
    reward, done = episodes.step(slot, np.array([[0.0, 1.0]]))
    assert done[0]
    return readings, float(reward[0])


def test_an_episode_that_walks_past_focus_ends_at_its_narrowest_reading() -> None:
    task = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    episodes, slot, unit = _episode(task)
    readings, _ = _walk(episodes, slot)
    settings, widths = zip(*readings, strict=True)
    best = int(np.argmin(widths))
    assert best < len(WALK) - 1, "the walk must go past its narrowest reading"
    assert episodes.setting[0, 0] == pytest.approx(settings[best])
    assert unit.read()["defocus"] == pytest.approx(settings[best])  # written, not only noted
    assert episodes.width[0] == pytest.approx(widths[best])
    assert episodes.acquisitions[0] == 1 + len(WALK)  # the way back acquires nothing
    # Without the option the same walk ends where it stopped, wider.
    plain, slot, _ = _episode(get_task("focus"))
    _walk(plain, slot)
    assert plain.setting[0, 0] == pytest.approx(settings[-1])
    assert plain.width[0] > episodes.width[0]


def test_the_verification_image_is_taken_at_the_narrowest_setting() -> None:
    task = TaskOptions(stop_at_best=True, verify_final=True).apply(get_task("focus"))
    episodes, slot, _ = _episode(task)
    readings, reward = _walk(episodes, slot)
    settings, widths = zip(*readings, strict=True)
    assert episodes.setting[0, 0] == pytest.approx(settings[int(np.argmin(widths))])
    assert episodes.acquisitions[0] == 1 + len(WALK) + 1  # the verification image
    # The final reward is paid on the verification, a fresh reading at the best setting.
    assert episodes.width[0] != pytest.approx(min(widths), rel=1e-12)
    assert episodes.width[0] == pytest.approx(min(widths), rel=0.2)
    before = float(episodes.cost_before[0])
    assert reward == pytest.approx(before - float(episodes.width[0]))


class _RefusesWrites:
    """A column whose driver refuses every write after the first few."""

    def __init__(self, unit, allowed: int) -> None:
        self._unit, self._allowed = unit, allowed

    def write(self, values):
        if self._allowed <= 0:
            raise ApparatusError("the driver refused the write")
        self._allowed -= 1
        return self._unit.write(values)

    def __getattr__(self, name):
        return getattr(self._unit, name)


def test_a_refused_write_back_leaves_the_last_reading_and_says_why() -> None:
    task = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    inner = make_apparatus("family:focus", {"analytic": True}, seed=3)
    unit = _RefusesWrites(inner, allowed=1 + len(WALK))  # the start and the walk, not the way back
    episodes, slot, _ = _episode(task, unit)
    readings, _ = _walk(episodes, slot)
    assert episodes.setting[0, 0] == pytest.approx(readings[-1][0])
    assert episodes.width[0] == pytest.approx(readings[-1][1])
    assert "refused the write" in episodes.info[0].last_error


def test_only_a_width_task_may_end_at_its_best() -> None:
    with pytest.raises(ValueError, match="stop_at_best returns to the narrowest reading"):
        dataclasses.replace(get_task("stigmation"), stop_at_best=True)


def test_a_policy_in_a_session_leaves_the_column_at_its_narrowest_reading() -> None:
    """PolicyController (evaluation sessions, `alignrl align`): the column is left where the
    narrowest reading was taken, which the session's own verification then reads."""
    from alignrl.evaluation.controllers import PolicyController

    task = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    unit = make_apparatus("family:focus", {"analytic": True}, seed=3)
    unit.reset(21)
    low, high = unit.knobs["defocus"]
    unit.write({"defocus": unit.optimum()["defocus"] - 0.2 * (high - low)})
    actions = iter([[0.5, -1.0]] * 4 + [[0.0, 1.0]])
    seen: list[tuple[float, float]] = []

    def act(history: np.ndarray) -> np.ndarray:
        seen.append((unit.read()["defocus"], float(history[-1, 2])))
        return np.array(next(actions))

    controller = PolicyController(name="walk", act=act, task=task, history=8)
    controller.align_task(unit, task, budget=20)
    settings, quality = zip(*seen, strict=True)
    assert unit.read()["defocus"] == pytest.approx(settings[int(np.argmin(quality))])
    assert settings[int(np.argmin(quality))] != pytest.approx(settings[-1])

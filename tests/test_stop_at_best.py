"""The task option `stop_at_best`: an episode ends where its narrowest reading was taken, as a
classical autofocus does, in training (with and without the verification image), in an
evaluation session and through a driver that refuses the write back."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus.base import ApparatusError
from alignrl.apparatus.registry import make_apparatus
from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.endings import with_ending
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
        with_ending(get_task("stigmation"), stop_at_best=True)


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


def _hysteretic(seed: int = 3):
    """An analytic family column with strong backlash (2 % of the interval) and no drift."""
    args = {"analytic": True, "hysteresis_fraction": 0.02, "drift_fraction": 0.0}
    return make_apparatus("family:focus", args, seed=seed)


def _walk_with_errors(task):
    """The walk past focus on a backlashed column: each reading's focus error (the effective
    setting against the optimum), and the column's error once the episode has ended."""
    episodes, slot, unit = _episode(task, _hysteretic())
    errors = []
    for change in WALK:
        episodes.step(slot, np.array([[change, -1.0]]))
        errors.append((float(episodes.width[0]), unit.focus_error()))
    episodes.step(slot, np.array([[0.0, 1.0]]))
    narrowest_error = min(errors)[1]
    return episodes, unit, narrowest_error


def test_the_way_back_takes_up_backlash_as_the_narrowest_reading_was_approached() -> None:
    """The walk went up past focus; the way back comes down, which on a backlashed column
    would focus 2 h W away from where the narrowest reading did. Going past the setting first
    and arriving from below, as the reading did, restores its focus error exactly."""
    task = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    episodes, unit, narrowest_error = _walk_with_errors(task)
    assert unit.focus_error() == pytest.approx(narrowest_error, abs=1e-9)
    assert episodes.setting[0, 0] == pytest.approx(episodes.ends.narrowest(0).setting[0])
    # Without the overshoot the same setting is reached from above: off by the backlash.
    direct = with_ending(task, backlash_overshoot=0.0)
    _, plain, plain_error = _walk_with_errors(direct)
    lag = 2 * plain.draw.hysteresis_fraction * plain.draw.width
    assert plain.focus_error() - plain_error == pytest.approx(lag, rel=1e-6)


class _Recorder:
    """A column that keeps every value written to it."""

    def __init__(self, unit) -> None:
        self._unit, self.writes = unit, []

    def write(self, values):
        self.writes.append(float(values["defocus"]))
        return self._unit.write(values)

    def __getattr__(self, name):
        return getattr(self._unit, name)


def test_the_overshoot_stays_inside_the_interval_and_costs_no_acquisition() -> None:
    task = TaskOptions(stop_at_best=True, backlash_overshoot=0.5).apply(get_task("focus"))
    unit = _Recorder(_hysteretic())
    episodes, slot, _ = _episode(task, unit)
    _walk(episodes, slot)
    low, high = episodes.low[0, 0], episodes.high[0, 0]
    best = episodes.ends.narrowest(0).setting[0]
    past, back = unit.writes[-2:]
    assert past == pytest.approx(max(low, best - 0.5 * (high - low)))  # clipped at the bound
    assert back == pytest.approx(best)
    assert all(low <= value <= high for value in unit.writes)
    assert episodes.acquisitions[0] == 1 + len(WALK)


def test_a_way_back_from_the_side_of_the_reading_is_one_write() -> None:
    """Up past focus, down onto it (the narrowest reading, approached from above), up again:
    the way back comes down, from the reading's side: no overshoot, one write."""
    task = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    unit = _Recorder(_hysteretic())
    episodes, slot, _ = _episode(task, unit)
    readings = []
    for change in [0.9, 0.9, -0.5, -0.5, 0.5]:
        episodes.step(slot, np.array([[change, -1.0]]))
        readings.append((float(episodes.width[0]), float(episodes.setting[0, 0])))
    before = len(unit.writes)
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert int(np.argmin([width for width, _ in readings])) == 3, "narrowest on the way down"
    best = readings[3][1]
    assert unit.writes[before - 1] > best, "the walk must end above its narrowest reading"
    assert unit.writes[before:] == [pytest.approx(best)]


def test_a_fit_of_readings_on_both_flanks_places_the_optimum_between_them() -> None:
    from alignrl.envs.fit_features import bracketed_optimum

    settings = np.array([-30.0, -12.0, 4.0, 21.0])  # volts; focus at 2.5 V
    widths = np.sqrt(3.0**2 + (0.8 * (settings - 2.5)) ** 2)  # an exact hyperbola, px
    assert bracketed_optimum(settings, widths) == pytest.approx(2.5, abs=1e-9)
    assert bracketed_optimum(settings * 1e3, widths * 7.0) == pytest.approx(2500.0, rel=1e-9)
    # Readings on one flank only: the fit would extrapolate, so it says nothing.
    one_flank = np.array([4.0, 10.0, 21.0])
    assert bracketed_optimum(one_flank, np.sqrt(3.0**2 + (0.8 * (one_flank - 2.5)) ** 2)) is None
    assert bracketed_optimum(settings[:2], widths[:2]) is None  # two readings fit nothing


def _clean(seed: int = 3):
    """A noise-free analytic column on an exact hyperbola, without backlash or drift."""
    args = {
        "analytic": True,
        "reading_noise_rel": 0.0,
        "reading_noise_px": 0.0,
        "specimen_rel": 0.0,
        "curve_power": 2.0,
        "flat_fraction": 0.0,
        "asymmetry": 1.0,
        "hysteresis_fraction": 0.0,
        "drift_fraction": 0.0,
        "saturation_px": 80.0,
    }
    return make_apparatus("family:focus", args, seed=seed)


def test_an_episode_that_finishes_at_its_fit_ends_nearer_focus_than_its_narrowest() -> None:
    task = TaskOptions(stop_at_best=True, finish_at_fit=True).apply(get_task("focus"))
    episodes, slot, unit = _episode(task, _clean())
    errors = []
    for change in WALK:
        episodes.step(slot, np.array([[change, -1.0]]))
        errors.append((float(episodes.width[0]), abs(unit.focus_error())))
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert episodes.info[0].ended_at_fit
    narrowest_error = min(errors)[1]
    assert narrowest_error > 0.01 * episodes.span[0, 0]  # the walk's readings missed focus
    assert abs(unit.focus_error()) < 0.02 * narrowest_error  # the fit found it
    assert episodes.acquisitions[0] == 1 + len(WALK)  # no reading is taken there
    # Without the option the same walk ends at its narrowest reading.
    narrowest_only = TaskOptions(stop_at_best=True).apply(get_task("focus"))
    plain, slot, plain_unit = _episode(narrowest_only, _clean())
    _walk(plain, slot)
    assert not plain.info[0].ended_at_fit
    assert abs(plain_unit.focus_error()) == pytest.approx(narrowest_error)


def test_finishing_at_a_fit_needs_the_way_back_and_one_knob() -> None:
    with pytest.raises(ValueError, match="finish_at_fit ends the way back"):
        TaskOptions(finish_at_fit=True).apply(get_task("focus"))

"""The focus-curve fit features (alignrl/envs/fit_features.py, Task.fit_features): where a
local fit of the window's readings puts the optimum and the floor, unit-free, for
single-knob tasks only."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from alignrl.apparatus.registry import make_apparatus
from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes, feature_layout
from alignrl.envs.fit_features import FIT_FLOOR_MIN, FIT_STEP_LIMIT, fit_features
from alignrl.envs.task import get_task


def _window(settings: list[float], widths: list[float], reference: float, rows: int = 8):
    """History columns of one window: oldest rows padded (unmeasured), settings in [-1, 1]."""
    pad = rows - len(settings)
    knobs = np.array([0.0] * pad + settings)[None]
    quality = np.array([0.0] * pad + list(np.log(np.array(widths) / reference)))[None]
    measured = np.array([0.0] * pad + [1.0] * len(settings))[None]
    return knobs, quality, measured


def _hyperbola(x: np.ndarray, optimum: float, floor: float, gain: float) -> np.ndarray:
    return np.sqrt(floor**2 + (gain * (x - optimum)) ** 2)


def test_readings_on_a_hyperbola_place_its_optimum_and_floor() -> None:
    settings = [-0.5, 0.1, 0.35, 0.2]
    widths = list(_hyperbola(np.array(settings), optimum=0.27, floor=3.0, gain=40.0))
    step = 0.5  # one maximum step is a quarter of the interval: 0.5 in [-1, 1] units
    features = fit_features(*_window(settings, widths, reference=widths[0]), np.array([step]))
    valid, to_optimum, floor = features[0]
    assert valid == 1.0
    # The first reading is far (over 3x the narrowest) and left out; the other three fit.
    assert to_optimum == pytest.approx((0.27 - 0.2) / step, abs=1e-5)
    assert floor == pytest.approx(np.log(3.0 / widths[-1]), abs=1e-5)
    # The same readings in other pixels (x 2.5) and against another reference: the same.
    scaled = fit_features(
        *_window(settings, [2.5 * w for w in widths], reference=7.0), np.array([step])
    )
    np.testing.assert_allclose(scaled, features, atol=1e-5)


def test_an_optimum_far_off_is_clipped_and_a_v_shape_has_the_lowest_floor() -> None:
    settings = [0.0, 0.01, 0.02]
    widths = list(_hyperbola(np.array(settings), optimum=0.9, floor=2.0, gain=10.0))
    features = fit_features(*_window(settings, widths, 1.0), np.array([0.1]))[0]
    assert features[0] == 1.0 and features[1] == FIT_STEP_LIMIT
    # Readings whose parabola in w^2 dips below zero (sharper than any hyperbola, a V): the
    # floor feature is at its least.
    v_shape = np.array([0.62, 0.66, 0.7])
    widths = list(np.sqrt(100.0 * (v_shape - 0.5) ** 2 - 1.0))
    features = fit_features(*_window(list(v_shape), widths, 1.0), np.array([0.5]))[0]
    assert features[0] == 1.0 and features[2] == FIT_FLOOR_MIN
    assert features[1] == pytest.approx((0.5 - 0.7) / 0.5, abs=1e-5)


@pytest.mark.parametrize(
    ("settings", "widths", "measured_last"),
    [
        ([0.1, 0.2], [5.0, 4.0], True),  # two readings: no parabola
        ([0.1, 0.2, 0.2], [5.0, 4.0, 4.1], True),  # three readings at two settings
        ([0.1, 0.2, 0.3], [4.0, 5.0, 4.0], True),  # a parabola that opens downwards
        ([0.1, 0.2, 0.3, 0.25], [5.0, 4.0, 5.0, 4.2], False),  # the newest reading failed
    ],
)
def test_no_fit_where_the_readings_place_no_optimum(
    settings: list[float], widths: list[float], measured_last: bool
) -> None:
    knobs, quality, measured = _window(settings, widths, 1.0)
    measured[0, -1] = float(measured_last)
    np.testing.assert_array_equal(
        fit_features(knobs, quality, measured, np.array([0.5])), np.zeros((1, 3))
    )


def test_the_features_ride_in_the_newest_row_and_a_fit_step_reaches_focus() -> None:
    task = dataclasses.replace(get_task("focus"), quality_reference="first", fit_features=True)
    assert task.extra_features == 3
    assert dataclasses.replace(task, fit_features=False).extra_features == 0
    layout = feature_layout(1, 3)
    column = make_apparatus("instrument:val-mid", {"analytic": True})
    episodes = AlignmentEpisodes([column], task, history=10)
    slot = np.array([0])
    episodes.begin(slot, [4])
    episodes.misalign(slot, np.array([[0.0]]))
    # Three readings near focus, then where the fit says: within the spec.
    for offset in (0.3, -0.2, 0.1):
        target = (episodes.aligned[0, 0] - episodes.setting[0, 0]) / episodes.max_step[0, 0]
        episodes.step(slot, np.array([[target + offset, -1.0]]))
    features = episodes.observation(0)[-1, layout["extras"]]
    assert features[0] == 1.0
    before = episodes.width[0]
    episodes.step(slot, np.array([[features[1], -1.0]]))
    assert episodes.successes()[0] and episodes.width[0] < before


def test_a_wider_window_fits_the_flanks_of_a_steep_curve() -> None:
    # The narrowest reading 2.3 px; the others 5.2, 7.5 and 16.9 px: one within 3x, two in 6x.
    settings = [0.30, 0.36, 0.33, 0.315]
    widths = list(_hyperbola(np.array(settings), optimum=0.318, floor=2.0, gain=400.0))
    assert max(widths[:2]) / min(widths) > 3.0
    window = _window(settings, widths, reference=widths[0])
    assert fit_features(*window, np.array([0.5]))[0, 0] == 0.0  # two readings within 3x
    wide = fit_features(*window, np.array([0.5]), window=6.0)[0]
    assert wide[0] == 1.0 and wide[1] == pytest.approx((0.318 - 0.315) / 0.5, abs=1e-4)


def test_fit_features_are_a_single_knob_option() -> None:
    assert TaskOptions(fit_features=True).apply(get_task("focus")).fit_features
    assert TaskOptions(fit_window=6.0).apply(get_task("focus")).fit_window == 6.0
    with pytest.raises(ValueError, match="greater than 1"):
        TaskOptions(fit_window=1.0)
    with pytest.raises(ValueError, match="fit_features fits a focus curve along one knob"):
        TaskOptions(fit_features=True).apply(get_task("stigmation"))

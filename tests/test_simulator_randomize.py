"""Varied replay (`randomize`): each scenario's column is the recorded one with its optimum
shifted, its focus curve steeper or flatter and its edge widths scaled, drawn per reset and
reproducible by seed; without it the recording replays as it did."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.simulator import ScenarioSimulator, measure_batch
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task
from tests.test_simulator import KNOB, focus_width, make_record, write_file

WIDE = {"shift_v": 20.0, "gain": [0.7, 1.8], "width": [0.8, 1.6]}


@pytest.fixture
def focus_rows(tmp_path: Path) -> Path:
    """Twenty Gaussian-probe focus curves, optima 35..64 V, measurable over [0, 100]."""
    voltages = np.arange(0.0, 100.5, 0.5)
    rows = [make_record(i, voltages, focus_width(voltages, 35.0 + 1.5 * i)) for i in range(20)]
    return write_file(tmp_path / "focus.csv", rows)


def test_without_randomize_every_factor_is_one(focus_rows: Path) -> None:
    sim = ScenarioSimulator(focus_rows, noise=0.02)
    sim.reset(3)
    assert sim.randomize is None
    assert sim.optimum()[KNOB] == float(sim.optima[sim.row])
    assert sim.recorded_voltage(41.25) == 41.25 and sim.width_factor == 1.0


def test_a_width_factor_alone_scales_every_reading_and_keeps_the_noise(focus_rows: Path) -> None:
    plain = ScenarioSimulator(focus_rows, noise=0.05)
    wider = ScenarioSimulator(focus_rows, noise=0.05, randomize={"width": [1.5, 1.5]})
    for seed in (0, 7, 99):
        plain.reset(seed)
        wider.reset(seed)
        assert wider.row == plain.row and wider.optimum() == plain.optimum()
        assert wider.best_quality() == pytest.approx(1.5 * plain.best_quality(), rel=1e-12)
        for voltage in (12.0, 40.0, 63.5):
            plain.write({KNOB: voltage})
            wider.write({KNOB: voltage})
            # The same noise draw, 1.5 x as wide: the variation has its own random stream.
            assert wider.measure() == pytest.approx(1.5 * plain.measure(), rel=1e-12)


def test_the_varied_curve_is_the_recorded_one_shifted_stretched_and_scaled(
    focus_rows: Path,
) -> None:
    sim = ScenarioSimulator(focus_rows, randomize=WIDE)
    shifts, gains, scales = [], [], []
    for seed in range(200):
        sim.reset(seed)
        recorded = float(sim.optima[sim.row])
        optimum = sim.optimum()[KNOB]
        shift, gain, scale = optimum - recorded, sim.steepness, sim.width_factor
        shifts.append(shift)
        gains.append(gain)
        scales.append(scale)
        assert 5.0 <= optimum <= 95.0  # kept inside the interval, with a margin
        assert sim.best_quality() == pytest.approx(scale * focus_width(recorded, recorded), 1e-9)
        for offset in (-6.0, -1.0, 2.5, 9.0):
            setting = optimum + offset
            reading = recorded + gain * offset  # where the recorded curve is read
            if not 0 <= setting <= 100 or not 0 <= reading <= 100:
                continue
            sim.write({KNOB: setting})
            expected = scale * float(sim.query(np.array([sim.row]), np.array([reading]))[0])
            assert sim.measure() == pytest.approx(expected, rel=1e-12)
            # Symmetric about the new optimum, as the recorded curve is about its own.
            assert expected == pytest.approx(scale * focus_width(reading, recorded), rel=2e-3)
    assert min(shifts) < -15 and max(shifts) > 15
    assert 0.7 <= min(gains) < 0.8 and 1.6 < max(gains) <= 1.8
    assert 0.8 <= min(scales) < 0.9 and 1.45 < max(scales) <= 1.6


def test_variation_is_reproducible_by_seed(focus_rows: Path) -> None:
    first = ScenarioSimulator(focus_rows, noise=0.02, randomize=WIDE)
    second = ScenarioSimulator(focus_rows, noise=0.02, randomize=WIDE)
    for seed in (0, 1, 31):
        first.reset(seed)
        second.reset(seed)
        assert first.optimum() == second.optimum()
        assert (first.steepness, first.width_factor) == (second.steepness, second.width_factor)
        first.write({KNOB: 44.0})
        second.write({KNOB: 44.0})
        assert first.measure() == second.measure()
    first.reset(1)
    second.reset(2)
    assert first.optimum() != second.optimum() or first.steepness != second.steepness


def test_a_steeper_column_loses_its_edges_closer_to_focus(tmp_path: Path) -> None:
    voltages = np.arange(20.0, 80.5, 1.0)  # measurable 30 V either side of 50 V
    path = write_file(tmp_path / "span.csv", [make_record(0, voltages, focus_width(voltages, 50))])
    sim = ScenarioSimulator(path, randomize={"gain": [2.0, 2.0]})
    sim.reset(0)
    optimum = sim.optimum()[KNOB]
    sim.write({KNOB: optimum + 14.0})  # reads 28 V off the recorded focus: still edges
    assert np.isfinite(sim.measure())
    sim.write({KNOB: optimum + 16.0})  # 32 V off: beyond the recorded span
    with pytest.raises(NoEdgesError, match="outside the span"):
        sim.measure()


def test_batched_measurement_equals_one_by_one(focus_rows: Path) -> None:
    def units() -> list[ScenarioSimulator]:
        sims = [ScenarioSimulator(focus_rows, noise=0.03, randomize=WIDE) for _ in range(6)]
        for seed, sim in enumerate(sims):
            sim.reset(100 + seed)
        return sims

    settings = np.array([10.0, 33.3, 50.0, 61.0, 72.5, 90.0])
    batched = measure_batch(units(), settings)
    single = []
    for sim, setting in zip(units(), settings, strict=True):
        sim.write({KNOB: float(setting)})
        try:
            single.append(sim.measure())
        except NoEdgesError:
            single.append(np.nan)
    np.testing.assert_array_equal(batched, np.array(single))


def test_episodes_align_to_the_varied_optimum_and_best_width(focus_rows: Path) -> None:
    sims = [ScenarioSimulator(focus_rows, randomize=WIDE) for _ in range(4)]
    episodes = AlignmentEpisodes(sims, get_task("focus"), history=4)
    episodes.begin(np.arange(4), [5, 6, 7, 8])
    for index, sim in enumerate(sims):
        assert episodes.aligned[index, 0] == sim.optimum()[KNOB]
        assert episodes.best_width[index] == sim.best_quality()


@pytest.mark.parametrize(
    ("randomize", "message"),
    [
        ({"shift": 5}, "unknown key.*'shift'.*shift_v, gain, width"),
        ({"shift_v": -1}, "shift_v must be a number of volts >= 0"),
        ({"gain": [2, 1]}, r"randomize.gain must be \[low, high\] with 0 < low <= high"),
        ({"width": [0, 1]}, r"randomize.width must be \[low, high\]"),
        ({"width": 1.2}, r"randomize.width must be \[low, high\]"),
        ([1, 2], "randomize must be a mapping"),
    ],
)
def test_bad_randomization_is_refused_by_name(randomize: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        make_apparatus("csv:default", {"randomize": randomize})


def test_the_critics_secret_points_at_the_varied_optimum(focus_rows: Path) -> None:
    sims = [ScenarioSimulator(focus_rows, randomize=WIDE) for _ in range(4)]
    episodes = AlignmentEpisodes(sims, get_task("focus"), history=4)
    episodes.begin(np.arange(4), [11, 12, 13, 14])
    episodes.misalign(np.arange(4), np.full((4, 1), 0.5))
    secrets = episodes.secrets()
    for index, sim in enumerate(sims):
        expected = (sim.optimum()[KNOB] - sim.read()[KNOB]) / 100.0
        assert secrets[index, 0] == pytest.approx(expected, abs=1e-6)
        assert sim.optimum()[KNOB] != float(sim.optima[sim.row])  # really moved


def test_replays_of_one_recording_give_the_same_secrets_in_one_batch(focus_rows: Path) -> None:
    first = ScenarioSimulator(focus_rows, randomize=WIDE)
    sims = [first] + [
        ScenarioSimulator(scenarios=first.scenarios, randomize=WIDE) for _ in range(3)
    ]
    episodes = AlignmentEpisodes(sims, get_task("focus"), history=4)
    assert episodes._batched  # one numpy query for all four: the path under test
    episodes.begin(np.arange(4), [21, 22, 23, 24])
    episodes.misalign(np.arange(4), np.array([[-0.8], [-0.1], [0.3], [0.9]]))
    episodes.step(np.arange(4), np.array([[0.4, -1.0], [-0.2, -1.0], [0.1, -1.0], [-0.6, -1.0]]))
    one_by_one = np.stack([episodes.secret(index) for index in range(4)])
    np.testing.assert_array_equal(episodes.secrets(), one_by_one)
    for index, sim in enumerate(sims):
        expected = (sim.optimum()[KNOB] - sim.read()[KNOB]) / 100.0
        assert one_by_one[index, 0] == pytest.approx(expected, abs=1e-6)
    # An evaluation session adopts the column as it is: the secret still points at the optimum.
    episodes.adopt(np.arange(4))
    np.testing.assert_array_equal(
        episodes.secrets(), np.stack([episodes.secret(index) for index in range(4)])
    )

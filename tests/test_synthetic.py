"""The synthetic SEM: image formation, knobs, secrets, and the preset instruments."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignrl.apparatus import ApparatusError, SEMConfig, SyntheticSEM, make_apparatus
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config

QUIET = {"drift_v_per_acquisition": 0.0, "hysteresis_v": 0.0}


def quiet_sem(seed: int = 0, **changes: float) -> SyntheticSEM:
    return SyntheticSEM(SEMConfig(**{**QUIET, **changes}), seed=seed)


def test_probe_sigma_follows_the_focus_curve() -> None:
    sem = quiet_sem(gain_px_per_v=0.25, probe_sigma0_px=1.2)
    optimum = sem.optimum()["defocus"]
    for error_v in (-20.0, -3.0, 0.0, 7.5, 15.0):
        sem.write({"defocus": optimum + error_v})
        sigma_u, sigma_v, _ = sem.probe_sigmas_px()
        expected = math.sqrt(1.2**2 + (0.25 * error_v) ** 2)
        assert sigma_u == pytest.approx(expected) and sigma_v == pytest.approx(expected)


def test_measured_focus_curve_has_its_minimum_at_the_optimum() -> None:
    sem = make_apparatus("synthetic", seed=11)
    optimum = sem.optimum()["defocus"]
    voltages = np.arange(optimum - 12.0, optimum + 12.5, 1.0)
    widths = []
    for voltage in voltages:
        sem.write({"defocus": float(voltage)})
        widths.append(sem.measure())
    assert abs(voltages[int(np.argmin(widths))] - optimum) <= 2.0
    assert min(widths) < 3.2  # in focus: 2.563 * sigma0 (1 px) plus noise
    assert widths[0] > 2 * min(widths) and widths[-1] > 2 * min(widths)


def test_write_refuses_unknown_knobs_and_out_of_interval_values_and_changes_nothing() -> None:
    sem = make_apparatus("synthetic", seed=1)
    sem.write({"defocus": 42.0})
    before = sem.read()
    focus_error = sem.focus_error_v()
    for bad in ({"defocus": 100.5}, {"defocus": -0.1}, {"defocus": float("nan")}, {"focus": 3}):
        with pytest.raises(ValueError):
            sem.write(bad)
        assert sem.read() == before
        assert sem.focus_error_v() == focus_error
    with pytest.raises(ValueError, match=r"outside its allowed interval \[0, 100\]"):
        sem.write({"defocus": 120.0})
    with pytest.raises(ValueError, match="unknown knob 'condenser'"):
        sem.write({"condenser": 0.0})


def test_interval_bounds_are_allowed() -> None:
    sem = make_apparatus("synthetic", seed=1)
    sem.write({"defocus": 0.0})
    sem.write({"defocus": 100.0})
    assert sem.read()["defocus"] == 100.0


def test_reset_seed_makes_scenarios_reproducible() -> None:
    first, second = make_apparatus("synthetic"), make_apparatus("synthetic")
    first.reset(123)
    second.reset(123)
    assert first.optimum() == second.optimum()
    np.testing.assert_array_equal(first.acquire(), second.acquire())
    second.reset(124)
    assert first.optimum() != second.optimum()


def test_analytic_mode_draws_the_specimen_it_never_renders() -> None:
    """Analytic mode skips rendering the specimen at every reset, yet its generator moves
    past the same draws: after any reset both modes' next draws agree, and a frame asked of
    an analytic SEM is the frame the image path takes there."""
    analytic, imaging = (SyntheticSEM(seed=5, analytic=flag) for flag in (True, False))
    for seed in (9, 10, 11):
        for sem in (analytic, imaging):
            sem.reset(seed)
            sem.write({"defocus": 48.0})
        assert analytic._rng.bit_generator.state == imaging._rng.bit_generator.state
    assert np.array_equal(analytic.acquire(), imaging.acquire())
    assert analytic._rng.bit_generator.state == imaging._rng.bit_generator.state


def test_scenario_optima_spread_within_the_configured_range() -> None:
    sem = make_apparatus("synthetic")
    optima = []
    for seed in range(200):
        sem.reset(seed)
        optima.append(sem.optimum()["defocus"])
    # 50 +/- 20 V, moved by the hysteresis (0.3 V) toward the side it is approached from.
    assert 29.7 <= min(optima) < 34.0 and 66.0 < max(optima) <= 70.3


def test_frames_are_float_images_with_shot_noise() -> None:
    sem = quiet_sem(seed=4, dose_electrons_per_px=20.0, detector_noise=0.0)
    assert sem.image() is None
    frame = sem.acquire()
    assert frame.shape == (256, 256) and frame.dtype == np.float32
    assert sem.image() is frame
    # Poisson counts divided by the dose: every pixel is a multiple of 1/dose.
    np.testing.assert_allclose(frame * 20.0, np.round(frame * 20.0), atol=1e-3)
    assert sem.acquisitions == 1


def test_lower_dose_gives_noisier_frames() -> None:
    from alignrl.apparatus.quality import estimate_noise_std

    noisy = estimate_noise_std(quiet_sem(seed=2, dose_electrons_per_px=30.0).acquire())
    clean = estimate_noise_std(quiet_sem(seed=2, dose_electrons_per_px=3000.0).acquire())
    assert noisy > 5 * clean


def test_hysteresis_depends_on_the_direction_of_approach() -> None:
    sem = SyntheticSEM(SEMConfig(hysteresis_v=0.5, drift_v_per_acquisition=0.0), seed=0)
    sem.write({"defocus": 40.0})
    sem.write({"defocus": 50.0})  # approached from below
    from_below = sem.focus_error_v()
    sem.write({"defocus": 60.0})
    sem.write({"defocus": 50.0})  # approached from above
    from_above = sem.focus_error_v()
    assert from_above - from_below == pytest.approx(2 * 0.5)
    # The secret is the setting that focuses when written now, from either side.
    for start_v in (30.0, 70.0, 0.0, 100.0):
        sem.write({"defocus": start_v})
        sem.write({"defocus": sem.optimum()["defocus"]})
        assert sem.focus_error_v() == pytest.approx(0.0, abs=1e-9)


def test_drift_moves_the_optimum_per_acquisition() -> None:
    sem = SyntheticSEM(SEMConfig(drift_v_per_acquisition=0.5), seed=9)
    start = sem.optimum()["defocus"]
    for _ in range(20):
        sem.acquire()
    assert sem.optimum()["defocus"] != start
    steady = quiet_sem(seed=9)
    start = steady.optimum()["defocus"]
    steady.acquire()
    assert steady.optimum()["defocus"] == start


def test_astigmatism_makes_the_probe_elliptical() -> None:
    sem = quiet_sem(seed=3, astigmatism_max_v=20.0)
    sem.write({"stigmator_x": 0.0, "stigmator_y": 0.0})  # reset leaves them cancelling it
    sigma_u, sigma_v, _ = sem.probe_sigmas_px()
    assert sigma_u != pytest.approx(sigma_v, rel=0.05)
    round_probe = quiet_sem(seed=3)
    sigma_u, sigma_v, _ = round_probe.probe_sigmas_px()
    assert sigma_u == sigma_v


def test_off_axis_aperture_shifts_the_image_with_focus() -> None:
    sem = quiet_sem(
        seed=6,
        aperture_offset_max_um=20.0,
        aperture_shift_px_per_v_um=0.03,
        dose_electrons_per_px=5000.0,
    )
    optimum = sem.optimum()["defocus"]
    sem.write({"aperture_x": sem.optimum()["aperture_x"] - 10.0})  # 10 um off axis: 0.3 px/V
    sem.write({"defocus": optimum - 8.0})
    under = sem.acquire().astype(np.float64)
    sem.write({"defocus": optimum + 8.0})
    over = sem.acquire().astype(np.float64)
    (shift_x, shift_y), _ = cv2.phaseCorrelate(under, over)
    assert math.hypot(shift_x, shift_y) == pytest.approx(0.3 * 16.0, rel=0.1)


def test_failing_detector_raises_an_apparatus_error() -> None:
    sem = quiet_sem(acquisition_failure_rate=1.0)
    with pytest.raises(ApparatusError, match="acquisition failed"):
        sem.measure()


def test_presets_are_different_microscopes() -> None:
    first, second = make_apparatus("synthetic", seed=0), make_apparatus("synthetic-b", seed=0)
    assert first.knobs["defocus"] != second.knobs["defocus"]
    assert first.config.gain_px_per_v != second.config.gain_px_per_v
    assert first.config.dose_electrons_per_px != second.config.dose_electrons_per_px
    assert {path.stem for path in PRESET_DIR.glob("*.yaml")} >= {"synthetic", "synthetic-b"}


def test_unknown_config_key_is_an_error_naming_the_key(tmp_path: Path) -> None:
    config = tmp_path / "mine.yaml"
    config.write_text("name: mine\ngain_px_per_vv: 0.3\n")
    with pytest.raises(ValueError, match="gain_px_per_vv") as caught:
        load_sem_config(config)
    assert str(config) in str(caught.value)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("defocus_interval_v: [10, 5]\noptimum_v: 7\n", "defocus_interval_v"),
        ("optimum_v: 500\n", "outside defocus_interval_v"),
        ("dose_electrons_per_px: -3\n", "dose_electrons_per_px"),
        ("particles: [0, 3]\n", "particles"),
        ("[1, 2, 3]\n", "mapping"),
        ("gain_px_per_v: [oops\n", "not valid YAML"),
    ],
)
def test_bad_instrument_configs_are_refused(tmp_path: Path, text: str, fragment: str) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    with pytest.raises(ValueError, match=fragment):
        load_sem_config(config)


def test_missing_config_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.yaml"):
        load_sem_config(tmp_path / "nope.yaml")

"""The synthetic SEM as a five-knob column: stigmators, aperture, their physics, the directional
and wobble measurements, and analytic mode against the image path (docs/physics.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from alignrl.apparatus import (
    ApparatusError,
    NoEdgesError,
    SEMConfig,
    SyntheticSEM,
    make_apparatus,
    synthetic,
)
from alignrl.apparatus.directional import directional_widths
from alignrl.apparatus.probe import edge_widths_px, mean_edge_width_px
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.sem_config import PRESET_DIR, AnalyticModel, load_sem_config
from alignrl.apparatus.synthetic import KNOB_NAMES
from benchmarks.analytic_agreement import agreement, compare, misaligned_states

QUIET = {"drift_v_per_acquisition": 0.0, "hysteresis_v": 0.0}
COLUMN = {
    "astigmatism_max_v": 12.0,
    "stigmator_v_per_pct": 0.2,
    "aperture_offset_max_um": 30.0,
    "aperture_shift_px_per_v_um": 0.02,
    "aperture_blur_px_per_um": 0.05,
}
EXACT = AnalyticModel(  # analytic mode without bias, noise or failures: the probe itself
    reading_ratio=(1.0,) * 16,
    noise_rel=(0.0,) * 16,
    specimen_rel=(0.0,) * 16,
    directional_ratio=(1.0,) * 16,
    directional_noise_rel=(0.0,) * 16,
    directional_specimen_rel=(0.0,) * 16,
    orientation_power=1.0,
    no_edges_px=1e6,
    directional_no_edges_px=1e6,
    wobble_failure_sigma_px=1e6,
    wobble_ratio=1.0,
    wobble_scatter_px_per_px=0.0,
)


def column(seed: int = 0, analytic: bool = False, **changes: object) -> SyntheticSEM:
    """A quiet five-knob column (no drift, no hysteresis unless asked for)."""
    return SyntheticSEM(SEMConfig(**{**QUIET, **COLUMN, **changes}), seed=seed, analytic=analytic)


def misalign_stigmators(sem: SyntheticSEM, residual_v: float, axis_rad: float) -> None:
    """Leave a residual astigmatism of residual_v volts with its axis at axis_rad."""
    optimum, gain = sem.optimum(), sem.config.stigmator_v_per_pct
    sem.write(
        {
            "stigmator_x": optimum["stigmator_x"] - residual_v * math.cos(2 * axis_rad) / gain,
            "stigmator_y": optimum["stigmator_y"] - residual_v * math.sin(2 * axis_rad) / gain,
        }
    )


def test_five_knobs_in_order_with_their_intervals() -> None:
    sem = make_apparatus("synthetic-b", seed=0)
    assert tuple(sem.knobs) == KNOB_NAMES
    assert sem.knobs["defocus"] == (0.0, 120.0)
    assert sem.knobs["stigmator_x"] == sem.knobs["stigmator_y"] == (-100.0, 100.0)
    assert sem.knobs["aperture_x"] == sem.knobs["aperture_y"] == (-60.0, 60.0)
    assert tuple(sem.read()) == KNOB_NAMES and tuple(sem.optimum()) == KNOB_NAMES
    plain = SyntheticSEM(SEMConfig(stigmator_interval_pct=(-80, 90)))
    assert plain.knobs["stigmator_y"] == (-80.0, 90.0)
    assert plain.knobs["aperture_x"] == (-50.0, 50.0)


@pytest.mark.parametrize("preset", ["synthetic", "synthetic-b"])
def test_presets_misalign_stigmators_and_aperture_differently(preset: str) -> None:
    config = make_apparatus(preset).config
    for field in COLUMN:
        assert getattr(config, field) > 0, field
    other = make_apparatus("synthetic-b" if preset == "synthetic" else "synthetic").config
    assert all(getattr(config, field) != getattr(other, field) for field in COLUMN)


def test_the_default_analytic_calibration_is_the_synthetic_preset_s() -> None:
    # SEMConfig's defaults image the synthetic preset's specimen at its dose and noise.
    assert (
        SEMConfig().analytic_calibration == make_apparatus("synthetic").config.analytic_calibration
    )
    assert (
        make_apparatus("synthetic-b").config.analytic_calibration
        != SEMConfig().analytic_calibration
    )


def test_reset_leaves_stigmators_and_aperture_aligned() -> None:
    sem = make_apparatus("synthetic", seed=0)
    offsets = []
    for seed in range(20):
        sem.reset(seed)
        optimum, setting = sem.optimum(), sem.read()
        for knob in KNOB_NAMES[1:]:
            assert setting[knob] == optimum[knob]
        assert np.all(sem.astigmatism_residual_v() == 0.0)
        assert np.all(sem.aperture_residual_um() == 0.0)
        sigma_u, sigma_v, _ = sem.probe_sigmas_px()
        assert sigma_u == sigma_v
        sem.write({"defocus": 20.0})
        assert np.all(sem.image_shift_px() == 0.0)
        offsets.append(np.hypot(optimum["aperture_x"], optimum["aperture_y"]))
    # The scenarios' misalignments are real: the optimum lies off centre.
    assert 5.0 < np.median(offsets) < 25.0 and max(offsets) <= 30.0


def test_the_focus_task_sees_the_focus_only_column() -> None:
    """Aligned stigmators and aperture render the frames of a column without either, from the
    same scenario draws: the optimum, the specimen and every frame are the same, bit for bit."""
    focus_only = SyntheticSEM(
        load_sem_config(
            PRESET_DIR / "synthetic.yaml",
            astigmatism_max_v=0.0,
            aperture_offset_max_um=0.0,
            aperture_shift_px_per_v_um=0.0,
            aperture_blur_px_per_um=0.0,
        ),
        seed=3,
    )
    full = make_apparatus("synthetic", seed=3)
    for seed in (11, 12345):
        focus_only.reset(seed)
        full.reset(seed)
        assert focus_only.optimum()["defocus"] == full.optimum()["defocus"]
        assert focus_only.best_quality() == full.best_quality()
        for voltage in (35.0, full.optimum()["defocus"], 61.0):
            focus_only.write({"defocus": voltage})
            full.write({"defocus": voltage})
            np.testing.assert_array_equal(focus_only.acquire(), full.acquire())
            assert focus_only.focus_error_v() == full.focus_error_v()  # drift alike too


def test_probe_axes_follow_the_stigmator_residual() -> None:
    sem = column(seed=1)
    optimum_v = sem.optimum()["defocus"]
    for axis_deg in (0.0, 30.0, 45.0, 120.0):
        misalign_stigmators(sem, 8.0, math.radians(axis_deg))
        residual = sem.astigmatism_residual_v()
        assert np.hypot(*residual) == pytest.approx(8.0)
        sem.write({"defocus": optimum_v - 3.0})
        sigma_u, sigma_v, axis = sem.probe_sigmas_px()
        assert math.degrees(axis) % 180.0 == pytest.approx(axis_deg, abs=1e-9)
        # The line foci sit 4 V above and below focus: sigma_u is the sigma0 + 7 V one.
        assert sigma_u == pytest.approx(math.hypot(1.0, 0.2 * 7.0))
        assert sigma_v == pytest.approx(math.hypot(1.0, 0.2 * 1.0))
        # A straight edge whose normal lies along the axis is blurred by sigma_u.
        covariance = sem.probe_covariance_px2()
        normals = np.radians([axis_deg, axis_deg + 90.0])
        np.testing.assert_allclose(
            edge_widths_px(covariance, normals), TEN_NINETY_PER_SIGMA * np.array([sigma_u, sigma_v])
        )
        # Over focus the long axis turns by 90 degrees; at the round-beam focus it is round.
        sem.write({"defocus": optimum_v + 3.0})
        sigma_u, sigma_v, _ = sem.probe_sigmas_px()
        assert sigma_v > sigma_u
        sem.write({"defocus": optimum_v})
        sigma_u, sigma_v, _ = sem.probe_sigmas_px()
        assert sigma_u == pytest.approx(sigma_v)


@pytest.mark.parametrize("axis_deg", [45.0, 90.0])
def test_measured_edge_widths_stretch_along_perpendicular_axes_through_focus(
    axis_deg: float,
) -> None:
    sem = column(seed=2, dose_electrons_per_px=2000.0)
    misalign_stigmators(sem, 12.0, math.radians(axis_deg))
    optimum_v = sem.optimum()["defocus"]
    for error_v, widest_deg in ((-6.0, axis_deg), (6.0, axis_deg + 90.0)):
        sem.write({"defocus": optimum_v + error_v})
        measured = directional_widths(sem.acquire())
        difference = (math.degrees(measured.axis_rad) - widest_deg + 90.0) % 180.0 - 90.0
        assert abs(difference) < 12.0, (error_v, math.degrees(measured.axis_rad))
        assert measured.astigmatism_px > 2.0


def test_stigmators_at_their_optimum_make_the_probe_round_again() -> None:
    sem = column(seed=4)
    misalign_stigmators(sem, 10.0, 0.7)
    sem.write({"defocus": sem.optimum()["defocus"] - 5.0})
    sigma_u, sigma_v, _ = sem.probe_sigmas_px()
    assert sigma_u > 1.5 * sigma_v
    optimum = sem.optimum()
    sem.write({"stigmator_x": optimum["stigmator_x"], "stigmator_y": optimum["stigmator_y"]})
    sigma_u, sigma_v, _ = sem.probe_sigmas_px()
    assert sigma_u == sigma_v


def test_an_off_axis_aperture_moves_the_image_content_by_the_shift() -> None:
    """Content moves by +shift (x = column, y = row): compared with a frame of the same noise
    whose aperture sits on the axis, the frame is the same picture rolled by (dx, dy)."""
    changes = {"dose_electrons_per_px": 1e9, "detector_noise": 0.0, "aperture_blur_px_per_um": 0.0}
    centred, tilted = column(seed=5, **changes), column(seed=5, **changes)
    optimum = tilted.optimum()
    for sem in (centred, tilted):
        sem.write({"defocus": optimum["defocus"] + 10.0})
    # k dV d = 0.02 px/(V um) x 10 V x (15, -10) um = (3, -2) px.
    tilted.write(
        {"aperture_x": optimum["aperture_x"] - 15.0, "aperture_y": optimum["aperture_y"] + 10}
    )
    np.testing.assert_allclose(tilted.image_shift_px(), [3.0, -2.0])
    rolled = np.roll(centred.acquire(), shift=(-2, 3), axis=(0, 1))
    np.testing.assert_allclose(tilted.acquire(), rolled, atol=1e-3)


def test_aperture_residual_blurs_the_probe_in_quadrature() -> None:
    sem = column(seed=6)
    optimum = sem.optimum()
    sem.write(
        {
            "defocus": optimum["defocus"],
            "aperture_x": optimum["aperture_x"] + 12.0,
            "aperture_y": optimum["aperture_y"] - 16.0,
        }
    )
    sigma_u, sigma_v, _ = sem.probe_sigmas_px()
    assert sigma_u == sigma_v == pytest.approx(math.hypot(1.0, 0.05 * 20.0))
    assert np.all(sem.image_shift_px() == 0.0)  # in focus the tilt does not show


@pytest.mark.parametrize("analytic", [False, True])
def test_wobble_grows_linearly_with_the_aperture_residual_and_vanishes_at_zero(
    analytic: bool,
) -> None:
    sem = column(
        seed=7, analytic=analytic, dose_electrons_per_px=1000.0, analytic_calibration=EXACT
    )
    optimum = sem.optimum()
    direction = np.array([0.6, -0.8])
    for residual_um in (0.0, 5.0, 10.0, 20.0):
        aperture = (
            np.array([optimum["aperture_x"], optimum["aperture_y"]]) - residual_um * direction
        )
        sem.write({"aperture_x": aperture[0], "aperture_y": aperture[1]})
        shift = sem.measure_wobble(5.0)
        expected = 0.02 * 10.0 * residual_um * direction  # k x (2 x amplitude) x d
        tolerance = 1e-12 if analytic else 0.05 + 0.03 * residual_um * 0.2
        np.testing.assert_allclose(shift, expected, atol=tolerance)


@pytest.mark.parametrize("analytic", [False, True])
def test_a_wobble_takes_two_acquisitions_and_restores_the_lens(analytic: bool) -> None:
    sem = column(seed=8, analytic=analytic, hysteresis_v=0.5)
    in_focus_v = sem.read()["defocus"] - sem.focus_error_v()  # no voltage change yet
    sem.write({"aperture_x": sem.optimum()["aperture_x"] - 10.0, "defocus": in_focus_v + 2.0})
    sem.write({"defocus": in_focus_v - 1.0})  # last step down: the lens lags upwards
    before, error, target = sem.read(), sem.focus_error_v(), sem.optimum()
    count = sem.acquisitions
    shift = sem.measure_wobble(4.0)
    assert sem.acquisitions == count + 2
    assert sem.read() == before and sem.focus_error_v() == error and sem.optimum() == target
    # Hysteresis acts on the swing: the plus frame is reached upwards (focus error 3 - 0.5 V),
    # the minus one downwards (-5 + 0.5 V): k x 7 V x 10 um.
    assert shift[0] == pytest.approx(0.02 * (8.0 - 2 * 0.5) * 10.0, abs=0.1)
    # At the top of the interval the plus frame is clamped: a swing of 4 V, not 8.
    narrow = column(
        seed=8,
        analytic=analytic,
        analytic_calibration=EXACT,
        optimum_spread_v=0.0,
        defocus_interval_v=(40.0, 60.0),
    )
    narrow.write({"aperture_x": narrow.optimum()["aperture_x"] - 10.0, "defocus": 60.0})
    before, error = narrow.read(), narrow.focus_error_v()
    shift = narrow.measure_wobble(4.0)
    assert narrow.read() == before and narrow.focus_error_v() == error
    assert shift[0] == pytest.approx(0.02 * 4.0 * 10.0, abs=0.1)
    # A failed acquisition restores the lens too.
    failing = column(seed=8, analytic=analytic, acquisition_failure_rate=1.0)
    failing.write({"defocus": 40.0})
    before, error = failing.read(), failing.focus_error_v()
    with pytest.raises(ApparatusError):
        failing.measure_wobble(5.0)
    assert failing.read() == before and failing.focus_error_v() == error
    with pytest.raises(ValueError, match="amplitude"):
        sem.measure_wobble(-1.0)


@pytest.mark.parametrize("preset", ["synthetic", "synthetic-b"])
def test_writing_the_optimum_gives_the_best_quality(preset: str) -> None:
    config = make_apparatus(preset).config.model_copy(update={"drift_v_per_acquisition": 0.0})
    sem = SyntheticSEM(config, seed=9)
    rng = np.random.default_rng(0)
    for _ in range(3):
        sem.write({k: float(rng.uniform(*interval)) for k, interval in sem.knobs.items()})
        assert sem.probe_width_px() > 1.2 * sem.best_quality()
        sem.write(sem.optimum())
        best = TEN_NINETY_PER_SIGMA * sem.config.probe_sigma0_px
        assert sem.best_quality() == pytest.approx(best)
        assert sem.probe_width_px() == pytest.approx(best)
        assert sem.measure() == pytest.approx(best, rel=0.1)


@pytest.mark.parametrize("knob", KNOB_NAMES)
def test_an_out_of_interval_write_to_any_knob_changes_nothing(knob: str) -> None:
    sem = make_apparatus("synthetic", seed=10)
    sem.write({"defocus": 42.0, "stigmator_x": 10.0, "aperture_y": -5.0})
    before, covariance, shift = sem.read(), sem.probe_covariance_px2(), sem.image_shift_px()
    high = sem.knobs[knob][1]
    for bad in ({knob: high + 0.5}, {knob: float("nan")}, {"defocus": 41.0, knob: high + 1.0}):
        with pytest.raises(ValueError, match=knob):
            sem.write(bad)
        assert sem.read() == before
        np.testing.assert_array_equal(sem.probe_covariance_px2(), covariance)
        np.testing.assert_array_equal(sem.image_shift_px(), shift)
    sem.write({knob: high})  # the bound itself is allowed
    assert sem.read()[knob] == high


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"stigmator_interval_pct": (50.0, -50.0)}, "stigmator_interval_pct: low 50"),
        ({"aperture_interval_um": (0.0, 0.0)}, "aperture_interval_um: low 0"),
        ({"astigmatism_max_v": 30.0}, r"must contain \+/- 150 %"),
        ({"aperture_offset_max_um": 60.0}, r"must contain \+/- aperture_offset_max_um"),
        ({"stigmator_v_per_pct": 0.0}, "stigmator_v_per_pct"),
        ({"aperture_shift_px_per_v_um": -0.01}, "aperture_shift_px_per_v_um"),
        ({"aperture_blur_px_per_um": -1.0}, "aperture_blur_px_per_um"),
        ({"analytic_calibration": {"noise_rel": [0.1, 0.2]}}, "noise_rel: need 16 values"),
        ({"analytic_calibration": {"knots_px": [3.0, 2.0]}}, "knots_px"),
    ],
)
def test_bad_column_configs_are_refused_with_the_field_named(
    tmp_path: Path, changes: dict, fragment: str
) -> None:
    with pytest.raises(ValueError, match=fragment):
        load_sem_config(PRESET_DIR / "synthetic.yaml", **changes)


def test_the_old_aperture_field_is_refused(tmp_path: Path) -> None:
    config = tmp_path / "old.yaml"
    config.write_text("aperture_shift_px_per_v: 0.1\n")
    with pytest.raises(ValueError, match="aperture_shift_px_per_v: Extra inputs"):
        load_sem_config(config)


def test_analytic_mode_from_a_spec_has_no_images() -> None:
    sem = make_apparatus("synthetic-b", {"analytic": True, "dose_electrons_per_px": 80.0}, seed=1)
    assert sem.analytic and sem.config.dose_electrons_per_px == 80.0
    sem.write(sem.optimum())
    width = sem.measure()
    mean, bins = sem.measure_directional()
    assert sem.image() is None and sem.acquisitions == 2
    assert width == pytest.approx(sem.best_quality(), rel=0.2) and bins.shape == (4,)
    assert mean == pytest.approx(width, rel=0.2)
    assert not make_apparatus("synthetic", seed=1).analytic
    with pytest.raises(ValueError, match="analytic must be true or false"):
        make_apparatus("synthetic", {"analytic": "yes"})


def test_analytic_mode_reads_the_probe_exactly_without_its_noise() -> None:
    sem = column(seed=11, analytic=True, analytic_calibration=EXACT)
    misalign_stigmators(sem, 10.0, math.radians(45.0))
    sem.write({"defocus": sem.optimum()["defocus"] - 4.0})
    covariance = sem.probe_covariance_px2()
    assert sem.measure() == pytest.approx(mean_edge_width_px(covariance))
    width, bins = sem.measure_directional()
    assert width == pytest.approx(mean_edge_width_px(covariance))
    assert int(np.argmax(bins)) == 1  # the 45 degree bin: the long axis under focus
    assert bins[1] < edge_widths_px(covariance, np.radians([45.0]))[0]  # averaged over the bin


def test_the_expected_width_is_the_median_analytic_reading() -> None:
    """expected_width_px is the analytic reading without its scatter: the median reading over
    scenarios (specimens) and fresh noise; it neither acquires nor moves anything."""
    config = make_apparatus("synthetic-b").config
    ratios = []
    for seed in range(400):
        sem = SyntheticSEM(config, seed=seed, analytic=True)
        sem.write({"defocus": sem.optimum()["defocus"] + 6.0})
        before = (sem.acquisitions, sem.read())
        expected = sem.expected_width_px()
        assert (sem.acquisitions, sem.read()) == before
        assert expected != pytest.approx(sem.probe_width_px(), rel=1e-3)  # calibrated ratio
        ratios.append(sem.measure() / expected)
    assert np.median(ratios) == pytest.approx(1.0, abs=0.01)
    assert 0.01 < np.std(np.log(ratios)) < 0.1  # the scatter is the reading's, not the mean's


def test_analytic_mode_fails_like_the_image_path() -> None:
    far = column(seed=12, analytic=True, gain_px_per_v=3.0)
    far.write({"defocus": 0.0})  # a probe ~ 100 px wide
    with pytest.raises(NoEdgesError):
        far.measure()
    faulty = column(seed=12, analytic=True, acquisition_failure_rate=1.0)
    with pytest.raises(ApparatusError, match="acquisition failed"):
        faulty.measure()
    # Its noise comes from the scenario's generator: a seed repeats the readings.
    first, second = column(seed=13, analytic=True), column(seed=13, analytic=True)
    for sem in (first, second):
        sem.write({"defocus": 45.0, "stigmator_y": 20.0})
    readings = [[sem.measure(), *sem.measure_directional()[1]] for sem in (first, second)]
    assert readings[0] == readings[1]
    assert len(set(readings[0])) == 5


@pytest.mark.parametrize(
    ("preset", "typical_rel", "within_share"),
    [("synthetic", 0.05, 0.5), ("synthetic-b", 0.08, 0.3)],
)
def test_analytic_mode_agrees_with_the_image_path(
    preset: str, typical_rel: float, within_share: float
) -> None:
    """The benchmark's criterion on 30 misaligned states per preset: unbiased within 5 %. A
    single state differs by the image path's noise and specimen (more on synthetic-b, with
    half the dose): benchmarks/analytic_agreement.py and docs/physics.md have the figures."""
    config = make_apparatus(preset).config
    figures = agreement(compare(config, misaligned_states(config, 30, seed=1)))
    assert abs(figures["width_median_rel"]) < 0.05
    assert figures["width_median_abs_rel"] < typical_rel
    assert figures["expected_median_abs_rel"] < 0.05  # the model's value, without its scatter
    assert figures["width_within_5pct"] > within_share
    assert abs(figures["dir_median_rel"]) < 0.05 and figures["dir_median_abs_rel"] < 0.1
    assert figures["wobble_median_error_px"] < 0.25


def test_a_nominal_reset_leaves_the_stigmators_and_aperture_at_zero() -> None:
    aligned = make_apparatus("synthetic", {"analytic": True}, seed=5)
    nominal = make_apparatus("synthetic", {"analytic": True, "reset_state": "nominal"}, seed=5)
    assert nominal.optimum() == aligned.optimum()  # the same column, not yet corrected
    assert {k: v for k, v in nominal.read().items() if k != "defocus"} == dict.fromkeys(
        ("stigmator_x", "stigmator_y", "aperture_x", "aperture_y"), 0.0
    )
    assert aligned.read()["stigmator_x"] == aligned.optimum()["stigmator_x"] != 0.0


def test_the_instrument_parameters_stay_importable_from_synthetic() -> None:
    """benchmarks/ and driver examples import these from alignrl.apparatus.synthetic."""
    assert synthetic.SEMConfig is SEMConfig and synthetic.AnalyticModel is AnalyticModel
    assert synthetic.load_sem_config is load_sem_config and synthetic.PRESET_DIR == PRESET_DIR
    assert synthetic.edge_widths_px is edge_widths_px
    assert synthetic.mean_edge_width_px is mean_edge_width_px
    assert callable(synthetic.directional_edge_widths_px)

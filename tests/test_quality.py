"""The edge-width algorithm is a measurement: validated against analytic blurred edges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from alignrl.apparatus import (
    NoEdgesError,
    SEMConfig,
    SyntheticSEM,
    edge_width,
    make_apparatus,
    measure_edges,
)
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, estimate_noise_std

SIZE = 256
DARK, BRIGHT = 0.2, 0.8

_erf = np.vectorize(math.erf)


def blurred_step(
    sigma_px: float,
    angle_deg: float,
    *,
    noise: float = 0.0,
    poisson_dose: float | None = None,
    seed: int = 0,
) -> np.ndarray:
    """A straight dark-to-bright step through the frame centre, blurred by a Gaussian.

    Sampled analytically: intensity = dark + (bright - dark) * Phi(d / sigma) with d the
    signed distance of the pixel centre from the edge line, which is exactly the Gaussian
    blur of a sharp step.
    """
    rows, columns = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    angle = np.deg2rad(angle_deg)
    centre = (SIZE - 1) / 2
    distance = (columns - centre) * np.cos(angle) + (rows - centre) * np.sin(angle) + 0.37
    image = DARK + (BRIGHT - DARK) * 0.5 * (1.0 + _erf(distance / (sigma_px * math.sqrt(2))))
    rng = np.random.default_rng(seed)
    if poisson_dose is not None:
        image = rng.poisson(image * poisson_dose) / poisson_dose
    if noise:
        image = image + noise * rng.standard_normal(image.shape)
    return image


ANGLES = (0.0, 17.0, 45.0, 60.0, 90.0, 135.0, 200.0, 290.0)
SIGMAS = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)


@pytest.mark.parametrize("sigma", SIGMAS)
@pytest.mark.parametrize("angle", ANGLES)
def test_step_edge_matches_analytic_width_without_noise(sigma: float, angle: float) -> None:
    expected = TEN_NINETY_PER_SIGMA * sigma
    assert edge_width(blurred_step(sigma, angle)) == pytest.approx(expected, rel=0.10)


@pytest.mark.parametrize("sigma", SIGMAS)
@pytest.mark.parametrize("angle", (0.0, 30.0, 45.0, 110.0, 250.0))
def test_step_edge_matches_analytic_width_with_gaussian_noise(sigma: float, angle: float) -> None:
    # 5 % of full scale: a contrast-to-noise ratio of 12 per pixel, a grainy SEM frame.
    image = blurred_step(sigma, angle, noise=0.05, seed=int(sigma * 100 + angle))
    assert edge_width(image) == pytest.approx(TEN_NINETY_PER_SIGMA * sigma, rel=0.10)


@pytest.mark.parametrize("sigma", (1.0, 2.0, 4.0, 8.0))
def test_step_edge_matches_analytic_width_with_shot_noise(sigma: float) -> None:
    image = blurred_step(sigma, 33.0, poisson_dose=100.0, seed=7)
    assert edge_width(image) == pytest.approx(TEN_NINETY_PER_SIGMA * sigma, rel=0.10)


def test_width_does_not_depend_on_contrast_or_offset() -> None:
    image = blurred_step(3.0, 20.0)
    reference = edge_width(image)
    assert edge_width(5.0 * image + 100.0) == pytest.approx(reference, rel=1e-3)
    assert edge_width(1.0 - image) == pytest.approx(reference, rel=0.02)  # bright-to-dark


def test_accepts_uint8_and_colour_images() -> None:
    grey = np.clip(blurred_step(2.0, 10.0) * 255, 0, 255).astype(np.uint8)
    colour = np.repeat(grey[:, :, None], 3, axis=2)
    expected = TEN_NINETY_PER_SIGMA * 2.0
    assert edge_width(grey) == pytest.approx(expected, rel=0.10)
    assert edge_width(colour) == pytest.approx(edge_width(grey), rel=1e-6)


def _specimen_frames(probe_sigmas: list[float], dose: float) -> list[np.ndarray]:
    """Frames of one specimen area with the probe blurred to each sigma (px)."""
    config = SEMConfig(dose_electrons_per_px=dose, detector_noise=0.0, drift_v_per_acquisition=0)
    sem = SyntheticSEM(config, seed=3)
    optimum = sem.optimum()["defocus"]
    frames = []
    for sigma in probe_sigmas:
        focus_error = math.sqrt(sigma**2 - config.probe_sigma0_px**2) / config.gain_px_per_v
        sem.write({"defocus": optimum + focus_error})
        assert sem.probe_sigmas_px()[0] == pytest.approx(sigma, rel=0.01)
        frames.append(sem.acquire())
    return frames


def test_width_grows_monotonically_with_blur_on_a_clean_specimen() -> None:
    sigmas = [1.05, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    widths = [edge_width(frame) for frame in _specimen_frames(sigmas, dose=1e6)]
    assert np.all(np.diff(widths) > 0), widths
    # Particle rims are steps: where the blur is small against the particles, the specimen
    # reading is the analytic width too.
    for sigma, width in zip(sigmas[:6], widths[:6], strict=True):
        assert width == pytest.approx(TEN_NINETY_PER_SIGMA * sigma, rel=0.15)


def test_width_grows_monotonically_with_blur_on_a_noisy_specimen() -> None:
    sigmas = [1.05, 2.0, 3.0, 4.5, 6.0, 8.0]
    widths = [edge_width(frame) for frame in _specimen_frames(sigmas, dose=200.0)]
    assert np.all(np.diff(widths) > 0), widths


def test_blank_frame_has_no_edges() -> None:
    with pytest.raises(NoEdgesError, match="no edges"):
        edge_width(np.full((SIZE, SIZE), 0.4))


def test_pure_noise_has_no_edges() -> None:
    rng = np.random.default_rng(1)
    for seed in range(5):
        noise = 0.5 + 0.1 * np.random.default_rng(seed).standard_normal((SIZE, SIZE))
        with pytest.raises(NoEdgesError):
            edge_width(noise)
    shot_noise = rng.poisson(40.0, (SIZE, SIZE)).astype(np.float32)
    with pytest.raises(NoEdgesError):
        edge_width(shot_noise)


def test_hopelessly_defocused_frame_has_no_edges() -> None:
    config = SEMConfig(dose_electrons_per_px=50.0, gain_px_per_v=2.0)
    sem = SyntheticSEM(config, seed=5)
    sem.write({"defocus": 0.0})  # sigma ~ 60-140 px: the particles dissolve into the noise
    with pytest.raises(NoEdgesError):
        sem.measure()


def test_no_edges_error_is_a_value_error() -> None:
    assert issubclass(NoEdgesError, ValueError)


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros(300), "2-D"),
        (np.zeros((8, 8)), "16x16"),
        (np.full((64, 64), np.nan), "NaN"),
    ],
)
def test_bad_images_are_refused_with_a_reason(image: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message) as caught:
        edge_width(image)
    assert not isinstance(caught.value, NoEdgesError)


def test_noise_estimate_ignores_edges() -> None:
    image = blurred_step(1.0, 30.0, noise=0.03, seed=2)
    assert estimate_noise_std(image) == pytest.approx(0.03, rel=0.1)
    assert estimate_noise_std(blurred_step(1.0, 30.0)) < 0.003


def test_measurement_reports_its_edges() -> None:
    result = measure_edges(blurred_step(2.0, 45.0))
    assert result.edge_widths_px.shape == result.edge_points.shape
    assert result.edge_points.sum() >= 100  # the edge crosses the whole frame
    assert result.width_px == pytest.approx(
        np.average(result.edge_widths_px, weights=result.edge_points)
    )


def test_far_out_of_focus_frames_never_read_as_sharp() -> None:
    """A defocused frame must not pass for a focused one: that would fool every controller."""
    sem = make_apparatus("synthetic", seed=0)
    rng = np.random.default_rng(2024)
    readings = []
    for index in range(120):
        if index % 6 == 0:
            sem.reset(int(rng.integers(2**31)))
        optimum = sem.optimum()["defocus"]
        side = 1.0 if rng.random() < 0.5 else -1.0
        error_v = side * rng.uniform(30.0, 50.0)  # probe sigma 6-10 px
        sem.write({"defocus": float(np.clip(optimum + error_v, 0.0, 100.0))})
        true_sigma = sem.probe_sigmas_px()[0]
        if true_sigma < 5.0:
            continue
        readings.append(sem.measure())
    in_focus = TEN_NINETY_PER_SIGMA * sem.config.probe_sigma0_px
    assert len(readings) > 80
    assert min(readings) > 3 * in_focus, sorted(readings)[:5]


def test_recorded_glitch_frame_is_measured_as_blurred() -> None:
    """Regression: scenario 1722 of an earlier default recording read 2.55 px at 10 V, 40 V
    from focus, from a noise-made step on the flank of a blurred particle."""
    from alignrl.apparatus.recorder import sweep, sweep_plan

    sem = make_apparatus("synthetic")
    frames: dict[float, np.ndarray] = {}
    measure = sem.measure

    def keep_frame() -> float:
        width = measure()
        frames[sem.read()["defocus"]] = sem.image()
        return width

    sem.measure = keep_frame  # type: ignore[method-assign]
    record = sweep(sem, sweep_plan(sem.knobs), 1722, 3824399162)
    assert record is not None
    assert record.edge_widths[1] > 10.0  # at 10 V
    assert edge_width(frames[10.0]) > 10.0


def _low_readings_10_to_15_v_out(seeds) -> list[tuple]:
    """Readings of synthetic-b 10 and 15 V either side of focus (5 a setting) that fall below
    0.7 of the frame's true edge width."""
    sem = make_apparatus("synthetic-b")
    low = []
    for seed in seeds:
        sem.reset(seed)
        optimum = sem.optimum()["defocus"]
        for error_v in (-15.0, -10.0, 10.0, 15.0):
            sem.write({"defocus": float(np.clip(optimum + error_v, 0.0, 120.0))})
            expected = sem.expected_width_px()
            for _ in range(5):
                reading = sem.measure()
                if reading < 0.7 * expected:
                    low.append((seed, error_v, round(reading, 2), round(expected, 2)))
    return low


# The scenarios of the 15 below whose frames the finest scale alone read low (a reading
# from its first trusted edges, as before the fix: 4.45, 5.42 and 4.61 px against 8.0-8.3 px
# edges): `make test` measures these, `make test-all` all 15.
SPURIOUS_EDGE_SEEDS = (3, 12, 14)


def test_moderately_defocused_frames_are_not_read_from_one_spurious_edge() -> None:
    """Regression: 10-15 V out of focus on synthetic-b, about 2 % of frames read 4-5 px where
    their edges are 8 px wide: the finest detection scale trusted one short edge made by the
    noise and looked no further. A thinly supported reading is now checked at a coarser
    scale, and the scale with the most trusted edge points gives the reading."""
    low = _low_readings_10_to_15_v_out(SPURIOUS_EDGE_SEEDS)
    assert not low, low


@pytest.mark.long
def test_moderately_defocused_frames_are_not_read_from_one_spurious_edge_in_15_scenarios() -> None:
    """The regression above over 15 scenarios, 300 readings (7.5 s of one worker)."""
    low = _low_readings_10_to_15_v_out(range(15))
    assert not low, low

"""Directional edge widths and the wobble shift: validated against analytic probes and shifts.

The specimens are drawn here (round particles on a substrate, periodic across the frame) and
blurred in Fourier space by an elliptical Gaussian probe of known covariance C, in (x = column,
y = row) pixels. A straight edge of unit normal n then has the 10-90 % width
K sqrt(n^T C n), K = TEN_NINETY_PER_SIGMA. Noise is shot noise (in its Gaussian limit) plus
1 % detector noise. The accuracy tests use 500 electrons per pixel, a slower scan than the
synthetic SEM's default of 200; at 200 the directional widths scatter by about 3 % per bin
more, which one test below covers with a looser tolerance.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignrl.apparatus import (
    MeasurementError,
    NoEdgesError,
    directional,
    edge_width,
    quality,
    wobble,
)
from alignrl.apparatus.directional import (
    ORIENTATION_BINS_DEG,
    DirectionalWidths,
    astigmatism_from_widths,
    directional_widths,
)
from alignrl.apparatus.edge_profiles import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.wobble import wobble_shift

K = TEN_NINETY_PER_SIGMA
SUBSTRATE, PARTICLE = 0.25, 0.9
DOSE = 500.0  # electrons per pixel of the accuracy tests


def particles(
    size: int,
    seed: int,
    radius_px: tuple[float, float],
    gap_px: float,
    count: int,
) -> np.ndarray:
    """Up to `count` round particles on a flat substrate, periodic across the frame.

    Particles at least `gap_px` apart keep each rim's profile free of its neighbours out to
    the 10-90 % window of the widest probes tested, so that the reading is the probe's.
    """
    rng = np.random.default_rng(seed)
    coordinates = np.arange(size, dtype=np.float64)
    image = np.full((size, size), SUBSTRATE)
    placed: list[tuple[float, float, float]] = []
    for _ in range(50 * count):
        if len(placed) == count:
            break
        x, y = rng.uniform(0, size, 2)
        radius = rng.uniform(*radius_px)
        if gap_px >= 0 and any(
            math.hypot((x - px + size / 2) % size - size / 2, (y - py + size / 2) % size - size / 2)
            < radius + pr + gap_px
            for px, py, pr in placed
        ):
            continue
        placed.append((x, y, radius))
        dx = (coordinates - x + size / 2) % size - size / 2
        dy = (coordinates - y + size / 2) % size - size / 2
        distance = np.hypot(dx[None, :], dy[:, None])
        coverage = np.clip(radius - distance + 0.5, 0.0, 1.0)  # anti-aliased rim
        image += coverage * (PARTICLE * rng.uniform(0.9, 1.1) - image)
    return image


def covariance(sigma_u: float, sigma_v: float, axis_deg: float) -> np.ndarray:
    """Probe covariance in (x, y) px: sigma_u along the axis at axis_deg, sigma_v across."""
    c, s = math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg))
    rotation = np.array([[c, -s], [s, c]])
    return rotation @ np.diag([sigma_u**2, sigma_v**2]) @ rotation.T


def probe(
    specimen: np.ndarray, cov: np.ndarray, shift_px: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """The specimen blurred by a Gaussian of covariance `cov` and moved by shift_px = (dx, dy):
    a feature at (x, y) lands at (x + dx, y + dy). Exact in Fourier space (periodic frame)."""
    fy = np.fft.fftfreq(specimen.shape[0])[:, None]
    fx = np.fft.rfftfreq(specimen.shape[1])[None, :]
    quadratic = cov[0, 0] * fx**2 + 2 * cov[0, 1] * fx * fy + cov[1, 1] * fy**2
    phase = fx * shift_px[0] + fy * shift_px[1]
    transfer = np.exp(-2 * np.pi**2 * quadratic - 2j * np.pi * phase)
    return np.fft.irfft2(np.fft.rfft2(specimen) * transfer, s=specimen.shape)


def noisy(image: np.ndarray, seed: int, dose: float = 200.0) -> np.ndarray:
    """Shot noise at `dose` electrons per pixel (Gaussian limit) and 1 % detector noise."""
    rng = np.random.default_rng(seed)
    shot = np.sqrt(np.clip(image, 0, None) / dose) * rng.standard_normal(image.shape)
    return (image + shot + 0.01 * rng.standard_normal(image.shape)).astype(np.float32)


def analytic_widths(cov: np.ndarray) -> np.ndarray:
    """K sqrt(n^T C n) for the normal n at each bin centre."""
    angles = np.deg2rad(ORIENTATION_BINS_DEG)
    normals = np.stack([np.cos(angles), np.sin(angles)])
    return K * np.sqrt(np.einsum("in,ij,jn->n", normals, cov, normals))


def wide_particles(seed: int) -> np.ndarray:
    """Large, well separated particles: rims of little curvature, plateaus on both sides."""
    return particles(384, seed, radius_px=(20.0, 30.0), gap_px=24.0, count=30)


# --- directional widths -----------------------------------------------------------------


PROBES = [(1.5, 1.0), (2.5, 1.0), (3.0, 1.5), (4.0, 1.5), (4.0, 2.0)]
AXES_DEG = (0.0, 30.0, 45.0, 90.0, 120.0)


@pytest.mark.parametrize(("sigma_u", "sigma_v"), PROBES)
@pytest.mark.parametrize("axis_deg", AXES_DEG)
def test_directional_widths_match_an_elliptical_probe(
    sigma_u: float, sigma_v: float, axis_deg: float
) -> None:
    cov = covariance(sigma_u, sigma_v, axis_deg)
    seed = int(10 * sigma_u + sigma_v + axis_deg)
    image = noisy(probe(wide_particles(seed % 3), cov), seed, DOSE)
    measured = directional_widths(image)
    np.testing.assert_allclose(measured.widths_px, analytic_widths(cov), rtol=0.10)
    assert measured.width_px == edge_width(image)  # one detection, the same overall reading


@pytest.mark.parametrize(("sigma_u", "sigma_v", "axis_deg"), [(2.5, 1.0, 30.0), (4.0, 2.0, 120.0)])
def test_directional_widths_at_the_synthetic_sem_dose(
    sigma_u: float, sigma_v: float, axis_deg: float
) -> None:
    cov = covariance(sigma_u, sigma_v, axis_deg)
    measured = directional_widths(noisy(probe(wide_particles(1), cov), 11, dose=200.0))
    np.testing.assert_allclose(measured.widths_px, analytic_widths(cov), rtol=0.15)


@pytest.mark.parametrize(("sigma_u", "sigma_v"), [(2.5, 1.0), (4.0, 1.5)])
@pytest.mark.parametrize("axis_deg", AXES_DEG)
def test_astigmatism_and_axis_of_a_clearly_elliptical_probe(
    sigma_u: float, sigma_v: float, axis_deg: float
) -> None:
    cov = covariance(sigma_u, sigma_v, axis_deg)
    seed = int(10 * sigma_u + sigma_v + axis_deg)
    measured = directional_widths(noisy(probe(wide_particles(seed % 3), cov), seed, DOSE))
    assert measured.astigmatism_px == pytest.approx(K * (sigma_u - sigma_v), rel=0.10)
    axis_error = (math.degrees(measured.axis_rad) - axis_deg + 90.0) % 180.0 - 90.0
    assert abs(axis_error) < 10.0


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.5, 4.0])
def test_round_probe_reads_alike_in_every_direction(sigma: float) -> None:
    image = noisy(probe(wide_particles(int(sigma * 2) % 3), covariance(sigma, sigma, 0)), 5, DOSE)
    measured = directional_widths(image)
    assert measured.widths_px.max() / measured.widths_px.min() < 1.08, measured.widths_px
    assert measured.astigmatism_px < 0.1 * K * sigma
    np.testing.assert_allclose(measured.widths_px, K * sigma, rtol=0.10)


def test_bins_follow_the_pixel_axes() -> None:
    """The convention: normals at atan2(ny, nx) with x = column (right), y = row (down)."""
    specimen = wide_particles(0)
    along_x = directional_widths(noisy(probe(specimen, covariance(3.0, 1.2, 0.0)), 1, DOSE))
    assert np.argmax(along_x.widths_px) == 0  # blur along x widens edges with normal along x
    # Blur along the diagonal x = y (right and down) widens edges whose normal is at 45°.
    diagonal = directional_widths(noisy(probe(specimen, covariance(3.0, 1.2, 45.0)), 2, DOSE))
    assert np.argmax(diagonal.widths_px) == 1
    assert diagonal.axis_rad == pytest.approx(math.pi / 4, abs=math.radians(10))


def test_directional_widths_on_small_particles_of_the_synthetic_specimen_kind() -> None:
    """Particles of 4-14 px radius, overlapping, as the synthetic SEM draws them: a round
    probe still reads alike in all bins, close to edge_width, at the synthetic SEM's dose."""
    specimen = particles(256, 4, radius_px=(4.0, 14.0), gap_px=-1.0, count=25)
    image = noisy(probe(specimen, covariance(1.5, 1.5, 0.0)), 3)
    measured = directional_widths(image)
    np.testing.assert_allclose(measured.widths_px, measured.width_px, rtol=0.10)
    assert measured.width_px == pytest.approx(K * 1.5, rel=0.10)


def test_astigmatism_from_analytic_widths_is_exact() -> None:
    for sigma_u, sigma_v, axis_deg in [(3.0, 1.0, 0.0), (2.0, 1.5, 30.0), (4.0, 0.5, 170.0)]:
        astigmatism, axis = astigmatism_from_widths(
            analytic_widths(covariance(sigma_u, sigma_v, axis_deg))
        )
        assert astigmatism == pytest.approx(K * (sigma_u - sigma_v))
        assert axis == pytest.approx(math.radians(axis_deg))
    widths = np.array([2.0, 3.0, 4.0, 3.0])  # widest normal at 90°
    result = DirectionalWidths(width_px=3.0, widths_px=widths)
    assert (result.astigmatism_px, result.axis_rad) == astigmatism_from_widths(widths)
    assert result.axis_rad == pytest.approx(math.pi / 2)
    assert astigmatism_from_widths(np.full(4, 2.5)) == (0.0, 0.0)


@pytest.mark.parametrize(
    ("widths", "message"),
    [
        ([1.0, 2.0, 3.0], "four"),
        ([1.0, np.nan, 1.0, 1.0], "finite"),
        ([1.0, -1.0, 1.0, 1.0], "non-negative"),
    ],
)
def test_astigmatism_refuses_bad_widths(widths: list[float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        astigmatism_from_widths(np.array(widths))


def test_blank_and_noise_frames_have_no_directional_widths() -> None:
    with pytest.raises(NoEdgesError, match="no edges"):
        directional_widths(np.full((256, 256), 0.4))
    noise = 0.5 + 0.1 * np.random.default_rng(1).standard_normal((256, 256))
    with pytest.raises(NoEdgesError, match="no edges"):
        directional_widths(noise)


def test_edges_of_one_orientation_name_the_empty_bins() -> None:
    columns = np.arange(256)
    stripes = np.where((columns // 32) % 2 == 0, SUBSTRATE, PARTICLE)[None, :].repeat(256, 0)
    image = noisy(probe(stripes, covariance(2.0, 2.0, 0.0)), 4)
    assert edge_width(image) == pytest.approx(K * 2.0, rel=0.10)  # the image has edges ...
    with pytest.raises(NoEdgesError) as caught:  # ... all with normals along x
        directional_widths(image)
    message = str(caught.value)
    assert "normals near 45° or 90° or 135°" in message
    assert " 0°" not in message


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros(300), "2-D"),
        (np.zeros((8, 8)), "16x16"),
        (np.where(np.eye(64) > 0, np.nan, 0.5), "NaN"),
    ],
)
def test_directional_widths_refuse_bad_images(image: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message) as caught:
        directional_widths(image)
    assert not isinstance(caught.value, NoEdgesError)
    assert "directional_widths" in str(caught.value)


# --- wobble shift -----------------------------------------------------------------------


def sem_like_specimen(seed: int) -> np.ndarray:
    return particles(256, seed, radius_px=(4.0, 14.0), gap_px=-1.0, count=25)


@pytest.mark.parametrize(
    "shift",
    [(3.0, 0.0), (-3.0, 0.0), (0.0, 2.0), (0.0, -5.0), (1.37, -0.62), (-0.25, 0.4), (7.5, 4.25)],
)
@pytest.mark.parametrize("sigma", [1.5, 4.0])
def test_wobble_shift_recovers_known_shifts(shift: tuple[float, float], sigma: float) -> None:
    specimen = sem_like_specimen(int(10 * abs(shift[0]) + abs(shift[1])) % 5)
    cov = covariance(sigma, sigma, 0.0)
    minus = noisy(probe(specimen, cov), 1)
    plus = noisy(probe(specimen, cov, shift), 2)
    measured = wobble_shift(minus, plus)
    assert measured.shape == (2,)
    np.testing.assert_allclose(measured, shift, atol=0.2)


def test_wobble_shift_sign_convention() -> None:
    """A bright square at (x, y) in the minus frame and at (x + 5, y - 3) in the plus frame."""
    minus = np.full((128, 128), 0.2)
    minus[40:60, 50:70] = 0.8  # rows (y) 40-59, columns (x) 50-69
    plus = np.full((128, 128), 0.2)
    plus[37:57, 55:75] = 0.8
    rng = np.random.default_rng(0)
    minus += 0.02 * rng.standard_normal(minus.shape)
    plus += 0.02 * rng.standard_normal(plus.shape)
    np.testing.assert_allclose(wobble_shift(minus, plus), [5.0, -3.0], atol=0.2)
    np.testing.assert_allclose(wobble_shift(plus, minus), [-5.0, 3.0], atol=0.2)


def test_wobble_shift_with_different_blur_in_the_two_frames() -> None:
    """A wobble swings the focus: the two frames need not be equally blurred."""
    specimen = sem_like_specimen(7)
    minus = noisy(probe(specimen, covariance(1.5, 1.5, 0.0)), 3)
    plus = noisy(probe(specimen, covariance(4.0, 3.0, 60.0), (-2.3, 1.1)), 4)
    np.testing.assert_allclose(wobble_shift(minus, plus), [-2.3, 1.1], atol=0.2)


def test_wobble_shift_refuses_frames_without_a_correlation_peak() -> None:
    rng = np.random.default_rng(5)
    for _ in range(3):
        with pytest.raises(MeasurementError, match="no correlation peak above the noise"):
            wobble_shift(rng.standard_normal((256, 256)), rng.standard_normal((256, 256)))
    shot = rng.poisson(20.0, (2, 256, 256)).astype(np.float32)
    with pytest.raises(MeasurementError, match="no correlation peak"):
        wobble_shift(shot[0], shot[1])
    # Blurred to sigma = 30 px the particles are gone: nothing left to correlate.
    specimen = sem_like_specimen(1)
    cov = covariance(30.0, 30.0, 0.0)
    with pytest.raises(MeasurementError, match="no correlation peak"):
        wobble_shift(noisy(probe(specimen, cov), 1), noisy(probe(specimen, cov, (2, 1)), 2))


def test_wobble_shift_refuses_a_blank_frame() -> None:
    frame = noisy(probe(sem_like_specimen(0), covariance(1.5, 1.5, 0.0)), 0)
    with pytest.raises(MeasurementError, match="blank"):
        wobble_shift(frame, np.full_like(frame, 0.3))
    with pytest.raises(MeasurementError, match="blank"):
        wobble_shift(np.zeros((64, 64)), np.zeros((64, 64)))


@pytest.mark.parametrize(
    ("minus", "plus", "message"),
    [
        (np.zeros((64, 64)), np.zeros((64, 80)), "one shape"),
        (np.full((64, 64), np.nan), np.zeros((64, 64)), "NaN"),
        (np.zeros(64), np.zeros(64), "2-D"),
    ],
)
def test_wobble_shift_refuses_bad_frames(minus: np.ndarray, plus: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message) as caught:
        wobble_shift(minus, plus)
    assert not isinstance(caught.value, MeasurementError)


def test_a_frame_whose_extra_points_miss_every_trusted_edge_is_measured() -> None:
    """A synthetic-b frame (recorded by the analytic-agreement benchmark) where none of the
    points sampled for the orientation bins lies on a trusted edge: cv2.remap used to be
    handed zero rows and raised cv2.error instead of a measurement."""
    frame = np.load(Path(__file__).with_name("data") / "directional-no-trusted-points.npz")
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # OpenCV's threading moves the points a little; with one, it hit
    try:
        measured = directional_widths(frame["frame"])
    finally:
        cv2.setNumThreads(threads)
    assert np.all(np.isfinite(measured.widths_px))
    assert measured.width_px == pytest.approx(edge_width(frame["frame"]))


@pytest.mark.parametrize(
    ("reset_seed", "stigmators"),
    [(406590133, (-13.94, -52.9)), (3191017431, (-54.23, -29.47))],
    ids=["scenario-45", "scenario-96"],
)
def test_one_segment_measured_across_a_neighbour_does_not_widen_its_bin(
    reset_seed: int, stigmators: tuple[float, float]
) -> None:
    """Regression: two columns of the held-out stigmation session (seed 0, scenarios 45 and 96)
    that an aligner left nearly round (edge width 1.05-1.11 x the best) failed their
    verification on one bin read at 1.4-1.7 x: a single segment, measured across a
    neighbouring particle's rim, read 10-12 px among segments of 2.5-3 px and pulled its bin's
    mean up (at scenario 96's setting in 9 of 12 frames). Segments that far from their bin's
    median are now dropped; the bins read within 1.2 x the best in every frame."""
    from alignrl.apparatus import make_apparatus

    sem = make_apparatus("synthetic")
    sem.reset(reset_seed)
    # Every other knob at its optimum, the stigmators where the aligner left them.
    sem.write({**sem.optimum(), "stigmator_x": stigmators[0], "stigmator_y": stigmators[1]})
    best = sem.best_quality()
    ratios = np.array([directional_widths(sem.acquire()).widths_px / best for _ in range(12)])
    assert ratios.max() < 1.2, ratios.round(2)
    assert ratios.min() > 1.0, ratios.round(2)


def test_the_image_measures_stay_importable_from_quality() -> None:
    """alignrl.apparatus.quality is the front door of the image measures (design.md)."""
    assert quality.directional_widths is directional.directional_widths
    assert quality.astigmatism_from_widths is directional.astigmatism_from_widths
    assert quality.DirectionalWidths is directional.DirectionalWidths
    assert quality.ORIENTATION_BINS_DEG is directional.ORIENTATION_BINS_DEG
    assert quality.wobble_shift is wobble.wobble_shift
    assert quality.TEN_NINETY_PER_SIGMA == TEN_NINETY_PER_SIGMA

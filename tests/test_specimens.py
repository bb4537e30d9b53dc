"""The specimens of the instrument family's image path (alignrl/apparatus/specimens.py).

They must be what the image path assumes: yields within [0, 1.2]; periodic, so the FFT blur
leaves no border artefact; drawn from the generator alone (same seed, same specimen); and
sharp, so that `edge_width` reads 2.563 sigma (within 20 %) for a probe of 1-4 px, grows
with the probe up to 8 px, and finds nothing (NoEdgesError, never another exception) on a
flat frame or one blurred by 200 px. The blur and the noise of `render` are checked against
their definitions.
"""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, edge_width
from alignrl.apparatus.specimens import SPECIMENS, blur, draw_specimen, render

SIZE = 256
DOSE = 200.0  # electrons per pixel, as the synthetic SEM
DETECTOR_NOISE = 0.01


def specimen_fft(kind: str, seed: int, size: int = SIZE) -> np.ndarray:
    return np.fft.rfft2(draw_specimen(kind, size, np.random.default_rng(seed)))


def frame(kind: str, seed: int, sigma_px: float) -> np.ndarray:
    noise_rng = np.random.default_rng([seed, 7])
    return render(specimen_fft(kind, seed), sigma_px, SIZE, DOSE, DETECTOR_NOISE, noise_rng)


def seam_ratio(image: np.ndarray) -> tuple[float, float]:
    """(mean |difference| across the wrap-around, mean over the interior neighbours), over
    columns and rows together."""
    wrap, interior = [], []
    for axis in (0, 1):
        steps = np.abs(np.diff(image, axis=axis, append=np.take(image, [0], axis=axis)))
        per_line = steps.mean(axis=1 - axis)  # one value per neighbouring pair of lines
        wrap.append(per_line[-1])
        interior.append(per_line[:-1].mean())
    return float(np.mean(wrap)), float(np.mean(interior))


# --- the catalogue ----------------------------------------------------------------------


def test_the_kinds_are_the_five_of_the_family() -> None:
    assert SPECIMENS == ("particles", "grid", "bars", "fibres", "texture")


def test_unknown_kind_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="unknown") as caught:
        draw_specimen("gold-on-carbon", SIZE, np.random.default_rng(0))
    for kind in SPECIMENS:
        assert kind in str(caught.value)


@pytest.mark.parametrize("size", [8, 31, 64.0, True])
def test_bad_size_is_refused(size: object) -> None:
    with pytest.raises(ValueError, match="size"):
        draw_specimen("grid", size, np.random.default_rng(0))  # type: ignore[arg-type]


# --- the specimens themselves -----------------------------------------------------------


@pytest.mark.parametrize("kind", SPECIMENS)
@pytest.mark.parametrize("size", [32, 100, SIZE])
def test_yields_are_substrate_and_features_within_range(kind: str, size: int) -> None:
    specimen = draw_specimen(kind, size, np.random.default_rng(3))
    assert specimen.shape == (size, size)
    assert specimen.dtype == np.float64
    assert np.all(np.isfinite(specimen))
    assert specimen.min() >= 0.0 and specimen.max() <= 1.2
    # A dark substrate and bright features, neither filling the frame.
    dark, bright = np.mean(specimen < 0.4), np.mean(specimen > 0.7)
    assert 0.05 < dark < 0.99, dark
    assert 0.01 < bright < 0.95, bright


@pytest.mark.parametrize("kind", SPECIMENS)
def test_same_seed_same_specimen_other_seed_other_specimen(kind: str) -> None:
    first = draw_specimen(kind, SIZE, np.random.default_rng(11))
    again = draw_specimen(kind, SIZE, np.random.default_rng(11))
    other = draw_specimen(kind, SIZE, np.random.default_rng(12))
    np.testing.assert_array_equal(first, again)
    assert np.mean(np.abs(first - other)) > 0.01


@pytest.mark.parametrize("kind", SPECIMENS)
def test_no_seam_at_the_frame_edges(kind: str) -> None:
    """Across the wrap-around the (slightly blurred) specimen changes as much as between
    interior neighbours; a frame cut out of a specimen (not periodic) shows a seam."""
    wraps, interiors = zip(
        *(seam_ratio(blur(specimen_fft(kind, seed), 1.0, SIZE)) for seed in range(6)),
        strict=True,
    )
    assert np.mean(wraps) < 2.5 * np.mean(interiors), (np.mean(wraps), np.mean(interiors))
    for wrap, interior in zip(wraps, interiors, strict=True):
        assert wrap < 12.0 * interior  # no single draw with a seam either
    cut = draw_specimen(kind, SIZE, np.random.default_rng(0))[:224, :224]
    wrap, interior = seam_ratio(blur(np.fft.rfft2(cut), 1.0, 224))
    assert wrap > 4.0 * interior, (wrap, interior)  # the check does see a seam


# --- blur and render ----------------------------------------------------------------------


def test_blur_by_zero_is_the_specimen_and_blur_keeps_the_mean() -> None:
    specimen = draw_specimen("texture", 64, np.random.default_rng(0))
    transform = np.fft.rfft2(specimen)
    np.testing.assert_allclose(blur(transform, 0.0, 64), specimen, atol=1e-12)
    blurred = blur(transform, 3.0, 64)
    assert blurred.shape == (64, 64)
    assert blurred.mean() == pytest.approx(specimen.mean(), abs=1e-12)
    assert blurred.std() < 0.9 * specimen.std()


def test_blur_of_a_point_is_a_gaussian_of_sigma_px() -> None:
    point = np.zeros((64, 64))
    point[20, 40] = 1.0
    spot = blur(np.fft.rfft2(point), 2.5, 64)
    rows, columns = np.indices(spot.shape)
    assert spot.sum() == pytest.approx(1.0)
    assert np.sum(spot * rows) == pytest.approx(20.0, abs=1e-9)
    assert np.sum(spot * columns) == pytest.approx(40.0, abs=1e-9)
    assert np.sum(spot * (rows - 20.0) ** 2) == pytest.approx(2.5**2, rel=1e-6)
    assert np.sum(spot * (columns - 40.0) ** 2) == pytest.approx(2.5**2, rel=1e-6)


def test_blur_refuses_a_wrong_transform_or_sigma() -> None:
    transform = np.fft.rfft2(np.zeros((64, 64)))
    with pytest.raises(ValueError, match="rfft2"):
        blur(transform, 1.0, 32)
    with pytest.raises(ValueError, match="sigma_px"):
        blur(transform, -1.0, 64)
    with pytest.raises(ValueError, match="sigma_px"):
        blur(transform, float("nan"), 64)


@pytest.mark.parametrize("dose", [DOSE, 8.0])  # the Gaussian limit, and Poisson counts
def test_render_noise_is_shot_noise_plus_detector_noise(dose: float) -> None:
    level = 0.5
    transform = np.fft.rfft2(np.full((128, 128), level))
    image = render(transform, 2.0, 128, dose, 0.02, np.random.default_rng(5))
    assert image.dtype == np.float32 and image.shape == (128, 128)
    assert image.mean() == pytest.approx(level, abs=0.005)
    expected_std = np.sqrt(level / dose + 0.02**2)
    assert image.std() == pytest.approx(expected_std, rel=0.05)


def test_render_counts_whole_electrons_at_low_dose_and_is_reproducible() -> None:
    transform = specimen_fft("particles", 1, 64)
    image = render(transform, 1.0, 64, 8.0, 0.0, np.random.default_rng(2))
    electrons = image.astype(np.float64) * 8.0
    np.testing.assert_allclose(electrons, np.round(electrons), atol=1e-4)
    again = render(transform, 1.0, 64, 8.0, 0.0, np.random.default_rng(2))
    np.testing.assert_array_equal(image, again)


def test_render_refuses_a_bad_dose_or_noise() -> None:
    transform = np.fft.rfft2(np.full((64, 64), 0.5))
    with pytest.raises(ValueError, match="dose"):
        render(transform, 1.0, 64, 0.0, 0.01, np.random.default_rng(0))
    with pytest.raises(ValueError, match="detector_noise"):
        render(transform, 1.0, 64, DOSE, -0.1, np.random.default_rng(0))


# --- what the edge measure reads on them ------------------------------------------------


@pytest.mark.parametrize("kind", SPECIMENS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_width_reads_the_probe_within_20_percent(kind: str, seed: int) -> None:
    for sigma in (1.0, 2.5, 4.0):
        width = edge_width(frame(kind, seed, sigma))
        expected = TEN_NINETY_PER_SIGMA * sigma
        assert width == pytest.approx(expected, rel=0.2), (sigma, width, expected)


@pytest.mark.parametrize("kind", SPECIMENS)
def test_edge_width_grows_with_the_probe_up_to_8_px(kind: str) -> None:
    widths = [edge_width(frame(kind, 4, sigma)) for sigma in (1.0, 2.0, 3.0, 4.0, 6.0, 8.0)]
    assert np.all(np.diff(widths) > 0), widths


@pytest.mark.parametrize("kind", SPECIMENS)
def test_a_hopelessly_blurred_frame_has_no_edges(kind: str) -> None:
    with pytest.raises(NoEdgesError):
        edge_width(frame(kind, 0, 200.0))


@pytest.mark.parametrize("level", [0.25, 0.9])
def test_a_flat_frame_has_no_edges(level: float) -> None:
    flat = np.fft.rfft2(np.full((SIZE, SIZE), level))
    noisy = render(flat, 1.0, SIZE, DOSE, DETECTOR_NOISE, np.random.default_rng(0))
    with pytest.raises(NoEdgesError):
        edge_width(noisy)
    with pytest.raises(NoEdgesError):
        edge_width(np.full((SIZE, SIZE), level, dtype=np.float32))


@pytest.mark.parametrize("kind", SPECIMENS)
def test_far_out_of_focus_a_width_or_no_edges_never_another_error(kind: str) -> None:
    for sigma in (12.0, 35.0, 100.0, 1000.0):
        try:
            width = edge_width(frame(kind, 1, sigma))
        except NoEdgesError:
            continue
        assert np.isfinite(width) and width > 0, (sigma, width)

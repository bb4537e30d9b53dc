"""Wobble shift: how far the image moves between two frames of a wobbled lens, in pixels.

Lens wobbling (defocus swung to -d and +d) shifts the image when the beam is off the lens
axis; `wobble_shift` measures that shift (dx, dy) between the two frames by phase
correlation, refined to a few hundredths of a pixel, and raises `MeasurementError` where the
frames share nothing to correlate.
"""

from __future__ import annotations

import cv2
import numpy as np

from alignrl.apparatus.base import MeasurementError
from alignrl.apparatus.edge_profiles import as_gray

__all__ = ["wobble_shift"]

# Phase-correlation peak in units of a noise-only pair's (_capture_shift). Measured on 3,600
# pairs of pure noise, shot noise or unrelated textures (64-512 px): 99 % score below 36, the
# highest 45; frames of one specimen blurred up to sigma = 8 px score 56 and more.
WOBBLE_MIN_SCORE = 50.0
WOBBLE_MIN_LEVEL_PX = 32  # smallest pyramid level searched for the peak
WOBBLE_MAX_ITERATIONS = 20  # Lucas-Kanade steps; three or four settle a captured shift
WOBBLE_SETTLED_PX = 0.01  # ... to a step this small, well below the noise of the estimate


def wobble_shift(image_minus: np.ndarray, image_plus: np.ndarray) -> np.ndarray:
    """Displacement (dx, dy) px of image_plus's content against image_minus's.

    A feature at (x, y) in image_minus appears at (x + dx, y + dy) in image_plus (x = column,
    y = row). Two steps:

    * Capture: OpenCV's phase correlation (Hanning-windowed) on the frames and on their
      Gaussian pyramid. Phase correlation whitens the spectrum, so it finds the shift
      whatever the blur, but every frequency counts alike: on a blurred frame most of them
      are noise, the peak broadens past OpenCV's 5x5 centroid and the sub-pixel estimate is
      off by up to pixels. The pyramid level where the frames agree best (the highest peak
      in units of the noise's) gives a shift good to a pixel or two, and says whether
      there is a peak at all.
    * Refinement: Lucas-Kanade least squares on the full frames, smoothed at that level's
      scale, weighted by the same window: it weighs each frequency by its power, as a
      matched filter does, and reaches a few hundredths of a pixel on focused frames.

    MeasurementError where the peak does not stand out of the noise (blank or unrelated
    frames, pure noise, a blur that leaves nothing to correlate); ValueError for unusable
    input.
    """
    minus = as_gray(image_minus, "wobble_shift").astype(np.float64)
    plus = as_gray(image_plus, "wobble_shift").astype(np.float64)
    if minus.shape != plus.shape:
        raise ValueError(
            f"wobble_shift needs two frames of one shape, got {minus.shape} and {plus.shape}"
        )
    for frame, name in ((minus, "minus"), (plus, "plus")):
        if np.ptp(frame) == 0:
            raise MeasurementError(f"wobble: the {name} frame is blank")
    minus -= minus.mean()
    plus -= plus.mean()
    shift, factor = _capture_shift(minus, plus)
    return _refine_shift(minus, plus, shift, smoothing_px=float(factor))


def _capture_shift(minus: np.ndarray, plus: np.ndarray) -> tuple[np.ndarray, int]:
    """Phase-correlation shift (px) at the pyramid level where the frames agree best, and
    that level's pixel size (px); MeasurementError where no level has a peak.

    OpenCV's response sums the correlation surface over the 5x5 pixels around the peak.
    For a noise-only pair the whitened surface is itself white noise of unit total power,
    each of its N pixels of standard deviation 1 / sqrt(N): response x sqrt(N) puts every
    level, and every frame size, on one scale.
    """
    best = (-np.inf, 0.0, np.zeros(2), 1)  # (score, response, shift px, pixel size px)
    factor = 1
    while True:
        window = cv2.createHanningWindow(minus.shape[::-1], cv2.CV_64F)
        (dx, dy), response = cv2.phaseCorrelate(minus, plus, window)
        score = response * np.sqrt(minus.size)
        if score > best[0]:
            best = (score, response, factor * np.array([dx, dy]), factor)
        if min(minus.shape) < 2 * WOBBLE_MIN_LEVEL_PX:
            break
        minus, plus, factor = cv2.pyrDown(minus), cv2.pyrDown(plus), 2 * factor
    score, response, shift, factor = best
    if not score >= WOBBLE_MIN_SCORE:
        raise MeasurementError(
            f"wobble: no correlation peak above the noise (response {response:.3f}, "
            f"{score:.0f} in units of the noise's, needs {WOBBLE_MIN_SCORE:.0f})"
        )
    return shift, factor


def _refine_shift(
    minus: np.ndarray, plus: np.ndarray, shift: np.ndarray, smoothing_px: float
) -> np.ndarray:
    """Lucas-Kanade refinement of a shift: minimise sum w (plus(x + d) - minus(x))^2.

    Both frames are smoothed alike (a common blur moves nothing) so that noise in the
    gradients does not bias the estimate towards zero; the Hanning weights keep out the
    border, where the shifted frame is made up.
    """
    sigma = max(1.0, smoothing_px)
    minus = cv2.GaussianBlur(minus, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    plus = cv2.GaussianBlur(plus, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    weights = cv2.createHanningWindow(minus.shape[::-1], cv2.CV_64F)
    size = minus.shape[::-1]
    shift = np.array(shift, dtype=np.float64)
    for _ in range(WOBBLE_MAX_ITERATIONS):
        back = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
        aligned = cv2.warpAffine(  # aligned(x) = plus(x + shift)
            plus,
            back,
            size,
            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REFLECT,
        )
        # The mean gradient of both frames: the linearisation error is then second order.
        mean = 0.5 * (minus + aligned)
        grad_x = cv2.Sobel(mean, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
        grad_y = cv2.Sobel(mean, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
        difference = weights * (aligned - minus)
        wx, wy = weights * grad_x, weights * grad_y
        normal = np.array(
            [[np.sum(wx * grad_x), np.sum(wx * grad_y)], [np.sum(wx * grad_y), np.sum(wy * grad_y)]]
        )
        eigen = np.linalg.eigvalsh(normal)
        if not eigen[0] > 1e-6 * eigen[1]:
            raise MeasurementError("wobble: the frames have structure along one direction only")
        step = -np.linalg.solve(normal, [np.sum(difference * grad_x), np.sum(difference * grad_y)])
        shift += step
        if np.hypot(*step) < WOBBLE_SETTLED_PX:
            return shift
    raise MeasurementError(f"wobble: the shift did not settle (last step {np.hypot(*step):.3f} px)")

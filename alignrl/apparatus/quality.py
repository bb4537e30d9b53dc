"""Image quality: edge widths in pixels (seed section 6.2), by direction, and image shifts.

A focused beam gives sharp edges; a defocused one spreads each edge over more pixels. The
algorithm detects edges with OpenCV's Canny detector, samples the intensity profile across
every edge point along its gradient direction, averages the aligned profiles of each connected
edge, and measures each edge's 10-90 % rise distance on its averaged profile. The result is the
mean over edges, weighted by their length. For a straight step blurred by a Gaussian of
standard deviation sigma this is 2 * 1.2816 * sigma = 2.563 sigma.

Detection thresholds are tied to the image's own noise level (estimated robustly from the
Laplacian), so an image of pure noise, a blank frame or a hopelessly defocused one raises
`NoEdgesError` instead of returning a number measured on nothing.

An astigmatic probe is an elliptical Gaussian of covariance C: it widens an edge of unit
normal n to TEN_NINETY_PER_SIGMA * sqrt(n^T C n), so edges of different orientations have
different widths. `directional_widths` splits the same edges by the orientation of their
normals into four bins (ORIENTATION_BINS_DEG) and measures each bin, from one detection;
`astigmatism_from_widths` turns four such widths into the probe's astigmatism and axis.

Lens wobbling (defocus swung to -d and +d) shifts the image when the beam is off the lens
axis; `wobble_shift` measures that shift between the two frames by phase correlation, refined
to a few hundredths of a pixel, and raises `MeasurementError` where the frames share nothing
to correlate.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import cv2
import numpy as np

from alignrl.apparatus.base import MeasurementError, NoEdgesError

__all__ = [
    "ORIENTATION_BINS_DEG",
    "TEN_NINETY_PER_SIGMA",
    "DirectionalWidths",
    "EdgeMeasurement",
    "astigmatism_from_widths",
    "directional_widths",
    "edge_width",
    "measure_edges",
    "wobble_shift",
]

TEN_NINETY_PER_SIGMA = 2.0 * 1.2815515655446004  # 10-90 % width of a Gaussian-blurred step
# Orientation bins of the edge normal (x = column, y = row; angle atan2(ny, nx) mod 180°),
# each +/- 22.5° wide.
ORIENTATION_BINS_DEG = (0.0, 45.0, 90.0, 135.0)

# Smoothing scales tried for detection, finest first; they locate edges, never measure them.
DETECTION_SIGMAS_PX = (1.5, 3.0, 6.0)
PROFILE_STEP_PX = 0.5  # sampling pitch along the edge normal
MAX_HALF_WINDOW_PX = 40.0  # widest profile half-length: edges up to sigma ~ 9 px measured exactly
MIN_EDGE_POINTS = 8  # an edge shorter than this is too noisy to measure
# Trusted edge points below which a reading is checked at the next coarser scale: in a blurred
# frame the finest scale can trust one short spurious edge (a 4 px reading of a frame whose
# edges are 8 px wide, ~2 % of frames 10-15 V out of focus on synthetic-b), where a coarser
# scale finds the real edges. The scale with the most trusted points gives the reading.
THIN_SUPPORT_POINTS = 200
MAX_EDGE_POINTS = 1000  # edge points sampled per image; more only costs time
# ... and for directional widths, whose four bins share them, twice as many: a bin's scatter
# drops by ~1.4 at a cost that only frames with over 1000 edge pixels notice.
DIRECTIONAL_MAX_EDGE_POINTS = 2 * MAX_EDGE_POINTS
# A segment whose width is this far (either way) from the point-weighted median of its bin's
# segments is dropped from the bin: within one orientation bin every segment sees the same
# probe width, but now and then one is measured across a neighbouring particle's rim and
# reads 3-4 x the rest (~2 % of nearly round frames on `synthetic`, a bin at 1.7 x the best
# width where the probe gives 1.08 x). An elliptical probe widens bins against each other,
# never the segments of one bin.
SEGMENT_OUTLIER_RATIO = 2.0
DETECTION_SNR = 6.0  # gradient threshold in units of the noise's gradient std (Rayleigh tail 1e-8)
MIN_CONTRAST_SNR = 5.0  # an edge's step must stand this far above its averaged noise
COARSE_SCALE_MIN_SIGMA = 0.75  # at a coarse scale, edges must be at least this wide (x scale)
SELECTION_MARGIN = 1.5  # ... and this far above the step that detection alone selects from noise

# Phase-correlation peak in units of a noise-only pair's (_capture_shift). Measured on 3,600
# pairs of pure noise, shot noise or unrelated textures (64-512 px): 99 % score below 36, the
# highest 45; frames of one specimen blurred up to sigma = 8 px score 56 and more.
WOBBLE_MIN_SCORE = 50.0
WOBBLE_MIN_LEVEL_PX = 32  # smallest pyramid level searched for the peak
WOBBLE_MAX_ITERATIONS = 20  # Lucas-Kanade steps; three or four settle a captured shift
WOBBLE_SETTLED_PX = 0.01  # ... to a step this small, well below the noise of the estimate


@dataclass(frozen=True)
class EdgeMeasurement:
    """What the edge-width algorithm saw in one image."""

    width_px: float  # length-weighted mean 10-90 % width of the measured edges
    edge_widths_px: np.ndarray  # per measured edge
    edge_points: np.ndarray  # edge points (pixels) behind each measured edge
    noise_std: float  # estimated pixel noise, image units
    detection_sigma_px: float  # smoothing scale at which the edges were found


def estimate_noise_std(image: np.ndarray) -> float:
    """Standard deviation of white pixel noise, robust to edges (median of a Laplacian mask).

    The mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth intensity and multiplies white noise
    by 6; the median absolute response ignores the few pixels that sit on edges.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    image = np.asarray(image, dtype=np.float32)
    response = cv2.filter2D(image, cv2.CV_32F, mask, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    return float(1.4826 * np.median(np.abs(response)) / 6.0)


def _as_gray(image: np.ndarray, caller: str) -> np.ndarray:
    """The image as a float32 grey array; ValueError, naming `caller`, where it is unusable."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] in (1, 3, 4):
        array = array[..., :3].mean(axis=2)
    if array.ndim != 2:
        raise ValueError(f"{caller} needs a 2-D grey image, got an array of shape {array.shape}")
    if min(array.shape) < 16:
        raise ValueError(f"{caller} needs at least 16x16 pixels, got {array.shape}")
    gray = array.astype(np.float32)
    if not np.all(np.isfinite(gray)):
        raise ValueError(f"{caller}: the image contains NaN or infinite pixels")
    return gray


def _segment_means(profiles: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Mean profile of each edge (rows sorted by edge); NaN where too few stay in the image."""
    finite = np.isfinite(profiles)
    sums = np.add.reduceat(np.where(finite, profiles, 0.0), starts, axis=0)
    valid = np.add.reduceat(finite.astype(np.int32), starts, axis=0)
    means = sums / np.maximum(valid, 1)
    enough = valid >= np.maximum(3, counts // 4)[:, None]
    return np.where(enough, means, np.nan)


def _row_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of each row over its finite, masked entries (NaN where there are none)."""
    chosen = mask & np.isfinite(values)
    ordered = np.sort(np.where(chosen, values, np.inf), axis=1)  # masked-out entries last
    count = chosen.sum(axis=1)
    rows = np.arange(values.shape[0])
    upper = ordered[rows, np.maximum(count, 1) // 2]
    lower = ordered[rows, np.maximum(count - 1, 0) // 2]
    return np.where(count > 0, 0.5 * (upper + lower), np.nan)


def _ten_ninety(
    profiles: np.ndarray, t: np.ndarray, half_window: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """10-90 % rise distance of rising edge profiles centred at t = 0 (one per row).

    Only the samples with |t| <= half_window of each row count. The dark and bright levels
    are medians over the outer half of each side: extremes (min, max) of a noisy profile
    overstate the step and widen the span, while the outer half of a ~4 sigma window lies
    beyond 2 sigma, where a Gaussian edge is flat. The crossings are searched outwards from
    the centre, so other features inside the window cannot create false ones.
    Returns (width, dark level, bright level); width is NaN where a row has no clean rise.
    """
    rows = np.arange(profiles.shape[0])
    centre = int(np.argmin(np.abs(t)))
    window = np.abs(t)[None, :] <= half_window[:, None] + 1e-9
    dark = window & (t[None, :] <= -0.5 * half_window[:, None])
    bright = window & (t[None, :] >= 0.5 * half_window[:, None])
    low = _row_medians(profiles, dark)
    high = _row_medians(profiles, bright)
    contrast = high - low
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = np.where(window, (profiles - low[:, None]) / contrast[:, None], np.nan)
    index = np.arange(t.size)
    below = (rise <= 0.1) & (index <= centre)
    above = (rise >= 0.9) & (index >= centre)
    left = np.where(below, index, -1).max(axis=1)
    right = np.where(above, index, t.size).min(axis=1)
    ok = (contrast > 0) & (left >= 0) & (right < t.size)
    ok &= (rise[:, centre] > 0.1) & (rise[:, centre] < 0.9)
    left, right = np.where(ok, left, 0), np.where(ok, right, 1)
    r_left, r_left_next = rise[rows, left], rise[rows, left + 1]
    r_right_prev, r_right = rise[rows, right - 1], rise[rows, right]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Linear interpolation between the samples that straddle each level.
        t10 = t[left] + (0.1 - r_left) / (r_left_next - r_left) * PROFILE_STEP_PX
        t90 = t[right - 1] + (0.9 - r_right_prev) / (r_right - r_right_prev) * PROFILE_STEP_PX
    width = np.where(ok, t90 - t10, np.nan)
    width[~np.isfinite(width)] = np.nan
    return width, low, high


def _fit_window(
    profiles: np.ndarray, t: np.ndarray, max_half: float, start: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """10-90 % widths measured in a window of ~4 sigma each side of each edge.

    Four sigma reaches both plateaus of a Gaussian edge and keeps neighbouring features out;
    the window is iterated from `start` (default: a guess of sigma ~ 2 px). A window is only
    accepted where the levels are flat beyond it: on a wide ramp a small window would find
    a self-consistent but false narrow "edge" in the noise, so where the step continues
    outside the window, the window is doubled.
    Returns (width, half window, dark level, bright level) per row.
    """
    half_window = np.full(profiles.shape[0], min(10.0, max_half)) if start is None else start
    floor = np.zeros_like(half_window)  # windows proven too small, doubled
    for _ in range(8):
        width, low, high = _ten_ninety(profiles, t, half_window)
        continuing = _step_continues(profiles, t, half_window, low, high, max_half)
        floor = np.where(continuing, np.minimum(2.0 * half_window, max_half), floor)
        sigma = width / TEN_NINETY_PER_SIGMA
        new_half = np.maximum(np.clip(4.0 * sigma + 3.0, 4.0, max_half), floor)
        new_half = np.where(continuing, floor, new_half)
        moving = (np.isfinite(width) | continuing) & (
            np.abs(new_half - half_window) >= PROFILE_STEP_PX
        )
        if not moving.any():
            break
        half_window = np.where(moving, new_half, half_window)
    width = np.where(continuing, np.nan, width)  # never settled on a flat window
    return width, half_window, low, high


def _step_continues(
    profiles: np.ndarray,
    t: np.ndarray,
    half_window: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    max_half: float,
) -> np.ndarray:
    """Whether the intensity keeps rising beyond the window (by over 30 % of the step).

    Only a continuation in the edge's own direction counts: a neighbouring particle makes the
    dark side brighter or the bright side darker, which says nothing about this edge.
    """
    outer = np.minimum(2.0 * half_window, max_half)
    beyond_dark = (t[None, :] >= -outer[:, None]) & (t[None, :] < -half_window[:, None])
    beyond_bright = (t[None, :] <= outer[:, None]) & (t[None, :] > half_window[:, None])
    darker = low - _row_medians(profiles, beyond_dark)
    brighter = _row_medians(profiles, beyond_bright) - high
    rise = np.nan_to_num(np.maximum(darker, 0.0)) + np.nan_to_num(np.maximum(brighter, 0.0))
    with np.errstate(invalid="ignore"):
        return (rise > 0.3 * (high - low)) & (half_window < max_half)


def _realign(
    profiles: np.ndarray,
    t: np.ndarray,
    mid_level: np.ndarray,
    sigma_px: np.ndarray,
    half_window: np.ndarray,
) -> np.ndarray:
    """Shift each profile so that its mid-level crossing nearest the centre sits at t = 0.

    On a wide, noisy edge Canny's pixel wanders off the true edge by more than the parabola
    can correct, and averaging misaligned profiles would widen the edge. The crossing is
    found on a copy smoothed over ~ sigma: a symmetric box steadies the crossing without
    moving it. All arguments but t are per row.
    """
    rows = np.arange(profiles.shape[0])
    centre = int(np.argmin(np.abs(t)))
    radius = np.maximum(0, np.round(0.5 * sigma_px / PROFILE_STEP_PX)).astype(np.int64)
    smooth = np.empty_like(profiles)
    for box_radius in np.unique(radius):
        same = radius == box_radius
        size = (2 * int(box_radius) + 1, 1)
        smooth[same] = cv2.blur(profiles[same], size, borderType=cv2.BORDER_REPLICATE)
    above = smooth >= mid_level[:, None]
    crossing = above[:, 1:] != above[:, :-1]  # (points, samples - 1)
    crossing &= np.isfinite(smooth[:, 1:]) & np.isfinite(smooth[:, :-1])
    gap_centre = np.arange(crossing.shape[1]) + 0.5 - centre  # samples from the centre
    search = np.maximum(1.0, 0.5 * half_window / PROFILE_STEP_PX)
    crossing &= np.abs(gap_centre)[None, :] <= search[:, None]
    distance = np.where(crossing, np.abs(gap_centre)[None, :], np.inf)
    nearest = np.argmin(distance, axis=1)
    found = np.isfinite(distance[rows, nearest])
    before, after = smooth[rows, nearest], smooth[rows, nearest + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(found, (mid_level - before) / (after - before), 0.0)
    shift = np.where(found, t[nearest] + fraction * PROFILE_STEP_PX, 0.0)  # px
    # Resample each profile at t + shift: the profiles form an image, rows stay rows.
    grid = ((t - t[0]) / PROFILE_STEP_PX).astype(np.float32)
    sample_x = grid[None, :] + (shift / PROFILE_STEP_PX).astype(np.float32)[:, None]
    sample_y = np.repeat(rows.astype(np.float32)[:, None], grid.size, axis=1)
    return cv2.remap(
        profiles,
        sample_x,
        sample_y,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )


@dataclass(frozen=True)
class _Found:
    """Edge pixels found at one smoothing scale, before any profile is sampled."""

    grad_x: np.ndarray  # gradient of the smoothed image, per pixel
    grad_y: np.ndarray
    magnitude: np.ndarray
    labels: np.ndarray  # connected edge of each pixel (0 off the edges)
    ys: np.ndarray  # edge pixels, raster order
    xs: np.ndarray
    detection_sigma: float  # smoothing scale, px
    noise_gradient: float  # std of one gradient component of the smoothed noise


@dataclass(frozen=True)
class _EdgePoints:
    """Sampled edge points and the intensity profiles across them."""

    labels: np.ndarray  # connected edge of each point
    normal_x: np.ndarray  # unit normal from the dark to the bright side, x = column (right)
    normal_y: np.ndarray  # ... y = row (down)
    gradient: np.ndarray  # gradient magnitude of the smoothed image at each point
    profiles: np.ndarray  # (points, samples): intensity along the normal, rising
    t: np.ndarray  # positions of the samples along the normal, px
    max_half: float  # widest profile half-length, px
    detection_sigma: float  # smoothing scale of the detection, px
    noise_gradient: float  # std of one gradient component of the smoothed noise


def _find_edges(gray: np.ndarray, noise_std: float, detection_sigma: float) -> _Found | str:
    """Canny edge pixels at one smoothing scale, labelled by connected edge, or why none."""
    smooth = cv2.GaussianBlur(gray, (0, 0), detection_sigma, borderType=cv2.BORDER_REFLECT)
    # Sobel with ksize 3 sums 8 weighted differences: divide by 8 for a per-pixel derivative.
    grad_x = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    grad_y = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    magnitude = np.hypot(grad_x, grad_y)

    # Std of one derivative of Gaussian-smoothed white noise: sigma_n / (sqrt(8 pi) s^2).
    noise_gradient = noise_std / (np.sqrt(8.0 * np.pi) * detection_sigma**2)
    strong = float(np.percentile(magnitude[::2, ::2], 99.5))  # a subsample is plenty
    high = max(DETECTION_SNR * noise_gradient, 0.25 * strong)
    low = max(0.5 * DETECTION_SNR * noise_gradient, 0.1 * strong)
    if strong <= 0 or high <= 0 or magnitude.max() < high:
        return "the image has no intensity step above its noise"

    # Canny on our own gradients (int16, as OpenCV wants them), so thresholds stay physical.
    scale = 30000.0 / float(magnitude.max())
    edges = cv2.Canny(
        np.round(grad_x * scale).astype(np.int16),
        np.round(grad_y * scale).astype(np.int16),
        low * scale,
        high * scale,
        L2gradient=True,
    )
    # Drop a frame of 2 px: Sobel and smoothing there see the reflected border, not the specimen.
    edges[:2, :], edges[-2:, :], edges[:, :2], edges[:, -2:] = 0, 0, 0, 0
    # Noise breaks a wide edge into fragments; label on a dilated map so that the fragments
    # of one edge are averaged together (more profiles, less noise in the measurement).
    joined = cv2.dilate(edges, np.ones((5, 5), np.uint8))
    _, labels = cv2.connectedComponents(joined, connectivity=8)
    ys, xs = np.nonzero(edges)
    if ys.size == 0:
        return "Canny found no edge above the noise threshold"
    return _Found(grad_x, grad_y, magnitude, labels, ys, xs, detection_sigma, noise_gradient)


def _spread(count: int, limit: int) -> np.ndarray:
    """Indices of at most `limit` of `count` items, evenly spread (all of them if they fit)."""
    if count <= limit:
        return np.arange(count)
    return np.linspace(0, count - 1, limit).astype(np.int64)


def _sample_points(gray: np.ndarray, found: _Found, index: np.ndarray) -> _EdgePoints:
    """The edge points `index` (into found.ys, found.xs) with their profiles across the edge."""
    ys, xs = found.ys[index], found.xs[index]
    magnitude = found.magnitude
    normal_x = found.grad_x[ys, xs] / magnitude[ys, xs]
    normal_y = found.grad_y[ys, xs] / magnitude[ys, xs]

    # Sub-pixel edge position: parabola through the gradient magnitude at -1, 0, +1 px.
    steps = np.array([-1.0, 0.0, 1.0], dtype=np.float32)
    map_x = (xs[:, None] + steps[None, :] * normal_x[:, None]).astype(np.float32)
    map_y = (ys[:, None] + steps[None, :] * normal_y[:, None]).astype(np.float32)
    g = cv2.remap(magnitude, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    curvature = g[:, 0] - 2.0 * g[:, 1] + g[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (g[:, 0] - g[:, 2]) / curvature, 0.0)
    offset = np.clip(offset, -1.0, 1.0)
    centre_x = xs + offset * normal_x
    centre_y = ys + offset * normal_y

    # Intensity profiles across each edge point, rising from dark to bright side.
    max_half = min(MAX_HALF_WINDOW_PX, min(gray.shape) / 4.0)
    t = np.arange(-max_half, max_half + 1e-9, PROFILE_STEP_PX, dtype=np.float32)
    centre_x, centre_y = centre_x.astype(np.float32), centre_y.astype(np.float32)
    normal_x, normal_y = normal_x.astype(np.float32), normal_y.astype(np.float32)
    map_x = centre_x[:, None] + t[None, :] * normal_x[:, None]
    map_y = centre_y[:, None] + t[None, :] * normal_y[:, None]
    profiles = cv2.remap(
        gray, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
    )
    return _EdgePoints(
        labels=found.labels[ys, xs],
        normal_x=normal_x,
        normal_y=normal_y,
        gradient=magnitude[ys, xs],
        profiles=profiles,
        t=t,
        max_half=max_half,
        detection_sigma=found.detection_sigma,
        noise_gradient=found.noise_gradient,
    )


def _credible(
    width: np.ndarray,
    contrast: np.ndarray,
    peak_gradient: np.ndarray,
    counts: np.ndarray,
    points: _EdgePoints,
    noise_std: float,
    min_sigma_px: float,
) -> np.ndarray:
    """Which measured edges (or segments of edges) noise cannot have made, per row.

    The tests compare each edge's contrast and detected gradient with what noise can make
    of them. Edges narrower than `min_sigma_px` are refused too: at a coarse scale, tried
    because the finer one found nothing it could trust, a sharp edge can only be noise.
    """
    sigma = width / TEN_NINETY_PER_SIGMA
    # A Gaussian edge of contrast C and sigma s shows a smoothed peak gradient of
    # C / (sqrt(2 pi) sqrt(s^2 + smoothing^2)).
    smoothed_sigma = np.sqrt(sigma**2 + points.detection_sigma**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        clear_step = contrast >= MIN_CONTRAST_SNR * noise_std / np.sqrt(counts)
        # The detected gradient must match the measured width and contrast.
        steep_enough = peak_gradient >= 0.5 * contrast / (np.sqrt(2.0 * np.pi) * smoothed_sigma)
        # Detection picks points where noise pushed the gradient over the threshold, so even
        # pure noise averages to a step of about the threshold's contrast: demand more.
        noise_step = np.sqrt(2.0 * np.pi) * smoothed_sigma * DETECTION_SNR * points.noise_gradient
        above_selection = contrast >= SELECTION_MARGIN * noise_step
        wide_enough = sigma >= min_sigma_px
    return np.isfinite(width) & clear_step & steep_enough & above_selection & wide_enough


def _group(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows grouped by key, groups of fewer than MIN_EDGE_POINTS dropped.

    Returns (row order, key of each group, first position of each group in that order,
    rows per group).
    """
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    counts = np.diff(np.r_[starts, sorted_keys.size])
    long_enough = counts >= MIN_EDGE_POINTS
    order = order[np.repeat(long_enough, counts)]
    counts = counts[long_enough]
    return order, sorted_keys[starts[long_enough]], np.r_[0, np.cumsum(counts)[:-1]], counts


@dataclass(frozen=True)
class _Edges:
    """The trusted edges at one scale: widths, and what re-centres their profiles."""

    labels: np.ndarray  # connected-edge label
    widths: np.ndarray  # 10-90 % width, px
    counts: np.ndarray  # edge points measured
    mid_levels: np.ndarray  # intensity halfway up the step
    first_sigmas: np.ndarray  # sigma of the first, un-centred average, px
    half_windows: np.ndarray  # profile half-window the width settled on, px
    aligned: np.ndarray  # each sampled point's profile re-centred on its edge (NaN off edges)


def _measure_edges(points: _EdgePoints, noise_std: float, min_sigma_px: float) -> _Edges | str:
    """Widths of the connected edges among the points, or why none can be trusted.

    Each edge is measured on the average of its profiles, averaged again after re-centring
    each profile on the edge's mid level, and kept only if noise cannot have made it.
    """
    rows, labels, starts, counts = _group(points.labels)
    if rows.size == 0:
        return "every detected edge is shorter than a few pixels"
    profiles = points.profiles[rows]
    edge_of_point = np.repeat(np.arange(counts.size), counts)
    peak_gradient = np.add.reduceat(points.gradient[rows], starts) / counts

    t, max_half = points.t, points.max_half
    first_width, half_window, low, high = _fit_window(
        _segment_means(profiles, starts, counts), t, max_half
    )
    if not np.isfinite(first_width).any():
        return "no detected edge had a measurable rise"
    mid_level = 0.5 * (low + high)
    first_sigma = np.nan_to_num(first_width / TEN_NINETY_PER_SIGMA)
    realigned = _realign(
        profiles,
        t,
        mid_level=mid_level[edge_of_point],
        sigma_px=first_sigma[edge_of_point],
        half_window=half_window[edge_of_point],
    )
    width, _, _, _ = _fit_window(
        _segment_means(realigned, starts, counts), t, max_half, start=half_window
    )
    # The step is judged on the profiles as detected, since aligning noise on its own
    # crossings can manufacture a step; and re-centring removes jitter, it cannot halve a
    # real edge.
    with np.errstate(invalid="ignore"):
        consistent = width >= 0.5 * first_width
    trusted = consistent & _credible(
        width, high - low, peak_gradient, counts, points, noise_std, min_sigma_px
    )
    if not trusted.any():
        return "no detected edge had a measurable rise above the noise"
    aligned = np.full_like(points.profiles, np.nan)
    aligned[rows] = np.where(trusted[edge_of_point, None], realigned, np.nan)
    return _Edges(
        labels=labels[trusted],
        widths=width[trusted],
        counts=counts[trusted],
        mid_levels=mid_level[trusted],
        first_sigmas=first_sigma[trusted],
        half_windows=half_window[trusted],
        aligned=aligned,
    )


@dataclass(frozen=True)
class _Segments:
    """The orientation segments of the trusted edges at one scale."""

    bins: np.ndarray  # orientation bin of each segment (index into ORIENTATION_BINS_DEG)
    widths: np.ndarray  # 10-90 % width, px
    counts: np.ndarray  # edge points
    cos2: np.ndarray  # sum over its points of cos 2t, t the normal's orientation
    sin2: np.ndarray  # ... of sin 2t


def _edge_of(points: _EdgePoints, edges: _Edges) -> tuple[np.ndarray, np.ndarray]:
    """(points on the trusted edges, index of each one's edge in `edges`)."""
    edge = np.minimum(np.searchsorted(edges.labels, points.labels), edges.labels.size - 1)
    on_edge = np.flatnonzero(edges.labels[edge] == points.labels)  # edges.labels is sorted
    return on_edge, edge[on_edge]


def _align_to_edges(points: _EdgePoints, edges: _Edges) -> np.ndarray:
    """Profiles of points not used to measure the edges, re-centred as their edge's were."""
    on_edge, edge = _edge_of(points, edges)
    aligned = np.full_like(points.profiles, np.nan)
    if on_edge.size == 0:  # none of these points lies on a trusted edge (cv2.remap refuses 0 rows)
        return aligned
    aligned[on_edge] = _realign(
        points.profiles[on_edge],
        points.t,
        mid_level=edges.mid_levels[edge],
        sigma_px=edges.first_sigmas[edge],
        half_window=edges.half_windows[edge],
    )
    return aligned


def _measure_segments(
    points: _EdgePoints, aligned: np.ndarray, edges: _Edges, noise_std: float, min_sigma_px: float
) -> _Segments:
    """Split the trusted edges by the orientation of their normals and measure each piece.

    A particle rim is one connected edge with normals all round; under an elliptical probe
    its width changes along it, so each orientation bin of it is a segment of its own. A
    segment averages its points' profiles as re-centred for the edge (`aligned`, per point)
    and must pass the noise tests of `_credible` on its own point count.
    """
    on_edge, edge = _edge_of(points, edges)
    bins, cos2, sin2 = _orientations(points.normal_x[on_edge], points.normal_y[on_edge])
    order, keys, starts, counts = _group(edge * len(ORIENTATION_BINS_DEG) + bins)
    if order.size == 0:
        empty = np.empty(0)
        return _Segments(empty.astype(np.int64), empty, empty, empty, empty)
    rows = on_edge[order]
    width, _, low, high = _fit_window(
        _segment_means(aligned[rows], starts, counts),
        points.t,
        points.max_half,
        start=edges.half_windows[edge[order][starts]],
    )
    peak_gradient = np.add.reduceat(points.gradient[rows], starts) / counts
    ok = _credible(width, high - low, peak_gradient, counts, points, noise_std, min_sigma_px)
    return _Segments(
        bins=(keys % len(ORIENTATION_BINS_DEG))[ok],
        widths=width[ok],
        counts=counts[ok],
        cos2=np.add.reduceat(cos2[order], starts)[ok],
        sin2=np.add.reduceat(sin2[order], starts)[ok],
    )


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below which half the total weight lies."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _without_outliers(segments: _Segments) -> _Segments:
    """The segments less those SEGMENT_OUTLIER_RATIO or more from their bin's point-weighted
    median width (either way)."""
    keep = np.ones(segments.bins.size, bool)
    for bin_index in np.unique(segments.bins):
        members = segments.bins == bin_index
        median = _weighted_median(segments.widths[members], segments.counts[members])
        ratio = segments.widths[members] / median
        keep[members] = (ratio < SEGMENT_OUTLIER_RATIO) & (ratio > 1.0 / SEGMENT_OUTLIER_RATIO)
    if keep.all():
        return segments
    return replace(segments, **{f.name: getattr(segments, f.name)[keep] for f in fields(segments)})


def _orientations(
    normal_x: np.ndarray, normal_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(orientation bin, cos 2t, sin 2t) of unit normals; t = atan2(ny, nx) mod pi.

    The double angle forgets the normal's sign, which only says which side is bright.
    """
    nx, ny = normal_x.astype(np.float64), normal_y.astype(np.float64)
    cos2, sin2 = nx**2 - ny**2, 2.0 * nx * ny
    half_turns = np.arctan2(sin2, cos2) / np.pi  # 2t / pi in (-1, 1]
    bins = np.round(half_turns * len(ORIENTATION_BINS_DEG) / 2).astype(np.int64)
    return bins % len(ORIENTATION_BINS_DEG), cos2, sin2


def _min_sigma(scale_index: int, detection_sigma: float) -> float:
    """Narrowest edge (sigma, px) trusted at a detection scale: a sharp edge would have been
    found at the finer scale already, so at a coarser one it can only be noise."""
    return COARSE_SCALE_MIN_SIGMA * detection_sigma if scale_index else 0.0


def measure_edges(image: np.ndarray) -> EdgeMeasurement:
    """Detect the edges of a grey image and measure their 10-90 % widths in pixels.

    Detection starts at a fine smoothing scale and moves to coarser ones only where the fine
    scale finds no edge it can trust, or trusts fewer than THIN_SUPPORT_POINTS edge points:
    wide, faint edges stand out of the noise only after more smoothing. Of the scales tried,
    the one whose trusted edges have the most points gives the reading. Widths are always
    measured on the raw image.
    """
    gray = _as_gray(image, "edge_width")
    noise_std = estimate_noise_std(gray)
    reason = ""
    best: EdgeMeasurement | None = None
    for index, detection_sigma in enumerate(DETECTION_SIGMAS_PX):
        found = _find_edges(gray, noise_std, detection_sigma)
        if isinstance(found, str):
            reason = found
            continue
        points = _sample_points(gray, found, _spread(found.ys.size, MAX_EDGE_POINTS))
        edges = _measure_edges(points, noise_std, _min_sigma(index, detection_sigma))
        if isinstance(edges, str):
            reason = edges
            continue
        if best is None or edges.counts.sum() > best.edge_points.sum():
            best = EdgeMeasurement(
                width_px=float(np.average(edges.widths, weights=edges.counts)),
                edge_widths_px=edges.widths,
                edge_points=edges.counts,
                noise_std=noise_std,
                detection_sigma_px=detection_sigma,
            )
        if best.edge_points.sum() >= THIN_SUPPORT_POINTS:
            break
    if best is None:
        raise NoEdgesError(f"no edges: {reason}")
    return best


def edge_width(image: np.ndarray) -> float:
    """Average 10-90 % edge width of an image in pixels; NoEdgesError where there is none."""
    return measure_edges(image).width_px


@dataclass(frozen=True)
class DirectionalWidths:
    """Edge widths of one image by the orientation of the edge normal, px.

    `widths_px[i]` is the 10-90 % width of edges whose normal points along
    ORIENTATION_BINS_DEG[i]; `width_px` is what `edge_width` reads on the same image.
    """

    width_px: float
    widths_px: np.ndarray  # (4,), one per orientation bin

    @property
    def astigmatism_px(self) -> float:
        """Width of the widest minus the narrowest edges (principal axes of the probe), px."""
        return astigmatism_from_widths(self.widths_px)[0]

    @property
    def axis_rad(self) -> float:
        """Orientation of the normal of the widest edges, radians in [0, pi)."""
        return astigmatism_from_widths(self.widths_px)[1]


def astigmatism_from_widths(widths: np.ndarray) -> tuple[float, float]:
    """(w_max - w_min px, axis rad) of the elliptical probe behind four directional widths.

    A Gaussian probe of covariance C widens a straight edge of unit normal n = (cos t, sin t)
    to w(t) = K sqrt(n^T C n), K = TEN_NINETY_PER_SIGMA, so the squared width
    q(t) = P + Qc cos 2t + Qs sin 2t is a constant plus one harmonic in 2t, fixed by its values
    at 0, 45, 90 and 135 degrees: P their mean, Qc = (q0 - q90) / 2, Qs = (q45 - q135) / 2.
    Its extremes P +/- hypot(Qc, Qs) belong to the principal axes of C, and the widest
    edges have their normal at 0.5 atan2(Qs, Qc) (mod pi).
    """
    q = np.asarray(widths, dtype=np.float64)
    if q.shape != (len(ORIENTATION_BINS_DEG),) or not np.all(np.isfinite(q)) or np.any(q < 0):
        raise ValueError(f"need four finite, non-negative widths (px), got {widths!r}")
    q = q**2
    mean = float(q.mean())
    cos_part, sin_part = 0.5 * (q[0] - q[2]), 0.5 * (q[1] - q[3])
    amplitude = float(np.hypot(cos_part, sin_part))
    widest, narrowest = np.sqrt(mean + amplitude), np.sqrt(max(mean - amplitude, 0.0))
    axis = float((0.5 * np.arctan2(sin_part, cos_part)) % np.pi)
    return float(widest - narrowest), axis


def _refer_to_bin_centres(widths: np.ndarray, cos2: np.ndarray, sin2: np.ndarray) -> np.ndarray:
    """Directional widths at the bin centres, from bins that average over +/- 22.5 degrees.

    A bin's squared width is about the mean of q(t) = P + Qc cos 2t + Qs sin 2t over its
    points, P + Qc <cos 2t> + Qs <sin 2t>: on round particles, whose normals fill the bin
    evenly, that is the harmonic shrunk by sin(pi/4) / (pi/4) = 0.90, which would hide a
    tenth of the astigmatism and, under a 4:1 probe, widen the narrowest bin by a third.
    The harmonic is fitted to the four bins with their own mean orientations (least
    squares), and each bin is moved along it to its centre; straight edges already at the
    centre stay as they are. A squared width pushed below zero by noise is clipped to zero.
    """
    q = widths**2
    centres = np.deg2rad(ORIENTATION_BINS_DEG)
    design = np.column_stack([np.ones_like(q), cos2, sin2])
    _, q_cos, q_sin = np.linalg.lstsq(design, q, rcond=None)[0]
    shift = q_cos * (np.cos(2.0 * centres) - cos2) + q_sin * (np.sin(2.0 * centres) - sin2)
    return np.sqrt(np.maximum(q + shift, 0.0))


def directional_widths(image: np.ndarray) -> DirectionalWidths:
    """Edge widths of an image in the four orientation bins of the edge normal, px.

    One edge detection serves both readings. The connected edges, measured on the points
    `edge_width` samples, give its value. Each trusted edge is then split by the orientation
    of its normals (a particle rim, whose normals point all round, gives a segment to every
    bin), each segment measured like an edge on up to DIRECTIONAL_MAX_EDGE_POINTS points of
    the image, and a bin's width is the point-weighted mean of its segments, referred to the
    bin centre. A bin left empty at the finest detection scale is filled at a coarser one
    where possible, as `edge_width` does for the whole image (whose reading, on thin support,
    may come from a coarser scale, exactly as `edge_width` chooses). NoEdgesError where the image,
    or one of the bins, has nothing to measure.
    """
    gray = _as_gray(image, "directional_widths")
    noise_std = estimate_noise_std(gray)
    bins = len(ORIENTATION_BINS_DEG)
    overall: float | None = None
    overall_support = 0  # trusted edge points behind `overall`
    width_sum, points_sum = np.zeros(bins), np.zeros(bins)  # width x points, points
    cos2_sum, sin2_sum = np.zeros(bins), np.zeros(bins)
    reason = ""
    for index, detection_sigma in enumerate(DETECTION_SIGMAS_PX):
        found = _find_edges(gray, noise_std, detection_sigma)
        if isinstance(found, str):
            reason = found
            continue
        measured = _spread(found.ys.size, MAX_EDGE_POINTS)
        points = _sample_points(gray, found, measured)
        min_sigma = _min_sigma(index, detection_sigma)
        edges = _measure_edges(points, noise_std, min_sigma)
        if isinstance(edges, str):
            reason = edges
            continue
        if overall is None or edges.counts.sum() > overall_support:  # as edge_width reads
            overall = float(np.average(edges.widths, weights=edges.counts))
            overall_support = int(edges.counts.sum())
        # Four bins share the edges: give them more points than the edges were measured on.
        rest = np.setdiff1d(np.arange(found.ys.size), measured, assume_unique=True)
        more = rest[_spread(rest.size, DIRECTIONAL_MAX_EDGE_POINTS - measured.size)]
        aligned = edges.aligned
        if more.size:
            extra = _sample_points(gray, found, more)
            aligned = np.concatenate([aligned, _align_to_edges(extra, edges)])
            points = _joined(points, extra)
        segments = _without_outliers(
            _measure_segments(points, aligned, edges, noise_std, min_sigma)
        )
        fresh = points_sum[segments.bins] == 0  # a bin takes the finest scale that fills it
        for total, values in (
            (width_sum, segments.widths * segments.counts),
            (points_sum, segments.counts),
            (cos2_sum, segments.cos2),
            (sin2_sum, segments.sin2),
        ):
            total += np.bincount(segments.bins[fresh], weights=values[fresh], minlength=bins)
        if np.all(points_sum > 0) and overall_support >= THIN_SUPPORT_POINTS:
            break
    if overall is None:
        raise NoEdgesError(f"no edges: {reason}")
    if not np.all(points_sum > 0):
        empty = np.flatnonzero(points_sum == 0)
        names = " or ".join(f"{ORIENTATION_BINS_DEG[i]:g}°" for i in empty)
        raise NoEdgesError(f"no measurable edges with normals near {names}")
    widths = _refer_to_bin_centres(
        width_sum / points_sum, cos2_sum / points_sum, sin2_sum / points_sum
    )
    return DirectionalWidths(width_px=overall, widths_px=widths)


def _joined(first: _EdgePoints, second: _EdgePoints) -> _EdgePoints:
    """The points of two samples of one detection, as one sample."""
    return replace(
        first,
        **{
            name: np.concatenate([getattr(first, name), getattr(second, name)])
            for name in ("labels", "normal_x", "normal_y", "gradient", "profiles")
        },
    )


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
    minus = _as_gray(image_minus, "wobble_shift").astype(np.float64)
    plus = _as_gray(image_plus, "wobble_shift").astype(np.float64)
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

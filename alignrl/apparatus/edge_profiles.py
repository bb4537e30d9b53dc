"""Edge profiles: how the edge-width measures of alignrl/apparatus/quality.py and
alignrl/apparatus/directional.py find edges and read their 10-90 % widths, in pixels.

Canny (OpenCV) finds the edge pixels at a smoothing scale, with thresholds tied to the image's
own noise (`estimate_noise_std`); `sample_points` takes the intensity profile across each
point along its gradient direction; `measure_trusted_edges` averages the profiles of each
connected edge, re-centres and averages them again, measures the rise distance on the average
(`fit_window`) and keeps only the edges noise cannot have made (`credible`). The names here
are the machinery of those two modules, not a public interface: measure images with
`quality.edge_width`, `quality.measure_edges` or `directional.directional_widths`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "DETECTION_SIGMAS_PX",
    "MAX_EDGE_POINTS",
    "TEN_NINETY_PER_SIGMA",
    "THIN_SUPPORT_POINTS",
    "EdgePoints",
    "FoundEdges",
    "TrustedEdges",
    "as_gray",
    "credible",
    "estimate_noise_std",
    "find_edges",
    "fit_window",
    "group_rows",
    "measure_trusted_edges",
    "min_sigma_at",
    "realign",
    "sample_points",
    "segment_means",
    "spread_indices",
]

TEN_NINETY_PER_SIGMA = 2.0 * 1.2815515655446004  # 10-90 % width of a Gaussian-blurred step

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
DETECTION_SNR = 6.0  # gradient threshold in units of the noise's gradient std (Rayleigh tail 1e-8)
MIN_CONTRAST_SNR = 5.0  # an edge's step must stand this far above its averaged noise
COARSE_SCALE_MIN_SIGMA = 0.75  # at a coarse scale, edges must be at least this wide (x scale)
SELECTION_MARGIN = 1.5  # ... and this far above the step that detection alone selects from noise


def estimate_noise_std(image: np.ndarray) -> float:
    """Standard deviation of white pixel noise, robust to edges (median of a Laplacian mask).

    The mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth intensity and multiplies white noise
    by 6; the median absolute response ignores the few pixels that sit on edges.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    image = np.asarray(image, dtype=np.float32)
    response = cv2.filter2D(image, cv2.CV_32F, mask, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    return float(1.4826 * np.median(np.abs(response)) / 6.0)


def as_gray(image: np.ndarray, caller: str) -> np.ndarray:
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


def segment_means(profiles: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
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


def fit_window(
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


def realign(
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
class FoundEdges:
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
class EdgePoints:
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


def find_edges(gray: np.ndarray, noise_std: float, detection_sigma: float) -> FoundEdges | str:
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
    return FoundEdges(grad_x, grad_y, magnitude, labels, ys, xs, detection_sigma, noise_gradient)


def spread_indices(count: int, limit: int) -> np.ndarray:
    """Indices of at most `limit` of `count` items, evenly spread (all of them if they fit)."""
    if count <= limit:
        return np.arange(count)
    return np.linspace(0, count - 1, limit).astype(np.int64)


def sample_points(gray: np.ndarray, found: FoundEdges, index: np.ndarray) -> EdgePoints:
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
    return EdgePoints(
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


def credible(
    width: np.ndarray,
    contrast: np.ndarray,
    peak_gradient: np.ndarray,
    counts: np.ndarray,
    points: EdgePoints,
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


def group_rows(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
class TrustedEdges:
    """The trusted edges at one scale: widths, and what re-centres their profiles."""

    labels: np.ndarray  # connected-edge label
    widths: np.ndarray  # 10-90 % width, px
    counts: np.ndarray  # edge points measured
    mid_levels: np.ndarray  # intensity halfway up the step
    first_sigmas: np.ndarray  # sigma of the first, un-centred average, px
    half_windows: np.ndarray  # profile half-window the width settled on, px
    aligned: np.ndarray  # each sampled point's profile re-centred on its edge (NaN off edges)


def measure_trusted_edges(
    points: EdgePoints, noise_std: float, min_sigma_px: float
) -> TrustedEdges | str:
    """Widths of the connected edges among the points, or why none can be trusted.

    Each edge is measured on the average of its profiles, averaged again after re-centring
    each profile on the edge's mid level, and kept only if noise cannot have made it.
    """
    rows, labels, starts, counts = group_rows(points.labels)
    if rows.size == 0:
        return "every detected edge is shorter than a few pixels"
    profiles = points.profiles[rows]
    edge_of_point = np.repeat(np.arange(counts.size), counts)
    peak_gradient = np.add.reduceat(points.gradient[rows], starts) / counts

    t, max_half = points.t, points.max_half
    first_width, half_window, low, high = fit_window(
        segment_means(profiles, starts, counts), t, max_half
    )
    if not np.isfinite(first_width).any():
        return "no detected edge had a measurable rise"
    mid_level = 0.5 * (low + high)
    first_sigma = np.nan_to_num(first_width / TEN_NINETY_PER_SIGMA)
    realigned = realign(
        profiles,
        t,
        mid_level=mid_level[edge_of_point],
        sigma_px=first_sigma[edge_of_point],
        half_window=half_window[edge_of_point],
    )
    width, _, _, _ = fit_window(
        segment_means(realigned, starts, counts), t, max_half, start=half_window
    )
    # The step is judged on the profiles as detected, since aligning noise on its own
    # crossings can manufacture a step; and re-centring removes jitter, it cannot halve a
    # real edge.
    with np.errstate(invalid="ignore"):
        consistent = width >= 0.5 * first_width
    trusted = consistent & credible(
        width, high - low, peak_gradient, counts, points, noise_std, min_sigma_px
    )
    if not trusted.any():
        return "no detected edge had a measurable rise above the noise"
    aligned = np.full_like(points.profiles, np.nan)
    aligned[rows] = np.where(trusted[edge_of_point, None], realigned, np.nan)
    return TrustedEdges(
        labels=labels[trusted],
        widths=width[trusted],
        counts=counts[trusted],
        mid_levels=mid_level[trusted],
        first_sigmas=first_sigma[trusted],
        half_windows=half_window[trusted],
        aligned=aligned,
    )


def min_sigma_at(scale_index: int, detection_sigma: float) -> float:
    """Narrowest edge (sigma, px) trusted at a detection scale: a sharp edge would have been
    found at the finer scale already, so at a coarser one it can only be noise."""
    return COARSE_SCALE_MIN_SIGMA * detection_sigma if scale_index else 0.0

"""Directional edge widths: the edge width of an image by the orientation of the edge normal.

An astigmatic probe is an elliptical Gaussian of covariance C: it widens an edge of unit
normal n to TEN_NINETY_PER_SIGMA * sqrt(n^T C n), so edges of different orientations have
different widths. `directional_widths` splits the edges that `edge_width`
(alignrl/apparatus/quality.py) measures by the orientation of their normals into four bins
(ORIENTATION_BINS_DEG) and measures each bin, from one detection, in pixels;
`astigmatism_from_widths` turns four such widths into the probe's astigmatism (px) and axis
(radians). NoEdgesError where the image, or one of the bins, has nothing to measure.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.edge_profiles import (
    DETECTION_SIGMAS_PX,
    MAX_EDGE_POINTS,
    THIN_SUPPORT_POINTS,
    EdgePoints,
    TrustedEdges,
    as_gray,
    credible,
    estimate_noise_std,
    find_edges,
    fit_window,
    group_rows,
    measure_trusted_edges,
    min_sigma_at,
    realign,
    sample_points,
    segment_means,
    spread_indices,
)

__all__ = [
    "ORIENTATION_BINS_DEG",
    "DirectionalWidths",
    "astigmatism_from_widths",
    "directional_widths",
]

# Orientation bins of the edge normal (x = column, y = row; angle atan2(ny, nx) mod 180°),
# each +/- 22.5° wide.
ORIENTATION_BINS_DEG = (0.0, 45.0, 90.0, 135.0)
# Edge points sampled per image for directional widths: their four bins share them, so twice
# MAX_EDGE_POINTS. A bin's scatter drops by ~1.4 at a cost that only frames with over 1000
# edge pixels notice.
DIRECTIONAL_MAX_EDGE_POINTS = 2 * MAX_EDGE_POINTS
# A segment whose width is this far (either way) from the point-weighted median of its bin's
# segments is dropped from the bin: within one orientation bin every segment sees the same
# probe width, but now and then one is measured across a neighbouring particle's rim and
# reads 3-4 x the rest (~2 % of nearly round frames on `synthetic`, a bin at 1.7 x the best
# width where the probe gives 1.08 x). An elliptical probe widens bins against each other,
# never the segments of one bin.
SEGMENT_OUTLIER_RATIO = 2.0


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
    gray = as_gray(image, "directional_widths")
    noise_std = estimate_noise_std(gray)
    bins = len(ORIENTATION_BINS_DEG)
    overall: float | None = None
    overall_support = 0  # trusted edge points behind `overall`
    width_sum, points_sum = np.zeros(bins), np.zeros(bins)  # width x points, points
    cos2_sum, sin2_sum = np.zeros(bins), np.zeros(bins)
    reason = ""
    for index, detection_sigma in enumerate(DETECTION_SIGMAS_PX):
        found = find_edges(gray, noise_std, detection_sigma)
        if isinstance(found, str):
            reason = found
            continue
        measured = spread_indices(found.ys.size, MAX_EDGE_POINTS)
        points = sample_points(gray, found, measured)
        min_sigma = min_sigma_at(index, detection_sigma)
        edges = measure_trusted_edges(points, noise_std, min_sigma)
        if isinstance(edges, str):
            reason = edges
            continue
        if overall is None or edges.counts.sum() > overall_support:  # as edge_width reads
            overall = float(np.average(edges.widths, weights=edges.counts))
            overall_support = int(edges.counts.sum())
        # Four bins share the edges: give them more points than the edges were measured on.
        rest = np.setdiff1d(np.arange(found.ys.size), measured, assume_unique=True)
        more = rest[spread_indices(rest.size, DIRECTIONAL_MAX_EDGE_POINTS - measured.size)]
        aligned = edges.aligned
        if more.size:
            extra = sample_points(gray, found, more)
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


@dataclass(frozen=True)
class _Segments:
    """The orientation segments of the trusted edges at one scale."""

    bins: np.ndarray  # orientation bin of each segment (index into ORIENTATION_BINS_DEG)
    widths: np.ndarray  # 10-90 % width, px
    counts: np.ndarray  # edge points
    cos2: np.ndarray  # sum over its points of cos 2t, t the normal's orientation
    sin2: np.ndarray  # ... of sin 2t


def _edge_of(points: EdgePoints, edges: TrustedEdges) -> tuple[np.ndarray, np.ndarray]:
    """(points on the trusted edges, index of each one's edge in `edges`)."""
    edge = np.minimum(np.searchsorted(edges.labels, points.labels), edges.labels.size - 1)
    on_edge = np.flatnonzero(edges.labels[edge] == points.labels)  # edges.labels is sorted
    return on_edge, edge[on_edge]


def _align_to_edges(points: EdgePoints, edges: TrustedEdges) -> np.ndarray:
    """Profiles of points not used to measure the edges, re-centred as their edge's were."""
    on_edge, edge = _edge_of(points, edges)
    aligned = np.full_like(points.profiles, np.nan)
    if on_edge.size == 0:  # none of these points lies on a trusted edge (cv2.remap refuses 0 rows)
        return aligned
    aligned[on_edge] = realign(
        points.profiles[on_edge],
        points.t,
        mid_level=edges.mid_levels[edge],
        sigma_px=edges.first_sigmas[edge],
        half_window=edges.half_windows[edge],
    )
    return aligned


def _measure_segments(
    points: EdgePoints,
    aligned: np.ndarray,
    edges: TrustedEdges,
    noise_std: float,
    min_sigma_px: float,
) -> _Segments:
    """Split the trusted edges by the orientation of their normals and measure each piece.

    A particle rim is one connected edge with normals all round; under an elliptical probe
    its width changes along it, so each orientation bin of it is a segment of its own. A
    segment averages its points' profiles as re-centred for the edge (`aligned`, per point)
    and must pass the noise tests of `credible` on its own point count.
    """
    on_edge, edge = _edge_of(points, edges)
    bins, cos2, sin2 = _orientations(points.normal_x[on_edge], points.normal_y[on_edge])
    order, keys, starts, counts = group_rows(edge * len(ORIENTATION_BINS_DEG) + bins)
    if order.size == 0:
        empty = np.empty(0)
        return _Segments(empty.astype(np.int64), empty, empty, empty, empty)
    rows = on_edge[order]
    width, _, low, high = fit_window(
        segment_means(aligned[rows], starts, counts),
        points.t,
        points.max_half,
        start=edges.half_windows[edge[order][starts]],
    )
    peak_gradient = np.add.reduceat(points.gradient[rows], starts) / counts
    ok = credible(width, high - low, peak_gradient, counts, points, noise_std, min_sigma_px)
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


def _joined(first: EdgePoints, second: EdgePoints) -> EdgePoints:
    """The points of two samples of one detection, as one sample."""
    return replace(
        first,
        **{
            name: np.concatenate([getattr(first, name), getattr(second, name)])
            for name in ("labels", "normal_x", "normal_y", "gradient", "profiles")
        },
    )

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

This module is the front door of the image measures: `edge_width` and `measure_edges` are
here, on the machinery of alignrl/apparatus/edge_profiles.py; the edge widths by orientation
(`directional_widths`, `astigmatism_from_widths`: alignrl/apparatus/directional.py) and the
wobble shift (`wobble_shift`: alignrl/apparatus/wobble.py) are importable from here too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.directional import (
    ORIENTATION_BINS_DEG,
    DirectionalWidths,
    astigmatism_from_widths,
    directional_widths,
)
from alignrl.apparatus.edge_profiles import (
    DETECTION_SIGMAS_PX,
    MAX_EDGE_POINTS,
    TEN_NINETY_PER_SIGMA,
    THIN_SUPPORT_POINTS,
    as_gray,
    estimate_noise_std,
    find_edges,
    measure_trusted_edges,
    min_sigma_at,
    sample_points,
    spread_indices,
)
from alignrl.apparatus.wobble import wobble_shift

__all__ = [
    "ORIENTATION_BINS_DEG",
    "TEN_NINETY_PER_SIGMA",
    "DirectionalWidths",
    "EdgeMeasurement",
    "astigmatism_from_widths",
    "directional_widths",
    "edge_width",
    "estimate_noise_std",
    "measure_edges",
    "wobble_shift",
]


@dataclass(frozen=True)
class EdgeMeasurement:
    """What the edge-width algorithm saw in one image."""

    width_px: float  # length-weighted mean 10-90 % width of the measured edges
    edge_widths_px: np.ndarray  # per measured edge
    edge_points: np.ndarray  # edge points (pixels) behind each measured edge
    noise_std: float  # estimated pixel noise, image units
    detection_sigma_px: float  # smoothing scale at which the edges were found


def measure_edges(image: np.ndarray) -> EdgeMeasurement:
    """Detect the edges of a grey image and measure their 10-90 % widths in pixels.

    Detection starts at a fine smoothing scale and moves to coarser ones only where the fine
    scale finds no edge it can trust, or trusts fewer than THIN_SUPPORT_POINTS edge points:
    wide, faint edges stand out of the noise only after more smoothing. Of the scales tried,
    the one whose trusted edges have the most points gives the reading. Widths are always
    measured on the raw image.
    """
    gray = as_gray(image, "edge_width")
    noise_std = estimate_noise_std(gray)
    reason = ""
    best: EdgeMeasurement | None = None
    for index, detection_sigma in enumerate(DETECTION_SIGMAS_PX):
        found = find_edges(gray, noise_std, detection_sigma)
        if isinstance(found, str):
            reason = found
            continue
        points = sample_points(gray, found, spread_indices(found.ys.size, MAX_EDGE_POINTS))
        edges = measure_trusted_edges(points, noise_std, min_sigma_at(index, detection_sigma))
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

"""Specimens for the image path of the instrument family, and the frames they image into.

A specimen is a (size, size) map of secondary-electron yields within [0, 1.2], a substrate
near 0.25 and features near 0.9 (as in alignrl/apparatus/synthetic.py). A frame: the
specimen blurred by a round Gaussian probe in Fourier space, plus shot and detector noise.

* Periodic: specimens live on a torus (distances wrap; line families repeat a whole number
  of times), so the FFT blur leaves no border artefact. A family of integer normal (a, b)
  has phase u = (a x + b y) / size, changing by an integer over a wrap; its lines u = c
  (mod 1) lie size / |(a, b)| px apart, and with (-b, a) it makes a square lattice.
* Sharp: a pixel covers a shape by its signed distance into it + 0.5, clipped to [0, 1]
  (anti-aliased over ~1 px): a probe of sigma s makes every boundary an edge of 10-90 %
  width 2.563 s for `alignrl.apparatus.quality.edge_width`.
* Wide: that measure reads an edge in a window of ~4 s + 3 px each side and wants both
  plateaus in it, so features and gaps are >= ~20 px across (thinner ones under-read at
  s = 4 px and stop growing with s before 8 px).

Kinds (`SPECIMENS`): particles (round, random radii, on a faint grainy substrate); grid (a
square lattice of bright bars with dark holes, a TEM grid: random pitch, bar width, angle,
offset); bars (parallel bars of random widths and gaps, a resolution target, at a random
angle); fibres (curved bright fibres on smooth periodic paths); texture (a two-phase
polycrystal: Voronoi grains with sharp boundaries, a grey level each).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

__all__ = ["SPECIMENS", "blur", "draw_specimen", "render"]

SPECIMENS: tuple[str, ...] = ("particles", "grid", "bars", "fibres", "texture")

SUBSTRATE = 0.25  # yield of the dark substrate
FEATURE = 0.9  # yield of the bright features
GRAIN_AMPLITUDE = 0.02  # std of the substrate's grain, yield units
GRAIN_SIGMA_PX = 2.0  # correlation length of the grain
GAUSSIAN_SHOT_NOISE_ABOVE = 30.0  # electrons per pixel where Poisson ~ Gaussian
MIN_SIZE = 32
REFERENCE_SIZE = 256  # the counts below are for this frame, scaled to others
PARTICLES = (10, 18)
PARTICLE_RADIUS_PX = (8.0, 22.0)
GRID_PITCH_PX = (50.0, 100.0)
GRID_BAR_FRACTION = (0.35, 0.5)  # bar width / pitch
BAR_PX = (20.0, 48.0)  # widths of the bars and of the gaps between them
BARS_PERIOD_MIN_PX = 100.0  # the pattern of bars repeats no sooner than this
FIBRES = (3, 5)  # per reference frame side
FIBRE_WIDTH_PX = (22.0, 30.0)
FIBRE_WANDER_PX = 10.0  # largest amplitude of a fibre path's first harmonic
GRAIN_PX = (48.0, 72.0)  # side of the lattice cell that holds one grain's seed


def _coverage(inside_px: np.ndarray) -> np.ndarray:
    """Fraction of each pixel inside a shape, from its signed distance into the shape (px):
    0.5 on the boundary, a linear ramp over one pixel (anti-aliasing)."""
    return np.clip(inside_px + 0.5, 0.0, 1.0)


def _wrap(delta: np.ndarray | float, period: float) -> np.ndarray:
    """The shortest periodic difference, in [-period / 2, period / 2)."""
    return (np.asarray(delta) + 0.5 * period) % period - 0.5 * period


def _count(low: int, high: int, size: int, rng: np.random.Generator, power: int = 2) -> int:
    """A random count in [low, high] for the reference frame, scaled with the frame's area
    (power 2; power 1: with its side, for features as long as the frame)."""
    scale = (size / REFERENCE_SIZE) ** power
    return max(1, round(int(rng.integers(low, high + 1)) * scale))


def _grain(size: int, rng: np.random.Generator) -> np.ndarray:
    """Faint substrate grain: white noise low-passed in Fourier space (periodic), std
    GRAIN_AMPLITUDE."""
    noise = rng.standard_normal((size, size))
    smooth = blur(np.fft.rfft2(noise), GRAIN_SIGMA_PX, size)
    return smooth * (GRAIN_AMPLITUDE / max(float(smooth.std()), 1e-12))


def _direction(max_norm: float, min_norm: float, rng: np.random.Generator) -> tuple[int, int]:
    """A random integer vector (a, b), min_norm <= |(a, b)| <= max_norm: the normal of a
    periodic line family with size / |(a, b)| pixels between its lines."""
    reach = range(-math.floor(max_norm), math.floor(max_norm) + 1)
    candidates = [
        (a, b) for a in reach for b in reach if min_norm <= math.hypot(a, b) <= max_norm
    ] or [(max(1, round(min_norm)), 0)]  # a frame too small for the range: the coarsest
    return candidates[int(rng.integers(len(candidates)))]


def _phase(size: int, a: int, b: int) -> np.ndarray:
    """u = (a x + b y) / size over the frame (x = column, y = row), shape (size, size)."""
    coordinates = np.arange(size, dtype=np.float64) / size
    return a * coordinates[None, :] + b * coordinates[:, None]


def _particles(size: int, rng: np.random.Generator) -> np.ndarray:
    """Round bright particles (radii PARTICLE_RADIUS_PX, yield 0.9 +/- 5 %: overlaps of
    unlike ones make weak steps that the edge measure joins to their rims) on a grainy
    substrate, later ones over earlier ones, each drawn on its own patch of the torus."""
    specimen = SUBSTRATE + _grain(size, rng)
    largest = min(PARTICLE_RADIUS_PX[1], 0.2 * size)  # a small frame holds small ones
    smallest = min(PARTICLE_RADIUS_PX[0], 0.5 * largest)
    for _ in range(_count(*PARTICLES, size, rng)):
        centre = rng.uniform(0.0, size, 2)
        radius = rng.uniform(smallest, largest)
        brightness = FEATURE * rng.uniform(0.95, 1.05)
        reach = math.ceil(radius + 2.0)
        offsets = np.arange(-reach, reach + 1)
        rows, columns = ((int(centre[axis]) + offsets) % size for axis in (1, 0))
        dy, dx = _wrap(rows - centre[1], size)[:, None], _wrap(columns - centre[0], size)
        cover = _coverage(radius - np.sqrt(dx[None, :] ** 2 + dy**2))
        patch = np.ix_(rows, columns)
        specimen[patch] += cover * (brightness - specimen[patch])
    return specimen


def _grid(size: int, rng: np.random.Generator) -> np.ndarray:
    """A square lattice of bright bars with dark square holes: two perpendicular periodic
    line families of pitch GRID_PITCH_PX (the frame is one cell where it is smaller), bars
    GRID_BAR_FRACTION of the pitch wide, each family offset at random."""
    a, b = _direction(size / GRID_PITCH_PX[0], max(1.0, size / GRID_PITCH_PX[1]), rng)
    pitch = size / math.hypot(a, b)
    half_width = 0.5 * pitch * rng.uniform(*GRID_BAR_FRACTION)
    cover = np.zeros((size, size))
    for u_a, u_b in ((a, b), (-b, a)):
        distance = np.abs(_wrap(_phase(size, u_a, u_b) - rng.uniform(), 1.0)) * pitch
        cover = np.maximum(cover, _coverage(half_width - distance))
    return SUBSTRATE + (FEATURE - SUBSTRATE) * cover + 0.5 * _grain(size, rng)


def _bars(size: int, rng: np.random.Generator) -> np.ndarray:
    """Parallel bright bars of random widths and gaps (BAR_PX each), along a periodic line
    family of period size / |(a, b)| >= BARS_PERIOD_MIN_PX (or the frame); the widths are
    scaled to fill one period exactly."""
    a, b = _direction(max(1.0, size / BARS_PERIOD_MIN_PX), 1.0, rng)
    period = size / math.hypot(a, b)
    pieces = max(2, 2 * round(period / sum(BAR_PX)))  # alternating bar, gap, bar, gap, ...
    lengths = rng.uniform(*BAR_PX, pieces)
    edges = np.concatenate(([0.0], np.cumsum(lengths * (period / lengths.sum()))))
    position = (_phase(size, a, b) - rng.uniform()) % 1.0 * period  # px along the normal
    cover = np.zeros((size, size))
    for start, stop in zip(edges[0:-1:2], edges[1::2], strict=True):
        middle, half = 0.5 * (start + stop), 0.5 * (stop - start)
        cover = np.maximum(cover, _coverage(half - np.abs(_wrap(position - middle, period))))
    brightness = FEATURE * rng.uniform(0.9, 1.05)
    return SUBSTRATE + (brightness - SUBSTRATE) * cover + 0.5 * _grain(size, rng)


def _fibres(size: int, rng: np.random.Generator) -> np.ndarray:
    """Curved bright fibres on a grainy substrate, some across the frame, some down it.

    A fibre across follows y = y0 + sum_k A_k sin(2 pi k x / size + phi_k), two whole
    harmonics k (down the frame: x and y swapped); the distance to it is the offset along y
    times cos(slope), exact to first order in the curvature. Fibres of one direction start
    evenly spaced (with a jitter), leaving substrate between them; the two directions cross.
    """
    specimen = SUBSTRATE + _grain(size, rng)
    along = np.arange(size, dtype=np.float64)
    order = np.arange(1, 3)[:, None]
    harmonics = max(1, round(size / REFERENCE_SIZE)) * order  # wavelengths ~ 256, 128 px
    widest = min(FIBRE_WIDTH_PX[1], 0.25 * size)  # a small frame holds thin ones
    narrowest = min(FIBRE_WIDTH_PX[0], 0.75 * widest)
    count = _count(*FIBRES, size, rng, power=1)
    down = rng.random(count) < 0.5
    for group in (False, True):
        members = int(np.count_nonzero(down == group))
        jitter = rng.uniform(-0.1, 0.1, members)
        starts = rng.uniform(0.0, size) + size / max(members, 1) * (np.arange(members) + jitter)
        for start in starts:
            amplitude = rng.uniform(0.0, FIBRE_WANDER_PX, (2, 1)) / order
            angle = 2.0 * np.pi * harmonics * along / size + rng.uniform(0, 2 * np.pi, (2, 1))
            path = start + (amplitude * np.sin(angle)).sum(axis=0)
            slope = (amplitude * np.cos(angle) * 2.0 * np.pi * harmonics / size).sum(axis=0)
            offset = _wrap(along[:, None] - path[None, :], size)  # (across, along)
            distance = np.abs(offset) / np.sqrt(1.0 + slope[None, :] ** 2)
            cover = _coverage(0.5 * rng.uniform(narrowest, widest) - distance)
            if group:  # runs down the frame: its path is x as a function of y
                cover = cover.T
            brightness = FEATURE * rng.uniform(0.95, 1.05)
            specimen += cover * (brightness - specimen)
    return specimen


def _texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """A two-phase polycrystal: periodic Voronoi grains of the dark (0.25) or the bright
    (0.8) phase, each with a grey level of its own within +/- 0.05 (orientation contrast).

    The edge measure averages a connected boundary network as a whole, and steps of unlike
    sizes mixed there widen the reading: so every step between the phases is of about one
    size. Seeds are jittered on an m x m lattice of cells of side c (GRAIN_PX), so a pixel's
    two nearest seeds lie within 3 cells of its own (the second is within 2 sqrt(2) c, a
    cell 4 away >= 3 c). A pixel blends its nearest seeds i, j by its signed distance to
    their bisector, (d_j^2 - d_i^2) / (2 |r_j - r_i|), r the displacements to their nearest
    periodic images: a boundary anti-aliased over one pixel.
    """
    cells = max(2, round(size / rng.uniform(*GRAIN_PX)))
    side = size / cells
    seed_x = ((np.arange(cells)[None, :] + rng.random((cells, cells))) * side).ravel()
    seed_y = ((np.arange(cells)[:, None] + rng.random((cells, cells))) * side).ravel()
    levels = np.where(rng.permutation(cells * cells) % 2 == 1, 0.8, SUBSTRATE)  # half each
    levels = levels + rng.uniform(-0.05, 0.05, cells * cells)
    coordinates = np.arange(size, dtype=np.float64)
    texture = np.empty((size, size))
    if cells < 7:  # few seeds: every one is a candidate for every pixel
        blocks = [(slice(0, size), slice(0, size), np.arange(cells * cells))]
    else:  # the 7 x 7 cells around each cell are the candidates for its pixels
        bounds = np.searchsorted(np.floor(coordinates / side), np.arange(cells + 1))
        steps = np.arange(-3, 4)
        blocks = [
            (
                slice(bounds[row], bounds[row + 1]),
                slice(bounds[column], bounds[column + 1]),
                (((row + steps) % cells)[:, None] * cells + (column + steps) % cells).ravel(),
            )
            for row in range(cells)
            for column in range(cells)
        ]
    for rows, columns, candidates in blocks:
        dx = _wrap(coordinates[None, columns] - seed_x[candidates, None], size)  # (seed, x)
        dy = _wrap(coordinates[None, rows] - seed_y[candidates, None], size)  # (seed, y)
        squared = dy[:, :, None] ** 2 + dx[:, None, :] ** 2  # (seed, y, x)
        y_index, x_index = np.indices(squared.shape[1:])
        nearest = np.argmin(squared, axis=0)
        d_near = squared[nearest, y_index, x_index]
        squared[nearest, y_index, x_index] = np.inf
        second = np.argmin(squared, axis=0)
        d_second = squared[second, y_index, x_index]
        separation = np.hypot(
            dx[nearest, x_index] - dx[second, x_index], dy[nearest, y_index] - dy[second, y_index]
        )
        inside = (d_second - d_near) / (2.0 * np.maximum(separation, 1e-9))
        weight = _coverage(inside)  # 1 deep in the nearest grain, 0.5 on the boundary
        near_level, second_level = levels[candidates[nearest]], levels[candidates[second]]
        texture[rows, columns] = weight * near_level + (1.0 - weight) * second_level
    return texture


_DRAWERS: dict[str, Callable[[int, np.random.Generator], np.ndarray]] = dict(
    zip(SPECIMENS, (_particles, _grid, _bars, _fibres, _texture), strict=True)
)


def draw_specimen(kind: str, size: int, rng: np.random.Generator) -> np.ndarray:
    """A (size, size) float64 map of yields within [0, 1.2], periodic across the frame
    edges, drawn from `rng`; ValueError naming the known kinds for an unknown kind."""
    if kind not in _DRAWERS:
        raise ValueError(f"specimen kind {kind!r} is unknown; the known kinds are {SPECIMENS}")
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < MIN_SIZE:
        raise ValueError(f"specimen {kind!r}: size must be an integer >= {MIN_SIZE}, got {size!r}")
    return np.clip(_DRAWERS[kind](int(size), rng), 0.0, 1.2)


def _transfer(sigma_px: float, size: int) -> np.ndarray:
    """exp(-2 pi^2 sigma^2 |f|^2) on the rfft2 grid of a (size, size) frame."""
    freq_y, freq_x = np.fft.fftfreq(size)[:, None], np.fft.rfftfreq(size)[None, :]
    return np.exp(-2.0 * np.pi**2 * sigma_px**2 * (freq_x**2 + freq_y**2))


def blur(specimen_fft: np.ndarray, sigma_px: float, size: int) -> np.ndarray:
    """Isotropic Gaussian blur (sigma_px, pixels) of a specimen given as its rfft2, in
    Fourier space (periodic): a (size, size) float64 image."""
    sigma_px = float(sigma_px)
    if not (math.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"blur: sigma_px must be a finite number >= 0, got {sigma_px}")
    expected = (int(size), int(size) // 2 + 1)
    if np.shape(specimen_fft) != expected:
        raise ValueError(
            f"blur: specimen_fft must be the rfft2 of a ({size}, {size}) frame, of shape "
            f"{expected}; got {np.shape(specimen_fft)}"
        )
    return np.fft.irfft2(specimen_fft * _transfer(sigma_px, int(size)), s=(int(size), int(size)))


def render(
    specimen_fft: np.ndarray,
    sigma_px: float,
    size: int,
    dose_electrons_per_px: float,
    detector_noise: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """One float32 frame in yield units: the blurred specimen with shot noise (Poisson, or
    its Gaussian limit where every pixel expects >= 30 electrons) and detector noise."""
    dose, noise = float(dose_electrons_per_px), float(detector_noise)
    if not (math.isfinite(dose) and dose > 0):
        raise ValueError(f"render: dose_electrons_per_px must be finite and > 0, got {dose}")
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"render: detector_noise must be finite and >= 0, got {noise}")
    signal = np.clip(blur(specimen_fft, sigma_px, size), 0.0, None)
    expected = signal * dose  # electrons per pixel
    if expected.min() >= GAUSSIAN_SHOT_NOISE_ABOVE:
        counts = expected + np.sqrt(expected) * rng.standard_normal(expected.shape)
    else:
        counts = rng.poisson(expected).astype(np.float64)
    frame = counts / dose
    if noise > 0:
        frame += noise * rng.standard_normal(frame.shape)
    return frame.astype(np.float32)

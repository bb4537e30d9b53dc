"""The synthetic SEM: a stand-in for a real scanning electron microscope column.

Image formation (design.md, docs/physics.md): image = specimen (*) probe, shifted, + noise.

* Specimen: gold particles with sharp rims on a faintly textured carbon substrate (the Zn-Au
  test specimen of seed section 6.2), drawn anew for every scenario from its seed. Intensities
  are secondary-electron yields: substrate ~0.25, gold ~0.9.
* Five knobs: `defocus` (V), the stigmators `stigmator_x`, `stigmator_y` (percent of full
  excitation) and the objective aperture's position `aperture_x`, `aperture_y` (um).
* Probe: an elliptical Gaussian. With focus error dV = V_eff - V_opt (volts), a residual
  astigmatism of A_res volts between the two line foci along axis phi_res, and an aperture
  residual |d| (um), the probe's standard deviations along its principal axes are
      sigma_u,v = sqrt(sigma0^2 + (gain * (dV -/+ A_res/2))^2 + (b_ap * |d|)^2)  pixels,
  sigma_u along phi_res. With A_res = 0 and d = 0 this is design.md's
  sigma = sqrt(sigma0^2 + (gain * (V - V_opt))^2).
* Astigmatism: the scenario's column has an astigmatism vector a = A (cos 2 phi, sin 2 phi)
  (volts); the stigmators subtract g_s (s_x, s_y), leaving r = a - g_s s, with
  A_res = |r| and phi_res = atan2(r_y, r_x) / 2.
* Aperture: the scenario's aperture sits o (um) off the optical axis; d = o - (a_x, a_y). An
  off-axis aperture tilts the beam, so a focus error shifts the image by
  shift = k_ap * dV * d pixels (the wobbler's symptom), and the off-axis ray bundle blurs the
  probe by b_ap |d| (in quadrature).
* Lens hysteresis: the field lags the last change of the defocus voltage, so the effective
  voltage is V_eff = V - hysteresis_v * s, with s the sign of the last change (+1 up, -1 down).
  Stigmators and aperture have none.
* Drift: the optimum wanders by a random walk of drift_v_per_acquisition per image.
* Noise: shot noise (Poisson, `dose_electrons_per_px` primary electrons per pixel; where every
  pixel expects at least 30 electrons, its Gaussian limit) and Gaussian detector noise.

`reset()` leaves the stigmators and the aperture aligned (residuals zero) and the defocus at
its nominal value: the focus task sees exactly the column it saw when focus was the only knob
(the new random numbers come from their own generator, so every existing stream is unchanged).

Measurements: `measure()` (mean edge width, px), `measure_directional()` (the mean and the
widths of four edge-normal orientation bins, one image) and `measure_wobble(amplitude_v)` (the
image shift between defocus +/- amplitude, two images). In analytic mode (`analytic=True`)
they are computed from the probe's covariance and shift without rendering an image: the
image path's bias, its scatter (the frame's noise per reading, the specimen's per scenario)
and its failures far from focus are reproduced as calibrated against it (`AnalyticModel`,
docs/physics.md), several hundred times faster.

Every number comes from a `SEMConfig`; the presets `synthetic` and `synthetic-b` live in
alignrl/apparatus/presets/*.yaml. The blur is applied in Fourier space: the specimen is drawn
periodic (particles wrap around the frame), so the FFT convolution has no border artefacts,
and a 256x256 frame renders in a few milliseconds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from alignrl.apparatus import quality
from alignrl.apparatus.base import ApparatusError, MeasurementError, NoEdgesError, check_write
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, edge_width
from alignrl.yaml_io import read_yaml_file

__all__ = [
    "KNOB_NAMES",
    "PRESET_DIR",
    "AnalyticModel",
    "SEMConfig",
    "SyntheticSEM",
    "directional_edge_widths_px",
    "edge_widths_px",
    "load_sem_config",
    "mean_edge_width_px",
]

PRESET_DIR = Path(__file__).with_name("presets")
KNOB_NAMES = ("defocus", "stigmator_x", "stigmator_y", "aperture_x", "aperture_y")

GAUSSIAN_SHOT_NOISE_ABOVE = 30.0  # electrons per pixel where Poisson ~ Gaussian
# Edge-normal orientations of the analytic mean width: the particles are round, so their rims
# show every orientation equally. The integrand is smooth and periodic, so the midpoint rule
# on 32 points is exact to rounding.
_ORIENTATIONS = (np.arange(32) + 0.5) * np.pi / 32
# Sub-orientations of one directional bin (+/- 22.5 deg): a bin's width averages them.
_BIN_OFFSETS = (np.arange(8) + 0.5) * (np.pi / 4) / 8 - np.pi / 8
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]
FloatTable = tuple[float, ...]

# The `synthetic` preset's calibration (python -m benchmarks.analytic_agreement --calibrate),
# the defaults: SEMConfig's defaults image the same specimen at the same dose and noise.
# fmt: off
_KNOTS_PX = (
    2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0,
    14.0, 16.0, 18.0, 20.0, 25.0, 30.0, 40.0, 60.0,
)
_READING_RATIO = (
    1.017, 1.007, 0.991, 0.974, 0.953, 0.92, 0.871, 0.835,
    0.808, 0.79, 0.678, 0.632, 0.609, 0.604, 0.558, 0.404,
)
_NOISE_REL = (
    0.012, 0.011, 0.013, 0.014, 0.015, 0.017, 0.021, 0.018,
    0.023, 0.043, 0.03, 0.03, 0.029, 0.036, 0.084, 0.086,
)
_SPECIMEN_REL = (
    0.024, 0.015, 0.019, 0.022, 0.025, 0.038, 0.043, 0.037,
    0.044, 0.028, 0.122, 0.048, 0.055, 0.055, 0.072, 0.309,
)
_DIRECTIONAL_RATIO = (
    1.032, 1.02, 1.001, 0.988, 0.962, 0.929, 0.882, 0.843,
    0.819, 0.789, 0.691, 0.635, 0.616, 0.6, 0.553, 0.453,
)
_DIRECTIONAL_NOISE_REL = (
    0.027, 0.023, 0.024, 0.023, 0.026, 0.027, 0.028, 0.027,
    0.03, 0.045, 0.044, 0.036, 0.043, 0.06, 0.083, 0.138,
)
_DIRECTIONAL_SPECIMEN_REL = (
    0.0, 0.022, 0.023, 0.027, 0.032, 0.04, 0.051, 0.04,
    0.05, 0.061, 0.116, 0.061, 0.054, 0.068, 0.092, 0.174,
)
# fmt: on
_TABLES = (
    "reading_ratio",
    "noise_rel",
    "specimen_rel",
    "directional_ratio",
    "directional_noise_rel",
    "directional_specimen_rel",
)


class AnalyticModel(BaseModel):
    """How analytic mode turns a probe into readings: the image path's bias, scatter and
    failures, fitted to it by `python -m benchmarks.analytic_agreement --calibrate` for one
    instrument (dose, noise, specimen).

    The tables are given at `knots_px` of the effective width w_p (the power mean over edge
    orientations of 2.563 sqrt(n^T C n), power `orientation_power`; a bin's own width for the
    directional tables) and interpolated linearly between them, held beyond the ends. A
    reading is w_p x ratio x exp(specimen x z + noise x e): z ~ N(0, 1) is drawn once per
    scenario (its specimen reads a little wide or narrow all along), e ~ N(0, 1) per reading.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    knots_px: FloatTable = Field(
        _KNOTS_PX, description="effective widths (px) at which the tables are given, increasing"
    )
    reading_ratio: FloatTable = Field(
        _READING_RATIO,
        description="median edge_width reading / w_p at each knot: ~1 near focus, below 1 where "
        "the blur outgrows the particles and the reading levels off",
    )
    noise_rel: FloatTable = Field(
        _NOISE_REL,
        description="standard deviation of log(reading) between readings of one state: the "
        "frame's shot and detector noise",
    )
    specimen_rel: FloatTable = Field(
        _SPECIMEN_REL,
        description="standard deviation of log(reading) between scenarios at one probe: the "
        "specimen's particles, fixed within a scenario",
    )
    directional_ratio: FloatTable = Field(
        _DIRECTIONAL_RATIO,
        description="median reading / true width of one orientation bin, at the bin's own true "
        "width (the knots)",
    )
    directional_noise_rel: FloatTable = Field(
        _DIRECTIONAL_NOISE_REL,
        description="standard deviation of log(bin reading) between readings of one state",
    )
    directional_specimen_rel: FloatTable = Field(
        _DIRECTIONAL_SPECIMEN_REL,
        description="standard deviation of log(bin reading) between scenarios at one probe",
    )
    orientation_power: float = Field(
        0.0,
        description="power p of the mean over edge orientations that makes w_p (1: arithmetic; "
        "below 1 weighs the steep edges, which detection finds more readily, more; 0: geometric)",
    )
    no_edges_px: PositiveFloat = Field(
        97.5, description="w_p (px) at which half of the frames show no edges"
    )
    no_edges_spread_px: PositiveFloat = Field(
        8.0,
        description="logistic spread of that limit: P(no edges) = 1 / (1 + exp(-(w_p - "
        "no_edges_px) / this))",
    )
    directional_no_edges_px: PositiveFloat = Field(
        75.5,
        description="w_p (px) at which half of the frames leave an orientation bin without a "
        "measurable edge",
    )
    directional_no_edges_spread_px: PositiveFloat = Field(
        5.0, description="logistic spread of that limit, px"
    )
    wobble_failure_sigma_px: PositiveFloat = Field(
        13.0,
        description="mean probe sigma (px) of a wobble pair at which half of the pairs leave "
        "nothing to correlate (MeasurementError)",
    )
    wobble_failure_spread_px: PositiveFloat = Field(
        1.5, description="logistic spread of that limit, px"
    )
    wobble_ratio: PositiveFloat = Field(
        0.994, description="median wobble shift read on the frames / the exact image shift"
    )
    wobble_scatter_px_per_px: NonNegativeFloat = Field(
        0.0181,
        description="standard deviation of each wobble shift component per px of the probe's "
        "mean sigma, px/px",
    )

    @model_validator(mode="after")
    def _check_tables(self) -> AnalyticModel:
        knots = np.asarray(self.knots_px)
        if knots.size < 2 or not np.all(np.diff(knots) > 0) or knots[0] <= 0:
            raise ValueError(f"knots_px: need at least two increasing widths > 0, got {knots}")
        for name in _TABLES:
            values = np.asarray(getattr(self, name))
            if values.shape != knots.shape:
                raise ValueError(
                    f"{name}: need {knots.size} values, one per knot, got {values.size}"
                )
            if not np.all(np.isfinite(values)) or np.any(values < 0):
                raise ValueError(f"{name}: values must be finite and >= 0")
            if name.endswith("ratio") and np.any(values <= 0):
                raise ValueError(f"{name}: ratios must be > 0")
        if not math.isfinite(self.orientation_power):
            raise ValueError("orientation_power must be finite")
        return self


class SEMConfig(BaseModel):
    """Instrument parameters of a synthetic SEM. Units in the field names."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("synthetic", description="instrument name, shown in recordings")
    image_size_px: int = Field(256, ge=32, le=2048, description="square frame, pixels")
    defocus_interval_v: tuple[float, float] = Field(
        (0.0, 100.0), description="allowed defocus-lens voltage (low, high), volts"
    )
    stigmator_interval_pct: tuple[float, float] = Field(
        (-100.0, 100.0),
        description="allowed excitation of each stigmator (low, high), percent of full scale",
    )
    aperture_interval_um: tuple[float, float] = Field(
        (-50.0, 50.0),
        description="allowed position of the objective aperture along x and y (low, high), um",
    )
    optimum_v: float = Field(50.0, description="nominal in-focus defocus-lens voltage, volts")
    optimum_spread_v: NonNegativeFloat = Field(
        20.0, description="the optimum of a scenario is uniform within optimum_v +/- this"
    )
    drift_v_per_acquisition: NonNegativeFloat = Field(
        0.0, description="std of the optimum's random walk per acquired image, volts"
    )
    gain_px_per_v: PositiveFloat = Field(
        0.2, description="growth of the probe sigma per volt of focus error, px/V"
    )
    probe_sigma0_px: PositiveFloat = Field(1.0, description="probe sigma in focus, pixels")
    hysteresis_v: NonNegativeFloat = Field(
        0.0, description="lag of the lens field behind the last voltage change, volts"
    )
    astigmatism_max_v: NonNegativeFloat = Field(
        0.0,
        description="a scenario's astigmatism, the defocus volts between its two line foci, is "
        "uniform in [0, this]; its axis is uniform in [0, 180) degrees",
    )
    stigmator_v_per_pct: PositiveFloat = Field(
        0.2, description="line-focus separation one percent of stigmator excitation cancels, V"
    )
    aperture_offset_max_um: NonNegativeFloat = Field(
        0.0,
        description="a scenario's aperture sits off the optical axis by a distance uniform in "
        "[0, this] in a uniform direction, um",
    )
    aperture_shift_px_per_v_um: NonNegativeFloat = Field(
        0.0,
        description="beam tilt of an off-axis aperture: image shift per volt of focus error per "
        "um of aperture offset, px/(V um)",
    )
    aperture_blur_px_per_um: NonNegativeFloat = Field(
        0.0,
        description="probe sigma added in quadrature per um of aperture offset (off-axis "
        "aberrations), px/um",
    )
    dose_electrons_per_px: PositiveFloat = Field(
        200.0, description="primary electrons per pixel; sets the shot noise"
    )
    detector_noise: NonNegativeFloat = Field(
        0.01, description="Gaussian detector noise, in secondary-electron yield units"
    )
    substrate_yield: NonNegativeFloat = Field(0.25, description="substrate brightness")
    particle_yield: NonNegativeFloat = Field(0.9, description="gold particle brightness")
    substrate_texture: NonNegativeFloat = Field(
        0.02, description="amplitude of the substrate's grain (yield units)"
    )
    particles: tuple[int, int] = Field((15, 30), description="particles per frame (min, max)")
    particle_radius_px: tuple[float, float] = Field(
        (4.0, 14.0), description="particle radius range, pixels"
    )
    acquisition_failure_rate: float = Field(
        0.0, ge=0.0, le=1.0, description="probability that an acquisition fails (driver fault)"
    )
    reset_state: Literal["aligned", "nominal"] = Field(
        "aligned",
        description="where a reset leaves the stigmators and the aperture: at their optimum "
        "(aligned), or at 0 (nominal: an uncorrected column, as alignrl align meets one)",
    )
    analytic_calibration: AnalyticModel = Field(
        default_factory=AnalyticModel,
        description="analytic mode's calibration against the image path (readings without images)",
    )

    @model_validator(mode="after")
    def _check_ranges(self) -> SEMConfig:
        for field in ("defocus_interval_v", "stigmator_interval_pct", "aperture_interval_um"):
            low, high = getattr(self, field)
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(f"{field}: low {low} must be below high {high}, both finite")
        low, high = self.defocus_interval_v
        if not low <= self.optimum_v <= high:
            raise ValueError(f"optimum_v {self.optimum_v} lies outside defocus_interval_v")
        # Every scenario's optimum must be a setting the knobs can reach.
        reach_pct = self.astigmatism_max_v / self.stigmator_v_per_pct
        low, high = self.stigmator_interval_pct
        if not (low <= -reach_pct and reach_pct <= high):
            raise ValueError(
                f"stigmator_interval_pct [{low:g}, {high:g}] must contain +/- {reach_pct:g} %: "
                f"cancelling astigmatism_max_v {self.astigmatism_max_v:g} V takes that much at "
                f"stigmator_v_per_pct {self.stigmator_v_per_pct:g} V/%"
            )
        low, high = self.aperture_interval_um
        reach_um = self.aperture_offset_max_um
        if not (low <= -reach_um and reach_um <= high):
            raise ValueError(
                f"aperture_interval_um [{low:g}, {high:g}] must contain +/- "
                f"aperture_offset_max_um ({reach_um:g} um), where the aperture may sit"
            )
        if self.particles[0] < 1 or self.particles[0] > self.particles[1]:
            raise ValueError(f"particles: need 1 <= min <= max, got {self.particles}")
        r_low, r_high = self.particle_radius_px
        if not 0 < r_low <= r_high:
            raise ValueError(f"particle_radius_px: need 0 < min <= max, got {(r_low, r_high)}")
        return self


SHOWN_PROBLEMS = 10  # problems of a bad instrument config listed in one message


def load_sem_config(path: str | Path, **overrides: Any) -> SEMConfig:
    """Read a synthetic-SEM YAML file (strictly: an unknown key is an error)."""
    path = Path(path)
    try:
        data = read_yaml_file(path)  # bounded, no duplicate keys (alignrl/yaml_io.py)
    except FileNotFoundError:
        raise FileNotFoundError(f"synthetic SEM config {path} does not exist") from None
    if data is None:
        raise ValueError(f"{path}: empty synthetic SEM config: write its instrument parameters")
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of instrument parameters")
    data.update(overrides)
    try:
        return SEMConfig(**data)
    except ValidationError as error:
        problems = []
        for item in error.errors():
            key = ".".join(str(part) for part in item["loc"]) or "(top)"
            # Say where the bad value came from: the file, or the caller's overrides.
            origin = "apparatus argument " if item["loc"] and item["loc"][0] in overrides else ""
            problems.append(f"{origin}{key[:200]}: {item['msg'][:400]}")
        shown = problems[:SHOWN_PROBLEMS]
        if len(problems) > SHOWN_PROBLEMS:
            shown.append(f"and {len(problems) - SHOWN_PROBLEMS} more problems")
        raise ValueError(f"{path}: {'; '.join(shown)}") from None


def _covariance(sigma_u: float, sigma_v: float, axis: float) -> np.ndarray:
    """Covariance (px^2) in (x, y) = (column, row) of a Gaussian with standard deviations
    sigma_u along the unit vector (cos axis, sin axis) and sigma_v across it: R diag R^T."""
    cos, sin = np.cos(axis), np.sin(axis)
    cov_xx = sigma_u**2 * cos**2 + sigma_v**2 * sin**2
    cov_yy = sigma_u**2 * sin**2 + sigma_v**2 * cos**2
    cov_xy = (sigma_u**2 - sigma_v**2) * sin * cos
    return np.array([[cov_xx, cov_xy], [cov_xy, cov_yy]])


def _logistic(value: float, middle: float, spread: float) -> float:
    """1 / (1 + exp(-(value - middle) / spread)), without overflow far from the middle."""
    return 0.5 * (1.0 + math.tanh(0.5 * (value - middle) / spread))


def edge_widths_px(covariance: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """10-90 % widths (px) of straight edges with unit normals at `angles` (rad, atan2(ny, nx))
    blurred by a Gaussian probe of this covariance: 2.563 sqrt(n^T C n)."""
    cos, sin = np.cos(angles), np.sin(angles)
    variance = (
        covariance[0, 0] * cos**2 + 2.0 * covariance[0, 1] * cos * sin + covariance[1, 1] * sin**2
    )
    return TEN_NINETY_PER_SIGMA * np.sqrt(variance)


def mean_edge_width_px(covariance: np.ndarray, power: float = 1.0) -> float:
    """Mean 10-90 % width (px) over uniformly distributed edge orientations, the rims of round
    particles, for a Gaussian probe of this covariance: the power mean (mean w^p)^(1/p), the
    arithmetic mean for p = 1, the geometric mean for p = 0."""
    widths = edge_widths_px(covariance, _ORIENTATIONS)
    if power == 0:
        return float(np.exp(np.log(widths).mean()))
    return float(np.mean(widths**power) ** (1.0 / power))


def directional_edge_widths_px(covariance: np.ndarray) -> np.ndarray:
    """True widths (px) of the four orientation bins of quality.ORIENTATION_BINS_DEG: the edge
    width 2.563 sqrt(n^T C n) averaged over each bin's +/- 22.5 degrees of normal orientation,
    as the rims of round particles fill a bin."""
    centres = np.deg2rad(np.asarray(quality.ORIENTATION_BINS_DEG, dtype=np.float64))
    return edge_widths_px(covariance, centres[:, None] + _BIN_OFFSETS[None, :]).mean(axis=1)


class SyntheticSEM:
    """A simulated SEM column with five knobs (defocus, two stigmators, the aperture's x and
    y) and a secret optimum. `analytic=True` computes every reading from the probe itself,
    without rendering images (`image()` is then None)."""

    def __init__(
        self, config: SEMConfig | None = None, seed: int | None = None, analytic: bool = False
    ) -> None:
        self.config = config or SEMConfig()
        self.analytic = bool(analytic)
        cfg = self.config
        intervals = (cfg.defocus_interval_v, cfg.stigmator_interval_pct, cfg.aperture_interval_um)
        defocus, stigmator, aperture = ((float(low), float(high)) for low, high in intervals)
        self.knobs: Mapping[str, tuple[float, float]] = dict(
            zip(KNOB_NAMES, (defocus, stigmator, stigmator, aperture, aperture), strict=True)
        )
        self._seeds = np.random.SeedSequence(seed)
        size = cfg.image_size_px
        freq_y = np.fft.fftfreq(size)[:, None]  # cycles per pixel, rows
        freq_x = np.fft.rfftfreq(size)[None, :]  # cycles per pixel, columns (real FFT half)
        self._fxx, self._fyy, self._fxy = freq_x**2, freq_y**2, freq_x * freq_y
        self._freq_x, self._freq_y = freq_x, freq_y
        self._specimen_shape = (size, size)
        self.acquisitions = 0
        self._last_image: np.ndarray | None = None
        self.reset(seed)

    # --- the Apparatus protocol ---------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """New scenario: a new specimen area, optimum, astigmatism and aperture offset.

        The defocus goes to its nominal value, the stigmators and the aperture to their
        optimum (`reset_state` "nominal": to 0, an uncorrected column). The draws of the
        focus-only column come first from the scenario's generator, in their old order; the
        aperture's distance from the axis, drawn since the aperture
        became a knob, comes from a generator of its own, so the rest is unchanged.
        """
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self._rng = np.random.default_rng(seed)
        cfg = self.config
        self._optimum_v = cfg.optimum_v + self._rng.uniform(-1, 1) * cfg.optimum_spread_v
        astigmatism_v = self._rng.uniform(0, cfg.astigmatism_max_v)
        self._astigmatism_axis = self._rng.uniform(0, np.pi)
        aperture_angle = self._rng.uniform(0, 2 * np.pi)
        self._specimen_fft = np.fft.rfft2(self._draw_specimen())
        column_rng = np.random.default_rng([seed, 2])  # draws new with the five-knob column
        offset_um = column_rng.uniform(0, cfg.aperture_offset_max_um)
        # How this scenario's specimen reads in analytic mode: wide or narrow, all along.
        self._specimen_draw = float(column_rng.standard_normal())
        # The stigmator setting that cancels a = A (cos 2 phi, sin 2 phi): a / g_s. Kept as a
        # setting, so that the residual g_s (s_opt - s) is exactly zero at the optimum.
        double_axis = 2.0 * self._astigmatism_axis
        self._stigmator_optimum_pct = (
            astigmatism_v
            / cfg.stigmator_v_per_pct
            * np.array([np.cos(double_axis), np.sin(double_axis)])
        )
        self._aperture_offset_um = offset_um * np.array(
            [np.cos(aperture_angle), np.sin(aperture_angle)]
        )
        low, high = self.knobs["defocus"]
        self._defocus_v = float(np.clip(cfg.optimum_v, low, high))
        self._direction = 0.0  # sign of the last voltage change, for hysteresis
        aligned = cfg.reset_state == "aligned"
        self._stigmator_pct = self._stigmator_optimum_pct.copy() if aligned else np.zeros(2)
        self._aperture_um = self._aperture_offset_um.copy() if aligned else np.zeros(2)
        self._last_image = None

    def read(self) -> dict[str, float]:
        return {
            "defocus": self._defocus_v,
            "stigmator_x": float(self._stigmator_pct[0]),
            "stigmator_y": float(self._stigmator_pct[1]),
            "aperture_x": float(self._aperture_um[0]),
            "aperture_y": float(self._aperture_um[1]),
        }

    def write(self, values: Mapping[str, float]) -> None:
        """Set any of the five knobs; a refused write (check_write) changes nothing."""
        check_write(self.knobs, values)
        if "defocus" in values:
            self._set_defocus(float(values["defocus"]))
        for index, axis in enumerate("xy"):
            if f"stigmator_{axis}" in values:
                self._stigmator_pct[index] = float(values[f"stigmator_{axis}"])
            if f"aperture_{axis}" in values:
                self._aperture_um[index] = float(values[f"aperture_{axis}"])

    def measure(self) -> float:
        """Acquire an image and return its edge width (px); NoEdgesError far out of focus."""
        if self.analytic:
            covariance = self._analytic_acquisition()[0]
            return self._analytic_width(covariance)
        return edge_width(self.acquire())

    def image(self) -> np.ndarray | None:
        return self._last_image

    def optimum(self) -> dict[str, float]:
        """The knob settings that align the column if written now.

        The stigmators cancel the astigmatism (a / g_s) and the aperture sits on the axis
        (o), whatever the history. The defocus field lags the voltage by the hysteresis h in
        the direction of the last change, so its target depends on the side it is approached
        from: V_opt + h from below, V_opt - h from above; the current setting itself if it is
        in focus already. Of the reachable targets, the nearer one.
        """
        h, setting = self.config.hysteresis_v, self._defocus_v
        if abs(self.focus_error_v()) < 1e-9:
            defocus = setting
        else:
            candidates = [
                target
                for target, reachable in (
                    (self._optimum_v + h, self._optimum_v + h > setting),
                    (self._optimum_v - h, self._optimum_v - h < setting),
                )
                if reachable
            ]
            defocus = min(candidates, key=lambda target: abs(target - setting))
        return {
            "defocus": defocus,
            "stigmator_x": float(self._stigmator_optimum_pct[0]),
            "stigmator_y": float(self._stigmator_optimum_pct[1]),
            "aperture_x": float(self._aperture_offset_um[0]),
            "aperture_y": float(self._aperture_offset_um[1]),
        }

    def best_quality(self) -> float:
        """Edge width (px) of a noise-free frame at the optimum: 2.563 x probe_sigma0_px."""
        return float(TEN_NINETY_PER_SIGMA * self.config.probe_sigma0_px)

    # --- further measurements -----------------------------------------------------------

    def measure_directional(self) -> tuple[float, np.ndarray]:
        """One acquisition: (mean edge width px, edge widths of the four edge-normal
        orientation bins of quality.ORIENTATION_BINS_DEG px). An astigmatic probe blurs edges
        whose normal lies along its long axis most. NoEdgesError where a bin has no edges."""
        if self.analytic:
            return self._analytic_directional(self._analytic_acquisition()[0])
        measured = quality.directional_widths(self.acquire())
        return float(measured.width_px), np.asarray(measured.widths_px, dtype=np.float64)

    def measure_wobble(self, amplitude_v: float) -> np.ndarray:
        """Two acquisitions, at defocus + amplitude and defocus - amplitude (each clamped into
        the defocus interval, written as knob changes, so hysteresis acts as on a real lens):
        the shift (dx, dy) px of the plus frame against the minus frame. An off-axis aperture
        makes it k_ap (dV+ - dV-) d; it vanishes with the aperture on the axis. Afterwards the
        defocus and the lens's hysteresis state are as before, also when an acquisition fails.
        """
        amplitude_v = float(amplitude_v)
        if not (math.isfinite(amplitude_v) and amplitude_v >= 0):
            raise ValueError(f"wobble amplitude must be a finite voltage >= 0, got {amplitude_v}")
        low, high = self.knobs["defocus"]
        setting, direction = self._defocus_v, self._direction
        readings = []
        try:
            for sign in (1.0, -1.0):
                self._set_defocus(float(np.clip(setting + sign * amplitude_v, low, high)))
                if self.analytic:
                    readings.append(self._analytic_acquisition())
                else:
                    readings.append(self.acquire())
        finally:
            self._defocus_v, self._direction = setting, direction
        if self.analytic:
            return self._analytic_wobble(*readings[0], *readings[1])
        plus, minus = readings
        return np.asarray(quality.wobble_shift(minus, plus), dtype=np.float64)

    # --- physics ------------------------------------------------------------------------

    def focus_error_v(self) -> float:
        """V_eff - V_opt in volts: what the probe really sees."""
        effective_v = self._defocus_v - self.config.hysteresis_v * self._direction
        return effective_v - self._optimum_v

    def astigmatism_residual_v(self) -> np.ndarray:
        """r = a - g_s s (volts of line-focus separation, as a vector in the 2 phi plane)."""
        return self.config.stigmator_v_per_pct * (self._stigmator_optimum_pct - self._stigmator_pct)

    def aperture_residual_um(self) -> np.ndarray:
        """d = o - (aperture_x, aperture_y): how far the aperture sits off the axis, um."""
        return self._aperture_offset_um - self._aperture_um

    def probe_sigmas_px(self) -> tuple[float, float, float]:
        """Probe standard deviations along its principal axes (px) and the axis angle (rad).

        sigma_u,v = sqrt(sigma0^2 + (gain (dV -/+ A_res / 2))^2 + (b_ap |d|)^2), sigma_u along
        phi_res = atan2(r_y, r_x) / 2: the two line foci sit A_res / 2 above and below the
        round-beam focus, so under- and over-focus stretch the probe along perpendicular
        axes. A round probe (A_res = 0) reports the scenario's astigmatism axis.
        """
        cfg = self.config
        error_v = self.focus_error_v()
        residual = self.astigmatism_residual_v()
        half_astigmatism = 0.5 * float(np.hypot(residual[0], residual[1]))
        axis = (
            0.5 * float(np.arctan2(residual[1], residual[0]))
            if half_astigmatism > 0
            else self._astigmatism_axis
        )
        aperture_blur = cfg.aperture_blur_px_per_um * float(np.hypot(*self.aperture_residual_um()))
        sigma_u = np.hypot(cfg.probe_sigma0_px, cfg.gain_px_per_v * (error_v - half_astigmatism))
        sigma_v = np.hypot(cfg.probe_sigma0_px, cfg.gain_px_per_v * (error_v + half_astigmatism))
        # hypot(s, 0) is s exactly: an aligned aperture leaves the focus-only probe untouched.
        return (
            float(np.hypot(sigma_u, aperture_blur)),
            float(np.hypot(sigma_v, aperture_blur)),
            axis,
        )

    def probe_covariance_px2(self) -> np.ndarray:
        """The probe's covariance in (x, y) = (column, row) pixels, 2x2."""
        return _covariance(*self.probe_sigmas_px())

    def probe_width_px(self) -> float:
        """The probe's true edge width (px) on round particles: the mean over edge-normal
        orientations of 2.563 sqrt(n^T C n), what a noise-free reading of sharp, well
        separated rims would give."""
        return mean_edge_width_px(self.probe_covariance_px2())

    def expected_width_px(self) -> float:
        """The analytic mode's edge-width reading of the present state without its scatter:
        the power-mean width w_p times the calibrated median ratio of the image path at w_p.
        What the analytic model predicts an image reads here (the median over specimens and
        noise); it acquires nothing and draws nothing."""
        model = self.config.analytic_calibration
        effective_px = mean_edge_width_px(self.probe_covariance_px2(), model.orientation_power)
        return float(effective_px * np.interp(effective_px, model.knots_px, model.reading_ratio))

    def image_shift_px(self) -> np.ndarray:
        """(dx, dy) px by which the image content moves: k_ap dV d, the tilt of the beam
        through an off-axis aperture times the focus error."""
        cfg = self.config
        return cfg.aperture_shift_px_per_v_um * self.focus_error_v() * self.aperture_residual_um()

    def acquire(self) -> np.ndarray:
        """Scan one frame at the current settings: blurred, shifted, noisy (float32)."""
        cfg = self.config
        self._check_detector()
        covariance = self.probe_covariance_px2()
        # Fourier transform of a normalised Gaussian: exp(-2 pi^2 f^T C f).
        exponent = (
            -2.0
            * np.pi**2
            * (
                covariance[0, 0] * self._fxx
                + 2 * covariance[0, 1] * self._fxy
                + covariance[1, 1] * self._fyy
            )
        )
        shift_x, shift_y = self.image_shift_px()
        # A factor exp(-2 pi i f . s) moves the content by +s.
        phase = -2.0 * np.pi * (self._freq_x * shift_x + self._freq_y * shift_y)
        transfer = np.exp(exponent + 1j * phase) if (shift_x or shift_y) else np.exp(exponent)
        signal = np.fft.irfft2(self._specimen_fft * transfer, s=self._specimen_shape)
        np.clip(signal, 0.0, None, out=signal)
        expected = signal * cfg.dose_electrons_per_px  # electrons per pixel
        if expected.min() >= GAUSSIAN_SHOT_NOISE_ABOVE:
            # The Gaussian limit of the Poisson law: indistinguishable here, twice as fast.
            counts = expected + np.sqrt(expected) * self._rng.standard_normal(expected.shape)
        else:
            counts = self._rng.poisson(expected)
        frame = counts / cfg.dose_electrons_per_px
        if cfg.detector_noise > 0:
            frame = frame + cfg.detector_noise * self._rng.standard_normal(frame.shape)
        self._last_image = frame.astype(np.float32)
        self._finish_acquisition()
        return self._last_image

    # --- internals ----------------------------------------------------------------------

    def _set_defocus(self, new_v: float) -> None:
        """Set the defocus voltage; a change sets the hysteresis state to its direction."""
        if new_v != self._defocus_v:
            self._direction = float(np.sign(new_v - self._defocus_v))
        self._defocus_v = new_v

    def _check_detector(self) -> None:
        """A simulated driver fault, at acquisition_failure_rate."""
        rate = self.config.acquisition_failure_rate
        if rate > 0 and self._rng.random() < rate:
            raise ApparatusError("acquisition failed: detector read-out timed out (simulated)")

    def _finish_acquisition(self) -> None:
        """Count the acquisition; the optimum drifts while the frame is scanned."""
        self.acquisitions += 1
        drift = self.config.drift_v_per_acquisition
        if drift > 0:
            self._optimum_v += drift * self._rng.standard_normal()

    def _analytic_acquisition(self) -> tuple[np.ndarray, np.ndarray]:
        """An acquisition without an image: the probe's covariance and the image shift now."""
        self._check_detector()
        covariance, shift = self.probe_covariance_px2(), self.image_shift_px()
        self._last_image = None
        self._finish_acquisition()
        return covariance, shift

    def _analytic_width(self, covariance: np.ndarray) -> float:
        """The edge width the image path would read for this probe.

        The particles are round, so their rims show every edge orientation: the reading
        follows the power mean w_p over orientations of 2.563 sqrt(n^T C n), times the
        calibrated median ratio at w_p, with the calibrated specimen and noise scatter; beyond
        the calibrated blur limit the frame shows no edges (NoEdgesError).
        """
        model = self.config.analytic_calibration
        effective_px = mean_edge_width_px(covariance, model.orientation_power)
        self._edges_or_raise(effective_px, model.no_edges_px, model.no_edges_spread_px, "edges")
        return float(
            self._reading(effective_px, model.reading_ratio, model.noise_rel, model.specimen_rel)
        )

    def _analytic_directional(self, covariance: np.ndarray) -> tuple[float, np.ndarray]:
        """The mean width and the widths of the four orientation bins (2.563 sqrt(n^T C n)
        averaged over each bin's +/- 22.5 deg), read with the calibrated ratios and scatters.
        A blurred frame leaves some bin empty sooner than it loses all its edges."""
        model = self.config.analytic_calibration
        effective_px = mean_edge_width_px(covariance, model.orientation_power)
        self._edges_or_raise(
            effective_px,
            model.directional_no_edges_px,
            model.directional_no_edges_spread_px,
            "measurable edges in every orientation bin",
        )
        width = self._reading(
            effective_px, model.reading_ratio, model.noise_rel, model.specimen_rel
        )
        bins = self._reading(
            directional_edge_widths_px(covariance),
            model.directional_ratio,
            model.directional_noise_rel,
            model.directional_specimen_rel,
        )
        return float(width), bins

    def _analytic_wobble(
        self,
        plus_covariance: np.ndarray,
        plus_shift: np.ndarray,
        minus_covariance: np.ndarray,
        minus_shift: np.ndarray,
    ) -> np.ndarray:
        """The shift the image path would read between the two frames of a wobble: the exact
        difference of their image shifts x the calibrated ratio, with Gaussian noise that
        grows with the blur (the registration's error). Beyond the calibrated blur the pair
        has nothing to correlate: MeasurementError."""
        model = self.config.analytic_calibration
        sigma = math.sqrt(0.25 * (np.trace(plus_covariance) + np.trace(minus_covariance)))
        if self._rng.random() < _logistic(
            sigma, model.wobble_failure_sigma_px, model.wobble_failure_spread_px
        ):
            raise MeasurementError(
                f"wobble: frames blurred by a {sigma:.1f} px probe leave nothing to correlate "
                f"(analytic mode: half of the pairs beyond {model.wobble_failure_sigma_px:g} px)"
            )
        noise = model.wobble_scatter_px_per_px * sigma * self._rng.standard_normal(2)
        return model.wobble_ratio * (plus_shift - minus_shift) + noise

    def _edges_or_raise(
        self, true_px: float, middle_px: float, spread_px: float, what: str
    ) -> None:
        """NoEdgesError with the calibrated probability 1 / (1 + exp(-(w - middle) / spread))."""
        if self._rng.random() < _logistic(true_px, middle_px, spread_px):
            raise NoEdgesError(
                f"no {what}: a probe {true_px:.1f} px wide blurs the specimen into the noise "
                f"(analytic mode: half of the frames lose them beyond {middle_px:g} px)"
            )

    def _reading(
        self,
        width_px: np.ndarray | float,
        ratio: FloatTable,
        noise: FloatTable,
        specimen: FloatTable,
    ) -> np.ndarray:
        """width x ratio x exp(specimen x z + noise x e), the tables interpolated at the width;
        z is the scenario's specimen draw, e a fresh N(0, 1) per value."""
        knots = self.config.analytic_calibration.knots_px
        width_px = np.asarray(width_px, dtype=np.float64)
        log_scatter = np.interp(width_px, knots, specimen) * self._specimen_draw + np.interp(
            width_px, knots, noise
        ) * self._rng.standard_normal(width_px.shape)
        return width_px * np.interp(width_px, knots, ratio) * np.exp(log_scatter)

    def _draw_specimen(self) -> np.ndarray:
        """Gold particles on a textured substrate, periodic across the frame edges."""
        cfg, rng = self.config, self._rng
        size = cfg.image_size_px
        # Substrate grain: white noise low-passed in Fourier space (periodic by construction).
        grain = np.fft.irfft2(
            np.fft.rfft2(rng.standard_normal((size, size)))
            * np.exp(-2.0 * np.pi**2 * 4.0 * (self._fxx + self._fyy)),
            s=(size, size),
        )
        grain *= cfg.substrate_texture / max(float(grain.std()), 1e-12)
        specimen = cfg.substrate_yield + grain
        coordinates = np.arange(size, dtype=np.float64)
        count = int(rng.integers(cfg.particles[0], cfg.particles[1] + 1))
        for _ in range(count):
            centre_x, centre_y = rng.uniform(0, size, 2)
            radius = rng.uniform(*cfg.particle_radius_px)
            brightness = cfg.particle_yield * rng.uniform(0.9, 1.1)
            # Distances on a torus, so that a particle leaving one side enters the other.
            dx = (coordinates - centre_x + size / 2) % size - size / 2
            dy = (coordinates - centre_y + size / 2) % size - size / 2
            distance = np.sqrt(dx[None, :] ** 2 + dy[:, None] ** 2)
            coverage = np.clip(radius - distance + 0.5, 0.0, 1.0)  # anti-aliased rim
            specimen = specimen + coverage * (brightness - specimen)
        return specimen

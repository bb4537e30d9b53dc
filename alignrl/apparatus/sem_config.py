"""Instrument parameters of the synthetic SEM: `SEMConfig`, its analytic mode's calibration
`AnalyticModel`, and the YAML files they are read from (`load_sem_config`; the presets
`synthetic` and `synthetic-b` are alignrl/apparatus/presets/*.yaml, PRESET_DIR).

Every field carries its unit in its name or description (volts, pixels, um, percent of full
excitation, electrons per pixel). A config is read strictly: an unknown key, a value out of
range or an inconsistent pair of fields is a ValueError naming them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from alignrl.apparatus.specimens import SPECIMENS
from alignrl.yaml_io import read_yaml_file

__all__ = [
    "PRESET_DIR",
    "SPECIMEN_KINDS",
    "AnalyticModel",
    "FloatTable",
    "SEMConfig",
    "load_sem_config",
    "preset_names",
]

PRESET_DIR = Path(__file__).with_name("presets")
PositiveFloat = Annotated[float, Field(gt=0)]
# What the image path images: the simulator's own gold particles (the fields below), or a
# kind of the instrument family's specimens (alignrl/apparatus/specimens.py).
SPECIMEN_KINDS: tuple[str, ...] = ("gold", *SPECIMENS)
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
    astigmatism_min_v: NonNegativeFloat = Field(
        0.0,
        description="the least astigmatism of a scenario, V: its line-focus separation is "
        "uniform in [this, astigmatism_max_v] (a column whose stigmators must sit near a bound)",
    )
    stigmator_v_per_pct: PositiveFloat = Field(
        0.2, description="line-focus separation one percent of stigmator excitation cancels, V"
    )
    stigmator_hysteresis_pct: NonNegativeFloat = Field(
        0.0,
        description="each stigmator's field lags its setting by this against its last change, "
        "in the stigmators' units",
    )
    stigmator_drift_pct_per_acquisition: NonNegativeFloat = Field(
        0.0,
        description="std of each stigmator's optimum random walk per acquired image, in the "
        "stigmators' units",
    )
    # How the stigmators act in the image (docs/physics.md, "How a column's knobs act"):
    # their axes turned against the image's, coupled, one of them wired the other way round.
    stigmator_rotation_deg: float = Field(
        0.0,
        ge=0.0,
        lt=180.0,
        description="the stigmators' axes rotated against the image's, degrees (an astigmatism "
        "along phi turns by twice this in the stigmators' plane)",
    )
    stigmator_coupling: float = Field(
        0.0,
        gt=-0.9,
        lt=0.9,
        description="cross-coupling: the share of each stigmator's action that the other "
        "stigmator's axis receives",
    )
    stigmator_mirror: bool = Field(
        False, description="stigmator_y acts with the opposite sign (a mirrored or rewired axis)"
    )
    aperture_offset_max_um: NonNegativeFloat = Field(
        0.0,
        description="a scenario's aperture sits off the optical axis by a distance uniform in "
        "[0, this] in a uniform direction, um",
    )
    aperture_offset_min_um: NonNegativeFloat = Field(
        0.0,
        description="the least distance of a scenario's aperture from the axis, um: uniform in "
        "[this, aperture_offset_max_um]",
    )
    aperture_shift_px_per_v_um: NonNegativeFloat = Field(
        0.0,
        description="beam tilt of an off-axis aperture: image shift per volt of focus error per "
        "um of aperture offset, px/(V um)",
    )
    aperture_rotation_deg: float = Field(
        0.0,
        ge=0.0,
        lt=360.0,
        description="the image turned against the aperture's x and y axes, degrees: the "
        "wobble's shift points this far round from the aperture's offset",
    )
    aperture_mirror: bool = Field(
        False, description="the image mirrored against the aperture's axes (y the other way)"
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
    specimen: str = Field(
        "gold",
        description="what the image path images: gold (the particles below) or a kind of "
        "alignrl/apparatus/specimens.py (particles, grid, bars, fibres, texture), drawn from "
        "the scenario's generator where gold is; analytic mode ignores it (its calibration "
        "is the base preset's, on gold)",
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

    @field_validator("specimen")
    @classmethod
    def _known_specimen(cls, kind: str) -> str:
        if kind not in SPECIMEN_KINDS:
            raise ValueError(f"no kind {kind!r}; the kinds are {', '.join(SPECIMEN_KINDS)}")
        return kind

    @model_validator(mode="after")
    def _check_ranges(self) -> SEMConfig:
        for field in ("defocus_interval_v", "stigmator_interval_pct", "aperture_interval_um"):
            low, high = getattr(self, field)
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(f"{field}: low {low} must be below high {high}, both finite")
        for least, most in (
            ("astigmatism_min_v", "astigmatism_max_v"),
            ("aperture_offset_min_um", "aperture_offset_max_um"),
        ):
            if getattr(self, least) > getattr(self, most):
                raise ValueError(
                    f"{least} {getattr(self, least):g} exceeds {most} {getattr(self, most):g}"
                )
        low, high = self.defocus_interval_v
        if not low <= self.optimum_v <= high:
            raise ValueError(f"optimum_v {self.optimum_v} lies outside defocus_interval_v")
        # Every scenario's optimum must be a setting the knobs can reach: coupled stigmators
        # need up to 1 / (1 - |coupling|) times as much excitation.
        weakest = self.stigmator_v_per_pct * (1.0 - abs(self.stigmator_coupling))
        reach_pct = self.astigmatism_max_v / weakest
        low, high = self.stigmator_interval_pct
        if not (low <= -reach_pct and reach_pct <= high):
            raise ValueError(
                f"stigmator_interval_pct [{low:g}, {high:g}] must contain +/- {reach_pct:g} %: "
                f"cancelling astigmatism_max_v {self.astigmatism_max_v:g} V takes that much at "
                f"stigmator_v_per_pct {self.stigmator_v_per_pct:g} V/% (coupling "
                f"{self.stigmator_coupling:g})"
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

    def stigmator_response(self) -> np.ndarray | None:
        """How the stigmators' settings (s_x, s_y) act on the astigmatism, in its (cos 2 phi,
        sin 2 phi) plane, per V of stigmator_v_per_pct: the 2 x 2 matrix R(2 rotation)
        [[1, c], [c, 1]] diag(1, -1 where mirrored); None where it is the identity (the
        presets: the same numbers as a column without it)."""
        if not (self.stigmator_rotation_deg or self.stigmator_coupling or self.stigmator_mirror):
            return None
        coupled = np.array([[1.0, self.stigmator_coupling], [self.stigmator_coupling, 1.0]])
        flip = np.diag([1.0, -1.0 if self.stigmator_mirror else 1.0])
        return _rotation(2.0 * math.radians(self.stigmator_rotation_deg)) @ coupled @ flip

    def aperture_response(self) -> np.ndarray | None:
        """How the aperture's offset from the axis shows in the image's (x, y): R(rotation)
        diag(1, -1 where mirrored); None where it is the identity."""
        if not (self.aperture_rotation_deg or self.aperture_mirror):
            return None
        flip = np.diag([1.0, -1.0 if self.aperture_mirror else 1.0])
        return _rotation(math.radians(self.aperture_rotation_deg)) @ flip


def _rotation(angle: float) -> np.ndarray:
    cos, sin = math.cos(angle), math.sin(angle)
    return np.array([[cos, -sin], [sin, cos]])


SHOWN_PROBLEMS = 10  # problems of a bad instrument config listed in one message


def preset_names() -> list[str]:
    """Names of the shipped synthetic instruments: every YAML file of PRESET_DIR."""
    return sorted(path.stem for path in PRESET_DIR.glob("*.yaml"))


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

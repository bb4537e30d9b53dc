"""The synthetic SEM: a stand-in for a real scanning electron microscope column.

Image formation (design.md): image = specimen (*) probe + noise.

* Specimen: gold particles with sharp rims on a faintly textured carbon substrate (the Zn-Au
  test specimen of seed section 6.2), drawn anew for every scenario from its seed. Intensities
  are secondary-electron yields: substrate ~0.25, gold ~0.9.
* Probe: an elliptical Gaussian. With focus error dV = V_eff - V_opt (volts) and astigmatism
  A (volts between the two line foci, axis phi), the probe's standard deviations along its
  principal axes are  sigma_u,v = sqrt(sigma0^2 + (gain * (dV -/+ A/2))^2)  pixels. With A = 0
  this is design.md's  sigma = sqrt(sigma0^2 + (gain * (V - V_opt))^2).
* Aperture: an off-axis objective aperture tilts the beam, so a focus error shifts the image
  by  shift = aperture_shift_px_per_v * dV * (offset direction)  pixels.
* Lens hysteresis: the field lags the last change of the voltage, so the effective voltage
  is V_eff = V - hysteresis_v * s, with s the sign of the last change (+1 up, -1 down).
* Drift: the optimum wanders by a random walk of drift_v_per_acquisition per image.
* Noise: shot noise (Poisson, `dose_electrons_per_px` primary electrons per pixel; where every
  pixel expects at least 30 electrons, its Gaussian limit) and Gaussian detector noise.

Every number comes from a `SEMConfig`; the presets `synthetic` and `synthetic-b` live in
alignrl/apparatus/presets/*.yaml. The blur is applied in Fourier space: the specimen is drawn
periodic (particles wrap around the frame), so the FFT convolution has no border artefacts,
and a 256x256 frame renders in a few milliseconds.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from alignrl.apparatus.base import ApparatusError, check_write
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, edge_width

__all__ = ["PRESET_DIR", "SEMConfig", "SyntheticSEM", "load_sem_config"]

PRESET_DIR = Path(__file__).with_name("presets")

GAUSSIAN_SHOT_NOISE_ABOVE = 30.0  # electrons per pixel where Poisson ~ Gaussian
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]


class SEMConfig(BaseModel):
    """Instrument parameters of a synthetic SEM. Units in the field names."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("synthetic", description="instrument name, shown in recordings")
    image_size_px: int = Field(256, ge=32, le=2048, description="square frame, pixels")
    defocus_interval_v: tuple[float, float] = Field(
        (0.0, 100.0), description="allowed defocus-lens voltage (low, high), volts"
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
        0.0, description="scenario astigmatism (line-focus separation) uniform in [0, this]"
    )
    aperture_shift_px_per_v: NonNegativeFloat = Field(
        0.0, description="image shift per volt of focus error from an off-axis aperture"
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

    @model_validator(mode="after")
    def _check_ranges(self) -> SEMConfig:
        low, high = self.defocus_interval_v
        if not low < high:
            raise ValueError(f"defocus_interval_v: low {low} must be below high {high}")
        if not low <= self.optimum_v <= high:
            raise ValueError(f"optimum_v {self.optimum_v} lies outside defocus_interval_v")
        if self.particles[0] < 1 or self.particles[0] > self.particles[1]:
            raise ValueError(f"particles: need 1 <= min <= max, got {self.particles}")
        r_low, r_high = self.particle_radius_px
        if not 0 < r_low <= r_high:
            raise ValueError(f"particle_radius_px: need 0 < min <= max, got {(r_low, r_high)}")
        return self


def load_sem_config(path: str | Path, **overrides: Any) -> SEMConfig:
    """Read a synthetic-SEM YAML file (strictly: an unknown key is an error)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise FileNotFoundError(f"synthetic SEM config {path} does not exist") from None
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not valid YAML: {error}") from None
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
            problems.append(f"{origin}{key}: {item['msg']}")
        raise ValueError(f"{path}: {'; '.join(problems)}") from None


class SyntheticSEM:
    """A simulated SEM column with one knob, `defocus` (volts), and a secret optimum."""

    def __init__(self, config: SEMConfig | None = None, seed: int | None = None) -> None:
        self.config = config or SEMConfig()
        low, high = self.config.defocus_interval_v
        self.knobs: Mapping[str, tuple[float, float]] = {"defocus": (float(low), float(high))}
        self._seeds = np.random.SeedSequence(seed)
        size = self.config.image_size_px
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
        """New scenario: a new specimen area, optimum, astigmatism and aperture offset."""
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self._rng = np.random.default_rng(seed)
        cfg = self.config
        self._optimum_v = cfg.optimum_v + self._rng.uniform(-1, 1) * cfg.optimum_spread_v
        self._astigmatism_v = self._rng.uniform(0, cfg.astigmatism_max_v)
        self._astigmatism_axis = self._rng.uniform(0, np.pi)
        aperture_angle = self._rng.uniform(0, 2 * np.pi)
        self._aperture_direction = np.array([np.cos(aperture_angle), np.sin(aperture_angle)])
        self._specimen_fft = np.fft.rfft2(self._draw_specimen())
        low, high = self.knobs["defocus"]
        self._defocus_v = float(np.clip(cfg.optimum_v, low, high))
        self._direction = 0.0  # sign of the last voltage change, for hysteresis
        self._last_image = None

    def read(self) -> dict[str, float]:
        return {"defocus": self._defocus_v}

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        if "defocus" in values:
            new_v = float(values["defocus"])
            if new_v != self._defocus_v:
                self._direction = float(np.sign(new_v - self._defocus_v))
            self._defocus_v = new_v

    def measure(self) -> float:
        """Acquire an image and return its edge width (px); NoEdgesError far out of focus."""
        return edge_width(self.acquire())

    def image(self) -> np.ndarray | None:
        return self._last_image

    def optimum(self) -> dict[str, float]:
        """The defocus setting that focuses the beam if written now.

        The field lags the voltage by the hysteresis h in the direction of the last change,
        so the target depends on the side it is approached from: V_opt + h from below,
        V_opt - h from above; the current setting itself if it is in focus already. Of the
        reachable targets, the nearer one.
        """
        h, setting = self.config.hysteresis_v, self._defocus_v
        if abs(self.focus_error_v()) < 1e-9:
            return {"defocus": setting}
        candidates = [
            target
            for target, reachable in (
                (self._optimum_v + h, self._optimum_v + h > setting),
                (self._optimum_v - h, self._optimum_v - h < setting),
            )
            if reachable
        ]
        return {"defocus": min(candidates, key=lambda target: abs(target - setting))}

    def best_quality(self) -> float:
        """Edge width (px) of a noise-free frame at the optimum: 2.563 x the probe sigma there."""
        cfg = self.config
        sigma = np.hypot(cfg.probe_sigma0_px, 0.5 * cfg.gain_px_per_v * self._astigmatism_v)
        return float(TEN_NINETY_PER_SIGMA * sigma)

    # --- physics ------------------------------------------------------------------------

    def focus_error_v(self) -> float:
        """V_eff - V_opt in volts: what the probe really sees."""
        effective_v = self._defocus_v - self.config.hysteresis_v * self._direction
        return effective_v - self._optimum_v

    def probe_sigmas_px(self) -> tuple[float, float, float]:
        """Probe standard deviations along its principal axes (px) and the axis angle (rad)."""
        cfg = self.config
        error_v = self.focus_error_v()
        half_astigmatism = 0.5 * self._astigmatism_v
        sigma_u = np.hypot(cfg.probe_sigma0_px, cfg.gain_px_per_v * (error_v - half_astigmatism))
        sigma_v = np.hypot(cfg.probe_sigma0_px, cfg.gain_px_per_v * (error_v + half_astigmatism))
        return float(sigma_u), float(sigma_v), float(self._astigmatism_axis)

    def acquire(self) -> np.ndarray:
        """Scan one frame at the current settings: blurred, shifted, noisy (float32)."""
        cfg = self.config
        if cfg.acquisition_failure_rate > 0 and self._rng.random() < cfg.acquisition_failure_rate:
            raise ApparatusError("acquisition failed: detector read-out timed out (simulated)")
        sigma_u, sigma_v, axis = self.probe_sigmas_px()
        cos, sin = np.cos(axis), np.sin(axis)
        # Covariance of the probe in (x, y) pixels: R diag(su^2, sv^2) R^T.
        cov_xx = sigma_u**2 * cos**2 + sigma_v**2 * sin**2
        cov_yy = sigma_u**2 * sin**2 + sigma_v**2 * cos**2
        cov_xy = (sigma_u**2 - sigma_v**2) * sin * cos
        # Fourier transform of a normalised Gaussian: exp(-2 pi^2 f^T C f).
        exponent = (
            -2.0 * np.pi**2 * (cov_xx * self._fxx + 2 * cov_xy * self._fxy + cov_yy * self._fyy)
        )
        shift_x, shift_y = (
            cfg.aperture_shift_px_per_v * self.focus_error_v() * self._aperture_direction
        )
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
        self.acquisitions += 1
        if cfg.drift_v_per_acquisition > 0:
            self._optimum_v += cfg.drift_v_per_acquisition * self._rng.standard_normal()
        return self._last_image

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

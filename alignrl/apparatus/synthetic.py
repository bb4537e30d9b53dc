"""The synthetic SEM: a stand-in for a real scanning electron microscope column.

Image formation (design.md, docs/physics.md): image = specimen (*) probe, shifted, + noise.

* Specimen: gold particles with sharp rims on a faintly textured carbon substrate (the Zn-Au
  test specimen of seed section 6.2), drawn anew for every scenario from its seed. Intensities
  are secondary-electron yields: substrate ~0.25, gold ~0.9. `SEMConfig.specimen` may name
  a kind of alignrl/apparatus/specimens.py instead (grid, texture, ...), drawn from the same
  generator at the same place and imaged the same way; analytic mode reads as for gold.
* Five knobs: `defocus` (V), the stigmators `stigmator_x`, `stigmator_y` (percent of full
  excitation) and the objective aperture's position `aperture_x`, `aperture_y` (um).
* Probe: an elliptical Gaussian. With focus error dV = V_eff - V_opt (volts), a residual
  astigmatism of A_res volts between the two line foci along axis phi_res, and an aperture
  residual |d| (um), the probe's standard deviations along its principal axes are
      sigma_u,v = sqrt(sigma0^2 + (gain * (dV -/+ A_res/2))^2 + (b_ap * |d|)^2)  pixels,
  sigma_u along phi_res. With A_res = 0 and d = 0 this is design.md's
  sigma = sqrt(sigma0^2 + (gain * (V - V_opt))^2).
* Astigmatism: the scenario's column has an astigmatism vector a = A (cos 2 phi, sin 2 phi)
  (volts); the stigmators subtract g_s M (s_x, s_y), leaving r = a - g_s M s, with
  A_res = |r| and phi_res = atan2(r_y, r_x) / 2. M is the identity unless the stigmators'
  axes are turned against the image, coupled or mirrored (`stigmator_rotation_deg`,
  `stigmator_coupling`, `stigmator_mirror`: SEMConfig.stigmator_response).
* Aperture: the scenario's aperture sits o (um) off the optical axis; d = o - (a_x, a_y). An
  off-axis aperture tilts the beam, so a focus error shifts the image by
  shift = k_ap * dV * N d pixels (the wobbler's symptom; N turns and mirrors the offset
  where the image is turned against the aperture's axes, `aperture_rotation_deg`,
  `aperture_mirror`), and the off-axis ray bundle blurs the probe by b_ap |d| (in quadrature).
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

The instrument parameters (`SEMConfig`, `AnalyticModel`, `load_sem_config`) are
alignrl/apparatus/sem_config.py, the probe's edge widths alignrl/apparatus/probe.py; their
names are importable from here as well.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping

import numpy as np

from alignrl.apparatus.base import ApparatusError, MeasurementError, NoEdgesError, check_write
from alignrl.apparatus.directional import directional_widths
from alignrl.apparatus.probe import (
    directional_edge_widths_px,
    edge_widths_px,
    logistic,
    mean_edge_width_px,
    probe_covariance,
)
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, edge_width
from alignrl.apparatus.sem_config import (
    PRESET_DIR,
    AnalyticModel,
    FloatTable,
    SEMConfig,
    load_sem_config,
)
from alignrl.apparatus.specimens import draw_specimen
from alignrl.apparatus.wobble import wobble_shift

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

KNOB_NAMES = ("defocus", "stigmator_x", "stigmator_y", "aperture_x", "aperture_y")
GAUSSIAN_SHOT_NOISE_ABOVE = 30.0  # electrons per pixel where Poisson ~ Gaussian


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
        self._stigmator_response = cfg.stigmator_response()  # None: the identity
        self._aperture_response = cfg.aperture_response()
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
        astigmatism_v = self._rng.uniform(cfg.astigmatism_min_v, cfg.astigmatism_max_v)
        self._astigmatism_axis = self._rng.uniform(0, np.pi)
        aperture_angle = self._rng.uniform(0, 2 * np.pi)
        # The specimen comes from the scenario's generator, before the readings' draws. In
        # analytic mode it is rendered only if a frame is asked for (rendering was nine
        # tenths of an analytic reset); the generator moves past its draws either way.
        self._specimen_fft: np.ndarray | None = None
        if self.analytic:
            self._specimen_rng = copy.deepcopy(self._rng)
            self._specimen_draws(self._rng)
        else:
            self._specimen_fft = np.fft.rfft2(self._draw_specimen(self._rng))
        column_rng = np.random.default_rng([seed, 2])  # draws new with the five-knob column
        offset_um = column_rng.uniform(cfg.aperture_offset_min_um, cfg.aperture_offset_max_um)
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
        if self._stigmator_response is not None:  # the setting whose action cancels it
            self._stigmator_optimum_pct = np.linalg.solve(
                self._stigmator_response, self._stigmator_optimum_pct
            )
        self._aperture_offset_um = offset_um * np.array(
            [np.cos(aperture_angle), np.sin(aperture_angle)]
        )
        low, high = self.knobs["defocus"]
        self._defocus_v = float(np.clip(cfg.optimum_v, low, high))
        self._direction = 0.0  # sign of the last voltage change, for hysteresis
        aligned = cfg.reset_state == "aligned"
        self._stigmator_pct = self._stigmator_optimum_pct.copy() if aligned else np.zeros(2)
        self._stigmator_direction = np.zeros(2)  # sign of each stigmator's last change
        # the stigmators' own drift walks on a generator of its own: every other stream stays
        self._stigmator_rng = np.random.default_rng([seed, 3])
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
                new = float(values[f"stigmator_{axis}"])
                if new != self._stigmator_pct[index]:
                    self._stigmator_direction[index] = np.sign(new - self._stigmator_pct[index])
                self._stigmator_pct[index] = new
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
        stigmators = self._stigmator_targets()
        return {
            "defocus": defocus,
            "stigmator_x": stigmators[0],
            "stigmator_y": stigmators[1],
            "aperture_x": float(self._aperture_offset_um[0]),
            "aperture_y": float(self._aperture_offset_um[1]),
        }

    def _stigmator_targets(self) -> tuple[float, float]:
        """Each stigmator's setting that cancels the astigmatism if written now: the optimum
        itself without hysteresis; with it, the optimum + h approached from below, - h from
        above, the nearer one (the setting itself where its lag leaves it there)."""
        h = self.config.stigmator_hysteresis_pct
        targets = []
        for axis in range(2):
            optimum, setting = self._stigmator_optimum_pct[axis], self._stigmator_pct[axis]
            if h == 0 or abs(setting - h * self._stigmator_direction[axis] - optimum) < 1e-12:
                targets.append(float(optimum if h == 0 else setting))
                continue
            above, below = optimum + h, optimum - h
            reachable = [t for t, ok in ((above, above > setting), (below, below < setting)) if ok]
            targets.append(float(min(reachable, key=lambda t: abs(t - setting))))
        return targets[0], targets[1]

    def best_quality(self) -> float:
        """Edge width (px) of a noise-free frame at the optimum: 2.563 x probe_sigma0_px."""
        return float(TEN_NINETY_PER_SIGMA * self.config.probe_sigma0_px)

    # --- further measurements -----------------------------------------------------------

    def measure_directional(self) -> tuple[float, np.ndarray]:
        """One acquisition: (mean edge width px, edge widths of the four edge-normal
        orientation bins of ORIENTATION_BINS_DEG px). An astigmatic probe blurs edges
        whose normal lies along its long axis most. NoEdgesError where a bin has no edges."""
        if self.analytic:
            return self._analytic_directional(self._analytic_acquisition()[0])
        measured = directional_widths(self.acquire())
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
        return np.asarray(wobble_shift(minus, plus), dtype=np.float64)

    # --- physics ------------------------------------------------------------------------

    def focus_error_v(self) -> float:
        """V_eff - V_opt in volts: what the probe really sees."""
        effective_v = self._defocus_v - self.config.hysteresis_v * self._direction
        return effective_v - self._optimum_v

    def astigmatism_residual_v(self) -> np.ndarray:
        """r = a - g_s M s (volts of line-focus separation, as a vector in the 2 phi plane;
        M the stigmators' response, SEMConfig.stigmator_response: the identity unless their
        axes are turned, coupled or mirrored)."""
        lag = self.config.stigmator_hysteresis_pct * self._stigmator_direction
        left = self._stigmator_optimum_pct - (self._stigmator_pct - lag)
        if self._stigmator_response is not None:
            left = self._stigmator_response @ left
        return self.config.stigmator_v_per_pct * left

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
        return probe_covariance(*self.probe_sigmas_px())

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
        """(dx, dy) px by which the image content moves: k_ap dV N d, the tilt of the beam
        through an off-axis aperture times the focus error (N the image's turn and mirror
        against the aperture's axes, SEMConfig.aperture_response: the identity unless set)."""
        cfg = self.config
        offset = self.aperture_residual_um()
        if self._aperture_response is not None:
            offset = self._aperture_response @ offset
        return cfg.aperture_shift_px_per_v_um * self.focus_error_v() * offset

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
        if self._specimen_fft is None:  # analytic mode, asked for a frame
            self._specimen_fft = np.fft.rfft2(self._draw_specimen(self._specimen_rng))
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
        walk = self.config.stigmator_drift_pct_per_acquisition
        if walk > 0:
            self._stigmator_optimum_pct += walk * self._stigmator_rng.standard_normal(2)

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
        if self._rng.random() < logistic(
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
        if self._rng.random() < logistic(true_px, middle_px, spread_px):
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

    def _specimen_draws(
        self, rng: np.random.Generator
    ) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
        """What a specimen is drawn from, in the order drawn: the substrate's white noise,
        then each particle's centre (x, y), radius and brightness spread."""
        cfg = self.config
        noise = rng.standard_normal((cfg.image_size_px, cfg.image_size_px))
        count = int(rng.integers(cfg.particles[0], cfg.particles[1] + 1))
        particles = [
            (
                *rng.uniform(0, cfg.image_size_px, 2),
                rng.uniform(*cfg.particle_radius_px),
                rng.uniform(0.9, 1.1),
            )
            for _ in range(count)
        ]
        return noise, particles

    def _draw_specimen(self, rng: np.random.Generator) -> np.ndarray:
        """The config's specimen, periodic across the frame edges: gold particles on a
        textured substrate, or a kind of alignrl/apparatus/specimens.py drawn from `rng`."""
        cfg = self.config
        size = cfg.image_size_px
        if cfg.specimen != "gold":
            return draw_specimen(cfg.specimen, size, rng)
        noise, particles = self._specimen_draws(rng)
        # Substrate grain: white noise low-passed in Fourier space (periodic by construction).
        grain = np.fft.irfft2(
            np.fft.rfft2(noise) * np.exp(-2.0 * np.pi**2 * 4.0 * (self._fxx + self._fyy)),
            s=(size, size),
        )
        grain *= cfg.substrate_texture / max(float(grain.std()), 1e-12)
        specimen = cfg.substrate_yield + grain
        coordinates = np.arange(size, dtype=np.float64)
        for centre_x, centre_y, radius, spread in particles:
            brightness = cfg.particle_yield * spread
            # Distances on a torus, so that a particle leaving one side enters the other.
            dx = (coordinates - centre_x + size / 2) % size - size / 2
            dy = (coordinates - centre_y + size / 2) % size - size / 2
            distance = np.sqrt(dx[None, :] ** 2 + dy[:, None] ** 2)
            coverage = np.clip(radius - distance + 0.5, 0.0, 1.0)  # anti-aliased rim
            specimen = specimen + coverage * (brightness - specimen)
        return specimen

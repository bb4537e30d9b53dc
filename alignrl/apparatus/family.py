"""The instrument family: a parametric focus column that can be any of the columns real
microscopes are, drawn anew for every episode (docs/physics.md, "The instrument family").

A `FocusFamily` is a box: every parameter is a point or a [low, high] range within its
physical range, read strictly from YAML (alignrl/apparatus/families/*.yaml for the boxes
training samples, alignrl/apparatus/instruments/<set>/*.yaml for the single instruments
judged on; the box, its ranges and its files: alignrl/apparatus/family_box.py). A
`FamilyColumn` draws one column from the box at each `reset(seed)` (`ColumnDraw`, seeded:
the same seed, the same column) and is an Apparatus with one knob, `defocus`, in whatever
units and interval the draw gave.

The column (e = V_eff - V_opt, the focus error in the knob's units; W the interval's width):
* the probe: sigma(e) = (sigma0^q + (g_side * max(0, |e| - f W))^q)^(1/q) px, with the gain
  g = blur_px_per_interval / W split by the asymmetry a into g / sqrt(a) below focus and
  g sqrt(a) above it, a flat bottom of half-width f W, and the curve's power q (2: the
  hyperbola of design.md);
* hysteresis (backlash): V_eff = V - h W s, s the sign of the last change of V, so the
  setting that focuses depends on the side it is approached from;
* drift: the optimum walks by N(0, (d W)^2) per acquisition;
* analytic readings (`analytic=True`): the true width w = 2.563 sigma levels off at the
  specimen's feature size, r = w_sat tanh(w / w_sat), and reads r exp(c z + n_rel e1) +
  n_px e2 (z ~ N(0, 1) once per episode: the specimen reads wide or narrow; e1, e2 ~ N(0, 1)
  per reading: multiplicative and additive noise); far from focus the frame has no edges
  with probability 1 / (1 + exp(-(w - w_none) / (0.1 w_none))): NoEdgesError;
* image readings (`analytic=False`): a specimen of the draw's kind (particles, grid, bars,
  fibres, texture: alignrl/apparatus/specimens.py) blurred by the probe, with shot noise at
  the draw's dose and detector noise, measured by `quality.edge_width`; a frame without
  edges raises NoEdgesError as a real one does.

`optimum()` and `best_quality()` are the simulator's secrets (KnowsOptimum, KnowsBestQuality):
the setting that focuses from the side it is approached, and the width a frame in focus
reads (analytic: r at sigma0; images: the median of three frames in focus, drawn from a
stream of their own so that no reading changes).

The family is open for more knobs: `FAMILY_KINDS` maps a family's `kind` to its model, and
the stigmator and aperture parameters will come as kinds of their own.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import NoEdgesError, check_write
from alignrl.apparatus.box_values import SAMPLINGS, at_fraction, check_sampling, unit_fractions
from alignrl.apparatus.family_box import (
    LOG_SCALE,
    PAIR_FIELDS,
    FocusFamily,
)
from alignrl.apparatus.probe import focus_sigma_px, logistic
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA, edge_width

__all__ = [
    "SAMPLINGS",
    "ColumnDraw",
    "FamilyColumn",
    "checked_design",
    "column_at",
    "design_names",
    "draw_column",
    "draw_fractions",
    "even_fractions",
]

NO_EDGES_SPREAD = 0.1  # logistic spread of the no-edges limit, as a share of it
BEST_QUALITY_FRAMES = 3  # frames in focus whose median reading is best_quality() (images)


@dataclass(frozen=True)
class ColumnDraw:
    """One column of a family: every parameter a number (FocusFamily's names)."""

    low: float
    high: float
    optimum: float
    blur_px_per_interval: float
    floor_sigma_px: float
    curve_power: float
    flat_fraction: float
    asymmetry: float
    reading_noise_rel: float
    reading_noise_px: float
    specimen_rel: float
    saturation_px: float
    no_edges_px: float
    drift_fraction: float
    hysteresis_fraction: float
    specimen: str
    dose_electrons_per_px: float
    detector_noise: float

    @property
    def width(self) -> float:
        return self.high - self.low


def draw_fractions(
    family: FocusFamily, rng: np.random.Generator, sampling: str = "uniform"
) -> tuple[dict[str, float], int]:
    """One draw per parameter, in the order of PAIR_FIELDS (a point drawn as well, so that
    narrowing one range leaves the other parameters' draws as they were), then the specimen's
    index: where in the box a column lies (`column_at`). `sampling` (SAMPLINGS): "uniform"
    over each range, or "edges": each fraction from the arcsine law Beta(1/2, 1/2), which
    puts 29 % of a parameter's draws in the outer tenth of its range (uniform: 10 %) and
    still a third in its middle half, so that training meets the box's edges (a column's
    optimum near its interval's end, the strongest backlash, the steepest curve) as often as
    its middle."""
    fractions = unit_fractions(PAIR_FIELDS, rng, sampling)
    return fractions, int(rng.integers(len(family.specimens)))


def even_fractions(dimensions: int, count: int, seed: int | None) -> np.ndarray:
    """`count` points of the unit cube of `dimensions`, (count, dimensions): a scrambled
    Sobol' sequence (generator `seed`), spread over every axis more evenly than independent
    draws (scipy.stats, 0.6 s to import, is imported by the first call)."""
    from scipy.stats import qmc

    return qmc.Sobol(dimensions, scramble=True, seed=seed).random(count)


def column_at(family: FocusFamily, fractions: Mapping[str, float], specimen: int) -> ColumnDraw:
    """The column at `fractions` of the box (0 its low end, 1 its high end; `LOG_SCALE`
    parameters on a log scale), with specimen number `specimen` of the family's list."""
    values: dict[str, float] = {}
    for name in PAIR_FIELDS:
        low, high = getattr(family, name)
        values[name] = at_fraction(low, high, float(fractions[name]), name in LOG_SCALE)
    width, centre = values.pop("interval_width"), values.pop("interval_centre")
    low, high = centre - 0.5 * width, centre + 0.5 * width
    optimum = low + values.pop("optimum_fraction") * width
    return ColumnDraw(
        low=low, high=high, optimum=optimum, specimen=family.specimens[specimen], **values
    )


def draw_column(family: FocusFamily, rng: np.random.Generator) -> ColumnDraw:
    """A column from the box, drawn uniformly (log-uniformly on `LOG_SCALE`)."""
    return column_at(family, *draw_fractions(family, rng))


# What only one reading path uses: a designer is offered the parameters its path reads.
ANALYTIC_ONLY = (
    "reading_noise_rel",
    "reading_noise_px",
    "specimen_rel",
    "saturation_px",
    "no_edges_px",
)
IMAGE_ONLY = ("dose_electrons_per_px", "detector_noise")


def design_names(family: FocusFamily, analytic: bool) -> tuple[str, ...]:
    """The parameters a designer of `family` chooses (issue 22): every one that is a range
    in the box and that its reading path uses, then `specimen` where images are rendered
    and the family has more than one."""
    skip = IMAGE_ONLY if analytic else ANALYTIC_ONLY
    names = [
        name
        for name in PAIR_FIELDS
        if name not in skip and getattr(family, name)[0] < getattr(family, name)[1]
    ]
    if not analytic and len(family.specimens) > 1:
        names.append("specimen")
    return tuple(names)


def checked_design(family: str, names: tuple[str, ...], fractions: np.ndarray) -> np.ndarray:
    """A designer's fractions, one per designed parameter of `names`, clipped to [0, 1];
    ValueError naming the family and the parameters where there are not as many, or one is
    not finite."""
    fractions = np.asarray(fractions, float).reshape(-1)
    if fractions.size != len(names) or not np.all(np.isfinite(fractions)):
        raise ValueError(
            f"a design of {family} takes {len(names)} finite fractions "
            f"({', '.join(names)}), got {fractions.tolist()}"
        )
    return np.clip(fractions, 0.0, 1.0)


class FamilyColumn:
    """A focus column drawn from `family` at every reset (module docstring). `analytic`:
    readings from the probe (fast, no images); otherwise rendered frames measured by
    edge_width."""

    draws_column_at_reset = True  # a new interval with every column (apparatus/base.py)

    def __init__(
        self,
        family: FocusFamily | None = None,
        seed: int | None = None,
        analytic: bool = False,
        sampling: str = "uniform",
    ) -> None:
        check_sampling(sampling)
        self.family = family or FocusFamily()
        self.analytic = bool(analytic)
        self.sampling = sampling
        self._seeds = np.random.SeedSequence(seed)
        self.acquisitions = 0
        self._last_image: np.ndarray | None = None
        self.reset(seed)

    # --- the Apparatus protocol ---------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """A new column and episode: the draw, the specimen, the setting at the interval's
        centre, no hysteresis state."""
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self._seed = int(seed)
        self._fractions, self._specimen_index = draw_fractions(
            self.family, np.random.default_rng([self._seed, 1]), self.sampling
        )
        self._begin(column_at(self.family, self._fractions, self._specimen_index))

    def _begin(self, draw: ColumnDraw) -> None:
        """The episode of this seed on column `draw`: nothing read yet."""
        self.draw = draw
        self._rng = np.random.default_rng([self._seed, 2])
        self.knobs: Mapping[str, tuple[float, float]] = {"defocus": (draw.low, draw.high)}
        self._optimum = draw.optimum
        self._specimen_draw = float(self._rng.standard_normal())
        self._setting = 0.5 * (draw.low + draw.high)
        self._direction = 0.0
        self._specimen_fft: np.ndarray | None = None
        self._best: float | None = None
        self._last_image = None

    # --- designing the column (issue 22: misaligners that design the instrument) ---------

    def design_names(self) -> tuple[str, ...]:
        """The parameters `design` sets (`design_names` of the family and reading path)."""
        return design_names(self.family, self.analytic)

    def design_draw(self) -> np.ndarray:
        """Where this episode's uniform draw put each designed parameter, as fractions of
        its range in [0, 1] (the specimen: the middle of its share)."""
        count = len(self.family.specimens)
        return np.array(
            [
                (self._specimen_index + 0.5) / count
                if name == "specimen"
                else self._fractions[name]
                for name in self.design_names()
            ]
        )

    def design(self, fractions: np.ndarray) -> None:
        """This episode's column with each designed parameter at its fraction of the box (one
        per `design_names`, clipped to [0, 1]; 0 the low end, 1 the high end, on a log scale
        where the box draws log-uniformly) and the others as drawn; the episode begins again
        on it, with its seed's noise (nothing read before is kept)."""
        names = self.design_names()
        chosen = dict(self._fractions)
        specimen = self._specimen_index
        checked = checked_design(self.family.name, names, fractions)
        for name, fraction in zip(names, checked, strict=True):
            if name == "specimen":
                specimen = min(
                    int(fraction * len(self.family.specimens)), len(self.family.specimens) - 1
                )
            else:
                chosen[name] = float(fraction)
        self._begin(column_at(self.family, chosen, specimen))

    def twin(self) -> FamilyColumn:
        """An independent copy in this very state, its noise stream included: what a
        reference plays the same column on, with common random numbers (issue 22)."""
        other = copy.copy(self)
        other._rng = copy.deepcopy(self._rng)
        other.knobs = dict(self.knobs)
        return other

    def read(self) -> dict[str, float]:
        return {"defocus": self._setting}

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        if "defocus" in values:
            new = float(values["defocus"])
            if new != self._setting:
                self._direction = float(np.sign(new - self._setting))
            self._setting = new

    def measure(self) -> float:
        """One acquisition: the edge width (px); NoEdgesError where the frame has none."""
        sigma = self.probe_sigma_px()
        self.acquisitions += 1
        try:
            if self.analytic:
                self._last_image = None
                return self._analytic_reading(sigma)
            frame = self._render(sigma, self._rng)
            self._last_image = frame
            return float(edge_width(frame))
        finally:
            drift = self.draw.drift_fraction * self.draw.width
            if drift > 0:
                self._optimum += drift * float(self._rng.standard_normal())

    def image(self) -> np.ndarray | None:
        return self._last_image

    # --- the simulator's secrets --------------------------------------------------------

    def optimum(self) -> dict[str, float]:
        """The setting that focuses if written now: V_opt + h W approached from below,
        V_opt - h W from above, the nearer reachable one; the setting itself if in focus."""
        lag = self.draw.hysteresis_fraction * self.draw.width
        if abs(self.focus_error()) < 1e-9 * self.draw.width:
            return {"defocus": self._setting}
        candidates = [
            target
            for target, reachable in (
                (self._optimum + lag, self._optimum + lag > self._setting),
                (self._optimum - lag, self._optimum - lag < self._setting),
            )
            if reachable
        ]
        best = min(candidates, key=lambda target: abs(target - self._setting))
        return {"defocus": float(np.clip(best, self.draw.low, self.draw.high))}

    def best_quality(self) -> float:
        """The width a frame in focus reads (px): analytic, the levelled-off width at sigma0;
        images, the median of three frames in focus (their own random stream)."""
        if self._best is None:
            sigma0 = self.draw.floor_sigma_px
            if self.analytic:
                self._best = self._levelled(TEN_NINETY_PER_SIGMA * sigma0)
            else:
                rng = np.random.default_rng([self._seed, 3])
                readings = []
                for _ in range(BEST_QUALITY_FRAMES):
                    try:
                        readings.append(edge_width(self._render(sigma0, rng)))
                    except NoEdgesError:
                        continue
                self._best = (
                    float(np.median(readings)) if readings else TEN_NINETY_PER_SIGMA * sigma0
                )
        return float(self._best)

    # --- physics ------------------------------------------------------------------------

    def focus_error(self) -> float:
        """V_eff - V_opt in the knob's units."""
        lag = self.draw.hysteresis_fraction * self.draw.width
        return self._setting - lag * self._direction - self._optimum

    def probe_sigma_px(self, error: float | None = None) -> float:
        """sigma(e) of the module docstring, px, at the present focus error or `error`."""
        draw = self.draw
        error = self.focus_error() if error is None else float(error)
        return float(
            focus_sigma_px(
                error,
                draw.blur_px_per_interval / draw.width,
                draw.floor_sigma_px,
                draw.curve_power,
                draw.flat_fraction * draw.width,
                draw.asymmetry,
            )
        )

    def _levelled(self, width_px: float) -> float:
        # math.tanh, not levelled_px's np.tanh: the two differ in the last bit, and readings
        # stay as they were
        saturation = self.draw.saturation_px
        return float(saturation * math.tanh(width_px / saturation))

    def _analytic_reading(self, sigma: float) -> float:
        draw = self.draw
        true_px = TEN_NINETY_PER_SIGMA * sigma
        if self._rng.random() < logistic(
            true_px, draw.no_edges_px, NO_EDGES_SPREAD * draw.no_edges_px
        ):
            raise NoEdgesError(
                f"no edges: a probe {true_px:.1f} px wide blurs the specimen into the noise "
                f"(half of the frames lose them beyond {draw.no_edges_px:.3g} px)"
            )
        scatter = draw.specimen_rel * self._specimen_draw
        noise = draw.reading_noise_rel * float(self._rng.standard_normal())
        reading = self._levelled(true_px) * math.exp(scatter + noise)
        reading += draw.reading_noise_px * float(self._rng.standard_normal())
        return float(max(reading, 0.1 * true_px))

    def _render(self, sigma: float, rng: np.random.Generator) -> np.ndarray:
        from alignrl.apparatus.specimens import draw_specimen, render

        size = self.family.image_size_px
        if self._specimen_fft is None:
            specimen_rng = np.random.default_rng([self._seed, 4])
            self._specimen_fft = np.fft.rfft2(draw_specimen(self.draw.specimen, size, specimen_rng))
        return render(
            self._specimen_fft,
            sigma,
            size,
            self.draw.dose_electrons_per_px,
            self.draw.detector_noise,
            rng,
        )

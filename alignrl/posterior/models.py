"""The column models of a focus family: what a column's readings look like, for the
posterior to weigh them (alignrl/posterior/inference.py).

`ColumnModels` holds the reading model of K columns drawn from a family's box
(alignrl/apparatus/family_box.py, `FocusFamily`): each parameter an array of shape (K, 1, 1)
in fractions of the knob's interval and px, which broadcasts against the posterior's states
(column, specimen scale, optimum). `reading` gives, at a focus error and a specimen scale, the
chance of a frame without edges and the mean and spread of a measured edge width: the focus
curve of alignrl/apparatus/probe.py, levelled off where measured widths saturate, with the
model's noise and what it does not know of a real column (`model_noise`, `far_noise`).

`focus_box` is the training box (alignrl/apparatus/families/focus.yaml), `widened` a box
reaching further, the prior for columns beyond the ones a policy trained on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from alignrl.apparatus.family import NO_EDGES_SPREAD, column_at, even_fractions
from alignrl.apparatus.family_box import (
    BOUNDED,
    LOG_SCALE,
    PAIR_FIELDS,
    FocusFamily,
    family_path,
    load_family,
)
from alignrl.apparatus.probe import focus_sigma_px, levelled_px
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA

__all__ = [
    "FAMILY_REACH",
    "FLAT_DECADES",
    "MODEL_FIELDS",
    "ColumnModels",
    "focus_box",
    "narrowest_spec",
    "widened",
]

# How far beyond the training box `family_posterior` looks (`widened`), chosen on
# set:validation (analytic, 30 alignments per instrument, seed 3,000,000): at 0 it aligned
# 170/180 at medians of 3-4 acquisitions, at 0.25 173/180 at medians of 4-7 (p90 up to 17).
FAMILY_REACH = 0.0
# How the posterior weighs a column's flat bottom (`flat_fraction`, the box's 0-1 % of the
# interval either side of the optimum): log-uniformly over FLAT_DECADES decades below the
# box's widest (`ColumnModels.at`), not uniformly as the box draws it. A plateau's width is
# a scale, known to its order of magnitude at best; drawn uniformly, half the columns have
# one wider than a steep column's whole passing window (0.3-0.5 %), and readings that never
# showed focus leave the posterior sure of a window no reading has seen (docs/benchmarks.md,
# twenty-first session). Two decades set beforehand; kept on set:validation (more columns
# aligned than the uniform prior at each confidence tried: 0.95, 0.97, 0.99).
FLAT_DECADES = 2.0


def narrowest_spec(family: FocusFamily, relative: float) -> float:
    """The narrowest half-width within the spec any column of the box has (fractions)."""
    reach = min((relative**q - 1.0) ** (1.0 / q) for q in family.curve_power)
    gain = family.blur_px_per_interval[1] * math.sqrt(family.asymmetry[1])
    return family.flat_fraction[0] + reach * family.floor_sigma_px[0] / gain


def widened(family: FocusFamily, reach: float) -> FocusFamily:
    """`family` with every range that the readings depend on reaching `reach` x its span
    further at both ends (on a log scale where the family draws on one), kept within what
    the family allows: a prior for columns beyond the box a policy trained on. Points stay
    points; the optimum's range is left alone (`FamilyPosterior.optimum_prior` says where
    the optimum may lie)."""
    if not (math.isfinite(reach) and reach >= 0.0):
        raise ValueError(f"reach must be a finite share >= 0, got {reach}")
    update = {}
    for name in MODEL_FIELDS.values():
        low, high = getattr(family, name)
        if name in LOG_SCALE:
            ratio = (high / low) ** reach
            low, high = low / ratio, high * ratio
        else:
            span = reach * (high - low)
            low, high = max(low - span, 0.0), high + span
        lowest, highest = BOUNDED.get(name, (0.0, math.inf))
        update[name] = (max(low, lowest), min(high, highest))
    return FocusFamily.model_validate({**family.model_dump(), **update})


# ColumnModels' parameters and the family's names for them
MODEL_FIELDS = {
    "gain": "blur_px_per_interval",
    "floor": "floor_sigma_px",
    "power": "curve_power",
    "flat": "flat_fraction",
    "asymmetry": "asymmetry",
    "noise_rel": "reading_noise_rel",
    "noise_px": "reading_noise_px",
    "specimen_rel": "specimen_rel",
    "saturation": "saturation_px",
    "no_edges": "no_edges_px",
    "drift": "drift_fraction",
    "lag": "hysteresis_fraction",
}


@dataclass(frozen=True)
class ColumnModels:
    """The reading model of K columns, each parameter an array of shape (K, 1, 1) in units of
    the interval (fractions) and px, broadcasting against the posterior's (K, Z, N)."""

    gain: np.ndarray  # px of sigma per interval
    floor: np.ndarray
    power: np.ndarray
    flat: np.ndarray
    asymmetry: np.ndarray
    noise_rel: np.ndarray
    noise_px: np.ndarray
    specimen_rel: np.ndarray
    saturation: np.ndarray
    no_edges: np.ndarray
    drift: np.ndarray
    lag: np.ndarray
    rows: np.ndarray  # (K, len(PAIR_FIELDS)): where each column was drawn (`at`)
    model_noise: float = 0.01
    far_noise: float | np.ndarray = 0.0  # one share for all, or one per column (K, 1, 1)

    @classmethod
    def of(
        cls, family: FocusFamily, draws: int, seed: int, model_noise: float, far_noise: float = 0.0,
        flat_decades: float = 0.0,
    ) -> ColumnModels:  # fmt: skip
        """One model where `family` is a single column in every parameter the readings
        depend on; else `draws` columns drawn from it: a scrambled Sobol' sequence over the
        box's fractions (generator `seed`), which spreads them over every parameter's range
        more evenly than independent draws (`flat_decades`: as `at` places them)."""
        single = all(
            getattr(family, name)[0] == getattr(family, name)[1] for name in MODEL_FIELDS.values()
        )
        rows = even_fractions(len(PAIR_FIELDS), 1 if single else draws, seed)
        return cls.at(family, rows, model_noise, far_noise, flat_decades)

    @classmethod
    def at(
        cls, family: FocusFamily, rows: np.ndarray, model_noise: float,
        far_noise: float | np.ndarray = 0.0, flat_decades: float = 0.0,
    ) -> ColumnModels:  # fmt: skip
        """The columns at `rows` (K, len(PAIR_FIELDS)) of fractions of the box (column_at);
        with `flat_decades`, a row's flat-bottom fraction u places it at 10^(-flat_decades
        (1 - u)) of the box's range (log-uniform over those decades, FLAT_DECADES) rather
        than at u; `far_noise` one share for all, or one per row (K,)."""
        placed = np.array(rows, float)
        if flat_decades:
            flat = PAIR_FIELDS.index("flat_fraction")
            placed[:, flat] = 10.0 ** (-flat_decades * (1.0 - placed[:, flat]))
        columns = [column_at(family, dict(zip(PAIR_FIELDS, row, strict=True)), 0) for row in placed]
        values = {
            name: np.array([getattr(draw, attribute) for draw in columns], float)[:, None, None]
            for name, attribute in MODEL_FIELDS.items()
        }
        far = np.asarray(far_noise, float).reshape(-1, 1, 1) if np.ndim(far_noise) else far_noise
        return cls(**values, rows=np.asarray(rows, float), model_noise=model_noise, far_noise=far)

    @property
    def count(self) -> int:
        return int(self.gain.shape[0])

    def best_px(self) -> np.ndarray:
        """The width a frame in focus reads, noise-free (K, 1, 1)."""
        return levelled_px(TEN_NINETY_PER_SIGMA * self.floor, self.saturation)

    def spec_half_width(self, relative: float) -> np.ndarray:
        """How far from the optimum (fractions) the probe stays within `relative` x its
        floor, on the steeper side (K, 1, 1)."""
        reach = (relative**self.power - 1.0) ** (1.0 / self.power) * self.floor
        return self.flat + reach / (self.gain * np.sqrt(self.asymmetry))

    def picked(self, columns: np.ndarray) -> ColumnModels:
        """The models of `columns` (S,), one per state: parameters of shape (S,)."""
        named = [*MODEL_FIELDS, *(["far_noise"] if np.ndim(self.far_noise) else [])]
        picked = {name: getattr(self, name)[columns, 0, 0] for name in named}
        return replace(self, **picked, rows=self.rows[columns])

    def reading(self, error: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, ...]:
        """At focus errors `error` (fractions) and specimen scales `scale` (the log of the
        specimen's factor): the chance of a frame without edges, the mean reading and its
        spread (px), broadcast against the parameters. The spread has the model's noise and
        `model_noise` x the mean more: what the model does not know of a real column; and
        `far_noise` x log(mean / the in-focus reading) x the mean: far from focus a measured
        edge width tells less of the blur than the model says (on a specimen whose features
        are a few blur widths across the readings level off early and fall again)."""
        true = TEN_NINETY_PER_SIGMA * focus_sigma_px(
            error, self.gain, self.floor, self.power, self.flat, self.asymmetry
        )
        spread_px = NO_EDGES_SPREAD * self.no_edges
        none = 0.5 * (1.0 + np.tanh(0.5 * (true - self.no_edges) / spread_px))
        levelled = levelled_px(true, self.saturation)
        mean = levelled * np.exp(scale)
        relative = self.model_noise**2
        if np.any(self.far_noise):
            relative = relative + (self.far_noise * np.log(levelled / self.best_px())) ** 2
        spread = np.sqrt((mean * self.noise_rel) ** 2 + self.noise_px**2 + relative * mean**2)
        return none, mean, spread


def focus_box(
    reach: float = FAMILY_REACH, saturation_px: tuple[float, float] | None = None
) -> FocusFamily:
    """The focus training box (alignrl/apparatus/families/focus.yaml), widened by `reach`;
    with `saturation_px`, its readings levelling off within that range of px instead
    (Task.posterior_saturation_px: where edge widths measured on images level off)."""
    box = widened(load_family(family_path("focus")), reach)
    if saturation_px is None:
        return box
    return FocusFamily.model_validate({**box.model_dump(), "saturation_px": saturation_px})

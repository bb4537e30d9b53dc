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

How the posterior computes with them cheaply and bit for bit as `reading` (issue 61, item
4): `reading_into` repeats `reading`'s operations into buffers (`ReadingConstants`: what it
computes of the parameters alone, once per column); `StateReadings` is the model of a
posterior's states (S,), what its stop and probe ask (`outcome_chances`, `expected_entropy`);
`first_draw` makes the columns a posterior first draws once per process, `scratch` and
`PosteriorBuffers` hold the arrays it computes into.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from alignrl.apparatus.family import NO_EDGES_SPREAD, even_fractions
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
from alignrl.posterior.workspace import read_only, remembered, scratch

__all__ = [
    "FAMILY_REACH",
    "FLAT_DECADES",
    "MODEL_FIELDS",
    "ColumnModels",
    "ReadingConstants",
    "first_draw",
    "focus_box",
    "narrowest_spec",
    "reading_into",
    "reading_work",
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
        cls,
        family: FocusFamily,
        draws: int,
        seed: int,
        model_noise: float,
        far_noise: float = 0.0,
        flat_decades: float = 0.0,
    ) -> ColumnModels:
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
        cls,
        family: FocusFamily,
        rows: np.ndarray,
        model_noise: float,
        far_noise: float | np.ndarray = 0.0,
        flat_decades: float = 0.0,
    ) -> ColumnModels:
        """The columns at `rows` (K, len(PAIR_FIELDS)) of fractions of the box (as
        alignrl/apparatus/family.py's column_at places one, `_placed`); with `flat_decades`,
        a row's flat-bottom fraction u places it at 10^(-flat_decades (1 - u)) of the box's
        range (log-uniform over those decades, FLAT_DECADES) rather than at u; `far_noise`
        one share for all, or one per row (K,)."""
        placed = np.array(rows, float)
        if flat_decades:
            flat = PAIR_FIELDS.index("flat_fraction")
            placed[:, flat] = 10.0 ** (-flat_decades * (1.0 - placed[:, flat]))
        values = {
            name: _placed(family, attribute, placed[:, PAIR_FIELDS.index(attribute)])
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

    @cached_property
    def constants(self) -> ReadingConstants:
        """What `reading` computes of the parameters alone, once (`reading_into`)."""
        root = np.sqrt(np.asarray(self.asymmetry, dtype=np.float64))
        return ReadingConstants(
            steeper=self.gain * root,
            gentler=self.gain * (1.0 / root),
            flat=self.flat,
            power=self.power,
            floor_power=self.floor**self.power,
            inverse_power=1.0 / self.power,
            no_edges=self.no_edges,
            no_edges_spread=NO_EDGES_SPREAD * self.no_edges,
            saturation=self.saturation,
            best=self.best_px(),
            far_noise=self.far_noise if np.any(self.far_noise) else None,
            noise_rel=self.noise_rel,
            noise_px_squared=self.noise_px**2,
            model_squared=self.model_noise**2,
        )

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

    def chunks(self, size: int) -> list[tuple[slice, ReadingConstants]]:
        """The columns in slices of `size`, each with its `constants` (K, 1, 1 sliced)."""
        cached = self.__dict__.setdefault("_chunks", {})
        if size not in cached:
            starts = range(0, self.count, size)
            slices = [slice(start, min(start + size, self.count)) for start in starts]
            cached[size] = [(rows, self.constants.of_columns(rows)) for rows in slices]
        return cached[size]

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


class ReadingConstants(NamedTuple):
    """What ColumnModels.reading computes of a column's parameters alone, each broadcasting
    against the focus errors (K, 1, 1 for columns; (S,) for states): `reading_into` computes
    the rest."""

    steeper: np.ndarray  # gain x sqrt(asymmetry): the gain above the optimum
    gentler: np.ndarray  # gain / sqrt(asymmetry)
    flat: np.ndarray
    power: np.ndarray
    floor_power: np.ndarray  # floor ** power
    inverse_power: np.ndarray  # 1 / power
    no_edges: np.ndarray
    no_edges_spread: np.ndarray  # NO_EDGES_SPREAD x no_edges
    saturation: np.ndarray
    best: np.ndarray  # best_px()
    far_noise: float | np.ndarray | None  # None: none
    noise_rel: np.ndarray
    noise_px_squared: np.ndarray
    model_squared: float

    def of_columns(self, rows: slice) -> ReadingConstants:
        """Those of the columns `rows` (each array K, 1, 1 sliced)."""
        return ReadingConstants(*(_part(value, rows) for value in self))

    def of_states(self, columns: np.ndarray) -> ReadingConstants:
        """Those of the states of `columns` (S,): the same numbers ColumnModels.picked's
        `constants` would compute."""
        return ReadingConstants(*(_part(value, columns, states=True) for value in self))


def reading_into(
    constants: ReadingConstants, error: np.ndarray, factor: np.ndarray | None, work: list
) -> tuple[np.ndarray, ...]:
    """ColumnModels.reading at focus errors `error` (a buffer it overwrites) times the
    specimen's `factor` (np.exp(scale); None where it is exactly 1 and widens nothing: a
    factor of 1 changes no number), computed with the same operations in the same order (the
    same numbers, bit for bit) into the buffers of `work`: a bool and two floats of
    `error`'s shape, then three floats of the states' shape (error's, widened by `factor`).
    Returns (none, mean, spread), views of `work` and `error`."""
    c = constants
    above, gains, level = work[0], work[1], work[2]
    np.greater(error, 0, out=above)
    np.copyto(gains, c.gentler)
    np.copyto(gains, c.steeper, where=above)
    np.abs(error, out=error)
    np.subtract(error, c.flat, out=error)
    np.maximum(0.0, error, out=error)
    np.multiply(gains, error, out=error)  # the blur
    np.power(error, c.power, out=error)
    np.add(c.floor_power, error, out=error)
    np.power(error, c.inverse_power, out=error)
    true = np.multiply(TEN_NINETY_PER_SIGMA, error, out=error)
    none = np.subtract(true, c.no_edges, out=gains)
    np.multiply(0.5, none, out=none)
    np.divide(none, c.no_edges_spread, out=none)
    np.tanh(none, out=none)
    np.add(1.0, none, out=none)
    np.multiply(0.5, none, out=none)
    np.divide(true, c.saturation, out=level)
    np.tanh(level, out=level)
    np.multiply(c.saturation, level, out=level)
    mean = level if factor is None else np.multiply(level, factor, out=work[3])
    relative: float | np.ndarray = c.model_squared
    if c.far_noise is not None:
        relative = np.divide(level, c.best, out=true)
        np.log(relative, out=relative)
        np.multiply(c.far_noise, relative, out=relative)
        np.square(relative, out=relative)
        np.add(c.model_squared, relative, out=relative)
    spread = np.multiply(mean, c.noise_rel, out=work[4])
    np.square(spread, out=spread)
    np.add(spread, c.noise_px_squared, out=spread)
    squared = np.square(mean, out=work[5])
    np.multiply(relative, squared, out=squared)
    np.add(spread, squared, out=spread)
    np.sqrt(spread, out=spread)
    return none, mean, spread


def reading_work(
    shape: tuple[int, ...], states: tuple[int, ...], extra: int = 0
) -> list[np.ndarray]:
    """`reading_into`'s buffers (`scratch`) for errors of `shape` and states of `states`, and
    `extra` more of the states' shape after them."""
    return [
        scratch("above", shape, bool),
        scratch("gains", shape),
        scratch("level", shape),
        *(scratch(f"state{index}", states) for index in range(3 + extra)),
    ]


_FIRST_DRAWS: OrderedDict = OrderedDict()  # first_draw's, per process


def first_draw(family: FocusFamily, *options: float) -> ColumnModels:
    """ColumnModels.of(family, *options), made once per process (read-only: every posterior
    of those options starts from the same columns)."""

    def make() -> tuple[ColumnModels]:
        models = ColumnModels.of(family, *options)
        read_only(*(value for value in vars(models).values() if isinstance(value, np.ndarray)))
        return (models,)

    return remembered(_FIRST_DRAWS, (family.model_dump_json(), *options), make)[0]


def _part(value: object, index: slice | np.ndarray, states: bool = False) -> object:
    """`value` (a (K, 1, 1) array, or a number or None: all alike) at `index`."""
    if not isinstance(value, np.ndarray) or value.ndim == 0:
        return value
    return value[index, 0, 0] if states else value[index]


def _placed(family: FocusFamily, name: str, fractions: np.ndarray) -> np.ndarray:
    """Parameter `name` of the columns at `fractions` (K,) of the box, (K, 1, 1): the numbers
    alignrl/apparatus/family.py's column_at gives, one row at a time (math.exp and
    math.log on a log scale, as it takes them)."""
    low, high = getattr(family, name)
    if name in LOG_SCALE:
        logs = math.log(low) + fractions * (math.log(high) - math.log(low))
        values = np.array([math.exp(each) for each in logs.tolist()], float)
    else:
        values = low + fractions * (high - low)
    return values.reshape(-1, 1, 1)


def focus_box(
    reach: float = FAMILY_REACH, saturation_px: tuple[float, float] | None = None
) -> FocusFamily:
    """The focus training box (alignrl/apparatus/families/focus.yaml), widened by `reach`;
    with `saturation_px`, its readings levelling off within that range of px instead
    (the task option posterior_saturation_px: where edge widths measured on images level off)."""
    box = widened(load_family(family_path("focus")), reach)
    if saturation_px is None:
        return box
    return FocusFamily.model_validate({**box.model_dump(), "saturation_px": saturation_px})

"""A whole column drawn anew from a column box at every reset (issue 62; the box:
alignrl/apparatus/column_box.py, docs/physics.md "Families for every knob").

`ColumnFamily` is an Apparatus with the synthetic SEM's five knobs, in whatever intervals
the draw gave: each `reset(seed)` draws where in the box the column lies (seeded: the same
seed, the same column; `sampling` "uniform" or "edges" as the focus family draws), builds
its `SEMConfig` and opens a `SyntheticSEM` on it with that seed, so every reading, the
directional widths and the wobble are the simulator's, images or analytic. A designer
(issue 22's misaligners, alignrl/envs/design.py) places the column inside the box
(`design_names`, `design_draw`, `design`, `twin`) as it does a focus family's.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

import numpy as np

from alignrl.apparatus.box_values import at_fraction, check_sampling, pick, unit_fractions
from alignrl.apparatus.column_box import (
    ANALYTIC_ONLY,
    FLAGS,
    IMAGE_ONLY,
    PAIR_FIELDS,
    PARAMETERS,
    SPECIMEN_DRAW,
    ColumnBox,
    column_config,
    column_specimen,
)
from alignrl.apparatus.family import FamilyColumn, checked_design
from alignrl.apparatus.family_box import AnyFamily
from alignrl.apparatus.synthetic import SyntheticSEM

__all__ = ["ColumnFamily", "column_values", "draw_column_fractions", "open_family"]


def draw_column_fractions(
    box: ColumnBox, rng: np.random.Generator, sampling: str = "uniform"
) -> dict[str, float]:
    """One fraction per parameter and per mirror, in that order (a point drawn as well, so
    that narrowing one range leaves the others' draws as they were): "uniform", or "edges"
    from the arcsine law Beta(1/2, 1/2) (family.draw_fractions)."""
    # the specimen last: adding it left the earlier draws as they were
    return unit_fractions((*PAIR_FIELDS, *FLAGS, SPECIMEN_DRAW), rng, sampling)


def column_values(
    box: ColumnBox, fractions: Mapping[str, float]
) -> tuple[dict[str, float], dict[str, bool]]:
    """The parameters at `fractions` of the box (0 the low end, 1 the high end, on a log
    scale where the parameter is drawn so), and each mirror's value (its list's share)."""
    values: dict[str, float] = {}
    for name, parameter in PARAMETERS.items():
        low, high = getattr(box, name)
        u = min(max(float(fractions[name]), 0.0), 1.0)
        values[name] = at_fraction(low, high, u, parameter.log and low < high)
    mirrors = {flag: bool(pick(getattr(box, flag), fractions[flag])) for flag in FLAGS}
    return values, mirrors


class ColumnFamily:
    """A column drawn from `box` at every reset (module docstring)."""

    draws_column_at_reset = True  # a new interval with every column (apparatus/base.py)

    def __init__(
        self,
        box: ColumnBox,
        seed: int | None = None,
        analytic: bool = False,
        sampling: str = "uniform",
    ) -> None:
        check_sampling(sampling)
        self.family = box
        self.analytic = bool(analytic)
        self.sampling = sampling
        self._seeds = np.random.SeedSequence(seed)
        self._spent = 0  # acquisitions of the columns before this one
        self.reset(seed)

    # --- the Apparatus protocol ---------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """A new column and scenario: the draw, then the simulator's scenario of `seed`."""
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self._seed = int(seed)
        rng = np.random.default_rng([self._seed, 1])
        self._fractions = draw_column_fractions(self.family, rng, self.sampling)
        self._begin(self._fractions)

    def _begin(self, fractions: Mapping[str, float]) -> None:
        previous = getattr(self, "sem", None)
        if previous is not None:
            self._spent += previous.acquisitions
        values, mirrors = column_values(self.family, fractions)
        self.values, self.mirrors = values, mirrors
        specimen = column_specimen(self.family, fractions.get(SPECIMEN_DRAW, 0.0))
        self.config = column_config(self.family, values, mirrors, specimen)
        self.sem = SyntheticSEM(self.config, seed=self._seed, analytic=self.analytic)

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self.sem.knobs

    @property
    def acquisitions(self) -> int:
        return self._spent + self.sem.acquisitions

    def read(self) -> dict[str, float]:
        return self.sem.read()

    def write(self, values: Mapping[str, float]) -> None:
        self.sem.write(values)

    def measure(self) -> float:
        return self.sem.measure()

    def image(self) -> np.ndarray | None:
        return self.sem.image()

    def measure_directional(self) -> tuple[float, np.ndarray]:
        return self.sem.measure_directional()

    def measure_wobble(self, amplitude_v: float) -> np.ndarray:
        return self.sem.measure_wobble(amplitude_v)

    # --- the simulator's secrets --------------------------------------------------------

    def optimum(self) -> dict[str, float]:
        return self.sem.optimum()

    def best_quality(self) -> float:
        return self.sem.best_quality()

    # --- designing the column (issue 22) -------------------------------------------------

    def design_names(self) -> tuple[str, ...]:
        """The parameters a designer sets: every range of the box (and each mirror that
        takes both values) that this reading path uses."""
        skip = IMAGE_ONLY if self.analytic else ANALYTIC_ONLY
        return tuple(name for name in self.family.ranged() if name not in skip)

    def design_draw(self) -> np.ndarray:
        """Where this episode's draw put each designed parameter, as fractions of its range."""
        return np.array([self._fractions[name] for name in self.design_names()])

    def design(self, fractions: np.ndarray) -> None:
        """This episode's column with each designed parameter at its fraction of the box
        (clipped to [0, 1]) and the others as drawn; the scenario begins again on it."""
        names = self.design_names()
        chosen = dict(self._fractions)
        checked = checked_design(self.family.name, names, fractions)
        for name, fraction in zip(names, checked, strict=True):
            chosen[name] = float(fraction)
        self._begin(chosen)

    def twin(self) -> ColumnFamily:
        """An independent copy in this very state, its noise stream included."""
        other = copy.copy(self)
        other.sem = copy.deepcopy(self.sem)
        return other


def open_family(
    family: AnyFamily, seed: int | None = None, analytic: bool = False, sampling: str = "uniform"
) -> FamilyColumn | ColumnFamily:
    """The apparatus that draws from `family`: a focus column (FamilyColumn) or a whole
    column (ColumnFamily), by the box's kind."""
    if isinstance(family, ColumnBox):
        return ColumnFamily(family, seed, analytic, sampling)
    return FamilyColumn(family, seed, analytic, sampling)

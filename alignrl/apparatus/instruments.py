"""Instrument sets: the single columns alignrl is judged and chosen on, and the wall that
keeps the held-out ones out of training.

alignrl/apparatus/instruments/<set>/<name>.yaml are instruments, each a family whose
parameters are points (only the optimum, the start and the noise vary between episodes):
focus columns (`FocusFamily`) in `validation` and `heldout`, whole columns (`ColumnBox`) for
each other task's knobs in `validation-KIND` and `heldout-KIND` (KIND: stigmation, aperture,
column; `task_set` finds a task's):

* the validation sets: for choices, the checkpoints a training run keeps and the champions a
  league ships (`eval_apparatus: set:validation`);
* the held-out sets (`held_out_sets`): for reporting generalization only. No training run,
  league or checkpoint choice may reach them: `held_out_reason` names how a spec would (the
  set, one of its instruments by name, a copy of one under another name or path, or a
  training box that contains one whole, compared by what they simulate: every parameter its
  task reads within SAME_WITHIN, never byte by byte), and the run configs refuse such a spec
  (alignrl/config/run.py).

Specs (alignrl/apparatus/registry.py): `instrument:NAME` one instrument, `set:NAME` a whole set
as one apparatus that moves to the set's next instrument at every reset (`InstrumentSet`).
`alignrl evaluate --set NAME` runs one session per instrument instead, one row each.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.apparatus.column_box import ColumnBox
from alignrl.apparatus.column_family import open_family
from alignrl.apparatus.family_box import (
    PAIR_FIELDS,
    AnyFamily,
    family_path,
    load_family,
)

__all__ = [
    "HELD_OUT_SET",
    "INSTRUMENT_DIR",
    "VALIDATION_SET",
    "InstrumentSet",
    "diagnosis_problem",
    "find_instrument",
    "held_out_reason",
    "held_out_sets",
    "instrument_names",
    "load_set",
    "set_names",
    "task_kind",
    "task_set",
]

INSTRUMENT_DIR = Path(__file__).with_name("instruments")
HELD_OUT_SET = "heldout"
VALIDATION_SET = "validation"


def set_names() -> list[str]:
    """The shipped instrument sets: the folders of alignrl/apparatus/instruments/."""
    if not INSTRUMENT_DIR.is_dir():  # an installation without its package data
        return []
    return sorted(path.name for path in INSTRUMENT_DIR.iterdir() if path.is_dir())


def held_out_sets() -> list[str]:
    """The held-out sets: `heldout` (focus) and `heldout-KIND` (the other tasks')."""
    return [name for name in set_names() if name.partition("-")[0] == HELD_OUT_SET]


# A task's instruments: its knobs' family kind (the column's stages read whole columns).
TASK_KINDS = {"focus": "focus", "stigmation": "stigmation", "aperture": "aperture"}


def task_kind(task_name: str) -> str:
    """The family kind of the instruments task `task_name` is judged on (the column's stages:
    whole columns)."""
    return TASK_KINDS.get(task_name, "column")


def task_set(set_name: str, task_name: str) -> str:
    """The set of `set_name`'s kind that task `task_name` is judged on: `heldout` and
    `validation` hold focus columns, and for another task name `NAME-KIND` (KIND its
    knobs' family: stigmation, aperture, column); a set named whole stays as it is."""
    kind = task_kind(task_name)
    if set_name in (HELD_OUT_SET, VALIDATION_SET) and kind != "focus":
        return f"{set_name}-{kind}"
    return set_name


def _set_paths(name: str) -> list[Path]:
    if name not in set_names():
        raise ValueError(f"no instrument set {name!r}; the sets are: {', '.join(set_names())}")
    return sorted((INSTRUMENT_DIR / name).glob("*.yaml"))


def instrument_names(set_name: str | None = None) -> dict[str, Path]:
    """Instrument name -> its file, of one set or of all of them."""
    sets = set_names() if set_name is None else [set_name]
    return {path.stem: path for name in sets for path in _set_paths(name)}


def _held_out_names() -> dict[str, Path]:
    return {
        name: path
        for set_name in held_out_sets()
        for name, path in instrument_names(set_name).items()
    }


def diagnosis_problem(name: str, purpose: str) -> str | None:
    """Why instrument `name` may not be looked into for `purpose` (a diagnosis, which informs
    choices, so it sees the validation set only): held out, or no validation instrument; None
    where it may."""
    if name in _held_out_names():
        return f"{name} is held out: {purpose} are for diagnosis, on validation instruments"
    known = instrument_names(VALIDATION_SET)
    if name not in known:
        return f"{name}: no such validation instrument ({', '.join(known)})"
    return None


def find_instrument(name: str) -> Path:
    """The file of instrument `name`; ValueError listing the instruments where none is."""
    known = instrument_names()
    if name not in known:
        raise ValueError(
            f"no instrument {name!r}; the instruments are: {', '.join(sorted(known))} "
            "(alignrl/apparatus/instruments/)"
        )
    return known[name]


def load_set(name: str) -> list[tuple[str, AnyFamily]]:
    """(name, instrument) of every instrument of set `name`, in file-name order."""
    return [(path.stem, load_family(path)) for path in _set_paths(name)]


class InstrumentSet:
    """A whole set as one apparatus: reset(seed) moves to instrument seed mod n of the set
    and draws its episode; everything else is that instrument's (FamilyColumn)."""

    draws_column_at_reset = True  # each instrument has its own interval (apparatus/base.py)

    def __init__(
        self,
        instruments: Sequence[AnyFamily],
        seed: int | None = None,
        analytic: bool = False,
    ) -> None:
        if not instruments:
            raise ValueError("an instrument set needs at least one instrument")
        self.columns = [open_family(family, seed, analytic) for family in instruments]
        self._seeds = np.random.SeedSequence(seed)
        self.current = self.columns[0]
        self.reset(seed)

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self.current.knobs

    @property
    def acquisitions(self) -> int:
        return sum(column.acquisitions for column in self.columns)

    def reset(self, seed: int | None = None) -> None:
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self.current = self.columns[int(seed) % len(self.columns)]
        self.current.reset(seed)

    def read(self) -> dict[str, float]:
        return self.current.read()

    def write(self, values: Mapping[str, float]) -> None:
        self.current.write(values)

    def measure(self) -> float:
        return self.current.measure()

    def image(self) -> np.ndarray | None:
        return self.current.image()

    def optimum(self) -> dict[str, float]:
        return self.current.optimum()

    def best_quality(self) -> float:
        return self.current.best_quality()


# --- the wall around the held-out set ------------------------------------------------------


# A copy of a held-out instrument with a parameter moved by a hair is the same instrument:
# the wall compares what the files simulate, every parameter within SAME_WITHIN of the
# held-out instrument's value (relative; of 1 for a value below 1, whose parameters are
# shares and px; of the interval's width for its centre), never byte by byte. A change a
# millionth of a parameter's size changes no reading a column gives.
SAME_WITHIN = 1e-6


def _slack(instrument: AnyFamily, name: str, value: float) -> float:
    """How far from `value` (an end of the held-out `instrument`'s `name`) a training box's
    end may lie and still be that instrument's (SAME_WITHIN)."""
    scale = max(abs(value), 1.0)
    if name.endswith("interval_centre"):
        width = "interval_width" if name == "interval_centre" else "defocus_interval_width"
        scale = max(scale, getattr(instrument, width)[1])
    return SAME_WITHIN * scale


def _compared(instrument: AnyFamily) -> tuple[str, ...]:
    """The parameters two families are compared on: every one of a focus column, the ones
    its task reads of a whole column's (ColumnBox.used)."""
    return instrument.used() if isinstance(instrument, ColumnBox) else PAIR_FIELDS


def _discrete_within(box: AnyFamily, instrument: AnyFamily, equal: bool) -> bool:
    """Whether the instrument's choices (specimens, or the mirrors its task reads) are the
    box's (`equal`) or among them."""
    if isinstance(instrument, ColumnBox):
        names = ("stigmator_mirror", "aperture_mirror")
        pairs = [(set(getattr(instrument, n)), set(getattr(box, n))) for n in names]
    else:
        pairs = [(set(instrument.specimens), set(box.specimens))]
    return all(mine == theirs if equal else mine <= theirs for mine, theirs in pairs)


def _contains(box: AnyFamily, instrument: AnyFamily) -> bool:
    """Whether every column of `instrument` is a column of `box` too (within `_slack`)."""
    if box.kind != instrument.kind or not _discrete_within(box, instrument, equal=False):
        return False
    for name in _compared(instrument):
        low, high = getattr(box, name)
        inner_low, inner_high = getattr(instrument, name)
        if inner_low < low - _slack(instrument, name, inner_low):
            return False
        if inner_high > high + _slack(instrument, name, inner_high):
            return False
    return True


def _same(family: AnyFamily, instrument: AnyFamily) -> bool:
    """Whether `family` simulates the columns of `instrument`: the same specimens (mirrors),
    every parameter's ends within `_slack` of the instrument's (its name, words, unit and
    frame size aside)."""
    if family.kind != instrument.kind or not _discrete_within(family, instrument, equal=True):
        return False
    return all(
        abs(mine - theirs) <= _slack(instrument, name, theirs)
        for name in _compared(instrument)
        for mine, theirs in zip(getattr(family, name), getattr(instrument, name), strict=True)
    )


def _family_of(spec: str, args: Mapping[str, Any] | None) -> tuple[AnyFamily, Path] | None:
    """The family a `family:` or `instrument:` spec simulates, or a `csv:` recording draws
    its columns from (`randomize.family`), with its file; None for other specs or a file
    that cannot be read (the registry reports that when it opens)."""
    # The reading path and how a family samples its box change no parameter of the box.
    overrides = {
        key: value for key, value in (args or {}).items() if key not in ("analytic", "sampling")
    }
    form, _, target = spec.partition(":")
    randomize = (args or {}).get("randomize")
    try:
        if form == "family":
            path = family_path(target)
        elif form == "instrument":
            path = find_instrument(target)
        elif form == "csv" and isinstance(randomize, Mapping):
            if not isinstance(randomize.get("family"), str):
                return None
            path, overrides = family_path(randomize["family"]), {}
        else:
            return None
    except ValueError:  # names nothing: the registry says so when it opens the spec
        return None
    try:
        return load_family(path, **overrides), path
    except (OSError, ValueError):
        return None


def held_out_reason(spec: str, args: Mapping[str, Any] | None = None) -> str | None:
    """How `spec` (with `args`) reaches the held-out set, in words; None where it does not."""
    if not isinstance(spec, str):
        return None
    if spec.startswith("set:") and spec[len("set:") :] in held_out_sets():
        return f"{spec} is the held-out set"
    found = _family_of(spec, args)
    if found is None:
        return None
    family, path = found
    held_out = [pair for name in held_out_sets() for pair in load_set(name)]
    folders = {(INSTRUMENT_DIR / name).resolve() for name in held_out_sets()}
    if path.resolve().parent in folders:
        return f"{spec} is the held-out instrument {path.stem!r}"
    for name, instrument in held_out:
        if _same(family, instrument):
            return (
                f"{spec} simulates the held-out instrument {name!r} (the same parameters, "
                f"each within {SAME_WITHIN:g} of its own)"
            )
    for name, instrument in held_out:
        if _contains(family, instrument):
            return f"{spec} contains the held-out instrument {name!r} whole (every parameter)"
    return None

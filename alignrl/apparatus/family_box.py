"""The instrument family's box: every parameter of a focus column, its physical range and
its units, and the YAML files that give a box or an instrument (alignrl/apparatus/families/
*.yaml, alignrl/apparatus/instruments/<set>/*.yaml). The columns drawn from a box are
alignrl/apparatus/family.py's, which re-exports everything here.

A `FocusFamily` is a box: every parameter a point or a [low, high] range, read strictly,
each within its physical range (`PHYSICAL`: a value beyond it, 1e300 volts of interval or a
probe of a millionth of a pixel, is refused naming the parameter, the value, the range and
the file or the apparatus argument it came from, never simulated).
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from alignrl.apparatus.box_values import pair, range_problem, shown_problems
from alignrl.apparatus.column_box import ColumnBox, product_data
from alignrl.yaml_io import read_yaml_file

__all__ = [
    "BOUNDED",
    "FAMILY_DIR",
    "FAMILY_KINDS",
    "LOG_SCALE",
    "PAIR_FIELDS",
    "PHYSICAL",
    "AnyFamily",
    "FocusFamily",
    "family_digest",
    "family_names",
    "family_path",
    "load_family",
]

FAMILY_DIR = Path(__file__).with_name("families")
Pair = tuple[float, float]


# Parameters drawn on a log scale (positive, spanning decades); the rest uniformly.
LOG_SCALE = (
    "interval_width",
    "blur_px_per_interval",
    "floor_sigma_px",
    "asymmetry",
    "saturation_px",
    "no_edges_px",
    "dose_electrons_per_px",
)


# The physical range of every parameter, in its units (issue 60): a box, an instrument or an
# apparatus argument beyond it is refused, naming the parameter, the value, the range and the
# file or argument. Generous: every shipped box and instrument lies far inside (widths of
# 12-20,000 knob units, centres within 2,000, 8-150 px of blur, 0.7-2.5 px in focus), yet at
# the ends the column's arithmetic holds (no overflow, an interval of distinct floats).
MAX_KNOB_UNITS = 1e6  # knob units (V of a lens, mA of a coil): interval width and |centre|
MIN_INTERVAL_WIDTH = 1e-6  # knob units: narrower, beside a centre of 1e6 it has few floats
MIN_PX = 0.1  # px: a probe, width or gain below a tenth of a pixel is no reading
MAX_PX = 1e4  # px: ten times the widest frame (1024 px)
MAX_ASYMMETRY = 100.0  # gain above focus / gain below it, either way
MIN_DOSE, MAX_DOSE = 0.01, 1e9  # primary electrons per px: a frame almost empty; 10^5 x bright
MAX_DETECTOR_NOISE = 10.0  # yield units: ten times a frame's whole signal
KNOB_UNITS = "knob units"  # shown as the family's own unit (`unit`: V, mA, ...)
PHYSICAL: dict[str, tuple[float, float, str]] = {  # name: (lowest, highest, unit)
    "interval_width": (MIN_INTERVAL_WIDTH, MAX_KNOB_UNITS, KNOB_UNITS),
    "interval_centre": (-MAX_KNOB_UNITS, MAX_KNOB_UNITS, KNOB_UNITS),
    "optimum_fraction": (0.0, 1.0, "of the interval, low to high"),
    "blur_px_per_interval": (MIN_PX, MAX_PX, "px"),
    "floor_sigma_px": (MIN_PX, MAX_PX, "px"),
    "curve_power": (1.0, 8.0, "(the curve's power q)"),
    "flat_fraction": (0.0, 0.2, "x W"),
    "asymmetry": (1.0 / MAX_ASYMMETRY, MAX_ASYMMETRY, "(a ratio of gains)"),
    "reading_noise_rel": (0.0, 0.5, "(std of log reading)"),
    "reading_noise_px": (0.0, MAX_PX, "px"),
    "specimen_rel": (0.0, 0.5, "(std of log reading)"),
    "saturation_px": (MIN_PX, MAX_PX, "px"),
    "no_edges_px": (MIN_PX, MAX_PX, "px"),
    "drift_fraction": (0.0, 0.05, "x W per acquisition"),
    "hysteresis_fraction": (0.0, 0.1, "x W"),
    "dose_electrons_per_px": (MIN_DOSE, MAX_DOSE, "electrons per px"),
    "detector_noise": (0.0, MAX_DETECTOR_NOISE, "yield units"),
}
PAIR_FIELDS = tuple(PHYSICAL)  # the parameters that are a point or a range, in draw order
BOUNDED = {name: (lowest, highest) for name, (lowest, highest, _) in PHYSICAL.items()}


class FocusFamily(BaseModel):
    """A box of focus columns. Each parameter is a point or [low, high]; `LOG_SCALE` ones are
    drawn log-uniformly, the others uniformly. Units: the knob's own (`unit`), px, or a
    fraction of the knob's interval width W."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["focus"] = Field("focus", description="which knobs the family moves")
    name: str = Field("family", min_length=1, description="shown in sessions and reports")
    description: str = Field("", description="what this box or instrument is, in words")
    unit: str = Field("V", min_length=1, description="the defocus knob's unit, for people")
    image_size_px: int = Field(256, ge=64, le=1024, description="square frame (image path), px")
    interval_width: Pair = Field(
        (40.0, 4000.0), description="W: width of the defocus interval, the knob's units"
    )
    interval_centre: Pair = Field(
        (-2000.0, 2000.0), description="centre of the defocus interval, the knob's units"
    )
    optimum_fraction: Pair = Field(
        (0.15, 0.85), description="where the optimum lies in the interval, 0 low .. 1 high"
    )
    blur_px_per_interval: Pair = Field(
        (10.0, 100.0), description="probe sigma growth over a focus error of W, px (the gain)"
    )
    floor_sigma_px: Pair = Field((0.8, 2.5), description="sigma0: the probe in focus, px")
    curve_power: Pair = Field(
        (1.5, 3.0), description="q of the focus curve (2: hyperbola; 1: a V; high: a U)"
    )
    flat_fraction: Pair = Field(
        (0.0, 0.01), description="half-width of the curve's flat bottom, fraction of W"
    )
    asymmetry: Pair = Field(
        (0.67, 1.5), description="gain above focus / gain below focus (1: symmetric)"
    )
    reading_noise_rel: Pair = Field(
        (0.005, 0.04), description="multiplicative noise: std of log(reading) (analytic)"
    )
    reading_noise_px: Pair = Field(
        (0.0, 0.1), description="additive noise of a reading, px (analytic)"
    )
    specimen_rel: Pair = Field(
        (0.0, 0.05), description="std of log(reading) between episodes: the specimen (analytic)"
    )
    saturation_px: Pair = Field(
        (20.0, 80.0), description="w_sat: readings level off at the features' size, px (analytic)"
    )
    no_edges_px: Pair = Field(
        (40.0, 150.0),
        description="true width at which half the frames show no edges, px (analytic)",
    )
    drift_fraction: Pair = Field(
        (0.0, 0.0005), description="std of the optimum's walk per acquisition, fraction of W"
    )
    hysteresis_fraction: Pair = Field(
        (0.0, 0.005), description="backlash: V_eff lags V by this x W against the last change"
    )
    specimens: tuple[str, ...] = Field(
        ("particles",), min_length=1, description="specimen kinds drawn from (image path)"
    )
    dose_electrons_per_px: Pair = Field(
        (100.0, 400.0), description="primary electrons per pixel (image path)"
    )
    detector_noise: Pair = Field(
        (0.005, 0.02), description="Gaussian detector noise, yield units (image path)"
    )

    @field_validator(*PAIR_FIELDS, mode="before")
    @classmethod
    def _points_are_ranges(cls, value: Any) -> Any:
        return pair(value)

    @model_validator(mode="after")
    def _check(self) -> FocusFamily:
        from alignrl.apparatus.specimens import SPECIMENS

        problems = []
        for name, (lowest, highest, unit) in PHYSICAL.items():
            low, high = getattr(self, name)
            shown = self.unit[:20] if unit == KNOB_UNITS else unit
            problem = range_problem(name, low, high, lowest, highest, shown)
            if problem is not None:
                problems.append(problem)
        unknown = [kind for kind in self.specimens if kind not in SPECIMENS]
        if unknown:
            problems.append(
                f"specimens: unknown {', '.join(unknown)[:200]} (known: {', '.join(SPECIMENS)})"
            )
        if problems:
            raise ValueError("; ".join(shown_problems(problems)))
        return self


# A family's `kind` -> its box: the focus column's own model, or whole synthetic SEMs for the
# stigmators, the aperture and the column (alignrl/apparatus/column_box.py).
FAMILY_KINDS: dict[str, type[FocusFamily] | type[ColumnBox]] = {
    "focus": FocusFamily,
    "stigmation": ColumnBox,
    "aperture": ColumnBox,
    "column": ColumnBox,
}
AnyFamily = FocusFamily | ColumnBox


def family_names() -> list[str]:
    """The shipped boxes: alignrl/apparatus/families/*.yaml."""
    return sorted(path.stem for path in FAMILY_DIR.glob("*.yaml"))


def family_path(target: str) -> Path:
    """The file a family is named by: a shipped box's name (families/NAME.yaml), or a path
    (ending in .yaml or .yml, or with a folder in it); ValueError for an unknown name."""
    if target.endswith((".yaml", ".yml")) or "/" in target:
        return Path(target)
    if target not in family_names():
        raise ValueError(
            f"no instrument family {target!r}; the shipped families are: "
            f"{', '.join(family_names())} (or give family:PATH.yaml)"
        )
    return FAMILY_DIR / f"{target}.yaml"


def load_family(path: str | Path, **overrides: Any) -> AnyFamily:
    """Read a family or instrument YAML file strictly, with `overrides` (the apparatus
    arguments) laid over its keys: an unknown key, a bad range, a parameter beyond its
    physical range (PHYSICAL) is a ValueError naming the file, the arguments it came from,
    the key and the value."""
    path = Path(path)
    try:
        data = read_yaml_file(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"instrument family {path} does not exist") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of family parameters")
    data.update(overrides)
    kind = data.get("kind", "focus")
    model = FAMILY_KINDS.get(kind) if isinstance(kind, str) else None
    if model is None:
        raise ValueError(f"{path}: kind {kind!r} is not a family kind ({', '.join(FAMILY_KINDS)})")
    try:
        if model is ColumnBox:  # a column may be the product of a stigmation and an aperture box
            data = product_data(data, _factor, path)
        return model.model_validate(data)  # a key that is no name is refused too
    except ValidationError as error:
        problems = []
        for item in error.errors():
            key = ".".join(str(part) for part in item["loc"])
            message = item["msg"].removeprefix("Value error, ")
            problems.append(f"{key[:200]}: {message[:2000]}" if key else message[:2000])
        text = "; ".join(shown_problems(problems))
        given = [
            str(key)[:100] for key in overrides if re.search(rf"\b{re.escape(str(key))}\b", text)
        ]
        where = f"{path} with the apparatus arguments {', '.join(given)}" if given else str(path)
        raise ValueError(f"{where}: {text}") from None


def _factor(name: str) -> AnyFamily:
    """A factor of a column's product: a stigmation or an aperture family (never a column,
    which could name itself)."""
    path = family_path(name)
    data = read_yaml_file(path)
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind not in ("stigmation", "aperture"):
        raise ValueError(
            f"{path}: a column's factor must be a stigmation or aperture family, not {kind!r}"
        )
    return load_family(path)


def family_digest(family: AnyFamily) -> str:
    """A fingerprint of what a family simulates (its name and words left out): two files
    that describe the same columns have the same digest, however they are named."""
    data = family.model_dump(exclude={"name", "description"})
    text = json.dumps(data, sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()

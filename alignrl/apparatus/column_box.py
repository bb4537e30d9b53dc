"""Boxes of whole columns: the stigmation, aperture and column families (issue 62), read
strictly from alignrl/apparatus/families/*.yaml, and single instruments of them from
alignrl/apparatus/instruments/<set>/*.yaml (docs/physics.md, "Families for every knob").

Where the focus family (alignrl/apparatus/family_box.py) is a model of its own, a column box
describes synthetic SEMs (alignrl/apparatus/synthetic.py): each draw is a `SEMConfig`, so the
stigmators, the aperture, the wobble and the directional widths are the simulator's, with its
images and its analytic mode. Its parameters are unit-free where a real column's units
differ, so that one box spans columns in volts or amperes, percent or DAC counts, um or mm:

* the defocus interval (width W, centre) and where the optimum lies in it, the focus gain as
  px of probe sigma over W, the backlash and drift as shares of W;
* the stigmators' interval (width Ws, symmetric about 0), the largest astigmatism in px of
  line-focus separation, how much of the stigmators' reach cancelling it takes
  (`astigmatism_reach`: the stigmators' gain follows), the least astigmatism as a share of
  the largest (a column that needs its stigmators near a bound), their axes turned against
  the image, coupled, mirrored;
* the aperture's interval (width Wa, symmetric about 0), how far off axis it sits as a share
  of Wa / 2, the wobble's image shift as px for a focus swing of W with the aperture at its
  interval's end, its blur at that end, the image turned and mirrored against its axes;
* dose and detector noise (image path), and a factor on the readings' noise (analytic path);
* the specimens the image path images (`specimens`: kinds of `SEMConfig.specimen`, one
  drawn per column from the list like a mirror, `column_specimen`; analytic mode ignores it).

Every numeric parameter is a point or [low, high] within its physical range (`PARAMETERS`),
drawn log-uniformly where it spans decades; each mirror is a list of the values drawn from
([false], [true] or [false, true]), and so is `specimens`. What the box does not name comes
from its `base` preset (the specimen's yields and sizes, the analytic calibration).

`kind` says which knobs the box is for: `stigmation` and `aperture` boxes vary their own
knobs' parameters, and a `column` box is their product (`product: [STIGMATION, APERTURE]`:
each knob's parameters from its own family, the focus and imaging ones agreed between
them), or its own parameters written out.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator, model_validator

from alignrl.apparatus.box_values import pair, pick, range_problem, shown_problems, span
from alignrl.apparatus.sem_config import (
    PRESET_DIR,
    SPECIMEN_KINDS,
    SEMConfig,
    load_sem_config,
    preset_names,
)

__all__ = [
    "COLUMN_KINDS",
    "FLAGS",
    "GROUPS",
    "PARAMETERS",
    "SPECIMEN_DRAW",
    "ColumnBox",
    "column_config",
    "column_specimen",
    "product_data",
]

COLUMN_KINDS = ("stigmation", "aperture", "column")
Pair = tuple[float, float]


@dataclass(frozen=True)
class Parameter:
    """One parameter of a column box: its group (whose knobs it belongs to), its default
    range, its physical range and unit, whether it is drawn log-uniformly, what it is."""

    group: str
    default: Pair
    lowest: float
    highest: float
    unit: str
    log: bool
    description: str


# The groups: a stigmation box owns "stigmators", an aperture box "aperture"; "focus" and
# "imaging" are every box's, and must agree between the factors of a product.
GROUPS = ("focus", "stigmators", "aperture", "imaging")
# Physical ranges are generous: every shipped box lies far inside, and at their ends a
# column's arithmetic holds.
# fmt: off
PARAMETERS: dict[str, Parameter] = {
    "defocus_interval_width": Parameter("focus", (40.0, 4000.0), 1e-6, 1e6, "defocus units", True, "W: width of the defocus interval"),  # noqa: E501
    "defocus_interval_centre": Parameter("focus", (-2000.0, 2000.0), -1e6, 1e6, "defocus units", False, "centre of the defocus interval"),  # noqa: E501
    "optimum_fraction": Parameter("focus", (0.3, 0.7), 0.0, 1.0, "of W", False, "the optimum's nominal place in the defocus interval"),  # noqa: E501
    "optimum_spread_fraction": Parameter("focus", (0.0, 0.2), 0.0, 0.5, "of W", False, "each scenario's optimum uniform within the nominal +/- this"),  # noqa: E501
    "blur_px_per_interval": Parameter("focus", (15.0, 60.0), 0.1, 1e4, "px", True, "probe sigma growth over a focus error of W (the focus gain)"),  # noqa: E501
    "probe_sigma0_px": Parameter("focus", (0.8, 1.6), 0.3, 20.0, "px", True, "the probe in focus"),
    "hysteresis_fraction": Parameter("focus", (0.0, 0.008), 0.0, 0.1, "of W", False, "the lens field lags the last change by this"),  # noqa: E501
    "drift_fraction": Parameter("focus", (0.0, 0.0005), 0.0, 0.05, "of W per acquisition", False, "std of the optimum's walk"),  # noqa: E501
    "stigmator_interval_width": Parameter("stigmators", (2.0, 2000.0), 1e-6, 1e6, "stigmator units", True, "Ws: each stigmator's interval, symmetric about 0"),  # noqa: E501
    "astigmatism_max_px": Parameter("stigmators", (1.0, 6.0), 0.0, 1e3, "px", True, "the largest astigmatism: line-focus separation x focus gain"),  # noqa: E501
    "astigmatism_floor": Parameter("stigmators", (0.0, 0.0), 0.0, 1.0, "of the largest", False, "the least astigmatism"),  # noqa: E501
    "astigmatism_reach": Parameter("stigmators", (0.2, 0.9), 0.01, 1.0, "of Ws / 2", False, "the stigmator setting that cancels the largest astigmatism"),  # noqa: E501
    "stigmator_rotation_deg": Parameter("stigmators", (0.0, 180.0), 0.0, 180.0, "degrees", False, "the stigmators' axes turned against the image"),  # noqa: E501
    "stigmator_coupling": Parameter("stigmators", (-0.4, 0.4), -0.85, 0.85, "", False, "the share of each stigmator's action the other axis receives"),  # noqa: E501
    "aperture_interval_width": Parameter("aperture", (2.0, 2000.0), 1e-6, 1e6, "aperture units", True, "Wa: each aperture axis's interval, symmetric about 0"),  # noqa: E501
    "aperture_offset_reach": Parameter("aperture", (0.2, 0.8), 0.0, 1.0, "of Wa / 2", False, "the aperture's largest distance from the axis"),  # noqa: E501
    "aperture_offset_floor": Parameter("aperture", (0.0, 0.0), 0.0, 1.0, "of the largest", False, "its least distance from the axis"),  # noqa: E501
    "wobble_shift_px_per_interval": Parameter("aperture", (40.0, 400.0), 0.0, 1e6, "px", True, "image shift for a focus swing of W, the aperture at Wa / 2 off axis"),  # noqa: E501
    "aperture_blur_px": Parameter("aperture", (0.5, 3.0), 0.0, 100.0, "px", False, "probe sigma added in quadrature with the aperture Wa / 2 off axis"),  # noqa: E501
    "aperture_rotation_deg": Parameter("aperture", (0.0, 360.0), 0.0, 360.0, "degrees", False, "the image turned against the aperture's axes"),  # noqa: E501
    "dose_electrons_per_px": Parameter("imaging", (100.0, 400.0), 0.01, 1e9, "electrons per px", True, "primary electrons per pixel (image path)"),  # noqa: E501
    "detector_noise": Parameter("imaging", (0.005, 0.02), 0.0, 10.0, "yield units", False, "Gaussian detector noise (image path)"),  # noqa: E501
    "reading_noise_factor": Parameter("imaging", (0.7, 1.5), 0.05, 20.0, "", True, "x the base's reading and wobble noise (analytic path)"),  # noqa: E501
    "stigmator_hysteresis_fraction": Parameter("stigmators", (0.0, 0.005), 0.0, 0.1, "of Ws", False, "each stigmator's field lags its last change by this"),  # noqa: E501
    "stigmator_drift_fraction": Parameter("stigmators", (0.0, 0.0005), 0.0, 0.05, "of Ws per acquisition", False, "std of the stigmators' optimum's walk"),  # noqa: E501
}
# fmt: on
FLAGS = {"stigmator_mirror": "stigmators", "aperture_mirror": "aperture"}  # drawn from lists
# The specimens are drawn from a list too, by a fraction of their own, drawn after the
# parameters' and the mirrors' (so that adding it left their draws as they were).
SPECIMEN_DRAW = "specimens"
UNITS = {"stigmator_unit": "stigmators", "aperture_unit": "aperture"}  # each knob's own
PAIR_FIELDS = tuple(PARAMETERS)
# What only one reading path uses: a designer is offered what its path reads.
ANALYTIC_ONLY = ("reading_noise_factor",)
IMAGE_ONLY = ("dose_electrons_per_px", "detector_noise")
OWNED = {"stigmation": ("stigmators",), "aperture": ("aperture",), "column": GROUPS}
# The groups a kind's task reads (the others' knobs stay at their optimum there).
USED = {
    "stigmation": ("focus", "stigmators", "imaging"),
    "aperture": ("focus", "aperture", "imaging"),
    "column": GROUPS,
}


def _flags(value: Any) -> Any:
    """A single true or false means the list of it."""
    return (value,) if isinstance(value, bool) else value


class _Base(BaseModel):
    """What a column box is beside its parameters (they come from `PARAMETERS`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["stigmation", "aperture", "column"] = Field(
        "column", description="which knobs the box is for"
    )
    name: str = Field("column-family", min_length=1, description="shown in sessions")
    description: str = Field("", description="what this box or instrument is, in words")
    base: str = Field(
        "synthetic",
        min_length=1,
        description="the preset whose other settings (specimen, analytic calibration) it keeps",
    )
    defocus_unit: str = Field("V", min_length=1, description="the defocus knob's unit")
    stigmator_unit: str = Field("%", min_length=1, description="the stigmators' unit")
    aperture_unit: str = Field("um", min_length=1, description="the aperture's unit")
    stigmator_mirror: tuple[bool, ...] = Field(
        (False, True), min_length=1, description="stigmator_y wired the other way round"
    )
    aperture_mirror: tuple[bool, ...] = Field(
        (False, True), min_length=1, description="the image mirrored against the aperture"
    )
    specimens: tuple[str, ...] = Field(
        ("gold",),
        min_length=1,
        description="the specimens a column's image path images, one drawn per column "
        f"(SEMConfig.specimen: {', '.join(SPECIMEN_KINDS)}); analytic mode ignores them",
    )


_FIELDS: dict[str, Any] = {
    name: (Pair, Field(parameter.default, description=parameter.description))
    for name, parameter in PARAMETERS.items()
}


class ColumnBox(create_model("_ColumnBoxFields", __base__=_Base, **_FIELDS)):  # type: ignore[misc]
    """A box of whole columns (module docstring): every parameter of `PARAMETERS` a point or
    [low, high] within its physical range, each mirror a list of the values it takes."""

    @field_validator(*PAIR_FIELDS, mode="before")
    @classmethod
    def _points_are_ranges(cls, value: Any) -> Any:
        return pair(value)

    @field_validator(*FLAGS, mode="before")
    @classmethod
    def _one_flag_is_a_list(cls, value: Any) -> Any:
        return _flags(value)

    @field_validator("specimens", mode="before")
    @classmethod
    def _one_specimen_is_a_list(cls, value: Any) -> Any:
        return (value,) if isinstance(value, str) else value

    @model_validator(mode="after")
    def _check(self) -> ColumnBox:
        problems = []
        for name, parameter in PARAMETERS.items():
            low, high = getattr(self, name)
            problem = range_problem(
                name, low, high, parameter.lowest, parameter.highest, parameter.unit
            )
            if problem is None and parameter.log and low <= 0:
                problem = f"{name} {span(low, high)}: drawn on a log scale, needs > 0"
            if problem is not None:
                problems.append(problem)
        low, high = self.optimum_fraction
        spread = self.optimum_spread_fraction[1]
        if low - spread < 0 or high + spread > 1:
            problems.append(
                f"optimum_fraction {span(*self.optimum_fraction)} +/- optimum_spread_fraction "
                f"{spread:g} leaves the defocus interval"
            )
        unknown = [kind for kind in self.specimens if kind not in SPECIMEN_KINDS]
        if unknown:
            problems.append(
                f"specimens: no kind {', '.join(map(repr, unknown))} "
                f"(the kinds are {', '.join(SPECIMEN_KINDS)})"
            )
        if len(set(self.specimens)) < len(self.specimens):
            problems.append(f"specimens: each kind once, got {list(self.specimens)}")
        if self.base not in preset_names():
            problems.append(f"base: no preset {self.base!r} ({', '.join(preset_names())})")
        if problems:
            raise ValueError("; ".join(shown_problems(problems)))
        return self

    def used(self) -> tuple[str, ...]:
        """The parameters its kind's task reads, in `PARAMETERS` order (a stigmation box's
        aperture stays at its optimum, whatever its parameters)."""
        return tuple(name for name in PAIR_FIELDS if PARAMETERS[name].group in USED[self.kind])

    def ranged(self) -> tuple[str, ...]:
        """The used parameters that are a range, then the used mirrors that take both
        values: where a designer may place a column."""
        names = [name for name in self.used() if getattr(self, name)[0] < getattr(self, name)[1]]
        names += [
            flag
            for flag, group in FLAGS.items()
            if group in USED[self.kind] and len(set(getattr(self, flag))) > 1
        ]
        return tuple(names)


@functools.cache
def _preset(name: str) -> SEMConfig:
    """A preset's config (frozen), read once per process."""
    return load_sem_config(PRESET_DIR / f"{name}.yaml")


def column_specimen(box: ColumnBox, fraction: float) -> str:
    """The specimen at `fraction` (in [0, 1], clipped) of the box's list, as a mirror is
    drawn from its list: each kind an equal share, in the list's order."""
    return pick(box.specimens, fraction)


def column_config(
    box: ColumnBox,
    values: Mapping[str, float],
    mirrors: Mapping[str, bool],
    specimen: str | None = None,
) -> SEMConfig:
    """The synthetic SEM of one column of `box`: every parameter a number (`values`, by
    `PARAMETERS` name; `mirrors` by `FLAGS` name), in the SEMConfig's own terms, imaging
    `specimen` (one of the box's; None: the first of its list)."""
    if specimen is None:
        specimen = box.specimens[0]
    elif specimen not in box.specimens:
        raise ValueError(
            f"specimen {specimen!r} is not one of the box's ({', '.join(box.specimens)})"
        )
    v = values
    width, centre = v["defocus_interval_width"], v["defocus_interval_centre"]
    low = centre - 0.5 * width
    gain = v["blur_px_per_interval"] / width  # px per defocus unit
    half_s = 0.5 * v["stigmator_interval_width"]
    half_a = 0.5 * v["aperture_interval_width"]
    coupling = v["stigmator_coupling"]
    astigmatism = v["astigmatism_max_px"] / gain  # defocus units between the line foci
    # the setting that cancels the largest astigmatism, at the weakest coupled direction
    per_unit = astigmatism / (v["astigmatism_reach"] * half_s * (1.0 - abs(coupling)))
    base = _preset(box.base).model_dump()  # read once: a column is drawn at every reset
    calibration = dict(base["analytic_calibration"])
    factor = v["reading_noise_factor"]
    for table in ("noise_rel", "directional_noise_rel"):
        calibration[table] = tuple(x * factor for x in calibration[table])
    calibration["wobble_scatter_px_per_px"] *= factor
    base.update(
        name=box.name,
        defocus_interval_v=(low, low + width),
        optimum_v=low + v["optimum_fraction"] * width,
        optimum_spread_v=v["optimum_spread_fraction"] * width,
        drift_v_per_acquisition=v["drift_fraction"] * width,
        gain_px_per_v=gain,
        probe_sigma0_px=v["probe_sigma0_px"],
        hysteresis_v=v["hysteresis_fraction"] * width,
        stigmator_interval_pct=(-half_s, half_s),
        stigmator_hysteresis_pct=v["stigmator_hysteresis_fraction"] * 2.0 * half_s,
        stigmator_drift_pct_per_acquisition=v["stigmator_drift_fraction"] * 2.0 * half_s,
        astigmatism_max_v=astigmatism,
        astigmatism_min_v=v["astigmatism_floor"] * astigmatism,
        stigmator_v_per_pct=per_unit,
        stigmator_rotation_deg=v["stigmator_rotation_deg"] % 180.0,
        stigmator_coupling=coupling,
        stigmator_mirror=bool(mirrors["stigmator_mirror"]),
        aperture_interval_um=(-half_a, half_a),
        aperture_offset_max_um=v["aperture_offset_reach"] * half_a,
        aperture_offset_min_um=v["aperture_offset_floor"] * v["aperture_offset_reach"] * half_a,
        aperture_shift_px_per_v_um=v["wobble_shift_px_per_interval"] / (width * half_a),
        aperture_blur_px_per_um=v["aperture_blur_px"] / half_a,
        aperture_rotation_deg=v["aperture_rotation_deg"] % 360.0,
        aperture_mirror=bool(mirrors["aperture_mirror"]),
        dose_electrons_per_px=v["dose_electrons_per_px"],
        detector_noise=v["detector_noise"],
        specimen=specimen,
        analytic_calibration=calibration,
        reset_state="aligned",
    )
    return SEMConfig.model_validate(base)


def product_data(data: dict[str, Any], load: Any, path: Path) -> dict[str, Any]:
    """A column box's keys with its `product` resolved: each factor (a family name, read by
    `load`) gives the parameters of its own knobs; the focus and imaging parameters and the
    base must agree between the factors (ValueError naming the first that does not), and
    keys the file writes itself win; its specimens are those both factors name. Without
    `product`, the keys as they are."""
    factors = data.pop("product", None)
    if factors is None:
        return data
    if not (isinstance(factors, list) and factors and all(isinstance(f, str) for f in factors)):
        raise ValueError(f"{path}: product must be a list of family names, got {factors!r}")
    boxes = [load(name) for name in factors]
    kinds = sorted(box.kind for box in boxes)
    if kinds != ["aperture", "stigmation"]:
        raise ValueError(
            f"{path}: a column is the product of one stigmation and one aperture family, "
            f"got {', '.join(f'{n} ({b.kind})' for n, b in zip(factors, boxes, strict=True))}"
        )
    merged: dict[str, Any] = {}
    shared = [name for name, p in PARAMETERS.items() if p.group in ("focus", "imaging")]
    for box in boxes:
        own = OWNED[box.kind]
        for name, parameter in PARAMETERS.items():
            if parameter.group in own:
                merged[name] = getattr(box, name)
        for flag, group in {**FLAGS, **UNITS}.items():
            if group in own:
                merged[flag] = getattr(box, flag)
    first, second = boxes
    for name in [*shared, "base", "defocus_unit"]:
        if getattr(first, name) != getattr(second, name):
            raise ValueError(
                f"{path}: the product's factors {factors[0]} and {factors[1]} disagree on "
                f"{name} ({getattr(first, name)} against {getattr(second, name)})"
            )
        merged[name] = getattr(first, name)
    # a column images the specimens on which both its knobs' controllers cope
    both = [kind for kind in first.specimens if kind in second.specimens]
    if not both:
        raise ValueError(
            f"{path}: the product's factors {factors[0]} and {factors[1]} share no specimen "
            f"({', '.join(first.specimens)} against {', '.join(second.specimens)})"
        )
    merged["specimens"] = both
    merged.update(data)
    return merged

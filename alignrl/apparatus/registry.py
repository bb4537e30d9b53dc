"""Apparatus specs: one string names any instrument alignrl can work on.

* a preset name: `synthetic`, `synthetic-b` (every YAML file in alignrl/apparatus/presets/),
* `sem:PATH.yaml`: a synthetic SEM with the instrument parameters of a YAML file,
* `family:NAME` or `family:PATH.yaml`: a column drawn anew every episode from an instrument
  family's box (alignrl/apparatus/families/NAME.yaml): a focus column (`focus`,
  alignrl/apparatus/family.py) or a whole synthetic SEM (`stigmation`, `aperture`, `column`,
  alignrl/apparatus/column_family.py),
* `instrument:NAME`: one instrument of alignrl/apparatus/instruments/<set>/NAME.yaml, and
  `set:NAME` a whole set of them, the next instrument at every reset
  (alignrl/apparatus/instruments.py),
* `csv:PATH`: the scenario simulator replaying a recorded CSV (`csv:default` is the shipped
  2000-scenario set of the `synthetic` preset),
* `package.module:Class`: a user's own driver, imported and constructed with the keyword
  arguments of `apparatus_args` / `--apparatus-args JSON`. alignrl needs no change for it.

For presets, `sem:`, `family:`, `instrument:` and `csv:` the same arguments override
instrument or simulator settings (for example `{"dose_electrons_per_px": 50}` or
`{"noise": 0.02, "split": "test"}`). For presets, `sem:`, `family:`, `instrument:` and `set:`
(which takes no other argument) the argument `analytic` (true or false) switches to the
analytic mode: readings computed from the probe, without images (docs/physics.md). `family:`
also takes `sampling`, how the column draws from its box: `uniform` (the default) or `edges`
(each parameter from the arcsine law, the box's edges as often as its middle).

A driver is a real instrument: `make_apparatus` returns it behind the safety shield
(alignrl/apparatus/shield.py: intervals, site limits, maximum steps, finite values, bounded
calls, audit), whatever command opens it, so nothing reaches a microscope around the shield.
Only `alignrl align`, which puts its own single-alignment shield around the driver, opens one
unshielded (`build_apparatus`).

`make_apparatus_copies` opens one spec several times, for the slots of a vectorized env:
scenario simulators then share one parsed recording.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from alignrl.apparatus.base import APPARATUS_METHODS, Apparatus
from alignrl.apparatus.column_family import open_family
from alignrl.apparatus.family import SAMPLINGS
from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.guard import (
    DEFAULT_CALL_TIMEOUT_S,
    checked_intervals,
    construct_within,
    within,
)
from alignrl.apparatus.instruments import InstrumentSet, find_instrument, load_set
from alignrl.apparatus.limits import ShieldOptions
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config, preset_names
from alignrl.apparatus.simulator import ScenarioSimulator, default_scenarios_path
from alignrl.apparatus.synthetic import SyntheticSEM
from alignrl.apparatus.training_shield import shield_apparatus

__all__ = [
    "build_apparatus",
    "make_apparatus",
    "make_apparatus_copies",
    "preset_names",
    "spec_form",
]


def _check_protocol(obj: object, spec: str) -> Apparatus:
    """`obj` if it implements the protocol with intervals that are intervals; a ValueError
    naming what is missing or wrong. Runs on the thread that constructed it (`within`): a
    getter that hangs or raises is bounded there like the constructor."""
    missing = [name for name in (*APPARATUS_METHODS, "knobs") if not hasattr(obj, name)]
    if missing:
        raise ValueError(
            f"apparatus {spec!r} does not implement the Apparatus protocol: missing "
            f"{', '.join(missing)} (see docs/apparatus.md)"
        )
    _, wrong = checked_intervals(obj.knobs)  # type: ignore[attr-defined]
    if wrong is not None:
        raise ValueError(f"apparatus {spec!r}: {wrong}")
    return obj  # type: ignore[return-value]


def _construct(target: Any, spec: str, args: Mapping[str, Any], **fixed: Any) -> Any:
    """Call `target(**args, **fixed)`, refusing arguments it does not take with a clear error
    (a typo in --apparatus-args must not surface as a traceback)."""
    clash = sorted(set(args) & set(fixed))
    if clash:
        raise ValueError(f"apparatus {spec!r}: {', '.join(clash)} cannot be an apparatus argument")
    try:
        signature = inspect.signature(target)
    except (TypeError, ValueError):
        signature = None  # no signature to check (a builtin): let the call speak
    if signature is not None:
        try:
            signature.bind(**args, **fixed)
        except TypeError as error:
            accepted = ", ".join(
                name for name in signature.parameters if name not in fixed and name != "self"
            )
            raise ValueError(
                f"apparatus {spec!r} does not accept the arguments {dict(args)}: {error} "
                f"(it takes: {accepted or 'no arguments'})"
            ) from None
    return target(**args, **fixed)


def _import_driver(
    spec: str, args: Mapping[str, Any], call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S
) -> Apparatus:
    module_name, _, attribute = spec.partition(":")
    try:
        # Bounded as the driver's calls are: a module may connect to its microscope on import.
        module = within(
            f"apparatus {spec!r}: importing module {module_name!r}",
            lambda: importlib.import_module(module_name),
            call_timeout_s,
            passes=(ImportError,),
        )
    except ImportError as error:
        raise ValueError(
            f"apparatus {spec!r}: cannot import module {module_name!r}: {error}"
        ) from None
    try:
        target = getattr(module, attribute)
    except AttributeError:
        raise ValueError(
            f"apparatus {spec!r}: module {module_name!r} has no {attribute!r}"
        ) from None
    if not callable(target):
        raise ValueError(f"apparatus {spec!r}: {attribute!r} is not a class or factory")
    return construct_within(
        f"apparatus {spec!r}: opening the driver (its constructor, its knobs)",
        lambda: _check_protocol(_construct(target, spec, args), spec),
        call_timeout_s,
    )


def spec_form(spec: str) -> str:
    """Which form a spec has: 'csv', 'sem', 'family', 'instrument', 'set', 'preset' or
    'driver'; a ValueError for none.
    Nothing is built or imported: a driver may be importable only on its microscope's PC."""
    if not isinstance(spec, str) or not spec:
        raise ValueError("an apparatus spec must be a non-empty string")
    if spec.startswith("csv:"):
        return "csv"
    for form in ("sem", "family", "instrument", "set"):
        if spec.startswith(f"{form}:"):
            return form
    if spec in preset_names():
        return "preset"
    if ":" in spec and all(part.isidentifier() for part in spec.replace(":", ".").split(".")):
        return "driver"
    raise ValueError(
        f"unknown apparatus {spec!r}: use a preset ({', '.join(preset_names())}), "
        "csv:PATH (or csv:default), sem:PATH.yaml, family:NAME, instrument:NAME, set:NAME, "
        "or an import path package.module:Class"
    )


def build_apparatus(
    spec: str,
    args: Mapping[str, Any] | None = None,
    seed: int | None = None,
    call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S,
) -> Apparatus:
    """The apparatus a spec names (see the module docstring), a driver unshielded: only for
    code that shields it itself (alignrl/deploy/align.py). Everything else: make_apparatus.
    A driver's constructor is bounded by `call_timeout_s` as its calls are."""
    args = dict(args or {})
    form = spec_form(spec)
    if form == "csv":
        location = spec[len("csv:") :]
        path = default_scenarios_path() if location == "default" else Path(location)
        return _construct(ScenarioSimulator, spec, args, path=path, seed=seed, scenarios=None)
    if form in ("sem", "preset", "family", "instrument", "set"):
        analytic = args.pop("analytic", False)
        if not isinstance(analytic, bool):
            raise ValueError(
                f"apparatus {spec!r}: analytic must be true or false, got {analytic!r}"
            )
        target = spec.partition(":")[2]
        if form == "set":
            if args:
                raise ValueError(
                    f"apparatus {spec!r}: a set takes only the argument analytic, got "
                    f"{', '.join(sorted(args))}"
                )
            return InstrumentSet([family for _, family in load_set(target)], seed, analytic)
        if form == "family":
            # How the column draws from its box (family.SAMPLINGS): the box itself is the same.
            sampling = args.pop("sampling", "uniform")
            if sampling not in SAMPLINGS:
                raise ValueError(
                    f"apparatus {spec!r}: sampling must be one of {', '.join(SAMPLINGS)}, "
                    f"got {sampling!r}"
                )
            family = load_family(family_path(target), **args)
            return open_family(family, seed, analytic, sampling)
        if form == "instrument":
            return open_family(load_family(find_instrument(target), **args), seed, analytic)
        path = Path(target) if form == "sem" else PRESET_DIR / f"{spec}.yaml"
        return SyntheticSEM(load_sem_config(path, **args), seed=seed, analytic=analytic)
    return _import_driver(spec, args, call_timeout_s)


def make_apparatus(
    spec: str,
    args: Mapping[str, Any] | None = None,
    seed: int | None = None,
    shield: ShieldOptions | None = None,
) -> Apparatus:
    """The apparatus a spec names; a driver always behind the shield (default options: the
    driver's own intervals, no site limits, DEFAULT_CALL_TIMEOUT_S a call, audit in memory),
    a simulator too where `shield.simulators` says so."""
    timeout_s = shield.call_timeout_s if shield is not None else DEFAULT_CALL_TIMEOUT_S
    return _shielded_where_due(build_apparatus(spec, args, seed, timeout_s), spec, shield)


def _shielded_where_due(apparatus: Apparatus, spec: str, shield: ShieldOptions | None) -> Apparatus:
    """A driver behind the shield always, a simulator where `shield.simulators` says so."""
    if spec_form(spec) == "driver" or (shield is not None and shield.simulators):
        return shield_apparatus(apparatus, shield)
    return apparatus


def make_apparatus_copies(
    spec: str, args: Mapping[str, Any] | None, count: int, shield: ShieldOptions | None = None
) -> list[Apparatus]:
    """`count` independent instances of one spec, each as `make_apparatus` opens it;
    scenario simulators share the parsed recording. Drivers (and, with `shield.simulators`,
    simulators) come behind the shield, their audit records naming units 1..count."""
    options = shield or ShieldOptions()
    units = [dataclasses.replace(options, unit=str(number + 1)) for number in range(count)]
    built = build_apparatus(spec, args, None, options.call_timeout_s)
    first = _shielded_where_due(built, spec, units[0])
    if isinstance(built, ScenarioSimulator):
        extra = dict(args or {})
        copies: list[Apparatus] = [
            ScenarioSimulator(scenarios=built.scenarios, **extra) for _ in range(count - 1)
        ]
        if first is not built:  # shielded: so are its copies
            copies = [shield_apparatus(c, u) for c, u in zip(copies, units[1:], strict=True)]
        return [first, *copies]
    return [first] + [make_apparatus(spec, args, shield=unit) for unit in units[1:]]

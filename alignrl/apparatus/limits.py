"""The rules the shield writes by: where each knob may go, how far one write may move it,
and the options a command opens an apparatus with (alignrl/apparatus/shield.py applies them).

`resolve_limits` joins an apparatus's intervals with the site limits (`--limits`) and the
maximum steps (`--max-step`), refusing what cannot be used (ShieldConfigError) before anything
is written; `clamp_write` decides one write. Pure functions over instrument units (volts for
lenses): no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from alignrl.apparatus.audit import AuditSink
from alignrl.apparatus.guard import DEFAULT_CALL_TIMEOUT_S, RefusedWrite

__all__ = [
    "KnobLimits",
    "ShieldConfigError",
    "ShieldOptions",
    "WriteDecision",
    "clamp_write",
    "resolve_limits",
]


class ShieldConfigError(ValueError):
    """Site limits or maximum steps that cannot be used; raised before anything is written."""


@dataclass(frozen=True)
class KnobLimits:
    """Where one knob may go: the interval the shield clamps to (and which rule set each
    bound) and the largest change per write (None: no limit), instrument units."""

    low: float
    high: float
    low_rule: str  # "apparatus interval" or "site limit"
    high_rule: str
    max_step: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"low": self.low, "high": self.high, "max_step": self.max_step}


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ShieldConfigError(f"{where}: {value!r} is not a number")
    number = float(value)
    if not math.isfinite(number):
        raise ShieldConfigError(f"{where}: {value!r} is not a finite number")
    return number


def _known_knob(knobs: Mapping[str, tuple[float, float]], name: str, option: str) -> None:
    if name not in knobs:
        have = ", ".join(sorted(knobs)) or "none"
        raise ShieldConfigError(f"{option}: unknown knob {name!r}; this apparatus has {have}")


def resolve_limits(
    knobs: Mapping[str, tuple[float, float]],
    site_limits: Mapping[str, Any] | None = None,
    max_step: Mapping[str, Any] | None = None,
) -> dict[str, KnobLimits]:
    """The limits of every knob of the apparatus, from its intervals, the site limits
    (`{"defocus": [low, high]}`) and the maximum steps (`{"defocus": 2.0}`).

    A site limit must lie inside the apparatus's interval (it can only tighten it): a bound
    outside, low >= high, a non-finite number, an unknown knob or a maximum step that is not
    positive is a ShieldConfigError naming the option and the knob.
    """
    site_limits = dict(site_limits or {})
    max_step = dict(max_step or {})
    for name in site_limits:
        _known_knob(knobs, name, "--limits")
    for name in max_step:
        _known_knob(knobs, name, "--max-step")
    limits = {}
    for name, interval in knobs.items():
        low, high = float(interval[0]), float(interval[1])
        low_rule = high_rule = "apparatus interval"
        if name in site_limits:
            bounds = site_limits[name]
            if not isinstance(bounds, list | tuple) or len(bounds) != 2:
                raise ShieldConfigError(
                    f"--limits: {name!r} needs [low, high] in instrument units, got {bounds!r}"
                )
            site_low = _number(bounds[0], f"--limits {name!r} low")
            site_high = _number(bounds[1], f"--limits {name!r} high")
            if not site_low < site_high:
                raise ShieldConfigError(
                    f"--limits: {name!r} low {site_low:g} must be below high {site_high:g}"
                )
            if site_low < low or site_high > high:
                raise ShieldConfigError(
                    f"--limits: {name!r} [{site_low:g}, {site_high:g}] is not inside the "
                    f"apparatus's interval [{low:g}, {high:g}]: site limits can only tighten it"
                )
            if site_low > low:
                low, low_rule = site_low, "site limit"
            if site_high < high:
                high, high_rule = site_high, "site limit"
        step = None
        if name in max_step:
            step = _number(max_step[name], f"--max-step {name!r}")
            if not step > 0:
                raise ShieldConfigError(
                    f"--max-step: {name!r} must be a positive change per write, got {step:g}"
                )
        limits[name] = KnobLimits(low, high, low_rule, high_rule, step)
    return limits


@dataclass(frozen=True)
class WriteDecision:
    """What the shield makes of one requested write: the values to write and, per clamped
    knob, {"knob", "from", "to", "rule"}."""

    values: dict[str, float]
    clamps: tuple[dict[str, Any], ...]


def clamp_write(
    limits: Mapping[str, KnobLimits],
    current: Mapping[str, float],
    requested: Mapping[str, float],
) -> WriteDecision:
    """Clamp a requested write into the limits, then each change from `current` to its
    maximum step. RefusedWrite for an unknown knob or a non-finite value.

    `current` lies inside the limits (the shield refuses to start elsewhere), so a change cut
    to the maximum step still ends inside them.
    """
    values: dict[str, float] = {}
    clamps = []
    for name, value in requested.items():
        if name not in limits:
            raise RefusedWrite(f"unknown knob {name!r}")
        number = float(value)
        if not math.isfinite(number):
            raise RefusedWrite(f"{name} = {number} is not a finite value")
        knob = limits[name]
        target, rules = number, []
        if target < knob.low:
            target, rules = knob.low, [f"{knob.low_rule} low {knob.low:g}"]
        elif target > knob.high:
            target, rules = knob.high, [f"{knob.high_rule} high {knob.high:g}"]
        if knob.max_step is not None and name in current:
            change = target - current[name]
            if abs(change) > knob.max_step:
                target = current[name] + math.copysign(knob.max_step, change)
                rules.append(f"max step {knob.max_step:g}")
        if rules:
            clamps.append({"knob": name, "from": number, "to": target, "rule": ", ".join(rules)})
        values[name] = target
    return WriteDecision(values, tuple(clamps))


# --- what every command wraps an apparatus in ---------------------------------------------


@dataclass(frozen=True)
class ShieldOptions:
    """How a command shields the apparatus it opens: site limits and maximum steps (JSON
    objects by knob, as `--limits` and `--max-step` take them), the limit on one driver
    call, and where the audit records go (None: the newest MEMORY_AUDIT_RECORDS in memory).
    `simulators`: shield a simulated apparatus too (an adaptation audits every call on
    whatever it adapts to); drivers loaded by import path are always shielded."""

    site_limits: Mapping[str, Any] = field(default_factory=dict)
    max_step: Mapping[str, Any] = field(default_factory=dict)
    call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S
    audit: AuditSink | None = None
    simulators: bool = False
    unit: str = "1"

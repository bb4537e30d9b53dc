"""`alignrl calibrate`: a champion adapted to one microscope in ten alignments, by
calibrating the posterior that walks and ends its alignments (issue 21).

The policy (a champion or any export whose task ends at the focus posterior,
finish_at_posterior, and approaches every setting from below) runs a session of
`alignments` on the apparatus, every write through the shield as in `alignrl evaluate`; the
readings of those alignments calibrate the column's reading model
(alignrl/posterior/calibration.py: no optimum needed, a driver that cannot tell its own is
calibrated alike); the policy is then exported to `out` (safetensors, with its learner state
where it has one) with that column as its posterior's (`task_options.posterior_column`),
read with the far noise fitted with it (`posterior_far_noise`: searched over
FAR_NOISE_SEARCHED, or the one given), stopping at CALIBRATED_STOP (`stop_when_sure`,
`probe_until_sure`), and `calibration.json`
beside it says what was read and found. The network is the policy's own, tensor for tensor:
what changes is what its posterior knows of the column, and how sure it must be.

Every reading of an alignment but its first is approached from below, so those readings
cannot tell the column's backlash. After each alignment `from_above` more readings (default
FROM_ABOVE: two) are taken approached from above, at settings the alignment read from
below on the curve's flank (the widths nearest twice the alignment's narrowest): the same
settings on the other branch, whose shift says the backlash.

Nothing is written to the column before everything that can be checked without it is
(`plan_calibration`: the counts, the search's memory, the output folder, the policy, its
card against its learner state and the knob intervals its export will carry; the session
then checks the apparatus's knob and the spec before its first write). Nothing calibrated
is written from readings that do not support a column (alignrl/posterior/calibration.py,
`check_support`: widths that do not follow the setting, or a focus the limits keep out of
reach): an UncalibratedError says why. The export and calibration.json are published
together, whole or not at all: an interrupted calibration leaves nothing.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alignrl.apparatus.base import Apparatus
from alignrl.posterior.calibration import (
    ALIGNMENTS,
    CALIBRATED,
    CALIBRATED_STOP,
    COLUMN_FIELDS,
    FROM_ABOVE,
    POPULATION,
    ROUNDS,
    Calibration,
    calibrate,
    check_far_noise,
    check_search,
    check_support,
    measured_sweeps,
    sweeps_of,
)

__all__ = [
    "CALIBRATION_FILE",
    "Calibrated",
    "CalibrationPlan",
    "calibrate_policy",
    "calibrated_overrides",
    "plan_calibration",
    "read_from_above",
    "run_calibration",
]

CALIBRATION_FILE = "calibration.json"


@dataclass(frozen=True)
class Calibrated:
    """What `calibrate_policy` did: the export folder, the session it ran, the calibration,
    and how many readings from above it took besides the session's."""

    out: Path
    session: Any  # alignrl.evaluation.session.SessionResult
    calibration: Calibration
    seconds: float
    from_above: int = 0


@dataclass(frozen=True)
class CalibrationPlan:
    """A calibration checked before anything touches a column (`plan_calibration`): the
    policy to run, its source (learner state loaded and checked against its card), where
    it goes, and the search."""

    spec: str
    policy: Any  # alignrl.deploy.policy.DeployablePolicy
    source: Any  # alignrl.runs.sources.PolicySource
    out: Path
    alignments: int = ALIGNMENTS
    population: int = POPULATION
    rounds: int = ROUNDS
    from_above: int = FROM_ABOVE
    far_noise: float | None = None
    force: bool = False
    started: float = 0.0


def calibrated_overrides(
    column: dict[str, float], far_noise: float = CALIBRATED["far_noise"]
) -> list[str]:
    """The `--set` assignments that give a policy this calibrated column (a YAML mapping),
    the far noise it was fitted with and the calibrated stop (CALIBRATED_STOP)."""
    values = ", ".join(f"{name}: {column[name]:.9g}" for name in COLUMN_FIELDS)
    return [
        f"task_options.posterior_column={{{values}}}",
        f"task_options.posterior_far_noise={far_noise:.9g}",
        f"task_options.stop_when_sure={CALIBRATED_STOP}",
        f"task_options.probe_until_sure={CALIBRATED_STOP}",
    ]


def _check_policy(spec: str, task: Any) -> None:
    posterior, below = task.ending.at == "posterior", task.ending.approach_from_below
    if len(task.knobs) != 1 or not (posterior and below):
        raise ValueError(
            f"{spec}: calibrate adapts a one-knob focus policy whose alignments end at its "
            f"posterior and approach every setting from below (task options "
            f"finish_at_posterior and approach_from_below, as champion:focus-v2); this one's "
            f"task aligns {', '.join(task.knobs)} with finish_at_posterior="
            f"{posterior}, approach_from_below={below}"
        )


def plan_calibration(
    spec: str,
    out: str | Path,
    alignments: int = ALIGNMENTS,
    population: int = POPULATION,
    rounds: int = ROUNDS,
    from_above: int = FROM_ABOVE,
    far_noise: float | None = None,
    force: bool = False,
) -> CalibrationPlan:
    """Everything a calibration can check before it opens the apparatus: the counts, the
    search (its memory too: MAX_SEARCH_BYTES), the far noise, the output folder (a folder
    that can be written, empty unless `force`), the policy (one that can be calibrated), its
    card against its learner state and its recorded knob intervals (what the export will
    read). ValueError (ExportError, PolicySpecError) naming what is wrong."""
    from alignrl.deploy.export import check_out_folder, check_within_recorded, knob_limits
    from alignrl.deploy.policy import load_deployable
    from alignrl.runs.sources import resolve_source

    started = time.perf_counter()
    if alignments < 1:
        raise ValueError(f"a calibration runs at least one alignment, got {alignments}")
    if from_above < 0:
        raise ValueError(f"from_above counts readings per alignment, got {from_above}")
    check_search(population, rounds)
    check_far_noise(far_noise)
    out = Path(out)
    check_out_folder(out, force)
    policy = load_deployable(spec)
    _check_policy(spec, policy.task)
    source = resolve_source(spec)  # its learner state, where it has one, against its card
    # the intervals the export will carry: recorded, no wider than its run's, or refused now
    check_within_recorded(source, knob_limits(source), str(source.config_file or spec))
    return CalibrationPlan(
        spec,
        policy,
        source,
        out,
        alignments,
        population,
        rounds,
        from_above,
        far_noise,
        force,
        started,
    )


def calibrate_policy(
    spec: str,
    apparatus: Apparatus,
    out: str | Path,
    alignments: int = ALIGNMENTS,
    seed: int = 0,
    spec_px: float | None = None,
    budget: int | None = None,
    population: int = POPULATION,
    rounds: int = ROUNDS,
    force: bool = False,
    command: str | None = None,
    from_above: int = FROM_ABOVE,
    on_alignment: Callable[[Any], None] | None = None,
    on_round: Callable[[int, int, float], None] | None = None,
    far_noise: float | None = None,
) -> Calibrated:
    """Calibrate policy `spec` on `apparatus` and export it to `out` (module docstring):
    the far noise searched with the column, or `far_noise` where given. ValueError (before
    any alignment) for whatever `plan_calibration` refuses; UncalibratedError (after the
    alignments, nothing written) for readings that support no calibration; whatever
    run_session, the apparatus and the export refuse."""
    plan = plan_calibration(spec, out, alignments, population, rounds, from_above, far_noise, force)
    return run_calibration(plan, apparatus, seed, spec_px, budget, command, on_alignment, on_round)


def _limits(apparatus: Apparatus, knob: str) -> tuple[float, float]:
    """Where the shield lets `knob` go: its site limits within the interval (the interval
    where the apparatus is not shielded)."""
    limits = getattr(apparatus, "limits", None)
    if isinstance(limits, dict) and knob in limits:
        return float(limits[knob].low), float(limits[knob].high)
    low, high = apparatus.knobs[knob]
    return float(low), float(high)


def run_calibration(
    plan: CalibrationPlan,
    apparatus: Apparatus,
    seed: int = 0,
    spec_px: float | None = None,
    budget: int | None = None,
    command: str | None = None,
    on_alignment: Callable[[Any], None] | None = None,
    on_round: Callable[[int, int, float], None] | None = None,
) -> Calibrated:
    """The calibration `plan` checked: its alignments on `apparatus`, the search, the check
    that the readings support the column found (check_support: UncalibratedError, nothing
    written), and the export with calibration.json, published whole or not at all."""
    from alignrl.deploy.export import export_policy, with_acting_options
    from alignrl.evaluation.controllers import PolicyController
    from alignrl.evaluation.session import run_session

    policy = plan.policy
    controller = PolicyController(
        name=plan.spec, act=policy.act, task=policy.task, history=policy.history
    )
    knob = policy.task.knobs[0]
    overshoot = policy.task.ending.backlash_overshoot
    above: list[list[tuple[float, float, float]]] = []

    def after(record: Any) -> None:
        above.append(
            read_from_above(apparatus, knob, record.trajectory, plan.from_above, overshoot)
        )
        if on_alignment is not None:
            on_alignment(record)

    session = run_session(
        controller,
        apparatus,
        policy.task,
        scenarios=plan.alignments,
        seed=seed,
        spec_px=spec_px,
        budget=budget,
        on_scenario=after,
    )
    low, high = (float(value) for value in apparatus.knobs[knob])
    sweeps = measured_sweeps(
        [
            [*sweep, *(((v - low) / (high - low), width, side) for v, width, side in extra)]
            for sweep, extra in zip(sweeps_of(session.records, low, high), above, strict=True)
        ]
    )
    calibration = calibrate(
        sweeps,
        population=plan.population,
        rounds=plan.rounds,
        seed=seed,
        on_round=on_round,
        far_noise=plan.far_noise,
    )
    check_support(
        sweeps,
        calibration,
        (low, high),
        _limits(apparatus, knob),
        knob,
        policy.task.success.relative,
        seed,
    )
    overrides = calibrated_overrides(calibration.column, calibration.far_noise)
    source = with_acting_options(plan.source, overrides)
    record = {
        "format": "alignrl-calibration-1",
        "policy": plan.spec,
        "command": command,
        "seed": seed,
        "alignments": plan.alignments,
        "from_above": plan.from_above,
        "session": {
            "successes": session.successes,
            "median_acquisitions": session.median_acquisitions,
            "threshold_px": _finite(session.median_threshold_px),
        },
        "readings": calibration.readings,
        "far_noise": calibration.far_noise,  # with which the column was fitted
        # where it was searched (null: given)
        "far_noise_searched": calibration.far_noise_searched,  # JSON writes it as a list
        "log_evidence": calibration.log_evidence,
        "progress": list(calibration.progress),
        "column": calibration.column,
        "interval": [low, high],
        # per alignment: (setting as a fraction of the interval, width px or null: no
        # edges, side: +1 from below, -1 from above, 0 unknown)
        "sweeps": [
            [[u, width if math.isfinite(width) else None, side] for u, width, side in sweep]
            for sweep in sweeps
        ],
    }
    export_policy(  # calibration.json in the same folder, published with it
        source,
        plan.out,
        "safetensors",
        force=plan.force,
        command=command,
        learner_state=source.learner_state,
        named=plan.spec,
        extra_files={CALIBRATION_FILE: json.dumps(record, indent=2) + "\n"},
    )
    took = sum(len(readings) for readings in above)
    seconds = time.perf_counter() - plan.started
    return Calibrated(plan.out, session, calibration, seconds, took)


def read_from_above(
    apparatus: Apparatus,
    knob: str,
    trajectory: Any,
    count: int,
    overshoot: float,
) -> list[tuple[float, float, float]]:
    """`count` readings (setting in the knob's units, width px, -1) approached from above
    after an alignment whose `trajectory` ((setting, width or None), ...) was read from
    below but for its first: at its measured settings whose widths lie nearest twice its
    narrowest (on the flank, where a shift of the setting shows), each written `overshoot`
    x the interval above first, then the setting (within the interval: no higher than its
    top, and a setting at the top is left out)."""
    from alignrl.evaluation.controllers import measure_width

    if count == 0:
        return []
    low, high = (float(value) for value in apparatus.knobs[knob])
    high = min(high, _limits(apparatus, knob)[1])  # the shield's: site limits within
    measured = {
        float(setting): float(width)
        for setting, width in list(trajectory)[1:]
        if width is not None and math.isfinite(width) and float(setting) < high
    }
    if not measured:
        return []
    narrowest = min(measured.values())
    flank = sorted(measured, key=lambda setting: abs(math.log(measured[setting] / narrowest / 2)))
    readings = []
    for setting in flank[:count]:
        apparatus.write({knob: min(high, setting + overshoot * (high - low))})
        apparatus.write({knob: setting})
        readings.append((setting, measure_width(apparatus), -1.0))
    return readings


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None

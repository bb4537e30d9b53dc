"""`alignrl champions`: the shipped champions beside the classical controllers, each on
instruments it never trained on, measured now (the first part of `make run`).

* focus: `champion:focus-v2` on every instrument of the held-out set (docs/physics.md,
  "Instrument sets"), beside the hyperbola fit and golden-section on the same columns from
  the same starts; its figures calibrated on each column (`alignrl calibrate`, minutes a
  column) are the recorded ones, named as such;
* stigmation, aperture and the whole column: their champions (trained on `synthetic`) on
  their tasks' held-out sets (`heldout-stigmation`, `heldout-aperture`, `heldout-column`:
  columns in other units, turned, coupled, mirrored), beside the task's classical
  controllers, the searches and the model-based solves: today's figures, good or not.

Readings are analytic (computed from the probe, no images) so that the whole comparison
takes a minute or two on two cores; `alignrl evaluate --set heldout --task TASK` without
`--analytic` runs the same on images.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from alignrl.cli.common import _emit, _scenarios, _seed
from alignrl.cli.sessions import _progress, _trained_controller

# Where a champion of each task is shown beside the classical controllers
HELD_OUT_SET = "heldout"
FOCUS = "champion:focus-v2"
FOCUS_CLASSICAL = ("hyperbola", "golden-section")
COLUMN_STAGES = (
    "champion:column-focus-aperture-v1",
    "champion:column-focus-aperture-v1",
    "champion:column-focus-stigmation-v1",
    "champion:column-focus-stigmation-v1",
    "champion:column-focus-stigmation-v1",
)
COLUMN_NAME = "column-*-v1 (A A S S S)"  # the stages: focus-aperture twice, then -stigmation
# task -> the champion's stages (one, or the column's sequence), judged on the task's
# held-out set
OTHER_TASKS = {
    "stigmation": ("champion:stigmation-v1",),
    "aperture": ("champion:aperture-v1",),
    "column": COLUMN_STAGES,
}
# Recorded, not measured here: a calibration takes minutes a column (docs/benchmarks.md,
# "focus-v2 calibrated on the microscope")
CALIBRATED = (
    "focus-v2 calibrated on ten alignments of each held-out column (alignrl calibrate; "
    "minutes a column, not run here): 699/700 on images at medians of 2 to 4 acquisitions "
    "(docs/benchmarks.md)"
)


@dataclass(frozen=True)
class Showcase:
    """What `champions` measured: per task its held-out set's results (champion first, then
    the classical controllers), focus first."""

    focus: Sequence[Any]
    tasks: dict[str, Sequence[Any]]


def _controllers(policies: Sequence[str]) -> Any:
    """The champion (or the column's stages in sequence), each stage named by its
    champion's name, not its member's."""
    from alignrl.evaluation.controllers import SequenceController

    stages = tuple(
        dataclasses.replace(_trained_controller(policy), name=policy.removeprefix("champion:"))
        for policy in policies
    )
    return stages[0] if len(stages) == 1 else SequenceController(stages, label=COLUMN_NAME)


def measure(scenarios: int, seed: int, bar: Any) -> Showcase:
    """Every session of the module docstring, `scenarios` alignments each per instrument of
    each task's held-out set, at `seed`; `bar` counts the alignments."""
    from alignrl.apparatus.instruments import instrument_names, task_set
    from alignrl.envs.task import get_task
    from alignrl.evaluation.baselines import CLASSICAL, task_baselines
    from alignrl.evaluation.instrument_sets import run_set

    lineups = {"focus": [_controllers((FOCUS,)), *(CLASSICAL[name]() for name in FOCUS_CLASSICAL)]}
    for name, policies in OTHER_TASKS.items():
        lineups[name] = [
            _controllers(policies),
            *(make() for make in task_baselines(name).values()),
        ]
    results = {}
    for name, controllers in lineups.items():
        task, held_out = get_task(name), task_set(HELD_OUT_SET, name)
        count = len(instrument_names(held_out))
        sets = []
        for controller in controllers:
            bar.set_description(f"{controller.name} on set:{held_out} ({count} instruments)")
            sets.append(
                run_set(
                    controller,
                    HELD_OUT_SET,
                    task,
                    scenarios=scenarios,
                    seed=seed,
                    analytic=True,
                    on_scenario=lambda _result: bar.update(1),
                )
            )
        results[name] = tuple(sets)
    focus = results.pop("focus")
    return Showcase(focus, results)


def alignments(scenarios: int) -> int:
    """How many alignments `measure` runs."""
    from alignrl.apparatus.instruments import instrument_names, task_set
    from alignrl.evaluation.baselines import task_baselines

    focus = len(instrument_names(HELD_OUT_SET)) * (1 + len(FOCUS_CLASSICAL))
    others = sum(
        len(instrument_names(task_set(HELD_OUT_SET, name))) * (1 + len(task_baselines(name)))
        for name in OTHER_TASKS
    )
    return scenarios * (focus + others)


def cmd_champions(args: argparse.Namespace) -> int:
    from alignrl.evaluation import instrument_sets as sets

    if not 1 <= args.scenarios <= 1000:
        raise ValueError(f"--scenarios must be in 1-1000, got {args.scenarios}")
    bar = _progress(args, alignments(args.scenarios))
    try:
        shown = measure(args.scenarios, args.seed, bar)
    except KeyboardInterrupt:
        bar.close()
        return 130
    bar.close()
    first = shown.focus[0]
    lines = [
        "the shipped champions beside the classical controllers, on columns no training run "
        f"saw (analytic readings, seed {args.seed})",
        "",
        f"focus {sets.set_heading(first)}:",
        "",
        *sets.set_table(shown.focus),
        "",
        *(sets.set_summary(result) for result in shown.focus),
        CALIBRATED,
    ]
    payload: dict[str, Any] = {
        "seed": args.seed,
        "scenarios": args.scenarios,
        "focus": {result.controller: result.to_dict("test") for result in shown.focus},
        "calibrated": CALIBRATED,
    }
    for name, results in shown.tasks.items():
        heading = sets.set_heading(results[0])
        lines += ["", f"{name} {heading} (its champion trained on synthetic):", ""]
        lines += [*sets.set_table(results), ""]
        lines += [sets.set_summary(result) for result in results]
        payload[name] = {result.controller: result.to_dict("test") for result in results}
    _emit(payload, args.json, lines)
    return 0


def add_champions_parser(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = verbs.add_parser(
        "champions",
        help="the shipped champions beside the classical controllers, on columns never trained on",
        description="The shipped champions beside the classical controllers, each on columns "
        "it never trained on, measured now: focus-v2 on every held-out instrument beside the "
        "hyperbola fit and golden-section; the stigmation, aperture and column champions on "
        "their tasks' held-out sets beside their tasks' classical controllers. Analytic "
        "readings (no images); the first part of `make run`.",
    )
    parser.add_argument(
        "--scenarios",
        type=_scenarios,
        default=10,
        help="alignments per held-out instrument (default 10)",
    )
    parser.add_argument("--seed", type=_seed, default=0, help="the sessions' seed (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="machine-readable summary")
    parser.set_defaults(handler=cmd_champions)

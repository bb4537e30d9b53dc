"""The knobs outside a task at the start of its episode (alignrl/envs/core.py, `begin`; an
evaluation session's start alike): at their optimum where the apparatus knows it, or, where
the task names them in its `context`, misaligned within a reach of it, drawn from the
scenario's seed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from alignrl.apparatus.base import Apparatus, knows_optimum

__all__ = ["CONTEXT_STREAM", "align_others"]

CONTEXT_STREAM = 2  # second entropy word of the generator of a task's context offsets


def align_others(
    unit: Apparatus,
    knobs: Sequence[str],
    context: Mapping[str, float] | None = None,
    seed: int | None = None,
) -> None:
    """Set the knobs of `unit` outside `knobs` (a task's) to their optimum, where the
    apparatus knows it: a stigmation episode starts in focus. Nothing is written where the
    knobs are there already, or where the apparatus has no secret (a real column).

    `context` (Task.context) misaligns some of them instead: each named knob goes anywhere
    within that offset of its optimum (uniformly, inside its interval), drawn from a
    generator of (`seed`, CONTEXT_STREAM), so that a scenario seed fixes it; knobs the
    apparatus lacks are passed over."""
    if not knows_optimum(unit) or set(unit.knobs) <= set(knobs):
        return
    current = unit.read()
    targets = {
        knob: float(value)
        for knob, value in unit.optimum().items()
        if knob in unit.knobs and knob not in knobs
    }
    if context:
        rng = np.random.default_rng(None if seed is None else [seed, CONTEXT_STREAM])
        for knob in unit.knobs:  # the apparatus's order: the same draws every time
            if knob in targets and knob in context:
                low, high = unit.knobs[knob]
                centre, offset = targets[knob], float(context[knob])
                targets[knob] = float(
                    rng.uniform(max(low, centre - offset), min(high, centre + offset))
                )
    others = {knob: value for knob, value in targets.items() if value != current[knob]}
    if others:
        unit.write(others)

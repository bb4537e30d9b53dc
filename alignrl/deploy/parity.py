"""The parity check of an export: does the written policy file, loaded back, give the member's
own actions? `check_parity` compares it with `Agent.act(deterministic=True)` on random
histories such as the env produces, in action units and, for knob_step, in the apparatus's
units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from alignrl.agents.agent import Agent
from alignrl.deploy.graph import PolicyGraph, Runner, random_histories
from alignrl.envs.task import knob_change

__all__ = ["PARITY_HISTORIES", "PARITY_TOLERANCE", "Parity", "check_parity"]

PARITY_HISTORIES = 1000  # random histories the written file is checked on
# Largest |exported - PyTorch| allowed, in action units. Two float32 runtimes round a
# 256-wide network differently by about 1e-5 (onnxruntime against PyTorch on focus-v1:
# 1.1e-5, each about 6e-6 from a float64 evaluation); an export fault (a wrong weight, a
# wrong operator) shows as 1e-2 or more, and 1e-4 of a step is far below any knob's
# resolution (25 V steps: 2.5 mV).
PARITY_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Parity:
    """How closely the written file reproduces the PyTorch policy on random histories.

    max_abs_difference: |exported action - Agent.act(deterministic=True)|, action units;
    knob_step_max_abs_difference: |exported knob_step - that action x max_step|, instrument
    units.
    """

    histories: int
    max_abs_difference: float
    knob_step_max_abs_difference: float
    tolerance: float
    knob_step_tolerance: float
    runtime: str
    reference: str = "Agent.act(deterministic=True)"

    @property
    def passed(self) -> bool:
        return (
            self.max_abs_difference <= self.tolerance
            and self.knob_step_max_abs_difference <= self.knob_step_tolerance
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "histories": self.histories,
            "max_abs_difference": self.max_abs_difference,
            "knob_step_max_abs_difference": self.knob_step_max_abs_difference,
            # A field of card.json's format (alignrl-policy-card-1), null since the policies
            # keep no memory beyond their history window: kept so that cards stay one format.
            "memory_max_abs_difference": None,
            "tolerance": self.tolerance,
            "knob_step_tolerance": self.knob_step_tolerance,
            "runtime": self.runtime,
            "reference": self.reference,
            "passed": self.passed,
        }


def _max_difference(left: np.ndarray, right: np.ndarray) -> float:
    if left.shape != right.shape:
        return float("inf")
    difference = np.abs(left.astype(np.float64) - right.astype(np.float64))
    return float(np.nanmax(difference)) if np.all(np.isfinite(difference)) else float("inf")


def check_parity(
    agent: Agent,
    graph: PolicyGraph,
    run: Runner,
    runtime: str,
    histories: int = PARITY_HISTORIES,
    seed: int = 0,
    tolerance: float = PARITY_TOLERANCE,
) -> Parity:
    """Compare an exported graph (`run`) with the member on `histories` random histories
    (random_histories)."""
    rng = np.random.default_rng(seed)
    inputs = random_histories(histories, graph.history, graph.features, rng, graph.knobs)
    expected = agent.act(inputs, deterministic=True).astype(np.float64)  #   (histories, k+1)
    outputs = run({"history": inputs})
    max_step = graph.max_step.numpy().astype(np.float64)
    action_difference = _max_difference(outputs["action"], expected)
    floor = graph.move_floor.numpy().astype(np.float64)
    asked = knob_change(expected[:, : graph.knobs], max_step, graph.action_power, floor)
    knob_difference = _max_difference(outputs["knob_step"], asked)
    return Parity(
        histories=histories,
        max_abs_difference=action_difference,
        knob_step_max_abs_difference=knob_difference,
        tolerance=tolerance,
        knob_step_tolerance=tolerance * max(1.0, float(max_step.max())),
        runtime=runtime,
    )

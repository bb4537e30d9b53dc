"""The deployable policy of one aligner as a graph, and what running it takes.

`PolicyGraph` is exactly the deterministic policy of `Agent.act(deterministic=True)`:

    history    float32 (batch, H, F)  the env's history (alignrl/envs/core.py), as it is
      -> history encoder -> mean of the policy head -> tanh -> clip to [-1, 1]
    action     float32 (batch, k + 1) k knob actions, then the stop component (stop if > 0)
    knob_step  float32 (batch, k)     sign(a) (|a|^action_power x max_step + move_floor),
                                      a = action[:, :k]: the knob change asked for, in the
                                      apparatus's units (volts for a lens); power 1 and no
                                      floor (the defaults): a x max_step

The learners apply no normalisation of their own: the env already scales every feature of
the history (knobs to [-1, 1], quality as log(width / reference)), so there is nothing to fold
in but the action's squashing, clipping and scaling. The history window is the policy's whole
memory: the graph keeps no state from one call to the next.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.envs.core import feature_layout, observation_bounds
from alignrl.runs.sources import ExportError

__all__ = [
    "PolicyGraph",
    "PolicyInterface",
    "Runner",
    "graph_signature",
    "move_floors",
    "random_histories",
]

FULLY_PADDED_SHARE = 0.01  # share of parity histories with no valid row (a zero observation)


class PolicyGraph(nn.Module):
    """The deployable policy of one aligner: history -> action, knob_step. A copy of the
    policy network alone (no critics, no optimizer); the member itself is left untouched."""

    def __init__(
        self,
        agent: Agent,
        max_step: Sequence[float],
        action_power: float = 1.0,
        move_floor: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        self.action_power = float(action_power)  # the task's (alignrl.envs.task.knob_change)
        policy = agent.learner.acting_network  # SAC's actor, PPO's policy
        self.encoder = copy.deepcopy(policy.encoder)
        self.head = copy.deepcopy(policy.head)
        # SAC's head gives [mean, log_std]; PPO's gives the mean (its std is a parameter).
        self.action_dim = agent.spec.action_dim
        self.history, self.features = agent.spec.observation_shape
        self.knobs = len(max_step)
        if self.knobs != self.action_dim - 1:
            raise ExportError(
                f"member {agent.id!r} acts on {self.action_dim - 1} knob(s); "
                f"{self.knobs} max step(s) given"
            )
        self.register_buffer("max_step", torch.tensor(list(max_step), dtype=torch.float32))
        floor = [0.0] * self.knobs if move_floor is None else list(move_floor)
        self.register_buffer("move_floor", torch.tensor(floor, dtype=torch.float32))
        self.floored = any(value != 0 for value in floor)  # the task's move_floor x interval
        # Parameters keep requires_grad, as the member's own: with it off, PyTorch's CPU
        # kernels take other paths whose float32 rounding differs (1e-6 on a trained GTrXL).
        self.eval()

    @property
    def input_names(self) -> list[str]:
        return ["history"]

    @property
    def output_names(self) -> list[str]:
        return ["action", "knob_step"]

    def signature(self) -> dict[str, list[dict[str, Any]]]:
        """Names, dtypes and shapes of the inputs and outputs ("batch": any size)."""
        return graph_signature(self.history, self.features, self.knobs)

    def forward(self, history: Tensor) -> tuple[Tensor, Tensor]:
        encoded, _ = self.encoder(history)  #                                              (B, D)
        mean = self.head(encoded)[:, : self.action_dim]  #                                  (B, k+1)
        # Agent.act(deterministic=True) is tanh(mean) for SAC and PPO alike; the clip only
        # pins the contract (float32 tanh can round to exactly 1, never beyond).
        action = torch.tanh(mean).clamp(-1.0, 1.0)  #                                   (B, k+1)
        knob_action = action[:, : self.knobs]  #                                          (B, k)
        if self.action_power != 1.0:  # as Task.knob_change, which AlignmentEpisodes.step uses
            knob_action = torch.sign(knob_action) * knob_action.abs() ** self.action_power
        knob_step = knob_action * self.max_step  #                                         (B, k)
        if self.floored:
            knob_step = knob_step + torch.sign(knob_action) * self.move_floor
        return action, knob_step


def graph_signature(history: int, features: int, knobs: int) -> dict[str, list[dict[str, Any]]]:
    """The inputs and outputs of a policy graph: per tensor its name, dtype and shape
    ("batch": any size), as card.json lists them."""
    shapes = {
        "history": ["batch", history, features],
        "action": ["batch", knobs + 1],
        "knob_step": ["batch", knobs],
    }
    return {
        side: [{"name": name, "dtype": "float32", "shape": shapes[name]} for name in names]
        for side, names in (("inputs", ["history"]), ("outputs", ["action", "knob_step"]))
    }


def random_histories(
    count: int, history: int, features: int, rng: np.random.Generator, knobs: int = 1
) -> np.ndarray:
    """Histories such as the env produces: (count, history, features) float32, each with 1 to
    `history` valid rows at the end and zero padding in front, feature values drawn within
    their bounds (alignrl/envs/core.py); features beyond a row of `knobs` knobs are the
    task's extras. About 1 in 100 is all padding."""
    extras = features - 5 - 2 * knobs
    if knobs < 1 or extras < 0:
        raise ValueError(f"a history row of {features} features does not fit {knobs} knob(s)")
    low, high = observation_bounds(knobs, extras)
    layout = feature_layout(knobs, extras)
    rows = rng.uniform(low, high, (count, history, features)).astype(np.float32)
    rows[..., layout["valid"]] = 1.0
    rows[..., layout["measured"]] = rng.integers(0, 2, (count, history, 1))
    valid = rng.integers(1, history + 1, count)
    valid[rng.random(count) < FULLY_PADDED_SHARE] = 0
    padding = np.arange(history)[None, :] < (history - valid)[:, None]  #         (count, history)
    rows[padding] = 0.0
    return rows


# A policy file, opened: named float32 inputs, batch first -> every named output.
def move_floors(move_floor: float, knobs: Sequence[Mapping[str, Any]]) -> list[float]:
    """Each knob's least move (its units) on the intervals of a card's or run's `knobs`
    (low, high): the task's move_floor x the interval's width, as the env takes it."""
    return [move_floor * (float(knob["high"]) - float(knob["low"])) for knob in knobs]


Runner = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass(frozen=True)
class PolicyInterface:
    """What running a policy file takes besides the file: the names of its inputs and
    outputs, each knob's max_step, and the member's spec, which only a safetensors file
    needs (it holds weights, not a network). From the PolicyGraph when exporting, from
    card.json when loading."""

    input_names: list[str]
    output_names: list[str]
    max_step: list[float]
    spec: MemberSpec | None = None
    action_power: float = 1.0  # the task's: knob_step = sign(a) (|a|^power x max_step + floor)
    move_floor: list[float] | None = None  # per knob, its units: the task's floor x interval

"""The critics' secret in hindsight, on an apparatus that cannot tell its optimum (a real
column): `HindsightSecrets` holds each blind slot's episode until it ends, then gives its
transitions the secrets (optimum - setting, as a fraction of the knob's interval) of an
optimum found from the episode's readings; alignrl/posterior/hindsight.py (`PooledCurve`)
is the one-knob stand-in that draws it from the column's pooled focus curve.

Settings are fractions of each knob's interval, readings edge widths in pixels. numpy only:
this is the envs' secret told late, not a learner.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Literal, get_args

import numpy as np

from alignrl.posterior.hindsight import PooledCurve
from alignrl.transitions import Transition

__all__ = ["HINDSIGHT_OPTIMA", "HindsightOptimum", "HindsightSecrets"]

# What stands in for an episode's optimum in hindsight (alignrl.config.adaptation's section
# takes the same names).
HindsightOptimum = Literal["posterior", "sharpest"]
HINDSIGHT_OPTIMA: tuple[str, ...] = get_args(HindsightOptimum)


class HindsightSecrets:
    """The critics' secret on an apparatus that cannot tell its optimum (a real column).

    Pre-trained critics read the secret (optimum - setting, as a fraction of the interval);
    a column cannot tell them, and zeros in its place tell them "at the optimum" at every
    step, which misleads the policy they train. Here each episode's transitions on such a
    slot are held until the episode ends; then a stand-in for its optimum, found in
    hindsight from the episode's readings (the verification image included), gives the
    secrets they are stored with. `optimum` says which stand-in:

    * "sharpest": the setting of the episode's sharpest reading. An aligned episode ends
      within spec of the optimum, so it is off by less than the spec's width of the focus
      curve; but an episode that stopped on a reading at the spec's edge is told that it
      stopped at the optimum, and its critics learn that one more move there only loses.
    * "posterior" (one knob): a draw from the optimum's posterior given the episode's
      readings and the column's focus curve pooled over earlier episodes (PooledCurve);
      "sharpest" until the curve is known, and for tasks of more than one knob.

    Slots whose apparatus tells its optimum (`blind` false) are not held: their secrets are
    the true ones. Transitions of an episode still in flight when a run is killed are lost
    with it, as the episode itself is.
    """

    def __init__(
        self, blind: np.ndarray, optimum: HindsightOptimum = "posterior", seed: int = 0
    ) -> None:
        if optimum not in HINDSIGHT_OPTIMA:
            raise ValueError(f"hindsight optimum: one of {HINDSIGHT_OPTIMA}, got {optimum!r}")
        self.blind = np.asarray(blind, bool)
        self.optimum = optimum
        self.posterior = PooledCurve(seed)
        n = len(self.blind)
        self._positions: list[list[np.ndarray]] = [[] for _ in range(n)]
        self._widths: list[list[float]] = [[] for _ in range(n)]
        self._held: list[list[Transition]] = [[] for _ in range(n)]

    def start(self, infos: dict[str, Any]) -> None:
        """The first reading of every blind slot's episode (the infos of `reset`)."""
        for slot in np.flatnonzero(self.blind):
            self._begin(slot, infos["position"][slot], infos["edge_width_px"][slot])

    def step(self, step: Transition, infos: dict[str, Any]) -> list[Transition]:
        """Hold this step of every blind slot (`step`: one row per slot, its secrets as
        the apparatus told them); returns the transitions of the episodes that ended, one
        Transition per episode, with their hindsight secrets. The next_observation of a
        finished slot is its episode's last history (not the next episode's first)."""
        finished = []
        for slot in np.flatnonzero(self.blind):
            self._held[slot].append(step.rows([slot]))
            self._positions[slot].append(np.asarray(infos["position"][slot], np.float32))
            self._widths[slot].append(float(infos["edge_width_px"][slot]))
            if step.done[slot]:
                finished.append(self._release(slot))
                self._begin(slot, infos["start_position"][slot], infos["start_edge_width_px"][slot])
        return finished

    def _begin(self, slot: int, position: np.ndarray, width: float) -> None:
        self._positions[slot] = [np.asarray(position, np.float32)]
        self._widths[slot] = [float(width)]
        self._held[slot] = []

    def _release(self, slot: int) -> Transition:
        positions = np.stack(self._positions[slot])  # (steps + 1, k)
        widths = np.array(self._widths[slot])
        best = positions[np.nanargmin(widths)] if np.isfinite(widths).any() else positions[-1]
        if self.optimum == "posterior" and positions.shape[1] == 1:
            self.posterior.add(positions[:, 0], widths)
            drawn = self.posterior.sample(positions[:, 0], widths)
            if drawn is not None:
                best = np.array([drawn], np.float32)
        secrets = (best - positions).astype(np.float32)
        episode = Transition.joined(self._held[slot])
        return replace(episode, secret=secrets[:-1], next_secret=secrets[1:])

"""The critics' secret in hindsight, on an apparatus that cannot tell its optimum (a real
column): `HindsightSecrets` holds each blind slot's episode until it ends, then gives its
transitions the secrets (optimum - setting, as a fraction of the knob's interval) of an
optimum found from the episode's readings; `FocusPosterior` is the one-knob stand-in that
draws it from the column's pooled focus curve.

Settings are fractions of each knob's interval, readings edge widths in pixels. numpy only:
this is the envs' secret told late, not a learner.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Literal, get_args

import numpy as np

__all__ = ["HINDSIGHT_OPTIMA", "FocusPosterior", "HindsightOptimum", "HindsightSecrets"]

# What stands in for an episode's optimum in hindsight (alignrl.config's adaptation section
# takes the same names).
HindsightOptimum = Literal["posterior", "sharpest"]
HINDSIGHT_OPTIMA: tuple[str, ...] = get_args(HindsightOptimum)

Transition = tuple[np.ndarray, ...]  # what Agent.observe takes, secrets included


class FocusPosterior:
    """Where a column's optimum lies, in hindsight, from an episode's readings (one knob).

    Near focus a reading of the edge width follows the probe: w^2 = c^2 + a (x - x0)^2, with
    x the setting (a fraction of the interval), x0 the optimum, c the column's best width and
    a its focus curve's steepness. Both c and a belong to the column, not to the episode:
    they are pooled over the last `POOL` finished episodes (the medians of each episode's own
    parabola in x through its readings w^2 within `FIT_SPAN` x its sharpest), and the reading
    noise from pairs of readings at one setting (a stop and its verification image). An episode's
    optimum is then drawn from its posterior on a grid of the interval, so that a stop on a
    reading at the spec's edge is told "about this far from the optimum, on this side with
    these odds", where the sharpest reading alone would tell it "at the optimum".

    Far from focus the image path compresses the reading (a blurred edge reads narrower than
    the probe), so readings beyond `FAR` x c count with `FAR_LOOSENESS` x the noise. The pool
    lives in memory: a resumed run pools afresh from the episodes after the resume.
    """

    POOL = 256
    MIN_EPISODES = 32
    REFIT_EVERY = 16
    FIT_SPAN = 1.5
    DEFAULT_NOISE = 0.04
    FAR = 2.0
    FAR_LOOSENESS = 8.0
    GRID = np.linspace(0.0, 1.0, 2001)

    def __init__(self, seed: int = 0) -> None:
        self._episodes: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.POOL)
        self._rng = np.random.default_rng(seed)
        self._since_fit = 0
        self.curve: tuple[float, float, float] | None = None  # (a, c, relative noise)

    def add(self, positions: np.ndarray, widths: np.ndarray) -> None:
        """One finished episode: its settings (n,) and readings (n,), failed ones NaN."""
        ok = np.isfinite(widths) & (widths > 0)
        if ok.any():
            self._episodes.append((positions[ok], widths[ok]))
            self._since_fit += 1
        if len(self._episodes) >= self.MIN_EPISODES and (
            self.curve is None or self._since_fit >= self.REFIT_EVERY
        ):
            self.curve = self._fit()
            self._since_fit = 0

    def _fit(self) -> tuple[float, float, float] | None:
        slopes, floors, log_ratios = [], [], []
        for x, w in self._episodes:
            near = w <= self.FIT_SPAN * w.min()
            if len(np.unique(x[near])) >= 3:
                weight = 1.0 / w[near] ** 2  # relative noise: w^2 scatters as w^2
                design = np.stack([x[near] ** 2, x[near], np.ones(near.sum())], 1)
                solution = np.linalg.lstsq(
                    design * weight[:, None], w[near] ** 2 * weight, rcond=None
                )[0]
                slope, linear, constant = solution
                floor = constant - linear**2 / (4 * slope) if slope > 0 else -1.0
                if floor > 0:  # a parabola opening upwards over a positive best width
                    slopes.append(slope)
                    floors.append(floor)
            same = np.flatnonzero(np.diff(x) == 0)
            log_ratios.extend(np.log(w[same + 1] / w[same]))
        if len(slopes) < self.MIN_EPISODES // 4:
            return None
        noise = self.DEFAULT_NOISE
        if len(log_ratios) >= 16:  # two readings at one setting differ by sqrt(2) x the noise
            noise = float(np.clip(1.4826 * np.median(np.abs(log_ratios)) / np.sqrt(2), 0.005, 0.2))
        return float(np.median(slopes)), float(np.sqrt(np.median(floors))), noise

    def sample(self, positions: np.ndarray, widths: np.ndarray) -> float | None:
        """A draw of the episode's optimum (a fraction of the interval); None until the
        column's curve is known or where the episode has no reading."""
        ok = np.isfinite(widths) & (widths > 0)
        if self.curve is None or not ok.any():
            return None
        slope, best, noise = self.curve
        x, w = positions[ok], widths[ok]
        model = np.sqrt(best**2 + slope * (x[None, :] - self.GRID[:, None]) ** 2)
        scale = noise * model * np.where(model > self.FAR * best, self.FAR_LOOSENESS, 1.0)
        log_likelihood = -np.sum(0.5 * ((w[None, :] - model) / scale) ** 2 + np.log(scale), 1)
        posterior = np.exp(log_likelihood - log_likelihood.max())
        return float(self._rng.choice(self.GRID, p=posterior / posterior.sum()))


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
      readings and the column's focus curve pooled over earlier episodes (FocusPosterior);
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
        self.posterior = FocusPosterior(seed)
        n = len(self.blind)
        self._positions: list[list[np.ndarray]] = [[] for _ in range(n)]
        self._widths: list[list[float]] = [[] for _ in range(n)]
        self._held: list[list[tuple[np.ndarray, ...]]] = [[] for _ in range(n)]

    def start(self, infos: dict[str, Any]) -> None:
        """The first reading of every blind slot's episode (the infos of `reset`)."""
        for slot in np.flatnonzero(self.blind):
            self._begin(slot, infos["position"][slot], infos["edge_width_px"][slot])

    def step(
        self,
        observation: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        next_observation: np.ndarray,
        done: np.ndarray,
        infos: dict[str, Any],
    ) -> list[Transition]:
        """Hold this step of every blind slot; returns the transitions of the episodes that
        ended, one batch per episode, with their hindsight secrets. `next_observation` of a
        finished slot is its episode's last history (not the next episode's first)."""
        finished = []
        for slot in np.flatnonzero(self.blind):
            self._held[slot].append(
                (observation[slot], action[slot], reward[slot], next_observation[slot], done[slot])
            )
            self._positions[slot].append(np.asarray(infos["position"][slot], np.float32))
            self._widths[slot].append(float(infos["edge_width_px"][slot]))
            if done[slot]:
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
        observation, action, reward, next_observation, done = (
            np.stack(column) for column in zip(*self._held[slot], strict=True)
        )
        return (observation, secrets[:-1], action, reward, next_observation, secrets[1:], done)

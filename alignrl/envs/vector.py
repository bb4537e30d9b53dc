"""VectorAlignmentEnv: N alignment episodes on N apparatus, stepped together (seed section 6.3:
in practice agents train on several microscopes in parallel).

Each slot may be a different instrument (different recordings, synthetic presets, drivers).
Slot i behaves exactly like `AlignmentEnv` reset with seed `seed + i`: the same scenarios,
misalignments, measurements and rewards, step for step (tested). Scenario simulators that
replay one recording are answered in one batched numpy query per step.

Finished episodes reset at once ("same-step" autoreset): the returned observation of such a
slot is the first of its next episode, and `infos["final_observation"]` (and
`final_secret`) hold the last one, with `infos["_final"]` marking the slots that finished.
`acquisitions`, `edge_width_px`, `position`, `threshold_px` and `success` describe the step
just taken, so for a finished slot they are its episode's final figures (`position`: each
knob's setting as a fraction of its interval); `start_position` and `start_edge_width_px`
describe the first reading of the episodes that started in their place. `secret` always goes
with the returned observation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.envs.alignment import aligner_spaces
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import Task, get_task

# make_apparatus_copies lives in alignrl/apparatus/registry.py; importable from here as before.
__all__ = ["VectorAlignmentEnv", "make_apparatus_copies"]


class VectorAlignmentEnv:
    """N aligners on N apparatus; arrays in, arrays out."""

    def __init__(
        self,
        apparatus: Sequence[Apparatus],
        task: Task | str = "focus",
        history: int = 8,
        complexity: float = 1.0,
    ) -> None:
        self.task = get_task(task) if isinstance(task, str) else task
        self.episodes = AlignmentEpisodes(list(apparatus), self.task, history)
        self.num_envs = self.episodes.n
        self.set_complexity(complexity)
        self.single_observation_space, self.single_action_space = aligner_spaces(
            self.episodes.k, history, self.episodes.n_extra
        )
        self._generators: list[np.random.Generator] = []
        self._returns = np.zeros(self.num_envs)
        self._all = np.arange(self.num_envs)

    def set_complexity(self, level: float) -> None:
        self.episodes.set_complexity(level)

    def _start(self, indices: np.ndarray) -> None:
        # The same draws, in the same order, as AlignmentEnv.reset, per slot.
        seeds = [int(self._generators[i].integers(2**31 - 1)) for i in indices]
        self.episodes.begin(indices, seeds)
        actions = np.stack(
            [self._generators[i].uniform(-1.0, 1.0, self.episodes.k) for i in indices]
        )
        self.episodes.misalign(indices, actions)
        self._returns[indices] = 0.0

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start every slot; slot i is seeded with `seed + i` (random when seed is None)."""
        base = seed if seed is not None else int(np.random.SeedSequence().generate_state(1)[0])
        self._generators = [
            gymnasium.utils.seeding.np_random(base + index)[0] for index in range(self.num_envs)
        ]
        self._start(self._all)
        return self.episodes.history.copy(), self._infos(np.zeros(self.num_envs, bool))

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if not self._generators:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, self.episodes.k + 1):
            raise ValueError(
                f"actions must have shape {(self.num_envs, self.episodes.k + 1)}, "
                f"got {actions.shape}"
            )
        reward, done = self.episodes.step(self._all, actions)
        self._returns += reward
        infos = self._infos(done)
        if done.any():
            infos["final_observation"] = self.episodes.history.copy()
            infos["final_secret"] = infos["secret"]
            infos["_final"] = done.copy()
            infos["episode_return"] = np.where(done, self._returns, np.nan)
            self._start(np.flatnonzero(done))
            # The secret that goes with the returned observations: new episodes' where reset.
            infos["secret"] = self.episodes.secrets()
            infos["start_position"] = self.episodes.positions()
            infos["start_edge_width_px"] = self.episodes.width.copy()
        truncated = np.zeros(self.num_envs, bool)
        return self.episodes.history.copy(), reward, done, truncated, infos

    def _infos(self, done: np.ndarray) -> dict[str, Any]:
        episodes = self.episodes
        return {
            "secret": episodes.secrets(),
            "acquisitions": episodes.acquisitions.copy(),
            "edge_width_px": episodes.width.copy(),
            "position": episodes.positions(),
            "threshold_px": episodes.threshold.copy(),
            "success": episodes.successes() & done,
        }

    def close(self) -> None:
        pass

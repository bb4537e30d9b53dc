"""AlignmentEnv: one aligner against the built-in misalignment (Gymnasium).

Card
----
* Apparatus: any (default: the scenario simulator on the shipped 2000 scenarios, `csv:default`).
* Task: default `focus` (knob `defocus`, 10 steps, maximum change 1/4 of the interval).
* Start: each reset picks a new scenario and misaligns it uniformly within the complexity
  window (complexity 1: anywhere in the interval), or as a given misalignment policy says.
* Observation: Box (history, features) of float32, see alignrl/envs/core.py for the columns.
* Action: Box (-1, 1)^(knobs + 1): knob changes scaled by the task's maximum step, then stop.
* Reward: 0 per step inside the interval, -penalty per step that hits a bound, and at the end
  scale x (edge width before - edge width after) in pixels (seed section 4.3).
* Termination: stop (> 0) or the step limit. info: secret (optimum - setting per knob, as a
  fraction of the interval: for critics only), acquisitions, edge_width_px, threshold_px,
  and at the end success.
* Rendering: `render_mode="rgb_array"` (default None): `render()` gives the episode so far as
  an (H, W, 3) uint8 frame, the last image beside the walk on the focus curve
  (alignrl/animation.py; the frames of `alignrl align --gif`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from alignrl.animation import Reading, Scene, draw_frame
from alignrl.apparatus.base import Apparatus
from alignrl.apparatus.filming import take_reading
from alignrl.apparatus.registry import make_apparatus
from alignrl.envs.core import AlignmentEpisodes, observation_bounds
from alignrl.envs.task import Task, get_task

__all__ = ["AlignmentEnv", "MisalignmentPolicy"]

MisalignmentPolicy = Callable[[np.ndarray], np.ndarray]  # misaligner observation -> action


def resolve_apparatus(apparatus: Apparatus | str | None, args: dict | None, seed: int | None):
    if apparatus is None:
        apparatus = "csv:default"
    if isinstance(apparatus, str):
        return make_apparatus(apparatus, args, seed=seed)
    return apparatus


def resolve_task(task: Task | str) -> Task:
    return get_task(task) if isinstance(task, str) else task


def aligner_spaces(n_knobs: int, history: int, extras: int = 0) -> tuple[spaces.Box, spaces.Box]:
    """(observation, action) spaces of an aligner: a history, and knob changes plus stop.
    `extras`: the task's extra features per row (Task.extra_features)."""
    low, high = observation_bounds(n_knobs, extras)
    observation = spaces.Box(
        np.tile(low, (history, 1)), np.tile(high, (history, 1)), dtype=np.float32
    )
    return observation, spaces.Box(-1.0, 1.0, (n_knobs + 1,), dtype=np.float32)


def misaligner_spaces(n_knobs: int, n_design: int = 0) -> tuple[spaces.Box, spaces.Box]:
    """(observation, action) spaces of a misaligner: aligned settings and the complexity in,
    a place in the complexity window per knob out; a designer (`n_design` parameters,
    alignrl.envs.design) reads its draw and the complexity and also answers with a design."""
    leading = n_design if n_design else n_knobs
    observation = spaces.Box(
        np.append(np.full(leading, -1.0), 0.0).astype(np.float32),
        np.ones(leading + 1, np.float32),
        dtype=np.float32,
    )
    return observation, spaces.Box(-1.0, 1.0, (n_knobs + n_design,), dtype=np.float32)


def single_episode(
    apparatus: Apparatus | str | None,
    task: Task | str,
    history: int,
    complexity: float,
    apparatus_args: dict | None,
) -> AlignmentEpisodes:
    """The one-apparatus engine of AlignmentEnv and DuelEnv."""
    unit = resolve_apparatus(apparatus, apparatus_args, seed=None)
    episodes = AlignmentEpisodes([unit], resolve_task(task), history)
    episodes.set_complexity(complexity)
    return episodes


def episode_info(episodes: AlignmentEpisodes, index: int, done: bool) -> dict[str, Any]:
    """The info dict both environments report."""
    record = episodes.info[index]
    info: dict[str, Any] = {
        "secret": episodes.secret(index),
        "acquisitions": record.acquisitions,
        "edge_width_px": record.width_px,
        "threshold_px": record.threshold_px,
        "out_of_bounds": record.out_of_bounds,
        "failed_measurements": record.failed_measurements,
    }
    if done:
        info["success"] = episodes.success(index)
        info["edge_width_before_px"] = record.width_before_px
    return info


class AlignmentEnv(gym.Env):
    """One aligner, one apparatus (see the module docstring for the card)."""

    # gymnasium reads a class attribute; render_fps: how fast a recorder plays the frames
    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}  # noqa: RUF012

    def __init__(
        self,
        apparatus: Apparatus | str | None = None,
        task: Task | str = "focus",
        history: int = 8,
        complexity: float = 1.0,
        misalignment: MisalignmentPolicy | None = None,
        apparatus_args: dict | None = None,
        render_mode: str | None = None,
    ) -> None:
        super().__init__()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode {render_mode!r}: AlignmentEnv renders "
                f"{', '.join(self.metadata['render_modes'])} (or None, the default)"
            )
        self.render_mode = render_mode
        self.readings: list[Reading] = []  # the episode so far, kept where it renders
        self.episodes = single_episode(apparatus, task, history, complexity, apparatus_args)
        self.task, self.apparatus = self.episodes.task, self.episodes.apparatus[0]
        self.misalignment = misalignment
        self.observation_space, self.action_space = aligner_spaces(
            self.episodes.k, history, self.episodes.n_extra
        )
        self.misaligner_observation_space, _ = misaligner_spaces(self.episodes.k)
        self._index = np.array([0])

    @property
    def complexity(self) -> float:
        return self.episodes.complexity

    def set_complexity(self, level: float) -> None:
        """Width of the misalignment window as a fraction of the interval, in (0, 1]."""
        self.episodes.set_complexity(level)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        # Every random choice of the episode comes from the env's own generator.
        scenario_seed = int(self.np_random.integers(2**31 - 1))
        self.episodes.begin(self._index, [scenario_seed])
        if options and "misalignment" in options:
            action = np.asarray(options["misalignment"], float)
        elif self.misalignment is not None:
            action = np.asarray(self.misalignment(self.episodes.misaligner_observation(0)))
        else:
            action = self.np_random.uniform(-1.0, 1.0, self.episodes.k)
        self.episodes.misalign(self._index, action)
        self.readings = []
        self._film_step()
        return self.episodes.observation(0), episode_info(self.episodes, 0, done=False)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        steps = int(self.episodes.steps[0])
        reward, done = self.episodes.step(self._index, np.asarray(action)[None])
        if self.episodes.steps[0] > steps:  # an acquisition (a stop takes none)
            self._film_step()
        terminated = bool(done[0])
        info = episode_info(self.episodes, 0, done=terminated)
        return self.episodes.observation(0), float(reward[0]), terminated, False, info

    # --- rendering ----------------------------------------------------------------------

    def _film_step(self) -> None:
        """Keep the reading just taken, for render(): nothing where the env does not render."""
        if self.render_mode is None:
            return
        settings = dict(zip(self.task.knobs, self.episodes.setting[0].tolist(), strict=True))
        width = float(self.episodes.width[0])
        self.readings.append(
            take_reading(
                self.apparatus,
                settings,
                width if np.isfinite(width) else None,
                images=self.task.acquisitions_per_step,
            )
        )

    def render(self) -> np.ndarray | None:
        """With render_mode "rgb_array": the episode so far as an (H, W, 3) uint8 frame, the
        last acquired image beside the walk on the focus curve (alignrl/animation.py)."""
        if self.render_mode is None:
            return None
        if not self.readings:
            raise gym.error.ResetNeeded("render() before reset(): there is nothing to draw yet")
        episodes = self.episodes
        threshold = float(episodes.threshold[0])
        scene = Scene(
            knobs={
                knob: (float(episodes.low[0, i]), float(episodes.high[0, i]))
                for i, knob in enumerate(self.task.knobs)
            },
            title=f"AlignmentEnv: {self.task.name}",
            threshold_px=threshold if np.isfinite(threshold) else None,
        )
        return draw_frame(self.readings, scene)

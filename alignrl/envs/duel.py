"""DuelEnv: the zero-sum alignment game of seed section 3 (PettingZoo AEC).

Card
----
* Agents: "misaligner", then "aligner".
* Turn order: the misaligner acts once, at the start; then the aligner acts until it stops
  or reaches the task's step limit.
* Misaligner observation: Box(k + 1): the aligned knob settings in [-1, 1] and the
  complexity level; what it could know on a real instrument, never the aligner's future.
* Misaligner action: Box(-1, 1)^k: where in the complexity window around the aligned state
  each knob starts.
* Aligner observation/action: as in AlignmentEnv (history of settings, quality, actions;
  knob changes plus a stop component).
* Rewards, zero-sum at every step: at the misaligner's move it scores the misalignment it
  created, scale x (start width - best width), and the aligner is charged as much; then the
  aligner earns the seed's rewards (0 in the interval, -penalty at a bound, the final
  improvement of the edge width) and the misaligner the negative of each. The misaligner's
  total is what the aligner did not recover (alignrl.envs.rewards).
* Termination: both agents at the end of the alignment. info as in AlignmentEnv.
* Seeding: only through `self.np_random` (reset(seed=...)).
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv
from pettingzoo.utils import wrappers

from alignrl.apparatus.base import Apparatus
from alignrl.envs.alignment import aligner_spaces, episode_info, misaligner_spaces, single_episode
from alignrl.envs.task import Task

__all__ = ["ALIGNER", "MISALIGNER", "DuelEnv", "env", "raw_env"]

MISALIGNER, ALIGNER = "misaligner", "aligner"


class raw_env(AECEnv):
    """The alignment duel without wrappers; `env()` adds PettingZoo's standard ones."""

    metadata = {"name": "alignment_duel_v0", "render_modes": [], "is_parallelizable": False}  # noqa: RUF012

    def __init__(
        self,
        apparatus: Apparatus | str | None = None,
        task: Task | str = "focus",
        history: int = 8,
        complexity: float = 1.0,
        apparatus_args: dict | None = None,
    ) -> None:
        super().__init__()
        self.episodes = single_episode(apparatus, task, history, complexity, apparatus_args)
        self.task, self.apparatus = self.episodes.task, self.episodes.apparatus[0]
        spaces_of = {
            MISALIGNER: misaligner_spaces(self.episodes.k),
            ALIGNER: aligner_spaces(self.episodes.k, history, self.episodes.n_extra),
        }
        self._observation_spaces = {agent: pair[0] for agent, pair in spaces_of.items()}
        self._action_spaces = {agent: pair[1] for agent, pair in spaces_of.items()}
        self.possible_agents = [MISALIGNER, ALIGNER]
        self.agents: list[str] = []
        self._index = np.array([0])
        self.np_random, _ = gymnasium.utils.seeding.np_random(None)

    def set_complexity(self, level: float) -> None:
        self.episodes.set_complexity(level)

    @functools.cache  # noqa: B019 (spaces are fixed per env)
    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_spaces[agent]

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self._action_spaces[agent]

    def observe(self, agent: str) -> np.ndarray:
        if agent == MISALIGNER:
            return self.episodes.misaligner_observation(0)
        return self.episodes.observation(0)

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        if seed is not None:
            self.np_random, _ = gymnasium.utils.seeding.np_random(seed)
        self.episodes.begin(self._index, [int(self.np_random.integers(2**31 - 1))])
        self.agents = list(self.possible_agents)
        self.rewards = dict.fromkeys(self.agents, 0.0)
        self._cumulative_rewards = dict.fromkeys(self.agents, 0.0)
        self.terminations = dict.fromkeys(self.agents, False)
        self.truncations = dict.fromkeys(self.agents, False)
        self.infos = {agent: {} for agent in self.agents}
        self.agent_selection = MISALIGNER

    def step(self, action: np.ndarray | None) -> None:
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._was_dead_step(action)
            return
        self._cumulative_rewards[agent] = 0.0
        self._clear_rewards()
        if agent == MISALIGNER:
            self.episodes.misalign(self._index, np.asarray(action, float))
            score = float(self.episodes.misalignment_scores(self._index)[0])
            self.rewards[MISALIGNER], self.rewards[ALIGNER] = score, -score
            self.infos[ALIGNER] = episode_info(self.episodes, 0, done=False)
            self.agent_selection = ALIGNER
        else:
            reward, done = self.episodes.step(self._index, np.asarray(action, float)[None])
            # Zero-sum, step by step: whatever the aligner gains, the misaligner loses.
            self.rewards[ALIGNER] = float(reward[0])
            self.rewards[MISALIGNER] = -float(reward[0])
            info = episode_info(self.episodes, 0, done=bool(done[0]))
            self.infos = {ALIGNER: info, MISALIGNER: dict(info)}
            if done[0]:
                self.terminations = dict.fromkeys(self.agents, True)
                self.agent_selection = MISALIGNER  # dead steps: misaligner, then aligner
        self._accumulate_rewards()

    def close(self) -> None:
        pass


def env(**kwargs: Any) -> AECEnv:
    """The duel with PettingZoo's standard wrappers (order enforcing, action clipping)."""
    duel = raw_env(**kwargs)
    duel = wrappers.ClipOutOfBoundsWrapper(duel)
    return wrappers.OrderEnforcingWrapper(duel)


DuelEnv = raw_env

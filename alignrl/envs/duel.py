"""DuelEnv: the zero-sum alignment game of seed section 3 (PettingZoo AEC), and DuelBatch:
N duels stepped together, the form the league plays its matches in.

Card
----
* Agents: "misaligner", then "aligner".
* Turn order: the misaligner acts once, at the start; then the aligner acts until it stops
  or reaches the task's step limit.
* Misaligner observation: Box(k + 1): the aligned knob settings in [-1, 1] and the
  complexity level; what it could know on a real instrument, never the aligner's future.
  A league member reads it as a one-row history, [1, observation] (`misaligner_inputs`).
* Misaligner action: Box(-1, 1)^k: where in the complexity window around the aligned state
  each knob starts.
* A designing misaligner (`design=True`, an instrument family: alignrl.envs.design) reads
  Box(d + 1), its draw of the d design parameters and the complexity, and answers with
  Box(-1, 1)^(k + d): the start, then the column inside the family's box.
* Aligner observation/action: as in AlignmentEnv (history of settings, quality, actions;
  knob changes plus a stop component).
* Rewards, zero-sum at every step: at the misaligner's move it scores the misalignment it
  created, scale x (start width - best width), and the aligner is charged as much; then the
  aligner earns the seed's rewards (0 in the interval, -penalty at a bound, the final
  improvement of the edge width) and the misaligner the negative of each. The misaligner's
  total is what the aligner did not recover (alignrl.envs.rewards). With `payoff="regret"`
  the move scores instead what a reference earns on a twin of the column from the same start
  (alignrl.envs.design): the misaligner's total is the aligner's regret.
* Termination: both agents at the end of the alignment. info as in AlignmentEnv.
* Seeding: only through `self.np_random` (reset(seed=...)).

`raw_env` is a view of a DuelBatch of one slot: what `api_test` checks is what the league
plays (alignrl.league.matches.play_round), one code path.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv
from pettingzoo.utils import wrappers

from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.envs.alignment import aligner_spaces, episode_info, misaligner_spaces, single_episode
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.design import (
    PAYOFFS,
    Reference,
    can_twin,
    designer_input_shape,
    designs_columns,
    fractions_of,
    rated_scores,
    reference_returns,
    twin_of,
)
from alignrl.envs.task import Task

__all__ = [
    "ALIGNER",
    "MISALIGNER",
    "DuelBatch",
    "DuelEnv",
    "env",
    "misaligner_input_shape",
    "misaligner_inputs",
    "raw_env",
]

MISALIGNER, ALIGNER = "misaligner", "aligner"
AGENTS = (MISALIGNER, ALIGNER)


def misaligner_input_shape(n_knobs: int) -> tuple[int, int]:
    """The shape a misaligner member reads (`misaligner_inputs` of one observation)."""
    return (1, n_knobs + 2)


def misaligner_inputs(observations: np.ndarray) -> np.ndarray:
    """Misaligner observations (n, k + 1) as league members read them, (n, 1, k + 2): a
    one-row history [1, observation], the leading 1 marking the row valid for the sequence
    encoders."""
    valid = np.ones((len(observations), 1), np.float32)
    return np.concatenate([valid, observations], axis=1)[:, None]


class DuelBatch:
    """N duels over one engine (N apparatus), stepped together in the AEC turn order.

    `reset(seeds)` starts one duel per seed on slots 0..len(seeds)-1 (each apparatus reset
    with its seed); the misaligner is selected, and its `step(actions)` places every slot's
    start; then the aligner is, and each of its `step(actions)` moves the unfinished slots
    (`active`) until none is left. `observe(agent)` answers for the active slots, one row
    each; `rewards` (that step's, zero-sum) and `terminations` are arrays indexed by slot.
    No info dicts are built on the way: `info(slot)` builds one where it is wanted."""

    def __init__(
        self,
        episodes: AlignmentEpisodes,
        design: bool = False,
        payoff: str = "improvement",
        reference: Reference | None = None,
    ) -> None:
        if payoff not in PAYOFFS:
            raise ValueError(f"payoff must be one of {', '.join(PAYOFFS)}, got {payoff!r}")
        units = episodes.apparatus
        if payoff == "regret":
            if reference is None:
                raise ValueError("the regret payoff needs a reference to measure it against")
            if not all(can_twin(unit) for unit in units):
                raise ValueError(
                    "the regret payoff plays a twin of each column: it needs simulated "
                    "apparatus (a real microscope, or any driver behind the shield, has no twin)"
                )
        self.design_names: tuple[str, ...] = ()
        if design:
            if not all(designs_columns(unit) for unit in units):
                raise ValueError(
                    "a designing misaligner needs an apparatus whose column it can choose: an "
                    "instrument family with ranges to design (family:NAME)"
                )
            names = {unit.design_names() for unit in units}  # type: ignore[attr-defined]
            if len(names) > 1:
                raise ValueError("every apparatus of a designing duel must offer the same design")
            self.design_names = names.pop()
        self.possible_agents = list(AGENTS)
        self.episodes = episodes
        self.n = episodes.n
        self.design, self.payoff, self.reference = bool(design), payoff, reference
        d, k = len(self.design_names), episodes.k
        self.misaligner_shape = (
            (designer_input_shape(d), k + d) if design else (misaligner_input_shape(k), k)
        )
        self.designs = np.full((self.n, d), np.nan)  # fractions of the box each slot got
        self.reference_cost = np.full(self.n, np.nan)  # px where the reference left it
        self.reference_acquisitions = np.zeros(self.n, np.int64)
        self.reference_success = np.zeros(self.n, bool)
        self.slots = np.arange(0)  # the slots of this round
        self.active = np.arange(0)  # the slots the selected agent acts for
        self.agent_selection = MISALIGNER
        self.rewards = {agent: np.zeros(self.n) for agent in AGENTS}
        self.terminations = {agent: np.ones(self.n, bool) for agent in AGENTS}

    @property
    def complexity(self) -> float:
        return self.episodes.complexity

    def set_complexity(self, level: float) -> None:
        """Width of the misalignment window as a fraction of the interval, from the next
        reset on."""
        self.episodes.set_complexity(level)

    def reset(self, seeds: Sequence[int | None]) -> None:
        """One new duel per seed, on slots 0..len(seeds)-1; the misaligner moves first."""
        if not 0 < len(seeds) <= self.n:
            raise ValueError(f"a batch of {self.n} duels takes 1 to {self.n} seeds: {len(seeds)}")
        self.slots = np.arange(len(seeds))
        self.episodes.begin(self.slots, list(seeds))
        self.active = self.slots
        self.agent_selection = MISALIGNER
        for agent in AGENTS:
            self.rewards[agent][:] = 0.0
            self.terminations[agent][:] = True  # a slot outside the round plays no duel
            self.terminations[agent][self.slots] = False

    def observe(self, agent: str, slots: np.ndarray | None = None) -> np.ndarray:
        """What `agent` reads in `slots` (default: the active ones): (n, k + 1) for the
        misaligner, (n, H, F) histories for the aligner; fresh arrays."""
        slots = self.active if slots is None else slots
        if agent == MISALIGNER and self.design:
            draws = [2.0 * self.episodes.apparatus[int(i)].design_draw() - 1.0 for i in slots]  # type: ignore[attr-defined]
            level = np.full((len(slots), 1), self.episodes.complexity)
            return np.concatenate([np.stack(draws), level], axis=1).astype(np.float32)
        if agent == MISALIGNER:
            return np.stack([self.episodes.misaligner_observation(int(i)) for i in slots])
        return self.episodes.history[slots]

    def secrets(self, slots: np.ndarray | None = None) -> np.ndarray:
        """(n, k) optimum - setting of `slots` (default: the active ones): for critics, never
        for policies (info["secret"] of DuelEnv)."""
        return self.episodes.secrets()[self.active if slots is None else slots]

    def step(self, actions: np.ndarray) -> None:
        """The selected agent's actions, one row per active slot."""
        if not self.active.size:
            raise RuntimeError("every duel of the batch has ended: reset it first")
        for agent in AGENTS:
            self.rewards[agent][:] = 0.0
        if self.agent_selection == MISALIGNER:
            score = self._misalign(np.asarray(actions, float).reshape(len(self.slots), -1))
            self.rewards[MISALIGNER][self.slots] = score
            self.rewards[ALIGNER][self.slots] = -score
            self.agent_selection = ALIGNER
            return
        active = self.active
        reward, done = self.episodes.step(active, actions)
        # Zero-sum, step by step: whatever the aligner gains, the misaligner loses.
        self.rewards[ALIGNER][active] = reward
        self.rewards[MISALIGNER][active] = -reward
        for agent in AGENTS:
            self.terminations[agent][active[done]] = True
        self.active = active[~done]

    def _misalign(self, actions: np.ndarray) -> np.ndarray:
        """The misaligner's move on the round's slots (its design first, where it designs);
        returns what each move scores."""
        slots, episodes, k = self.slots, self.episodes, self.episodes.k
        if self.design:
            self.designs[slots] = fractions_of(actions[:, k:])
            episodes.design(slots, self.designs[slots])
        twins = [twin_of(episodes.apparatus[i]) for i in slots] if self.payoff == "regret" else []
        episodes.misalign(slots, actions[:, :k])
        if self.payoff != "regret":
            return episodes.misalignment_scores(slots)
        assert self.reference is not None
        for twin, slot in zip(twins, slots, strict=True):
            twin.write(dict(zip(episodes.task.knobs, episodes.setting[slot].tolist(), strict=True)))
            try:
                cost, images = self.reference.align(twin, episodes.task)
            except ApparatusError:  # a fault of the twin: the reference failed there
                cost, images = float("nan"), 0
            self.reference_cost[slot], self.reference_acquisitions[slot] = cost, images
        cost = self.reference_cost[slots]
        self.reference_success[slots] = np.isfinite(cost) & (cost <= episodes.threshold[slots])
        return reference_returns(
            episodes.cost_before[slots], cost, self.reference_acquisitions[slots], episodes.task
        )

    def rated(self) -> np.ndarray:
        """(n,) the aligner's rated score per slot of the round (alignrl.envs.design): its
        success, or under the regret payoff how it fared against the reference."""
        theirs = self.reference_success[self.slots] if self.payoff == "regret" else None
        return rated_scores(self.successes(), theirs)

    def info(self, slot: int) -> dict[str, Any]:
        """DuelEnv's info of `slot` (success and the width before once it has ended)."""
        return episode_info(self.episodes, slot, done=bool(self.terminations[ALIGNER][slot]))

    def successes(self) -> np.ndarray:
        """(n,) bool per slot of the round: its latest image meets every spec of the task."""
        return self.episodes.successes()[self.slots]

    def acquisitions(self) -> np.ndarray:
        """(n,) images acquired per slot of the round."""
        return self.episodes.acquisitions[self.slots].copy()


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
        design: bool = False,
        payoff: str = "improvement",
        reference: Reference | None = None,
    ) -> None:
        super().__init__()
        self.episodes = single_episode(apparatus, task, history, complexity, apparatus_args)
        self.batch = DuelBatch(self.episodes, design, payoff, reference)
        self.task, self.apparatus = self.episodes.task, self.episodes.apparatus[0]
        spaces_of = {
            MISALIGNER: misaligner_spaces(self.episodes.k, len(self.batch.design_names)),
            ALIGNER: aligner_spaces(self.episodes.k, history, self.episodes.n_extra),
        }
        self._observation_spaces = {agent: pair[0] for agent, pair in spaces_of.items()}
        self._action_spaces = {agent: pair[1] for agent, pair in spaces_of.items()}
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        self._slot = np.array([0])
        self.np_random, _ = gymnasium.utils.seeding.np_random(None)

    def set_complexity(self, level: float) -> None:
        self.batch.set_complexity(level)

    @functools.cache  # noqa: B019 (spaces are fixed per env)
    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_spaces[agent]

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self._action_spaces[agent]

    def observe(self, agent: str) -> np.ndarray:
        return self.batch.observe(agent, self._slot)[0]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        if seed is not None:
            self.np_random, _ = gymnasium.utils.seeding.np_random(seed)
        self.batch.reset([int(self.np_random.integers(2**31 - 1))])
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
        self.batch.step(np.asarray(action, float)[None])
        for each in self.agents:
            self.rewards[each] = float(self.batch.rewards[each][0])
        info = self.batch.info(0)
        if agent == MISALIGNER:
            self.infos[ALIGNER] = info
        else:
            self.infos = {ALIGNER: info, MISALIGNER: dict(info)}
        self.agent_selection = self.batch.agent_selection
        if self.batch.terminations[ALIGNER][0]:
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

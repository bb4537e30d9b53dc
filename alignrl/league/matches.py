"""Playing matches through the duel: the code every execution backend shares.

A round is one match per slot of a DuelBatch (alignrl.envs.duel, the batched DuelEnv): each
slot's apparatus is reset with its match's seed, the misaligner reads its observation (as a
member's one-row input, `misaligner_inputs`) and chooses the start, and the aligner acts on
the unfinished matches until all are done (a stop, or the task's last step). Who chooses,
and what happens to each step, is the caller's:

* the in-process backend lets learning members `explore` with the league's generator and
  `observe` and `learn` after every step (`play_round` with its own choosers);
* a Ray worker (alignrl.league.ray_backend) acts with copies of the members, each match's
  randomness drawn from a generator seeded by that match's seed, and records every step
  (`record_matches`); the driver then stores the trajectories in the learning members and
  learns (`learn_from_matches`).

Payoffs are the aligner's, in the zero-sum game: its return (the seed's rewards) minus what
the start was worth (the duel's reward to the misaligner's move); the misaligner's is the
negative.

Anchors (`make_anchors`: classical controllers with a fixed rating, alignrl.league.ratings)
play beside the aligner where they are asked to: once the misaligner has placed a start, each
aligns a twin of the column in its very state (alignrl.envs.design.twin_of), and each match
gives the aligner a score against each anchor (`anchor_scores`). The league's apparatus and
random streams are untouched by them. An apparatus without a twin (a real microscope) plays
no anchors.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.config_reading import ConfigError
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.design import Reference, can_twin, twin_of
from alignrl.envs.duel import (
    ALIGNER,
    MISALIGNER,
    DuelBatch,
    misaligner_input_shape,
    misaligner_inputs,
)
from alignrl.league.ratings import anchor_scores
from alignrl.transitions import Transition

__all__ = [
    "Choice",
    "Chooser",
    "MatchResult",
    "MatchTrajectory",
    "Round",
    "UniformStarts",
    "WorkerFailedError",
    "exploration_generator",
    "learn_from_matches",
    "learn_from_starts",
    "make_anchors",
    "make_duel",
    "play_round",
    "record_matches",
]

# A chooser answers a batch of inputs (the rows of the slots given) with actions in (-1, 1)
# and, where the member is PPO and sampled them itself, their pre-squash sample (else None).
Choice = tuple[np.ndarray, np.ndarray | None]
Chooser = Callable[[np.ndarray, np.ndarray], Choice]


UNIFORM_FORMAT = "alignrl-uniform-starts-1"


class UniformStarts:
    """A stand-in misaligner that starts each match uniformly over the complexity window,
    as the held-out sessions do. It never learns and is never rated: the league plays it
    against learning aligners for a share of their matches (`schedule.uniform_starts`) so
    that, hunting their weaknesses with the real misaligners, they keep the coverage of the
    starts they are judged on. Its randomness is `rng` in this process (set by the league
    before each batch) and each match's own generator on a Ray worker."""

    ID = "uniform-starts"

    def __init__(self, spec: MemberSpec) -> None:
        self.spec = spec
        self.rng = np.random.default_rng(0)

    @classmethod
    def for_knobs(cls, knobs: int) -> UniformStarts:
        """The stand-in for a task of `knobs` knobs, shaped as the league's misaligners."""
        return cls.for_shape(misaligner_input_shape(knobs), knobs, knobs)

    @classmethod
    def for_shape(cls, shape: tuple[int, int], actions: int, knobs: int) -> UniformStarts:
        """The stand-in for misaligners that read `shape` and answer with `actions` values
        (a designer's too: its uniform actions are the family's uniform draw, domain
        randomization)."""
        return cls(MemberSpec(cls.ID, "misaligner", "sac", shape, actions, knobs))

    @property
    def id(self) -> str:
        return self.spec.id

    def act(self, inputs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, (len(inputs), self.spec.action_dim))

    def explore(self, inputs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(-1.0, 1.0, (len(inputs), self.spec.action_dim))

    def explore_rows(
        self, inputs: np.ndarray, generators: Sequence[np.random.Generator], warm_up: bool = True
    ) -> tuple[np.ndarray, None]:
        return np.stack([g.uniform(-1.0, 1.0, self.spec.action_dim) for g in generators]), None

    def policy_state(self) -> dict[str, Any]:
        return {"format": UNIFORM_FORMAT, "spec": self.spec.to_dict()}


class WorkerFailedError(RuntimeError):
    """Matches could not be played: a worker was lost more often than it may be restarted.
    Nothing of the batch reached the members."""


class MatchResult:
    """The outcome of one batch of matches, from the aligner's side: its returns (the seed's
    rewards it learns from) and payoffs in the zero-sum game (its return minus the start's
    score; the misaligner's payoff is the negative)."""

    def __init__(self) -> None:
        self.successes: list[bool] = []
        self.acquisitions: list[int] = []
        self.returns: list[float] = []
        self.payoffs: list[float] = []
        self.rated: list[float] = []  # the aligner's rated score per match (envs.design)
        self.designs: list[np.ndarray] = []  # the box fractions a designer chose, per match
        # Per anchor, of the matches it played: the aligner's score against it, its success.
        self.anchor_scores: dict[str, list[float]] = {}
        self.anchor_successes: dict[str, list[bool]] = {}
        self.updates: dict[str, list[dict[str, float]]] = {}

    def add(
        self,
        success: bool,
        acquisitions: int,
        aligner_return: float,
        payoff: float,
        rated: float | None = None,
        design: np.ndarray | None = None,
        anchors: Mapping[str, tuple[float, bool]] | None = None,
    ) -> None:
        """One finished match (`rated`: its success unless given; `design`: where the
        misaligner designed the column; `anchors`: per anchor that played it, the aligner's
        score against it and whether it met the spec)."""
        self.successes.append(bool(success))
        self.acquisitions.append(int(acquisitions))
        self.returns.append(float(aligner_return))
        self.payoffs.append(float(payoff))
        self.rated.append(float(success) if rated is None else float(rated))
        if design is not None and np.size(design):
            self.designs.append(np.asarray(design, float))
        for name, (score, anchor_success) in (anchors or {}).items():
            self.anchor_scores.setdefault(name, []).append(float(score))
            self.anchor_successes.setdefault(name, []).append(bool(anchor_success))

    @property
    def anchored(self) -> int:
        """Matches every anchor played (0 without anchors)."""
        return min((len(scores) for scores in self.anchor_scores.values()), default=0)

    @property
    def matches(self) -> int:
        return len(self.successes)

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else 0.0

    @property
    def score_rate(self) -> float:
        """The aligner's mean rated score: its success rate under the improvement payoff."""
        return float(np.mean(self.rated)) if self.rated else 0.0

    def joined(self, other: MatchResult) -> MatchResult:
        """These matches, then `other`'s (a batch played in two parts)."""
        both = MatchResult()
        for name in ("successes", "acquisitions", "returns", "payoffs", "rated", "designs"):
            setattr(both, name, getattr(self, name) + getattr(other, name))
        for name in ("anchor_scores", "anchor_successes"):
            joined = {anchor: list(rows) for anchor, rows in getattr(self, name).items()}
            for anchor, rows in getattr(other, name).items():
                joined.setdefault(anchor, []).extend(rows)
            setattr(both, name, joined)
        both.updates = {m: list(rows) for m, rows in self.updates.items()}
        for member, rows in other.updates.items():
            both.updates.setdefault(member, []).extend(rows)
        return both


@dataclass
class Round:
    """One round of matches on slots 0..n-1, arrays indexed by slot."""

    rows: np.ndarray  # (n, 1, k + 2) what the misaligner read
    starts: np.ndarray  # (n, k) the misaligner's choices
    starts_pre_tanh: np.ndarray | None  # (n, k) its pre-squash sample, where it travels along
    scores: np.ndarray  # (n,) what each start was worth (charged to the aligner)
    returns: np.ndarray  # (n,) the aligner's return
    successes: np.ndarray  # (n,) bool, the final image within the threshold
    acquisitions: np.ndarray  # (n,) images acquired
    finish_order: list[int]  # slots in the order their matches ended
    rated: np.ndarray  # (n,) the aligner's rated score (its success, or against the reference)
    designs: np.ndarray  # (n, d) box fractions a designer chose (d = 0: it places starts only)
    # anchor -> ((n,) the aligner's score against it, (n,) bool whether it met the spec)
    anchors: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def anchors_of(self, slot: int) -> dict[str, tuple[float, bool]]:
        """Per anchor, the aligner's score against it in `slot` and the anchor's success."""
        return {
            name: (float(scores[slot]), bool(successes[slot]))
            for name, (scores, successes) in self.anchors.items()
        }


@dataclass
class MatchTrajectory:
    """Everything the driver needs of one match played elsewhere: the outcome, the
    misaligner's one step and the aligner's steps."""

    seed: int
    misaligner_row: np.ndarray  # (1, 1, k + 2)
    start: np.ndarray  # (1, k)
    start_pre_tanh: np.ndarray | None  # (1, k)
    score: float
    aligner_return: float
    success: bool
    acquisitions: int
    steps: Transition  # the aligner's, from the first step to the last, with their slots
    rated: float  # the aligner's rated score
    design: np.ndarray  # (d,) the box fractions the designer chose (empty: starts only)
    # anchor -> (the aligner's score against it, whether the anchor met the spec)
    anchors: dict[str, tuple[float, bool]] = field(default_factory=dict)

    @property
    def payoff(self) -> float:
        """The aligner's payoff; the misaligner's is the negative."""
        return self.aligner_return - self.score


def make_duel(episodes: AlignmentEpisodes, design: bool, payoff: str, reference: str) -> DuelBatch:
    """The duels a league plays over `episodes`: its misaligners designing the column or
    placing starts, paid by `payoff` (the regret measured against the classical controller
    `reference`: alignrl.evaluation.references); ConfigError where the apparatus cannot."""
    from alignrl.evaluation.references import make_reference

    try:
        against = make_reference(reference, episodes.task) if payoff == "regret" else None
        return DuelBatch(episodes, design, payoff, against)
    except ValueError as error:
        raise ConfigError(f"design: {design}, payoff: {payoff}: {error}") from None


def make_anchors(names: Sequence[str], units: Sequence[Apparatus]) -> list[Reference]:
    """The anchors `names` (classical controllers, checked against the task by the league's
    config) that play beside the aligners on `units`; none where an apparatus cannot give a
    twin of its column (a real microscope)."""
    from alignrl.evaluation.baselines import get_baseline
    from alignrl.evaluation.references import ControllerReference

    if not all(can_twin(unit) for unit in units):
        return []
    return [ControllerReference(get_baseline(name)) for name in names]


def _anchors_align(
    duel: DuelBatch, anchors: Sequence[Reference]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each anchor aligns a twin of every column of the round from its start (the aligner
    has not acted yet): per anchor, (n,) whether it met the spec and (n,) its final cost, px
    (the task's no-edges width where its last image failed)."""
    episodes, slots = duel.episodes, duel.slots
    played = {}
    for anchor in anchors:
        reference = duel.reference if duel.payoff == "regret" else None
        if reference is not None and reference.name == anchor.name:
            cost = duel.reference_cost[slots].copy()  # the regret's reference played them
        else:
            cost = np.full(len(slots), np.nan)
            for position, slot in enumerate(slots):
                try:
                    cost[position], _ = anchor.align(
                        twin_of(episodes.apparatus[slot]), episodes.task
                    )
                except ApparatusError:  # a fault of the twin: the anchor failed there
                    pass
        success = np.isfinite(cost) & (cost <= episodes.threshold[slots])
        played[anchor.name] = (
            success,
            np.where(np.isfinite(cost), cost, episodes.task.no_edges_px),
        )
    return played


def play_round(
    duel: DuelBatch,
    seeds: Sequence[int],
    choose_start: Chooser,
    choose_action: Chooser,
    on_step: Callable[[Transition], None],
    anchors: Sequence[Reference] = (),
) -> Round:
    """One match per seed on slots 0..len(seeds)-1 of `duel`, played to the end; `on_step`
    sees every aligner step as it happens; `anchors` align twins of the same columns from the
    same starts."""
    duel.reset(seeds)
    slots = duel.slots
    rows = misaligner_inputs(duel.observe(MISALIGNER))
    starts, starts_pre_tanh = choose_start(rows, slots)
    duel.step(starts)
    anchored = _anchors_align(duel, anchors)
    scores = duel.rewards[MISALIGNER][slots]
    returns = np.zeros(len(slots))
    finish_order: list[int] = []
    while duel.active.size:
        active = duel.active
        observation, secret = duel.observe(ALIGNER), duel.secrets()
        action, pre_tanh = choose_action(observation, active)
        duel.step(action)
        reward, done = duel.rewards[ALIGNER][active], duel.terminations[ALIGNER][active]
        returns[active] += reward
        on_step(
            Transition(
                observation,
                secret,
                action,
                reward,
                duel.observe(ALIGNER, active),
                duel.secrets(active),
                done,
                slots=active,
                pre_tanh=pre_tanh,
            )
        )
        finish_order += [int(slot) for slot in active[done]]
    successes, final_cost = duel.successes(), duel.episodes.cost[slots]
    return Round(
        rows,
        starts,
        starts_pre_tanh,
        scores,
        returns,
        successes,
        duel.acquisitions(),
        finish_order,
        duel.rated(),
        duel.designs[slots].copy(),
        {
            name: (anchor_scores(successes, final_cost, success, cost), success)
            for name, (success, cost) in anchored.items()
        },
    )


def learn_from_starts(
    misaligner: Agent,
    rows: np.ndarray,
    starts: np.ndarray,
    rewards: np.ndarray,
    rng: np.random.Generator,
    slots: np.ndarray | None = None,
    pre_tanh: np.ndarray | None = None,
) -> list[dict[str, float]]:
    """Store a misaligner's one-step episodes and run the updates that are due: each start
    is the action on its row, the reward its score minus the aligner's return (zero-sum),
    and nothing follows. Returns the updates' metrics."""
    count = len(rows)
    none = np.zeros((count, misaligner.spec.secret_dim), np.float32)
    done = np.ones(count, bool)
    step = Transition(rows, none, starts, rewards, rows, none, done, slots=slots, pre_tanh=pre_tanh)
    misaligner.observe(step)
    return misaligner.learn(rng, new_steps=count)


# --- matches played elsewhere (a Ray worker), learned from in the driver -------------------

EXPLORATION_STREAM = 1  # a match's exploration generator: seeded by [seed, this], not by seed


def exploration_generator(seed: int) -> np.random.Generator:
    """The generator of a match's exploration noise: a stream of its own, apart from the
    apparatus (which `reset(seed)` seeds)."""
    return np.random.default_rng([seed, EXPLORATION_STREAM])


def _seeded_chooser(
    agent: Agent, generators: list[np.random.Generator], learns: bool, deterministic: bool
) -> Chooser:
    """How `agent` chooses in a worker, as in-process: a learning member explores (SAC's
    warm-up included), another acts with its mean action if `deterministic`, else samples."""

    def choose(inputs: np.ndarray, slots: np.ndarray) -> Choice:
        if deterministic and not learns:
            return agent.act(inputs, deterministic=True), None
        return agent.explore_rows(inputs, [generators[slot] for slot in slots], warm_up=learns)

    return choose


def _per_match(steps: list[Transition], slot: int) -> Transition:
    """The rows of one slot's match, first step to last."""
    return Transition.joined([step.rows(step.slots == slot) for step in steps])


def record_matches(
    duel: DuelBatch,
    seeds: Sequence[int],
    aligner: Agent,
    misaligner: Agent,
    learns: tuple[bool, bool],
    deterministic: bool = False,
    on_step: Callable[[Transition], None] | None = None,
    anchors: Sequence[Reference] = (),
) -> list[MatchTrajectory]:
    """One match per seed, in rounds of `duel.n`, recorded in the order of `seeds`.
    `learns`: whether the aligner and the misaligner learn from these matches (they then
    explore); `anchors` play beside the aligner. Each match's randomness comes from its own
    seed alone, so it plays the same on any worker, beside any other matches."""
    aligner_learns, misaligner_learns = learns
    trajectories = []
    for first in range(0, len(seeds), duel.n):
        chunk = [int(seed) for seed in seeds[first : first + duel.n]]
        generators = [exploration_generator(seed) for seed in chunk]
        steps: list[Transition] = []

        def keep(step: Transition, steps: list[Transition] = steps) -> None:
            steps.append(step)
            if on_step:
                on_step(step)

        played = play_round(
            duel,
            chunk,
            _seeded_chooser(misaligner, generators, misaligner_learns, deterministic),
            _seeded_chooser(aligner, generators, aligner_learns, deterministic),
            keep,
            anchors,
        )
        for slot, seed in enumerate(chunk):
            pre_tanh = played.starts_pre_tanh
            trajectories.append(
                MatchTrajectory(
                    seed=seed,
                    misaligner_row=played.rows[slot : slot + 1],
                    start=np.asarray(played.starts[slot : slot + 1]),
                    start_pre_tanh=None if pre_tanh is None else pre_tanh[slot : slot + 1],
                    score=float(played.scores[slot]),
                    aligner_return=float(played.returns[slot]),
                    success=bool(played.successes[slot]),
                    acquisitions=int(played.acquisitions[slot]),
                    steps=_per_match(steps, slot),
                    rated=float(played.rated[slot]),
                    design=played.designs[slot],
                    anchors=played.anchors_of(slot),
                )
            )
    return trajectories


def learn_from_matches(
    trajectories: Sequence[MatchTrajectory],
    aligner: Agent,
    misaligner: Agent,
    learning: set[str],
    rng: np.random.Generator,
    on_episode: Callable[[bool], None] | None = None,
) -> MatchResult:
    """The outcome of matches played elsewhere; the members in `learning` store them in
    match order, each match's steps one transition at a time (so PPO links them as one
    episode), and run the updates that are due after each."""
    result = MatchResult()
    result.updates = {member.id: [] for member in (aligner, misaligner)}
    for match in trajectories:
        result.add(
            match.success,
            match.acquisitions,
            match.aligner_return,
            match.payoff,
            match.rated,
            match.design,
            match.anchors,
        )
        if on_episode:
            on_episode(match.success)
        if aligner.id in learning:
            steps = match.steps
            for t in range(len(steps)):
                # One step at a time, as slot 0: the worker's slots are not the driver's.
                aligner.observe(replace(steps.rows(slice(t, t + 1)), slots=None))
                result.updates[aligner.id] += aligner.learn(rng, new_steps=1)
        if misaligner.id in learning:
            result.updates[misaligner.id] += learn_from_starts(
                misaligner,
                match.misaligner_row,
                match.start,
                np.array([-match.payoff]),
                rng,
                pre_tanh=match.start_pre_tanh,
            )
    return result

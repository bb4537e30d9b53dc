"""Matches on Ray workers, one per microscope: the league's `backend: ray` (alignrl[ray]).

Each worker (`MatchWorker`, a Ray actor) owns its microscope: `envs` copies of one apparatus
spec, stepped together, and their alignment episodes; workers may drive different
microscopes. For every batch of matches the driver

1. puts the two members' policies into the object store once (the acting network's
   weights, the member spec, and steps_seen for SAC's random warm-up: `Agent.policy_state`);
2. draws one seed per match from the league's generator and gives each worker a contiguous
   share of the matches, in proportion to its envs;
3. gets back trajectories (`MatchTrajectory`: the misaligner's row, start and score, every
   aligner step, the outcome) and lets the learning members observe them in match order and
   learn, here in the driver (`learn_from_matches`).

How it differs from the in-process backend:
* learning follows the batch instead of every step: within one batch the members act with
  the weights they had when it began (in-process, later steps of a batch see updated
  weights), and SAC's random warm-up is decided once per batch;
* exploration noise comes from each match's own generator, seeded from its seed: a match
  plays the same on whichever worker, beside whichever other matches, and a replayed match
  plays as the first time;
* the curriculum's complexity changes between batches, not between rounds of one.
League sees only the MatchResult, so matchmaking, ratings, the payoff table, snapshots, PBT,
evaluation sessions (in the driver, on eval_apparatus), checkpoints and resume are the same
code for both backends.

A worker lost mid-batch (its process or its PC died) is restarted by Ray (`max_restarts`), or
made anew once Ray's restarts of it are spent, and its whole share is played again with the
same seeds; nothing of a lost batch reaches the members. A worker lost more than
`max_restarts` times within one batch stops the league with WorkerFailedError naming it;
League records an iteration only after `play` returns, so its last checkpoint is intact.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import ray
import torch
from ray.exceptions import (
    ActorDiedError,
    ActorUnavailableError,
    GetTimeoutError,
    RayActorError,
    RayTaskError,
)

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.envs import make_apparatus_copies
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import Task
from alignrl.league.config import LeagueConfig, RayWorkerConfig
from alignrl.league.matches import (
    UNIFORM_FORMAT,
    MatchResult,
    MatchTrajectory,
    UniformStarts,
    WorkerFailedError,
    learn_from_matches,
    make_anchors,
    make_duel,
    record_matches,
)
from alignrl.transitions import Transition

__all__ = ["MatchWorker", "RayBackend", "split_matches"]

WORKER_START_TIMEOUT_S = 300.0  # a worker on a microscope PC may take a while to connect
RESTART_POLL_S = 0.5  # how often a worker being restarted is asked whether it is back


def split_matches(matches: int, envs: list[int]) -> list[int]:
    """How many of `matches` each worker plays: in proportion to its envs, the remainder to
    the largest fractions (the first worker on ties)."""
    total = sum(envs)
    exact = [matches * count / total for count in envs]
    shares = [int(share) for share in exact]
    by_fraction = sorted(range(len(envs)), key=lambda i: (-(exact[i] - shares[i]), i))
    for index in by_fraction[: matches - sum(shares)]:
        shares[index] += 1
    return shares


class MatchWorker:
    """One microscope's worker: its apparatus, their duels (a DuelBatch over its episodes)
    and acting copies of the two members of the latest batch. Runs as a Ray actor; plain
    Python otherwise."""

    def __init__(
        self,
        index: int,
        apparatus: str,
        apparatus_args: dict[str, Any],
        envs: int,
        task: Task,
        history: int,
        threads: int,
        duel: tuple[bool, str, str] = (False, "improvement", "hyperbola"),
        anchors: tuple[str, ...] = (),
    ) -> None:
        torch.set_num_threads(threads)
        self.index, self.apparatus = index, apparatus
        units = make_apparatus_copies(apparatus, apparatus_args, envs)
        self.episodes = AlignmentEpisodes(units, task, history)
        self.duel = make_duel(self.episodes, *duel)  # (design, payoff, reference)
        self.anchors = make_anchors(anchors, units)  # none on a microscope: no twins there
        self._members: dict[str, Agent] = {}  # team -> acting copy, reused while the spec holds
        self._steps_to_failure: int | None = None

    def describe(self) -> dict[str, Any]:
        """Who and where this worker is."""
        return {
            "worker": self.index,
            "apparatus": self.apparatus,
            "envs": self.episodes.n,
            "host": socket.gethostname(),
            "pid": os.getpid(),
        }

    def fail_after(self, steps: int) -> None:
        """A drill: the worker's process exits after `steps` more aligner steps, as if its PC
        died mid-match. The restarted worker is a new process and keeps no such plan."""
        self._steps_to_failure = steps

    def play(
        self,
        policies: dict[str, dict[str, Any]],
        seeds: list[int],
        complexity: float,
        learns: tuple[bool, bool],
        deterministic: bool,
        anchored: bool = False,
    ) -> list[MatchTrajectory]:
        """One match per seed (see alignrl.league.matches.record_matches); `anchored`: the
        anchors align the same columns too, where this worker's apparatus has twins."""
        aligner = self._member("aligner", policies["aligner"])
        misaligner = self._member("misaligner", policies["misaligner"])
        self.duel.set_complexity(complexity)
        anchors = self.anchors if anchored else []
        return record_matches(
            self.duel, seeds, aligner, misaligner, learns, deterministic, self._count, anchors
        )

    def _member(self, team: str, state: dict[str, Any]) -> Agent | UniformStarts:
        if state.get("format") == UNIFORM_FORMAT:
            return UniformStarts(MemberSpec.from_dict(state["spec"]))
        agent = self._members.get(team)
        if agent is None or agent.spec.to_dict() != state["spec"]:
            agent = self._members[team] = Agent.from_policy_state(state)
        else:
            agent.load_policy_state(state)
        return agent

    def _count(self, step: Transition) -> None:
        if self._steps_to_failure is None:
            return
        self._steps_to_failure -= len(step)
        if self._steps_to_failure <= 0:
            os._exit(1)  # no cleanup, no exception: the way a crashed PC leaves


class RayBackend:
    """Plays matches on Ray workers (see the module docstring). Ray is joined or started,
    and the workers are created, at the first `play`: a league opened only to be read
    (status, leaderboard) starts nothing."""

    def __init__(self, config: LeagueConfig) -> None:
        self.config = config
        self.workers: list[RayWorkerConfig] = config.ray_workers()
        self.task = config.resolved_task()
        self._complexity = float(config.complexity)
        self._actors: list[Any] = []
        self.replays = [0] * len(self.workers)  # shares played again after a worker was lost
        self._started_ray = False
        self._remote_class: Any = None

    @property
    def complexity(self) -> float:
        return self._complexity

    def set_complexity(self, level: float) -> None:
        """Used from the next batch on (the workers' episodes check the range)."""
        if not 0.0 < level <= 1.0:
            raise ValueError(f"complexity level must be in (0, 1], got {level}")
        self._complexity = float(level)

    def _name(self, index: int) -> str:
        worker = self.workers[index]
        arguments = f" {worker.apparatus_args}" if worker.apparatus_args else ""
        return f"{worker.apparatus}{arguments} x{worker.envs}"

    # --- workers ------------------------------------------------------------------------

    def _start(self) -> None:
        if self._actors:
            return
        ray_config = self.config.ray
        needed = self._needed_resources()
        if not ray.is_initialized():
            if ray_config.address is None:
                # A Ray of our own on this machine; it pretends to have the workers'
                # microscope resources, so a cluster config also runs on one PC.
                custom = {k: v for k, v in needed.items() if k != "CPU"}
                ray.init(
                    address="local",
                    num_cpus=max(os.cpu_count() or 1, int(np.ceil(needed["CPU"]))),
                    resources=custom or None,
                    include_dashboard=False,
                    logging_level=logging.WARNING,
                )
            else:
                ray.init(address=ray_config.address, logging_level=logging.WARNING)
            self._started_ray = True
        self._check_resources(needed)
        self._remote_class = ray.remote(MatchWorker)
        self._actors = [self._create(index) for index in range(len(self.workers))]
        for index in range(len(self._actors)):
            if not self._answers(index):
                raise WorkerFailedError(f"worker {index} ({self._name(index)}) died starting")

    def _needed_resources(self) -> dict[str, float]:
        needed = {"CPU": self.config.ray.num_cpus_per_worker * len(self.workers)}
        for worker in self.workers:
            for name, amount in worker.resources.items():
                needed[name] = needed.get(name, 0.0) + amount
        return needed

    def _check_resources(self, needed: dict[str, float]) -> None:
        """Workers that cannot all be placed would wait forever: say so now."""
        offered = ray.cluster_resources()
        short = {k: v for k, v in needed.items() if offered.get(k, 0.0) < v}
        if short:
            has = {k: offered.get(k, 0.0) for k in short}
            advice = (
                "lower ray.num_cpus_per_worker or add machines"
                if "CPU" in short
                else "join every microscope PC to the cluster first, "
                "`ray start --address HEAD:6379 --resources '{\"NAME\": 1}'`"
            )
            raise WorkerFailedError(
                f"the Ray workers need {short} but the cluster offers {has}: {advice} "
                "(docs/scaling.md)"
            )

    def _create(self, index: int) -> Any:
        worker, ray_config = self.workers[index], self.config.ray
        actor_class = self._remote_class.options(
            num_cpus=ray_config.num_cpus_per_worker,
            resources=worker.resources or None,
            max_restarts=ray_config.max_restarts,
            max_task_retries=0,  # a lost share is replayed here, whole, with its seeds
        )
        return actor_class.remote(
            index,
            worker.apparatus,
            worker.apparatus_args,
            worker.envs,
            self.task,
            self.config.history,
            self.config.threads,
            (self.config.design, self.config.payoff, self.config.reference),
            tuple(self.config.anchor_ratings()),
        )

    def fail_after(self, worker: int, steps: int) -> None:
        """A drill: worker `worker`'s process exits after `steps` more aligner steps."""
        self._start()
        ray.get(self._actors[worker].fail_after.remote(steps))

    def close(self) -> None:
        """End the workers, and the Ray this backend started (not one it joined)."""
        for actor in self._actors:
            ray.kill(actor, no_restart=True)
        self._actors = []
        if self._started_ray and ray.is_initialized():
            ray.shutdown()
        self._started_ray = False

    # --- matches ------------------------------------------------------------------------

    def play(
        self,
        aligner: Agent,
        misaligner: Agent,
        matches: int,
        rng: np.random.Generator,
        learning: set[str],
        on_episode: Callable[[bool], None] | None = None,
        deterministic: bool = False,
        anchored: bool = False,
    ) -> MatchResult:
        """`matches` matches on the workers, then learning here: the same contract as
        alignrl.league.backends.InProcessBackend.play."""
        self._start()
        seeds = [int(seed) for seed in rng.integers(0, 2**31 - 1, matches)]
        policies = ray.put(
            {"aligner": aligner.policy_state(), "misaligner": misaligner.policy_state()}
        )
        learns = (aligner.id in learning, misaligner.id in learning)
        shares: dict[int, list[int]] = {}
        first = 0
        for index, count in enumerate(split_matches(matches, [w.envs for w in self.workers])):
            if count:
                shares[index] = seeds[first : first + count]
            first += count

        def submit(index: int) -> Any:
            return self._actors[index].play.remote(
                policies, shares[index], self._complexity, learns, deterministic, anchored
            )

        played = self._gather({index: submit(index) for index in shares}, submit)
        trajectories = [match for index in sorted(played) for match in played[index]]
        return learn_from_matches(trajectories, aligner, misaligner, learning, rng, on_episode)

    def _gather(
        self, pending: dict[int, Any], submit: Callable[[int], Any]
    ) -> dict[int, list[MatchTrajectory]]:
        """Every worker's trajectories; a lost worker's share is submitted again."""
        by_reference = {reference: index for index, reference in pending.items()}
        failures = dict.fromkeys(pending, 0)
        played: dict[int, list[MatchTrajectory]] = {}
        while by_reference:
            (ready,), _ = ray.wait(list(by_reference), num_returns=1)
            index = by_reference.pop(ready)
            try:
                played[index] = ray.get(ready)
            except RayActorError as error:
                failures[index] += 1
                self._recover(index, failures[index], error)
                by_reference[submit(index)] = index
            except RayTaskError as error:  # an exception in the worker's code: no replay helps
                raise WorkerFailedError(
                    f"worker {index} ({self._name(index)}) failed: {error}"
                ) from None
        return played

    def _recover(self, index: int, failures: int, error: RayActorError) -> None:
        """After worker `index` was lost: give up, or wait until it is back."""
        if error.actor_init_failed:
            raise WorkerFailedError(
                f"worker {index} ({self._name(index)}) could not start: {error}"
            ) from None
        limit = self.config.ray.max_restarts
        if failures > limit:
            raise WorkerFailedError(
                f"worker {index} ({self._name(index)}) was lost mid-batch {failures} "
                f"{'time' if failures == 1 else 'times'} (ray.max_restarts: {limit}); "
                f"its last error: {error}"
            ) from None
        if not self._answers(index):
            # Ray has spent this actor's restarts over the league's life: a new worker.
            self._actors[index] = self._create(index)
            if not self._answers(index):
                raise WorkerFailedError(
                    f"worker {index} ({self._name(index)}) died again as soon as it started"
                )
        self.replays[index] += 1

    def _answers(self, index: int) -> bool:
        """Wait until worker `index` answers (while Ray starts or restarts it); False if it
        is dead for good."""
        deadline = time.monotonic() + WORKER_START_TIMEOUT_S
        while True:
            try:
                left = max(deadline - time.monotonic(), 1.0)
                ray.get(self._actors[index].describe.remote(), timeout=left)
                return True
            except ActorUnavailableError:  # being restarted: calls are refused meanwhile
                if time.monotonic() > deadline:
                    break
                time.sleep(RESTART_POLL_S)
            except ActorDiedError as error:
                if error.actor_init_failed:
                    raise WorkerFailedError(
                        f"worker {index} ({self._name(index)}) could not start: {error}"
                    ) from None
                return False
            except GetTimeoutError:
                break
        resources = self.workers[index].resources or "(CPUs only)"
        raise WorkerFailedError(
            f"worker {index} ({self._name(index)}) did not answer within "
            f"{WORKER_START_TIMEOUT_S:.0f} s: is a PC that offers its resources {resources} "
            "in the cluster?"
        )

"""An aligner that learns from a teacher: a controller's moves, cloned into the network
(issue 21).

The Bayesian autofocus of alignrl/evaluation/posterior.py aligns more of the held-out columns
than any trained champion, in fewer acquisitions, but costs seconds per alignment. Here it
teaches a network that acts in one forward pass: it plays the alignment env's episodes (the
training family's columns), and at every step says the action it would take; the network is
fitted to those actions (behaviour cloning), and, in later rounds, the network itself plays
while the teacher labels every state it reaches (DAgger: the network learns to recover from
its own mistakes, not only to follow a path it never leaves).

`PosteriorTeacher` turns the posterior's settings into the env's actions: a probe becomes the
move that lands there (the inverse of Task.knob_change, within the task's maximum step and
above its floor), a stop becomes the stopping action whose move ends the episode at the
posterior's best setting (Task.final_move), once it is within one move. The teacher reads the
readings in px, as the env measures them; a unit-free policy sees their ratios only, so the
teacher that a network can follow is the posterior in an unknown pixel scale
(`PosteriorFocus(scale_free=True)`), whose decisions depend on the ratios alone: the box
posterior in the box's pixels takes its first probe from the first reading's pixels, which
no unit-free policy can tell apart (docs/benchmarks.md, "An aligner taught by the Bayesian
autofocus").

`collect` plays episodes and returns `Demonstrations` (the observations, the teacher's
actions, and each step as a transition for a SAC replay: the acting action, reward, next
observation, done, secrets); `clone` fits an Agent's actor to them. The transitions let an
adaptation continue with SAC from the cloned actor on what the teacher showed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import PosteriorFocus

__all__ = ["Demonstrations", "PosteriorTeacher", "clone", "collect"]

LABEL_LIMIT = 0.98  # teacher actions are fitted within (-this, this): tanh never reaches 1
# The per-step arrays of Demonstrations, in order.
STEP_FIELDS = (
    "observation", "label", "action", "reward", "next_observation", "done", "secret", "next_secret",
)  # fmt: skip


def action_for_move(move: float, max_step: float, power: float, floor: float) -> float:
    """The action in [-1, 1] whose knob change (Task.knob_change, fractions of the interval)
    is `move`, as near as the floor and the maximum step allow."""
    if move == 0.0:
        return 0.0
    reach = max(abs(move) - floor, 0.0) / max_step
    magnitude = min(reach ** (1.0 / power), 1.0)
    return math.copysign(max(magnitude, 1e-3), move)


class PosteriorTeacher:
    """One PosteriorFocus per env slot, fed every reading the slot takes (module doc)."""

    def __init__(self, env: VectorAlignmentEnv, posterior: Callable[[], PosteriorFocus]) -> None:
        episodes = env.episodes
        if episodes.k != 1:
            raise ValueError("the posterior teaches one-knob focus tasks only")
        task = env.task
        if not (task.final_move and task.approach_from_below):
            raise ValueError(
                "a posterior teacher needs task_options.final_move (it ends between its "
                "readings) and approach_from_below (its reading model)"
            )
        self.env = env
        self.power = task.action_power
        self.floor = task.move_floor
        self.posteriors = [posterior() for _ in range(env.num_envs)]

    def start(self, indices: np.ndarray) -> None:
        """New episodes in `indices`: their first readings, as the env holds them now."""
        episodes = self.env.episodes
        positions = episodes.positions()
        for index in indices:
            self.posteriors[index].begin()
            self.posteriors[index].observe(positions[index, 0], episodes.width[index])

    def read(self, indices: np.ndarray, infos: dict) -> None:
        """The readings the step just took on `indices` (slots whose episodes go on)."""
        for index in indices:
            self.posteriors[index].observe(
                infos["position"][index, 0], infos["edge_width_px"][index]
            )

    def actions(self) -> np.ndarray:
        """(N, 2): the teacher's action for every slot's present state."""
        episodes = self.env.episodes
        positions = episodes.positions()[:, 0]
        max_steps = (episodes.max_step / episodes.span)[:, 0]
        left = self.env.task.episode_steps - episodes.steps
        out = np.zeros((self.env.num_envs, 2))
        for index, posterior in enumerate(self.posteriors):
            target, done = posterior.decide()
            if left[index] <= 1 and not done:  # the last move: end at the best setting now
                target, done = posterior.final()[0], True
            move = float(np.clip(target, 0.0, 1.0)) - float(positions[index])
            if done and abs(move) <= max_steps[index]:
                out[index] = [action_for_move(move, max_steps[index], self.power, 0.0), 1.0]
            else:  # a probe, or on the way to a best setting beyond one move
                out[index] = [
                    action_for_move(move, max_steps[index], self.power, self.floor),
                    -1.0,
                ]
        return out


@dataclass
class Demonstrations:
    """Steps of played episodes: what the network sees and what the teacher would do there,
    and the transition each step was (for a replay buffer)."""

    observation: np.ndarray  # (T, H, F)
    label: np.ndarray  # (T, A) the teacher's action
    action: np.ndarray  # (T, A) the action taken (the teacher's or the student's)
    reward: np.ndarray  # (T,)
    next_observation: np.ndarray  # (T, H, F) the episode's last where it ended
    done: np.ndarray  # (T,) bool
    secret: np.ndarray  # (T, S)
    next_secret: np.ndarray  # (T, S)
    episodes: int = 0
    successes: int = 0
    acquisitions: tuple[int, ...] = ()

    def save(self, path: str) -> None:
        arrays = {name: getattr(self, name) for name in STEP_FIELDS}
        np.savez_compressed(
            path, **arrays, episodes=self.episodes, successes=self.successes,
            acquisitions=np.array(self.acquisitions, np.int64),
        )  # fmt: skip

    @classmethod
    def load(cls, path: str) -> Demonstrations:
        with np.load(path, allow_pickle=False) as data:
            fields = {name: data[name] for name in STEP_FIELDS}
            return cls(
                **fields, episodes=int(data["episodes"]), successes=int(data["successes"]),
                acquisitions=tuple(int(a) for a in data["acquisitions"]),
            )  # fmt: skip

    def rows(self, rows: np.ndarray) -> Demonstrations:
        """The steps `rows` alone (episode counts are left out)."""
        return Demonstrations(**{name: getattr(self, name)[rows] for name in STEP_FIELDS})

    @classmethod
    def joined(cls, parts: list[Demonstrations]) -> Demonstrations:
        arrays = {
            name: np.concatenate([getattr(part, name) for part in parts]) for name in STEP_FIELDS
        }
        return cls(
            **arrays,
            episodes=sum(part.episodes for part in parts),
            successes=sum(part.successes for part in parts),
            acquisitions=tuple(a for part in parts for a in part.acquisitions),
        )


def collect(
    env: VectorAlignmentEnv,
    teacher: PosteriorTeacher,
    episodes: int,
    seed: int,
    student: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Demonstrations:
    """Play `episodes` episodes on `env`, the teacher labelling every step; the teacher acts,
    or, given a `student` (observations -> actions), the student does (DAgger)."""
    observation, infos = env.reset(seed=seed)
    secret = infos["secret"]
    teacher.start(np.arange(env.num_envs))
    rows: dict[str, list[np.ndarray]] = {name: [] for name in STEP_FIELDS}
    finished = successes = 0
    acquisitions: list[int] = []
    while finished < episodes:
        label = teacher.actions()
        action = label if student is None else np.asarray(student(observation), np.float64)
        next_observation, reward, done, _, infos = env.step(action)
        last = np.where(done[:, None, None], infos.get("final_observation", next_observation),
                        next_observation)  # fmt: skip
        next_secret = infos.get("final_secret", infos["secret"])
        step = (observation, label, action, reward, last, done, secret, next_secret)
        for name, value in zip(STEP_FIELDS, step, strict=True):
            rows[name].append(np.asarray(value))
        ended = np.flatnonzero(done)
        teacher.read(np.flatnonzero(~done), infos)
        teacher.start(ended)
        finished += ended.size
        successes += int(infos["success"][ended].sum())
        acquisitions.extend(int(infos["acquisitions"][index]) for index in ended)
        if progress:
            progress(ended.size)
        observation, secret = next_observation, infos["secret"]
    arrays = {name: np.concatenate(values) for name, values in rows.items()}
    for name in ("observation", "next_observation"):
        arrays[name] = arrays[name].astype(np.float32)
    return Demonstrations(**arrays, episodes=finished, successes=successes,
                          acquisitions=tuple(acquisitions))  # fmt: skip


def clone(
    actor: torch.nn.Module,
    data: Demonstrations,
    epochs: int,
    seed: int,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    log: Callable[[int, float], None] | None = None,
    continue_weight: float = 1.0,
) -> float:
    """Fit `actor` (alignrl.agents.sac.Actor: a tanh-Gaussian) to the teacher's actions: its
    mean by least squares on their pre-tanh values, its spread by their likelihood around it;
    returns the last epoch's mean loss. `continue_weight` weighs the stop component of the
    steps where the teacher goes on (a stop too early loses the column, one too late costs an
    image)."""
    generator = torch.Generator().manual_seed(seed)
    observations = torch.as_tensor(data.observation, dtype=torch.float32)
    target = torch.atanh(
        torch.as_tensor(np.clip(data.label, -LABEL_LIMIT, LABEL_LIMIT), dtype=torch.float32)
    )
    weight = torch.ones_like(target)
    weight[:, -1] = torch.where(target[:, -1] < 0, continue_weight, 1.0)
    optimizer = torch.optim.Adam(actor.parameters(), lr=learning_rate)
    loss_value = math.nan
    for epoch in range(epochs):
        order = torch.randperm(len(observations), generator=generator)
        total, count = 0.0, 0
        for start in range(0, len(order), batch_size):
            batch = order[start : start + batch_size]
            mean, log_std = actor(observations[batch])
            # The mean by least squares on the pre-tanh actions, the spread by the
            # likelihood of the teacher's actions around that mean (its own gradient only).
            error = target[batch] - mean
            z = error.detach() / log_std.exp()
            loss = 0.5 * weight[batch] * error.square() + 0.5 * z.square() + log_std
            loss = loss.sum(-1).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * len(batch)
            count += len(batch)
        loss_value = total / count
        if log:
            log(epoch, loss_value)
    return loss_value

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
posterior's best setting (final_move), once it is within one move (of the fit's optimum
where the task's last move starts there: finish_at_fit). The teacher reads the
readings in px, as the env measures them; a unit-free policy sees their ratios only, so the
teacher that a network can follow is the posterior in an unknown pixel scale
(`BayesianAutofocus(scale_free=True)`), whose decisions depend on the ratios alone: the box
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
from dataclasses import dataclass, replace

import numpy as np
import torch

from alignrl.envs.core import feature_layout
from alignrl.envs.fit_features import FIT_FEATURES, bracketed_optimum, fit_features
from alignrl.envs.task import knob_change
from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import BayesianAutofocus

__all__ = ["Demonstrations", "PosteriorTeacher", "clone", "collect"]

LABEL_LIMIT = 0.98  # teacher actions are fitted within (-this, this): tanh never reaches 1
# The per-step arrays of Demonstrations, in order.
STEP_FIELDS = (
    "observation",
    "label",
    "action",
    "reward",
    "next_observation",
    "done",
    "secret",
    "next_secret",
)


def action_for_move(move: float, max_step: float, power: float, floor: float) -> float:
    """The action in [-1, 1] whose knob change (Task.knob_change, fractions of the interval)
    is `move`, as near as the floor and the maximum step allow."""
    if move == 0.0:
        return 0.0
    reach = max(abs(move) - floor, 0.0) / max_step
    magnitude = min(reach ** (1.0 / power), 1.0)
    return math.copysign(max(magnitude, 1e-3), move)


class PosteriorTeacher:
    """One BayesianAutofocus per env slot, fed every reading the slot takes (module doc)."""

    def __init__(self, env: VectorAlignmentEnv, posterior: Callable[[], BayesianAutofocus]) -> None:
        episodes = env.episodes
        if episodes.k != 1:
            raise ValueError("the posterior teaches one-knob focus tasks only")
        task = env.task
        if not (task.ending.final_move and task.ending.approach_from_below):
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

    def ends(self, indices: np.ndarray) -> np.ndarray:
        """(len(indices),): the knob action of a stopping move that ends each slot's episode
        at its posterior's best setting now (from the task's stop origin, within the last
        move's reach): what the teacher would end with, wherever it stands."""
        targets = np.array([self.posteriors[index].final()[0] for index in indices])
        return self._last_moves(indices, targets)[0]

    def _last_moves(self, indices: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, ...]:
        """The stopping knob actions that end `indices` at `targets` (fractions of the
        interval) from the task's stop origins (final_move; finish_at_fit), and where
        each target lies within the last move's reach."""
        episodes = self.env.episodes
        origins = (episodes.stop_origins(indices) - episodes.low[indices]) / episodes.span[indices]
        reach = (episodes.max_step / episodes.span)[
            indices, 0
        ] * self.env.task.ending.final_move_reach
        moves = np.clip(targets, 0.0, 1.0) - origins[:, 0]
        actions = [
            action_for_move(float(move), float(most), self.power, 0.0)
            for move, most in zip(moves, reach, strict=True)
        ]
        return np.array(actions), np.abs(moves) <= reach

    def actions(self) -> np.ndarray:
        """(N, 2): the teacher's action for every slot's present state: a stop where the
        posterior is done and its best setting lies within the last move's reach, else a
        probe (or a move on the way to a best setting beyond that reach)."""
        episodes = self.env.episodes
        max_steps = (episodes.max_step / episodes.span)[:, 0]
        left = self.env.task.episode_steps - episodes.steps
        targets, done = np.zeros(self.env.num_envs), np.zeros(self.env.num_envs, bool)
        for index, posterior in enumerate(self.posteriors):
            targets[index], done[index] = posterior.decide()
            if left[index] <= 1 and not done[index]:  # the last move: end at the best now
                targets[index], done[index] = posterior.final()[0], True
        targets = np.clip(targets, 0.0, 1.0)
        moves = targets - episodes.positions()[:, 0]
        out = np.zeros((self.env.num_envs, 2))
        out[:, 0] = [
            action_for_move(float(move), float(most), self.power, self.floor)
            for move, most in zip(moves, max_steps, strict=True)
        ]
        out[:, 1] = -1.0
        ending = np.flatnonzero(done)
        last, within = self._last_moves(ending, targets[ending])
        out[ending[within]] = np.stack([last[within], np.ones(within.sum())], axis=1)
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
    # The stopping actions move from a fit's optimum (collected with finish_at_fit, or
    # moved_from_fit), not from the present setting.
    ends_from_fit: bool = False

    def save(self, path: str) -> None:
        arrays = {name: getattr(self, name) for name in STEP_FIELDS}
        np.savez_compressed(
            path,
            **arrays,
            episodes=self.episodes,
            successes=self.successes,
            acquisitions=np.array(self.acquisitions, np.int64),
            ends_from_fit=self.ends_from_fit,
        )

    @classmethod
    def load(cls, path: str) -> Demonstrations:
        with np.load(path, allow_pickle=False) as data:
            fields = {name: data[name] for name in STEP_FIELDS}
            return cls(
                **fields,
                episodes=int(data["episodes"]),
                successes=int(data["successes"]),
                acquisitions=tuple(int(a) for a in data["acquisitions"]),
                ends_from_fit=bool(data["ends_from_fit"]) if "ends_from_fit" in data else False,
            )

    def rows(self, rows: np.ndarray) -> Demonstrations:
        """The steps `rows` alone (episode counts are left out)."""
        return Demonstrations(
            **{name: getattr(self, name)[rows] for name in STEP_FIELDS},
            ends_from_fit=self.ends_from_fit,
        )

    def with_fit_features(self, step: float, window: float) -> Demonstrations:
        """These steps as a task with `fit_features` would have shown them: every history
        row gains the fit features of the window it was written into (the rows up to it;
        alignrl/envs/fit_features.py), with one maximum step of `step` in the knob column's
        units and the task's `fit_window`. A window that had already lost its oldest rows
        (an episode longer than the history) is fitted on the rows it still holds."""
        fields = {name: getattr(self, name) for name in STEP_FIELDS}
        for name in ("observation", "next_observation"):
            fields[name] = _with_fit_features(fields[name], step, window)
        return replace(self, **fields)

    def moved_from_fit(
        self, max_step: float, power: float, window: float, reach: float = 1.0
    ) -> Demonstrations:
        """These steps as a task with final_move and finish_at_fit asks for them: every
        stopping action (the teacher's label, and the action taken) says the same end as a
        move from where a fit of the episode's readings puts the optimum (a bracketed one,
        within `window` x the narrowest; alignrl/envs/ending.py) instead of from the present
        setting, a move of `reach` x `max_step` at most (final_move_reach). `max_step`:
        one maximum step, a fraction of the interval; `power`: the task's action_power. An
        end beyond one last move of the fit is clipped to it (the episode then ends at the
        fit's side of it), and a fit is made on the readings the history still holds. Steps
        whose ends already move from a fit are returned as they are."""
        if self.ends_from_fit:
            return self
        moved = {}
        for name in ("label", "action"):
            actions = getattr(self, name).copy()
            for row in np.flatnonzero(actions[:, 1] > 0):
                actions[row, 0] = _from_fit(
                    self.observation[row], actions[row, 0], max_step, power, window, reach
                )
            moved[name] = actions
        return replace(self, **moved, ends_from_fit=True)

    @classmethod
    def joined(cls, parts: list[Demonstrations]) -> Demonstrations:
        if len({part.ends_from_fit for part in parts}) > 1:
            raise ValueError(
                "steps whose ends move from a fit and steps whose ends do not: "
                "move the others first (moved_from_fit)"
            )
        arrays = {
            name: np.concatenate([getattr(part, name) for part in parts]) for name in STEP_FIELDS
        }
        return cls(
            **arrays,
            episodes=sum(part.episodes for part in parts),
            successes=sum(part.successes for part in parts),
            acquisitions=tuple(a for part in parts for a in part.acquisitions),
            ends_from_fit=parts[0].ends_from_fit,
        )


def _from_fit(
    history: np.ndarray,
    action: float,
    max_step: float,
    power: float,
    window: float,
    reach: float,
) -> float:
    """The stopping action from the fit's optimum that ends where `action` from the present
    setting ends (Demonstrations.moved_from_fit)."""
    layout = feature_layout(1)
    knob = (history[:, layout["knobs"].start].astype(np.float64) + 1.0) / 2.0
    measured = (history[:, layout["valid"].start] > 0) & (history[:, layout["measured"].start] > 0)
    quality = history[:, layout["quality"].start].astype(np.float64)
    optimum = bracketed_optimum(knob[measured], np.exp(quality[measured]), window)
    end = knob[-1] + knob_change(np.array([action]), np.array([max_step]), power)[0]
    origin = knob[-1] if optimum is None else np.clip(optimum, 0.0, 1.0)
    return action_for_move(float(end - origin), reach * max_step, power, 0.0)


def _with_fit_features(histories: np.ndarray, step: float, window: float) -> np.ndarray:
    """(T, H, F) histories of a one-knob task without extra features -> (T, H, F + 3)."""
    count, rows, width = histories.shape
    layout = feature_layout(1)
    if width != layout["steps_left"].stop:
        raise ValueError(f"histories of {width} features: fit features go on rows without extras")
    out = np.zeros((count, rows, width + FIT_FEATURES), np.float32)
    out[:, :, :width] = histories
    steps = np.full(count, step)
    for row in range(rows):
        written = np.zeros((count, rows, width), np.float32)  # the window when row was new
        written[:, rows - 1 - row :] = histories[:, : row + 1]
        valid = written[:, -1, layout["valid"].start] > 0
        features = fit_features(
            written[valid, :, layout["knobs"].start],
            written[valid, :, layout["quality"].start],
            written[valid, :, layout["valid"].start] * written[valid, :, layout["measured"].start],
            steps[valid],
            window,
        )
        out[valid, row, width:] = features
    return out


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
        last = np.where(
            done[:, None, None], infos.get("final_observation", next_observation), next_observation
        )
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
    ending = env.task.ending
    return Demonstrations(
        **arrays,
        episodes=finished,
        successes=successes,
        acquisitions=tuple(acquisitions),
        ends_from_fit=ending.final_move and ending.at == "fit",
    )


def clone(
    actor: torch.nn.Module,
    data: Demonstrations,
    epochs: int,
    seed: int,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    log: Callable[[int, float], None] | None = None,
    continue_weight: float = 1.0,
    anneal: bool = False,
    end_weight: float = 1.0,
) -> float:
    """Fit `actor` (alignrl.agents.sac.Actor: a tanh-Gaussian) to the teacher's actions: its
    mean by least squares on their pre-tanh values, its spread by their likelihood around it;
    returns the last epoch's mean loss. `continue_weight` weighs the stop component of the
    steps where the teacher goes on (a stop too early loses the column, one too late costs an
    image); `end_weight` the knob components of the steps where it stops (the last move,
    which must land within the spec). `anneal`: the learning rate falls to zero over the
    epochs along a half cosine (the fit settles where a constant rate keeps it wandering)."""
    generator = torch.Generator().manual_seed(seed)
    observations = torch.as_tensor(data.observation, dtype=torch.float32)
    target = torch.atanh(
        torch.as_tensor(np.clip(data.label, -LABEL_LIMIT, LABEL_LIMIT), dtype=torch.float32)
    )
    weight = torch.ones_like(target)
    weight[:, -1] = torch.where(target[:, -1] < 0, continue_weight, 1.0)
    weight[:, :-1] = torch.where(target[:, -1:] > 0, end_weight, 1.0)
    optimizer = torch.optim.Adam(actor.parameters(), lr=learning_rate)
    batches = epochs * math.ceil(len(observations) / batch_size)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda done: 0.5 * (1.0 + math.cos(math.pi * done / batches)) if anneal else 1.0
    )
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
            schedule.step()
            total += float(loss.detach()) * len(batch)
            count += len(batch)
        loss_value = total / count
        if log:
            log(epoch, loss_value)
    return loss_value

"""alignrl/imitation.py: the posterior teaches the env's actions (probes land where it asked,
a stop ends at its best setting), episodes are collected with the teacher or a student acting,
and cloning fits an actor to the teacher's labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from alignrl.agents.sac import Actor, SACConfig
from alignrl.apparatus.family import family_path, load_family
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.config import TaskOptions
from alignrl.envs.task import get_task, knob_change
from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import PosteriorFocus
from alignrl.imitation import Demonstrations, PosteriorTeacher, action_for_move, clone, collect

OPTIONS = dict(
    final_move=True, approach_from_below=True, action_power=2.0, move_floor=0.02,
    quality_reference="first", verify_final=True,
)  # fmt: skip


def _env(envs: int = 2, **options) -> VectorAlignmentEnv:
    task = TaskOptions(**{**OPTIONS, **options}).apply(get_task("focus"))
    apparatus = make_apparatus_copies("family:focus", {"analytic": True}, envs)
    return VectorAlignmentEnv(apparatus, task, history=6)


def _small_posterior() -> PosteriorFocus:
    return PosteriorFocus(load_family(family_path("focus")), draws=16, specimen_points=1)


@pytest.mark.parametrize("power, floor", [(1.0, 0.0), (2.0, 0.02), (2.0, 0.0)])
def test_an_action_for_a_move_asks_for_that_move(power, floor) -> None:
    moves = np.array([-0.24, -0.1, -0.03, 0.025, 0.07, 0.2])
    actions = np.array([action_for_move(move, 0.25, power, floor) for move in moves])
    np.testing.assert_allclose(knob_change(actions, 0.25, power, floor), moves, atol=1e-9)
    # Beyond the reach: the longest move that way.
    assert action_for_move(0.9, 0.25, power, floor) == 1.0
    assert action_for_move(-0.9, 0.25, power, floor) == -1.0
    assert action_for_move(0.0, 0.25, power, floor) == 0.0


def test_a_teacher_needs_a_task_that_ends_between_readings() -> None:
    with pytest.raises(ValueError, match="final_move"):
        PosteriorTeacher(_env(final_move=False), _small_posterior)


def test_the_teachers_episodes_align_and_a_clone_learns_its_actions() -> None:
    env = _env(envs=2)
    data = collect(env, PosteriorTeacher(env, _small_posterior), episodes=6, seed=4)
    steps = len(data.label)
    assert data.episodes >= 6 and data.successes >= 4  # the teacher aligns the family
    assert data.observation.shape == (steps, 6, env.single_observation_space.shape[1])
    assert np.all(np.abs(data.label) <= 1.0)
    np.testing.assert_array_equal(data.action, data.label)  # the teacher acted
    assert data.done.sum() == data.episodes
    stops = data.label[:, 1] > 0
    assert np.all(data.done[stops])  # every stop ended its episode
    # Cloning: the actor's deterministic actions come nearer the labels than before.
    torch.manual_seed(0)
    actor = Actor(6, data.observation.shape[2], 2, SACConfig(encoder="mlp", hidden=(64, 64)))

    def error() -> float:
        with torch.no_grad():
            mean, _ = actor(torch.as_tensor(data.observation))
        return float(np.mean(np.abs(np.tanh(mean.numpy()) - data.label)))

    before = error()
    clone(actor, data, epochs=150, seed=0, batch_size=64)
    assert error() < 0.5 * before


def test_demonstrations_round_trip_and_join(tmp_path) -> None:
    env = _env(envs=1)
    data = collect(env, PosteriorTeacher(env, _small_posterior), episodes=1, seed=2)
    path = tmp_path / "d.npz"
    data.save(str(path))
    loaded = Demonstrations.load(str(path))
    np.testing.assert_array_equal(loaded.observation, data.observation)
    assert loaded.acquisitions == data.acquisitions and loaded.episodes == data.episodes
    both = Demonstrations.joined([data, loaded])
    assert len(both.label) == 2 * len(data.label) and both.episodes == 2 * data.episodes
    part = both.rows(np.array([0, len(data.label)]))  # the first step of each copy
    np.testing.assert_array_equal(part.observation[0], part.observation[1])
    np.testing.assert_array_equal(part.label[0], data.label[0])


def test_a_student_acts_while_the_teacher_labels() -> None:
    env = _env(envs=2)
    student_actions = np.array([[0.3, -1.0], [0.3, -1.0]])
    data = collect(
        env, PosteriorTeacher(env, _small_posterior), episodes=2, seed=1,
        student=lambda observation: student_actions,
    )  # fmt: skip
    assert np.all(data.action == student_actions[0])  # never stops: runs to the step limit
    assert not np.array_equal(data.label, data.action)
    assert len(data.label) == 2 * env.task.episode_steps


def test_a_continue_weight_tips_an_undecided_stop_towards_going_on() -> None:
    """The same history labelled stop half the time and go on the other half: weighing the
    go-on labels more makes the clone go on, weighing them less makes it stop."""
    rows = 64
    observation = np.zeros((rows, 6, 7), np.float32)
    observation[:, -1, 0] = 1.0
    label = np.zeros((rows, 2))
    label[:, 1] = np.where(np.arange(rows) % 2 == 0, 1.0, -1.0)
    data = Demonstrations(
        observation=observation, label=label, action=label, reward=np.zeros(rows),
        next_observation=observation, done=label[:, 1] > 0, secret=np.zeros((rows, 1)),
        next_secret=np.zeros((rows, 1)),
    )  # fmt: skip
    stops = {}
    for weight in (3.0, 1.0 / 3.0):
        torch.manual_seed(0)
        actor = Actor(6, 7, 2, SACConfig(encoder="mlp", hidden=(32,)))
        clone(actor, data, epochs=200, seed=0, batch_size=64, continue_weight=weight)
        with torch.no_grad():
            mean, _ = actor(torch.as_tensor(observation[:1]))
        stops[weight] = float(mean[0, 1])
    assert stops[3.0] < 0 < stops[1.0 / 3.0]

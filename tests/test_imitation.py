"""benchmarks/imitation.py: the posterior teaches the env's actions (probes land where it asked,
a stop ends at its best setting), episodes are collected with the teacher or a student acting,
and cloning fits an actor to the teacher's labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from alignrl.agents.sac import Actor, SACConfig
from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.registry import make_apparatus_copies
from alignrl.config.task_options import TaskOptions
from alignrl.envs.fit_features import bracketed_optimum
from alignrl.envs.task import get_task, knob_change
from alignrl.envs.vector import VectorAlignmentEnv
from alignrl.evaluation.posterior import BayesianAutofocus
from benchmarks.imitation import Demonstrations, PosteriorTeacher, action_for_move, clone, collect

OPTIONS = dict(
    final_move=True,
    approach_from_below=True,
    action_power=2.0,
    move_floor=0.02,
    quality_reference="first",
    verify_final=True,
)


def _env(envs: int = 2, history: int = 6, **options) -> VectorAlignmentEnv:
    task = TaskOptions(**{**OPTIONS, **options}).apply(get_task("focus"))
    apparatus = make_apparatus_copies("family:focus", {"analytic": True}, envs)
    return VectorAlignmentEnv(apparatus, task, history=history)


def _small_posterior() -> BayesianAutofocus:
    return BayesianAutofocus(load_family(family_path("focus")), draws=16, specimen_points=1)


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
    assert not loaded.ends_from_fit
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
        env,
        PosteriorTeacher(env, _small_posterior),
        episodes=2,
        seed=1,
        student=lambda observation: student_actions,
    )
    assert np.all(data.action == student_actions[0])  # never stops: runs to the step limit
    assert not np.array_equal(data.label, data.action)
    assert len(data.label) == 2 * env.task.episode_steps


def _one_row_steps(label: np.ndarray, knob: np.ndarray | None = None) -> Demonstrations:
    """Steps of histories of one valid row (its knob at `knob`, else 0) labelled `label`."""
    rows = len(label)
    observation = np.zeros((rows, 6, 7), np.float32)
    observation[:, -1, 0] = 1.0
    if knob is not None:
        observation[:, -1, 1] = knob
    return Demonstrations(
        observation=observation,
        label=label,
        action=label,
        reward=np.zeros(rows),
        next_observation=observation,
        done=label[:, 1] > 0,
        secret=np.zeros((rows, 1)),
        next_secret=np.zeros((rows, 1)),
    )


def _cloned_mean(data: Demonstrations, hidden: tuple[int, ...], **options) -> np.ndarray:
    """The pre-tanh mean action, on every step, of a small MLP actor cloned on `data`."""
    torch.manual_seed(0)
    actor = Actor(6, 7, 2, SACConfig(encoder="mlp", hidden=hidden))
    clone(actor, data, seed=0, batch_size=64, **options)
    with torch.no_grad():
        return actor(torch.as_tensor(data.observation))[0].numpy()


def test_a_continue_weight_tips_an_undecided_stop_towards_going_on() -> None:
    """The same history labelled stop half the time and go on the other half: weighing the
    go-on labels more makes the clone go on, weighing them less makes it stop."""
    label = np.zeros((64, 2))
    label[:, 1] = np.where(np.arange(64) % 2 == 0, 1.0, -1.0)
    data = _one_row_steps(label)
    stops = {
        weight: float(_cloned_mean(data, (32,), epochs=200, continue_weight=weight)[0, 1])
        for weight in (3.0, 1.0 / 3.0)
    }
    assert stops[3.0] < 0 < stops[1.0 / 3.0]


def test_an_end_weight_pulls_the_knob_towards_the_last_moves() -> None:
    """The same history labelled half as a stop with a knob of +0.5, half as a probe of -0.5:
    weighing the stops' knob error more pulls the knob towards +0.5, less towards -0.5."""
    stop = np.arange(64) % 2 == 0
    data = _one_row_steps(np.stack([np.where(stop, 0.5, -0.5), np.where(stop, 1.0, -1.0)], 1))
    knobs = {
        weight: float(_cloned_mean(data, (32,), epochs=200, end_weight=weight)[0, 0])
        for weight in (3.0, 1.0 / 3.0)
    }
    assert knobs[1.0 / 3.0] < 0 < knobs[3.0]


def test_an_annealed_clone_settles_on_a_sharp_switch() -> None:
    """The teacher's first probe switches direction across the interval (the posterior's
    mirror-image probes): with the learning rate annealed the clone follows the switch more
    closely than at a constant rate, over the same epochs."""
    knob = np.linspace(-1.0, 1.0, 512, dtype=np.float32)
    label = np.stack([np.where(knob < 0.1, 0.8, -0.8), -np.ones(512)], axis=1)
    data = _one_row_steps(label, knob)
    errors = {}
    for anneal in (False, True):
        mean = _cloned_mean(data, (32, 32), epochs=60, learning_rate=3e-3, anneal=anneal)
        errors[anneal] = float(np.mean(np.abs(np.tanh(mean[:, 0]) - label[:, 0])))
    assert errors[True] < 0.8 * errors[False]


def test_fit_features_added_afterwards_are_those_the_env_shows() -> None:
    """Steps collected without fit features, given them afterwards, read as the same
    teacher's steps collected in an env that shows them (the same columns and readings):
    a history longer than an episode, so that every window is whole."""
    plain, fitted = _env(envs=2, history=12), _env(envs=2, history=12, fit_features=True)
    base = collect(plain, PosteriorTeacher(plain, _small_posterior), episodes=4, seed=3)
    shown = collect(fitted, PosteriorTeacher(fitted, _small_posterior), episodes=4, seed=3)
    steps = 2.0 * fitted.episodes.max_step[:, 0] / fitted.episodes.span[:, 0]
    assert np.allclose(steps, steps[0])
    added = base.with_fit_features(float(steps[0]), fitted.task.fit_window)
    np.testing.assert_array_equal(added.label, shown.label)
    np.testing.assert_allclose(added.observation, shown.observation, atol=1e-6)
    np.testing.assert_allclose(added.next_observation, shown.next_observation, atol=1e-6)
    assert shown.observation[..., -3].max() == 1.0  # some rows were fitted
    with pytest.raises(ValueError, match="extras"):
        shown.with_fit_features(float(steps[0]), 3.0)


def test_a_last_move_from_the_fit_ends_where_the_teacher_asks() -> None:
    """With finish_at_fit the stopping move starts from the fit's optimum: the teacher's
    stopping actions end every episode at the posterior's best setting all the same, and
    steps collected in the plain task, moved from the fit afterwards, end where they did."""
    env = _env(envs=1, history=12, finish_at_fit=True)
    teacher = PosteriorTeacher(env, _small_posterior)
    env.reset(seed=5)
    teacher.start(np.arange(1))
    ends, moved_from_fit = 0, 0
    while ends < 4:
        action = teacher.actions()
        if action[0, 1] > 0:
            target = float(np.clip(teacher.posteriors[0].final()[0], 0.0, 1.0))
            origin = env.episodes.stop_origins(np.arange(1))[0, 0]
            moved_from_fit += origin != env.episodes.setting[0, 0]
        _, _, done, _, infos = env.step(action)
        if done[0]:
            if action[0, 1] > 0:
                ends += 1
                assert infos["position"][0, 0] == pytest.approx(target, abs=1e-9)
            teacher.start(np.arange(1))
        else:
            teacher.read(np.arange(1), infos)
    assert moved_from_fit >= 1
    plain = _env(envs=2, history=12)
    base = collect(plain, PosteriorTeacher(plain, _small_posterior), episodes=6, seed=5)
    step = float(plain.episodes.max_step[0, 0] / plain.episodes.span[0, 0])
    moved = base.moved_from_fit(step, plain.task.action_power, plain.task.ending.finish_window)
    stops = np.flatnonzero(base.label[:, 1] > 0)
    assert np.any(np.abs(moved.label[stops, 0] - base.label[stops, 0]) > 1e-3)
    assert moved.ends_from_fit and not base.ends_from_fit
    with pytest.raises(ValueError, match="moved_from_fit"):
        Demonstrations.joined([base, moved])
    for row in stops:
        history = base.observation[row]
        present = (history[-1, 1] + 1.0) / 2.0
        measured = (history[:, 0] > 0) & (history[:, 3] > 0)
        fit = bracketed_optimum(
            (history[measured, 1] + 1.0) / 2.0, np.exp(history[measured, 2].astype(float))
        )
        origin = present if fit is None else fit
        before = present + knob_change(base.label[row, :1], np.array([step]), 2.0)[0]
        after = origin + knob_change(moved.label[row, :1], np.array([step]), 2.0)[0]
        if abs(before - origin) <= step:
            assert after == pytest.approx(before, abs=1e-5)
        else:  # beyond one move of the fit: as far towards it as one move goes
            assert after == pytest.approx(origin + np.sign(before - origin) * step, abs=1e-5)


def test_finish_at_fit_needs_an_end_to_start_from() -> None:
    with pytest.raises(ValueError, match="finish_at_fit"):
        TaskOptions(finish_at_fit=True).apply(get_task("focus"))
    task = TaskOptions(finish_at_fit=True, final_move=True).apply(get_task("focus"))
    assert task.ending.at == "fit" and task.ending.final_move


def test_the_teachers_ends_land_where_its_posterior_would_end() -> None:
    """PosteriorTeacher.ends: a stopping move, from wherever the episode stands, that ends it
    at the posterior's best setting (as far as one last move reaches)."""
    env = _env(envs=2, final_move_reach=0.5, finish_at_fit=True)
    teacher = PosteriorTeacher(env, _small_posterior)
    env.reset(seed=8)
    slots = np.arange(2)
    teacher.start(slots)
    for _ in range(2):  # two probes of the teacher's, then the teacher's ends at once
        _, _, done, _, infos = env.step(teacher.actions() * np.array([1.0, 0.0]) - [0, 1])
        teacher.read(np.flatnonzero(~done), infos)
        teacher.start(np.flatnonzero(done))
    origin = ((env.episodes.stop_origins(slots) - env.episodes.low) / env.episodes.span)[:, 0]
    reach = 0.5 * (env.episodes.max_step / env.episodes.span)[:, 0]
    targets = np.array(
        [np.clip(posterior.final()[0], 0.0, 1.0) for posterior in teacher.posteriors]
    )
    action = np.stack([teacher.ends(slots), np.ones(2)], axis=1)
    _, _, done, _, infos = env.step(action)
    assert done.all()
    expected = np.clip(targets, origin - reach, origin + reach)
    np.testing.assert_allclose(infos["position"][:, 0], expected, atol=1e-9)

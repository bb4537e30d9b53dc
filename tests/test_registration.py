"""The environments under Gymnasium's registry (issue 23): `gymnasium.make("alignrl/...")`
builds an AlignmentEnv that passes Gymnasium's checker, plays the seeded episodes an
AlignmentEnv built by hand plays, and takes AlignmentEnv's keyword arguments."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from alignrl import GYMNASIUM_ENVS  # importing alignrl registers the ids
from alignrl.envs import AlignmentEnv

IDS = list(GYMNASIUM_ENVS)


@pytest.mark.parametrize("env_id", IDS)
def test_every_registered_env_is_made_and_passes_the_checker(env_id: str) -> None:
    env = gymnasium.make(env_id)
    assert isinstance(env.unwrapped, AlignmentEnv)
    check_env(env.unwrapped, skip_render_check=True)
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)


def test_a_made_env_plays_as_one_built_by_hand() -> None:
    made = gymnasium.make(
        "alignrl/Focus-v0", apparatus="synthetic", apparatus_args={"analytic": True}
    )
    built = AlignmentEnv(apparatus="synthetic", apparatus_args={"analytic": True})
    rng = np.random.default_rng(0)
    first = [made.reset(seed=5)[0], built.reset(seed=5)[0]]
    np.testing.assert_array_equal(*first)
    for _ in range(5):
        action = rng.uniform(-1, 1, 2).astype(np.float32)
        action[1] = -1.0  # no stop
        a, b = made.step(action), built.step(action)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:4] == b[1:4]


def test_the_family_env_draws_a_new_column_each_episode() -> None:
    env = gymnasium.make("alignrl/FocusFamily-v0")
    intervals = set()
    for seed in range(4):
        env.reset(seed=seed)
        intervals.add(tuple(env.unwrapped.apparatus.knobs["defocus"]))
    assert len(intervals) == 4


# --- render_mode="rgb_array": the frames of `alignrl align --gif` -------------------------


@pytest.mark.parametrize("env_id", ["alignrl/Focus-v0", "alignrl/Stigmation-v0"])
def test_a_rendering_env_passes_the_checker_with_its_render_check(env_id: str) -> None:
    env = gymnasium.make(env_id, render_mode="rgb_array")
    assert env.unwrapped.render_mode == "rgb_array"
    check_env(env.unwrapped)  # render modes and fps declared, frames of the right kind


def test_render_gives_an_rgb_frame_of_the_episode_so_far() -> None:
    env = gymnasium.make("alignrl/Focus-v0", apparatus="synthetic", render_mode="rgb_array")
    env.reset(seed=2)
    first = env.render()
    env.step(np.array([0.4, -1.0], np.float32))
    second = env.render()
    assert second.ndim == 3 and second.shape[2] == 3 and second.dtype == np.uint8
    assert first.shape == second.shape and np.any(first != second)
    readings = env.unwrapped.readings
    assert len(readings) == 2 and all(r.image is not None for r in readings)  # images of the SEM
    assert readings[1].settings["defocus"] != readings[0].settings["defocus"]
    env.step(np.array([0.0, 1.0], np.float32))  # a stop acquires nothing
    assert len(env.unwrapped.readings) == 2


def test_rendering_changes_nothing_in_the_episode() -> None:
    plain = AlignmentEnv(apparatus="synthetic", apparatus_args={"analytic": True})
    rendering = AlignmentEnv(
        apparatus="synthetic", apparatus_args={"analytic": True}, render_mode="rgb_array"
    )
    np.testing.assert_array_equal(plain.reset(seed=4)[0], rendering.reset(seed=4)[0])
    for change in (0.5, -0.2, 0.1):
        action = np.array([change, -1.0], np.float32)
        a, b = plain.step(action), rendering.step(action)
        rendering.render()
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:3] == b[1:3]
    assert plain.render() is None  # no render_mode: nothing drawn


def test_an_unknown_render_mode_and_a_render_before_reset_are_refused() -> None:
    with pytest.raises(ValueError, match=r"render_mode 'human'.*rgb_array"):
        AlignmentEnv(render_mode="human")
    with pytest.raises(gymnasium.error.ResetNeeded, match="before reset"):
        AlignmentEnv(render_mode="rgb_array").render()

"""The environments under Gymnasium's registry (issue 23): `gymnasium.make("alignrl/...")`
builds an AlignmentEnv that passes Gymnasium's checker, plays the seeded episodes an
AlignmentEnv built by hand plays, and takes AlignmentEnv's keyword arguments."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import alignrl.envs  # noqa: F401 (registers the ids)
from alignrl.envs import AlignmentEnv
from alignrl.envs.registration import ENV_IDS

IDS = [*ENV_IDS, "alignrl/FocusFamily-v0"]


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

"""benchmarks/sb3_sac.py: SB3 trains on our env as it is, on networks the size of ours, and its
learning table is well formed and reproducible. Skipped without the `bench` extra."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

pytest.importorskip("stable_baselines3")

from stable_baselines3.common.env_checker import check_env

from alignrl.config.experiment import load_experiment
from benchmarks.sb3_sac import DEFAULT_CONFIG, learn_sb3, make_env, update_speed

CONFIG = load_experiment(Path(__file__).parents[1] / DEFAULT_CONFIG)


@pytest.fixture(autouse=True)
def one_torch_thread() -> Iterator[None]:
    """Two threads on a 2-core machine that also runs training jobs are many times slower;
    nothing checked here depends on the thread count."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# SB3 warns about any observation that is neither an image nor a vector; its MlpPolicy
# flattens the (history, features) window, as our MLPEncoder does.
@pytest.mark.filterwarnings("ignore:Your observation .* has an unconventional shape")
def test_the_env_sb3_trains_on_passes_its_checker() -> None:
    env = make_env(CONFIG)
    check_env(env)
    assert env.observation_space.shape == (CONFIG.history, 7)


def test_the_speed_comparison_pits_networks_of_the_same_size() -> None:
    speed = update_speed(CONFIG, updates=3, repeats=1, transitions=300)
    assert speed.ours_parameters["actor"] == speed.sb3_parameters["actor"]
    # Our critics read the secret (one knob) in their second layer: 256 more weights.
    assert speed.ours_parameters["q"] - speed.sb3_parameters["q"] == 256
    assert len(speed.ours) == len(speed.sb3) == 1 and speed.ratio > 0


def test_sb3_learning_is_evaluated_like_ours_and_reproducible() -> None:
    first = learn_sb3(CONFIG, steps=200, eval_every=100, scenarios=5)
    second = learn_sb3(CONFIG, steps=200, eval_every=100, scenarios=5)
    assert [row.env_steps for row in first] == [100, 200]
    for row in first:
        assert row.learner == "SB3 SAC" and row.scenarios == 5
        assert 0 <= row.successes <= 5
        assert 1 <= row.median_acquisitions <= CONFIG.resolved_task().episode_steps + 1
        assert math.isfinite(row.wall_seconds) and row.wall_seconds > 0
    # Same seed, same updates, same held-out scenarios: the same outcomes (not the same time).
    outcome = lambda rows: [(r.successes, r.median_acquisitions) for r in rows]  # noqa: E731
    assert outcome(first) == outcome(second)

"""The league's matches are the duel: a policy written against the PettingZoo AEC API alone
plays a league match (play_round) and gets what it gets in DuelEnv, and a DuelBatch of N
duels gives, slot by slot, what N single DuelEnvs give with the same seeds and actions."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

from alignrl.envs import make_apparatus_copies
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.duel import (
    ALIGNER,
    MISALIGNER,
    DuelBatch,
    env,
    misaligner_input_shape,
    misaligner_inputs,
    raw_env,
)
from alignrl.envs.task import get_task
from alignrl.league.matches import Chooser, UniformStarts, play_round

ARGS = {"noise": 0.03}
HISTORY = 4


@pytest.fixture(scope="module")
def units() -> list:
    """Copies of the shipped scenarios, parsed once: a batch's, and single duels'. Every
    duel resets its apparatus with its seed, so the tests may share them."""
    return make_apparatus_copies("csv:default", ARGS, 8)


def _batch(units: list) -> DuelBatch:
    return DuelBatch(AlignmentEpisodes(units, get_task("focus"), HISTORY))


def _scenario_seed(seed: int) -> int:
    """The scenario DuelEnv.reset(seed) plays: the first draw of its generator."""
    generator, _ = gymnasium.utils.seeding.np_random(seed)
    return int(generator.integers(2**31 - 1))


# Policies that know nothing but the observations of the PettingZoo spaces.
def start_opposite(observation: np.ndarray) -> np.ndarray:
    """Start each knob on the far side of its aligned setting, farther at higher complexity."""
    aligned, complexity = observation[:-1], observation[-1]
    return np.where(aligned > 0, -1.0, 1.0) * complexity * 0.8


def walk_back(history: np.ndarray) -> np.ndarray:
    """Step against the last knob setting, and stop once half the steps are spent."""
    last = history[-1]
    knob, steps_left = last[1], last[-1]
    return np.array([-0.6 * knob, 1.0 if steps_left < 0.5 else -1.0], np.float32)


def _aec_match(apparatus, seed: int) -> dict[str, float]:
    """The standard AEC loop on env(): each agent's total, the outcome."""
    duel = env(apparatus=apparatus, history=HISTORY)
    duel.reset(seed=seed)
    totals = dict.fromkeys(duel.possible_agents, 0.0)
    outcome: dict[str, float] = {}
    for agent in duel.agent_iter():
        observation, reward, termination, truncation, info = duel.last()
        totals[agent] += reward
        if termination or truncation:
            outcome = {"success": info["success"], "acquisitions": info["acquisitions"]}
            duel.step(None)
            continue
        duel.step(start_opposite(observation) if agent == MISALIGNER else walk_back(observation))
    return {**totals, **outcome}


def _rewards(batch: DuelBatch, slot: int) -> dict[str, float]:
    return {agent: float(batch.rewards[agent][slot]) for agent in batch.possible_agents}


def _chooser(policy) -> Chooser:
    return lambda inputs, slots: (np.stack([policy(one) for one in inputs]), None)


def test_a_pettingzoo_policy_sits_in_a_league_match(units: list) -> None:
    seeds = [0, 1, 2]
    played = play_round(
        _batch(units[:4]),
        [_scenario_seed(seed) for seed in seeds],
        # A member reads [1, observation] as a one-row history: the policy its observation.
        _chooser(lambda row: start_opposite(row[0, 1:])),
        _chooser(walk_back),
        lambda step: None,
    )
    for slot, seed in enumerate(seeds):
        match = _aec_match(units[4 + slot], seed)
        payoff = played.returns[slot] - played.scores[slot]
        assert match[ALIGNER] == pytest.approx(payoff, abs=1e-9)
        assert match[MISALIGNER] == pytest.approx(-payoff, abs=1e-9)
        assert match["success"] == played.successes[slot]
        assert match["acquisitions"] == played.acquisitions[slot]
    assert len(set(played.finish_order)) == len(seeds)
    assert len({round(float(r), 6) for r in played.returns}) > 1  # the matches differ


def test_a_batch_of_duels_equals_single_duels_slot_by_slot(units: list) -> None:
    count, steps = 4, get_task("focus").episode_steps
    rng = np.random.default_rng(5)
    starts = rng.uniform(-1, 1, (count, 1))
    moves = rng.uniform(-1, 1, (steps, count, 2))
    moves[..., 1] = np.where(rng.random((steps, count)) < 0.2, 1.0, -1.0)  # stop now and then
    seeds = [10 + slot for slot in range(count)]

    batch = _batch(units[:count])
    batch.reset([_scenario_seed(seed) for seed in seeds])
    assert batch.agent_selection == MISALIGNER and list(batch.active) == list(range(count))
    np.testing.assert_array_equal(batch.observe(MISALIGNER).shape, (count, 2))
    batch.step(starts)
    batched = {slot: [_rewards(batch, slot)] for slot in range(count)}
    step = 0
    while batch.active.size:
        active = batch.active
        assert batch.agent_selection == ALIGNER
        batch.step(moves[step, active])
        for slot in active:
            batched[int(slot)].append(_rewards(batch, int(slot)))
        step += 1
    with pytest.raises(RuntimeError, match="reset it first"):
        batch.step(moves[0, :1])

    for slot, seed in enumerate(seeds):
        single = raw_env(apparatus=units[count + slot], history=HISTORY)
        single.reset(seed=seed)
        single.step(starts[slot])
        rewards = [dict(single.rewards)]
        for move in moves[:, slot]:
            single.step(move)
            rewards.append(dict(single.rewards))
            if single.terminations[ALIGNER]:
                break
        assert rewards == batched[slot]
        assert all(r[MISALIGNER] == -r[ALIGNER] for r in rewards)  # zero-sum every step
        assert all(single.terminations.values()) and batch.terminations[ALIGNER][slot]
        info, batch_info = single.infos[ALIGNER], batch.info(slot)
        assert info["success"] == batch.successes()[slot] == batch_info["success"]
        assert info["acquisitions"] == batch.acquisitions()[slot]
        np.testing.assert_array_equal(info.pop("secret"), batch_info.pop("secret"))
        assert info == batch_info
    assert len({len(r) for r in batched.values()}) > 1  # the duels ended at different steps


def test_a_misaligner_member_reads_the_duels_observation_as_one_row(units: list) -> None:
    batch = _batch(units[:2])
    batch.reset([3, 4])
    observations = batch.observe(MISALIGNER)
    inputs = misaligner_inputs(observations)
    assert inputs.shape == (2, *misaligner_input_shape(1)) and inputs.dtype == np.float32
    np.testing.assert_array_equal(inputs[:, 0, 0], 1.0)
    np.testing.assert_array_equal(inputs[:, 0, 1:], observations)
    assert UniformStarts.for_knobs(1).spec.observation_shape == misaligner_input_shape(1)
    with pytest.raises(ValueError, match="takes 1 to 2 seeds"):
        batch.reset([1, 2, 3])

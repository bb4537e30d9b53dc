"""AlignmentEnv, DuelEnv and the vector env: API conformance, the seed's rewards, zero-sum,
histories without secrets, determinism, and failures as defined outcomes."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
from fake_drivers import ParabolicLens
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, seed_test

from alignrl.apparatus import make_apparatus
from alignrl.envs import AlignmentEnv, DuelEnv, SuccessRule, Task
from alignrl.envs.core import feature_layout
from alignrl.envs.duel import ALIGNER, MISALIGNER
from alignrl.envs.duel import env as duel_env
from alignrl.envs.task import get_task
from alignrl.envs.vector import VectorAlignmentEnv, make_apparatus_copies

LENS = "fake_drivers:ParabolicLens"
LAYOUT = feature_layout(1)
# ParabolicLens has no best_quality: its tasks use an absolute spec.
LENS_TASK = Task(name="focus", knobs=("defocus",), success=SuccessRule(absolute_px=3.0))


def lens_width(error_v: float) -> float:
    return 2.563 * math.hypot(1.0, 0.2 * error_v)


@pytest.fixture(autouse=True)
def _quiet_api_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        yield


def test_alignment_env_passes_the_gymnasium_checker() -> None:
    check_env(AlignmentEnv(), skip_render_check=True)
    check_env(AlignmentEnv(apparatus="synthetic", history=4), skip_render_check=True)


def test_duel_env_passes_the_pettingzoo_api_and_seed_tests() -> None:
    api_test(duel_env(), num_cycles=300)
    seed_test(duel_env, num_cycles=300)


def test_default_constructors_build_the_focus_task_on_the_shipped_scenarios() -> None:
    env = AlignmentEnv()
    assert env.task.knobs == ("defocus",)
    assert env.apparatus.knobs == {"defocus": (0.0, 100.0)}
    assert len(env.apparatus.scenarios) == 2000
    duel = DuelEnv()
    assert duel.possible_agents == [MISALIGNER, ALIGNER]


def _lens_env(**kwargs) -> AlignmentEnv:
    return AlignmentEnv(apparatus=ParabolicLens(), task=kwargs.pop("task", LENS_TASK), **kwargs)


def test_steps_inside_the_interval_pay_nothing_until_the_final_reward() -> None:
    env = _lens_env()
    env.reset(seed=0, options={"misalignment": [0.0]})  # start at the optimum - 0
    lens = env.apparatus
    start = lens.voltage
    before = lens_width(start - lens.optimum_v)
    _, reward, terminated, _, info = env.step(np.array([0.1, -1.0]))  # +2.5 V, no stop
    assert reward == 0.0 and not terminated
    assert lens.voltage == pytest.approx(start + 2.5)
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))  # stop
    assert terminated
    after = lens_width(start + 2.5 - lens.optimum_v)
    assert reward == pytest.approx(before - after)
    assert info["acquisitions"] == 2  # the first image and one step; stopping costs nothing
    assert info["success"] == (after <= 3.0)


def test_a_step_beyond_the_interval_is_clipped_and_penalised() -> None:
    env = _lens_env()
    env.reset(seed=1, options={"misalignment": [1.0]})  # the top of the interval
    lens = env.apparatus
    assert lens.voltage == 100.0
    _, reward, _, _, _ = env.step(np.array([1.0, -1.0]))  # +25 V
    assert reward == -1.0
    assert lens.voltage == 100.0
    env.reset(seed=2, options={"misalignment": [-1.0]})
    env.step(np.array([-1.0, -1.0]))
    env.step(np.array([-1.0, -1.0]))
    env.step(np.array([-1.0, -1.0]))
    assert lens.voltage == 0.0
    _, reward, _, _, info = env.step(np.array([-1.0, -1.0]))
    assert reward == -1.0 and info["out_of_bounds"] >= 1


def test_the_episode_ends_at_the_step_limit_with_the_final_reward() -> None:
    task = Task(
        name="short", knobs=("defocus",), episode_steps=3, success=SuccessRule(absolute_px=3)
    )
    env = _lens_env(task=task)
    env.reset(seed=4, options={"misalignment": [-0.2]})
    lens = env.apparatus
    before = lens_width(lens.voltage - lens.optimum_v)
    total = 0.0
    for step in range(3):
        _, reward, terminated, truncated, info = env.step(np.array([0.02, -1.0]))
        total += reward
        assert terminated == (step == 2) and not truncated
    assert total == pytest.approx(before - lens_width(lens.voltage - lens.optimum_v))
    assert info["acquisitions"] == 4


def test_acquisition_cost_and_reward_scale_are_task_fields() -> None:
    task = Task(
        name="costly",
        knobs=("defocus",),
        acquisition_cost=0.1,
        final_reward_scale=2.0,
        success=SuccessRule(absolute_px=3.0),
    )
    env = _lens_env(task=task)
    env.reset(seed=0, options={"misalignment": [0.3]})
    lens = env.apparatus
    before = lens_width(lens.voltage - lens.optimum_v)
    _, reward, *_ = env.step(np.array([-0.05, -1.0]))
    assert reward == pytest.approx(-0.1)
    _, reward, *_ = env.step(np.array([0.0, 1.0]))
    assert reward == pytest.approx(2.0 * (before - lens_width(lens.voltage - lens.optimum_v)))


def test_history_is_oldest_first_zero_padded_and_masked() -> None:
    env = _lens_env(history=4)
    observation, _ = env.reset(seed=0, options={"misalignment": [0.0]})
    valid = observation[:, LAYOUT["valid"]][:, 0]
    assert list(valid) == [0, 0, 0, 1]
    assert np.all(observation[:3] == 0)
    actions = [0.1, -0.05, 0.2, 0.0, 0.1]
    for action in actions:
        observation, *_ = env.step(np.array([action, -1.0]))
    assert list(observation[:, LAYOUT["valid"]][:, 0]) == [1, 1, 1, 1]
    np.testing.assert_allclose(observation[:, LAYOUT["action"]][:, 0], actions[1:], atol=1e-6)
    lens = env.apparatus
    assert observation[-1, LAYOUT["knobs"]][0] == pytest.approx(lens.voltage / 50.0 - 1.0)
    expected_quality = math.log(lens_width(lens.voltage - lens.optimum_v) / 2.5)
    assert observation[-1, LAYOUT["quality"]][0] == pytest.approx(expected_quality, rel=1e-5)
    assert observation[-1, LAYOUT["steps_left"]][0] == pytest.approx(0.5)


def test_the_secret_reaches_info_but_never_the_observation() -> None:
    """Two scenarios with different optima but the same measurements along the way give
    identical observations: the policy cannot see where the optimum is."""
    observations, secrets = [], []
    for optimum in (30.0, 60.0):
        lens = ParabolicLens()
        env = AlignmentEnv(apparatus=lens, task=LENS_TASK)
        env.reset(seed=0, options={"misalignment": [0.0]})
        lens.optimum_v = optimum
        lens.measure = lambda: 7.0  # type: ignore[method-assign]  # a column that reads the same
        observation, _, _, _, info = env.step(np.array([0.1, -1.0]))
        observations.append(observation)
        secrets.append(info["secret"])
    np.testing.assert_array_equal(observations[0], observations[1])
    assert secrets[0][0] != secrets[1][0]
    assert secrets[1][0] == pytest.approx((60.0 - env.apparatus.voltage) / 100.0)


def test_failed_measurements_are_a_defined_outcome() -> None:
    env = AlignmentEnv(apparatus=ParabolicLens(blind_beyond_v=10.0), task=LENS_TASK)
    observation, info = env.reset(seed=0, options={"misalignment": [-1.0]})
    lens = env.apparatus
    assert lens.voltage == 0.0 and lens.optimum_v > 10.0  # far out: no edges to measure
    assert observation[-1, LAYOUT["measured"]][0] == 0.0
    assert observation[-1, LAYOUT["quality"]][0] == pytest.approx(4.0)
    assert info["failed_measurements"] == 1
    # Move into the measurable range: the improvement over "no edges" (25 px) is paid.
    for _ in range(3):  # at most 25 V per step
        env.step(np.array([np.clip((lens.optimum_v - 5.0 - lens.voltage) / 25.0, -1, 1), -1.0]))
    assert lens.voltage == pytest.approx(lens.optimum_v - 5.0)
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))
    assert terminated
    assert reward == pytest.approx(25.0 - lens_width(lens.voltage - lens.optimum_v))


def test_resets_are_reproducible_under_a_seed() -> None:
    def trajectory(seed: int) -> list[float]:
        env = AlignmentEnv(apparatus_args={"noise": 0.02})
        observation, _ = env.reset(seed=seed)
        values = [float(observation.sum())]
        rng = np.random.default_rng(0)
        for _ in range(30):
            observation, reward, terminated, _, _ = env.step(rng.uniform(-1, 1, 2))
            values += [float(observation.sum()), reward]
            if terminated:
                observation, _ = env.reset()
        return values

    assert trajectory(7) == trajectory(7)
    assert trajectory(7) != trajectory(8)


def test_misalignment_follows_the_complexity_window_and_a_given_policy() -> None:
    env = AlignmentEnv(complexity=0.1)
    for seed in range(20):
        env.reset(seed=seed)
        setting = env.apparatus.read()["defocus"]
        assert abs(setting - env.apparatus.optimum()["defocus"]) <= 10.0 + 1e-9
    seen = []
    env = AlignmentEnv(misalignment=lambda observation: seen.append(observation) or [-1.0])
    env.reset(seed=0)
    optimum = env.apparatus.optimum()["defocus"]
    assert env.apparatus.read()["defocus"] == pytest.approx(max(0.0, optimum - 100.0))
    assert seen[0][-1] == 1.0  # the misaligner sees the complexity level
    assert seen[0][0] == pytest.approx(optimum / 50.0 - 1.0)


def _duel_episode(duel) -> tuple[float, float]:
    totals = {MISALIGNER: 0.0, ALIGNER: 0.0}
    for agent in duel.agent_iter():
        _, reward, terminated, truncated, _ = duel.last()
        totals[agent] += reward
        if terminated or truncated:
            duel.step(None)
            continue
        duel.step(duel.action_space(agent).sample())
    return totals[MISALIGNER], totals[ALIGNER]


def test_every_duel_sums_to_zero_over_a_thousand_random_episodes() -> None:
    duel = duel_env()
    aligner_returns = []
    for episode in range(1000):
        duel.reset(seed=episode)
        duel.action_space(MISALIGNER).seed(episode)
        duel.action_space(ALIGNER).seed(episode)
        misaligner, aligner = _duel_episode(duel)
        assert misaligner + aligner == pytest.approx(0.0, abs=1e-9)
        aligner_returns.append(aligner)
    assert np.std(aligner_returns) > 0  # the games really differ


def test_duel_turn_order_and_spaces() -> None:
    duel = DuelEnv()
    duel.reset(seed=0)
    assert duel.agent_selection == MISALIGNER
    assert duel.observe(MISALIGNER).shape == (2,)
    duel.step(np.array([0.5], np.float32))
    assert duel.agent_selection == ALIGNER
    assert duel.observe(ALIGNER).shape == (8, 7)
    duel.step(np.array([0.0, 1.0], np.float32))  # the aligner stops at once
    assert all(duel.terminations.values())


def test_vector_env_equals_single_envs_step_by_step() -> None:
    count = 4
    vector = VectorAlignmentEnv(make_apparatus_copies("csv:default", {"noise": 0.03}, count))
    singles = [AlignmentEnv(apparatus_args={"noise": 0.03}) for _ in range(count)]
    batch_obs, _ = vector.reset(seed=10)
    for index, env in enumerate(singles):
        observation, _ = env.reset(seed=10 + index)
        np.testing.assert_array_equal(batch_obs[index], observation)
    rng = np.random.default_rng(1)
    for _ in range(60):
        actions = rng.uniform(-1, 1, (count, 2))
        batch_obs, rewards, dones, _, infos = vector.step(actions)
        for index, env in enumerate(singles):
            observation, reward, terminated, _, info = env.step(actions[index])
            assert reward == pytest.approx(rewards[index], abs=1e-12)
            assert terminated == dones[index]
            step_secret = infos["final_secret"] if terminated else infos["secret"]
            np.testing.assert_allclose(step_secret[index], info["secret"], atol=1e-6)
            assert infos["acquisitions"][index] == info["acquisitions"]
            if terminated:
                assert info["success"] == infos["success"][index]
                np.testing.assert_array_equal(infos["final_observation"][index], observation)
                observation, info = env.reset()
                np.testing.assert_allclose(infos["secret"][index], info["secret"], atol=1e-6)
            np.testing.assert_array_equal(batch_obs[index], observation)


def test_vector_env_mixes_different_microscopes() -> None:
    apparatus = [
        make_apparatus("csv:default"),
        make_apparatus(LENS),
    ]
    task = Task(name="focus", knobs=("defocus",), success=SuccessRule(absolute_px=3.0))
    vector = VectorAlignmentEnv(apparatus, task=task)
    observations, _ = vector.reset(seed=0)
    assert observations.shape == (2, 8, 7)
    observations, _, dones, _, _ = vector.step(np.array([[0.1, -1], [0.1, 1]]))
    assert dones.tolist() == [False, True]


@pytest.mark.parametrize(
    ("build", "fragment"),
    [
        (lambda: AlignmentEnv(task=Task(name="stig", knobs=("stigmator_x",))), "stigmator_x"),
        (lambda: AlignmentEnv(complexity=0.0), "complexity"),
        (lambda: AlignmentEnv(history=0), "history"),
        (lambda: Task(name="t", knobs=("defocus",), success=SuccessRule(relative=0.9)), "exceed 1"),
        (lambda: AlignmentEnv(apparatus=make_apparatus(LENS)), "--spec-px"),
        (lambda: Task(name="t", knobs=()), "names no knob"),
    ],
)
def test_bad_configurations_are_refused_with_a_reason(build, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        env = build()
        if isinstance(env, AlignmentEnv):
            env.reset(seed=0)


def test_the_optional_success_bonus_is_paid_only_within_spec() -> None:
    task = Task(
        name="bonus", knobs=("defocus",), success_bonus=5.0, success=SuccessRule(absolute_px=3.0)
    )
    env = _lens_env(task=task)
    env.reset(seed=0, options={"misalignment": [0.0]})
    lens = env.apparatus
    before = lens_width(lens.voltage - lens.optimum_v)
    to_focus = (lens.optimum_v - lens.voltage) / 25.0
    env.step(np.array([to_focus, -1.0]))
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))
    assert terminated and info["success"]
    assert reward == pytest.approx(before - lens_width(0.0) + 5.0)
    env.reset(seed=1, options={"misalignment": [-1.0]})  # far out, then stop at once
    _, reward, _, _, info = env.step(np.array([0.0, 1.0]))
    assert not info["success"] and reward == 0.0


def _bonus_episode(target_ratio: float) -> tuple[float, dict]:
    """One noise-free episode on the recordings that ends where the edge width is
    `target_ratio` x the best one; its final reward and info."""
    task = dataclasses.replace(
        get_task("focus"), success_bonus=5.0, bonus_relative=1.10
    )  # the spec stays 1.15 x best
    env = AlignmentEnv(apparatus_args={"noise": 0.0}, task=task)
    env.reset(seed=4, options={"misalignment": [0.0]})
    simulator, episodes = env.apparatus, env.episodes
    best, optimum = simulator.best_quality(), simulator.optimum()["defocus"]
    offsets = np.linspace(0.0, 20.0, 4001)
    widths = [
        simulator.query(np.array([simulator.row]), np.array([optimum + d]))[0] for d in offsets
    ]
    target = optimum + offsets[int(np.argmin(np.abs(np.array(widths) / best - target_ratio)))]
    move = (target - episodes.setting[0, 0]) / episodes.max_step[0, 0]
    assert abs(move) <= 1.0
    env.step(np.array([move, -1.0]))
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))
    assert terminated and info["edge_width_px"] / best == pytest.approx(target_ratio, abs=0.005)
    return reward - (info["edge_width_before_px"] - info["edge_width_px"]), info


def test_a_tighter_bonus_margin_leaves_the_spec_alone() -> None:
    # Within 1.10 x best: aligned and paid the bonus; between 1.10 and 1.15: aligned (the
    # spec), no bonus; beyond 1.15: neither.
    for ratio, success, bonus in ((1.02, True, 5.0), (1.13, True, 0.0), (1.25, False, 0.0)):
        paid, info = _bonus_episode(ratio)
        assert info["success"] is success and paid == pytest.approx(bonus, abs=1e-9), ratio


def _duel_totals(start: float, aligner: str) -> tuple[float, float]:
    """Totals (misaligner, aligner) of one noise-free duel from `start`, against an aligner
    that stops at once ("idle") or walks to the optimum with the secret ("oracle")."""
    duel = DuelEnv(apparatus_args={"noise": 0.0})
    duel.reset(seed=3)
    totals = {MISALIGNER: 0.0, ALIGNER: 0.0}
    duel.step(np.array([start], np.float32))
    totals[MISALIGNER] += duel.rewards[MISALIGNER]
    totals[ALIGNER] += duel.rewards[ALIGNER]
    episodes = duel.episodes
    while not duel.terminations[ALIGNER]:
        move = episodes.secrets()[0] * episodes.span[0] / episodes.max_step[0]
        done = aligner == "idle" or abs(move[0]) < 1e-9
        duel.step(np.array([np.clip(move[0], -1, 1), 1.0 if done else -1.0], np.float32))
        totals[MISALIGNER] += duel.rewards[MISALIGNER]
        totals[ALIGNER] += duel.rewards[ALIGNER]
    return totals[MISALIGNER], totals[ALIGNER]


def test_the_misaligner_is_paid_for_what_the_aligner_does_not_recover() -> None:
    # Against an aligner that does nothing, a far start is worth more than a near one...
    far, _ = _duel_totals(-1.0, "idle")
    near, _ = _duel_totals(0.02, "idle")
    assert far > near + 1.0
    # ...against one that reaches the optimum, no start is worth anything: had the misaligner
    # been paid minus the aligner's improvement, it would have learned to start at focus.
    for start in (-1.0, -0.5, 0.02, 0.6):
        misaligner, aligner = _duel_totals(start, "oracle")
        assert misaligner == pytest.approx(0.0, abs=0.05)
        assert misaligner + aligner == pytest.approx(0.0, abs=1e-9)


class _ScriptedLens:
    """A lens whose readings are given in advance, one per acquisition, whatever the setting:
    the noise of a real reading made to order."""

    def __init__(self, readings: list[float]) -> None:
        self.knobs = {"defocus": (0.0, 100.0)}
        self.readings = list(readings)
        self.voltage, self.measured = 50.0, 0

    def reset(self, seed: int | None = None) -> None:
        self.voltage = 50.0

    def read(self) -> dict[str, float]:
        return {"defocus": self.voltage}

    def write(self, values) -> None:
        self.voltage = float(values["defocus"])

    def measure(self) -> float:
        self.measured += 1
        return self.readings.pop(0)

    def image(self) -> None:
        return None


@pytest.mark.parametrize("verify", [False, True])
def test_verify_final_judges_a_lucky_last_reading_on_one_more_image(verify: bool) -> None:
    """The aligner stops on a lucky reading (2.5 px, within the 3 px spec); the column in
    fact reads 4 px there. Without verify_final it is paid on the lucky reading, bonus
    included; with it, on one more image at the same setting: no bonus, no success."""
    task = Task(
        name="verified",
        knobs=("defocus",),
        success_bonus=5.0,
        verify_final=verify,
        success=SuccessRule(absolute_px=3.0),
    )
    lens = _ScriptedLens([10.0, 2.5, 4.0])
    env = AlignmentEnv(apparatus=lens, task=task, history=4)
    env.reset(seed=0, options={"misalignment": [0.0]})
    env.step(np.array([0.2, -1.0]))  # one image: the lucky 2.5 px
    after_move = env.episodes.history[0].copy()
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))  # stop
    assert terminated
    if verify:
        assert reward == pytest.approx(10.0 - 4.0) and not info["success"]
        assert info["acquisitions"] == 3 and lens.measured == 3
        assert info["edge_width_px"] == 4.0
    else:
        assert reward == pytest.approx(10.0 - 2.5 + 5.0) and info["success"]
        assert info["acquisitions"] == 2 and lens.measured == 2
    # The verification is no step of the aligner's: its history is the same either way.
    np.testing.assert_array_equal(env.episodes.history[0], after_move)


def test_a_policy_trained_with_verify_final_acts_without_it() -> None:
    """Evaluation sessions and `align` verify on their own: the policy's episode takes no
    extra image there (its acquisitions are the policy's alone)."""
    from alignrl.evaluation.controllers import PolicyController
    from alignrl.evaluation.session import run_session

    task = dataclasses.replace(LENS_TASK, verify_final=True)
    assert task.for_acting().verify_final is False and LENS_TASK.for_acting() is LENS_TASK
    stop_at_once = lambda _history: np.array([0.0, 1.0])  # noqa: E731
    controller = PolicyController("stopper", stop_at_once, task, 4)
    result = run_session(controller, make_apparatus(LENS), LENS_TASK, scenarios=3, spec_px=3.0)
    assert [record.acquisitions for record in result.records] == [1, 1, 1]


@pytest.mark.parametrize(("last", "bonus"), [(2.95, 0.0), (2.8, 5.0)])
def test_on_a_column_without_a_known_best_the_bonus_margin_keeps_its_ratio_to_the_spec(
    last: float, bonus: float
) -> None:
    """A real column cannot tell its best width: with an absolute spec of 3 px, a bonus margin
    of 1.10 (against the rule's 1.15) pays the bonus within 3 x 1.10 / 1.15 = 2.87 px only;
    success is still the spec."""
    task = Task(
        name="real",
        knobs=("defocus",),
        success_bonus=5.0,
        bonus_relative=1.10,
        success=SuccessRule(absolute_px=3.0),
    )
    env = AlignmentEnv(apparatus=_ScriptedLens([10.0, last]), task=task, history=4)
    env.reset(seed=0, options={"misalignment": [0.0]})
    assert env.episodes.bonus_threshold[0] == pytest.approx(3.0 * 1.10 / 1.15)
    env.step(np.array([0.2, -1.0]))
    _, reward, terminated, _, info = env.step(np.array([0.0, 1.0]))
    assert terminated and info["success"]
    assert reward == pytest.approx(10.0 - last + bonus)

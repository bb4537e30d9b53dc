"""The task option `finish_at_posterior`: an episode ends (the way back of stop_at_best, or the
start of final_move's last move) where the scale-free posterior over the focus training box
puts the best setting given the episode's readings; nearer focus than its narrowest reading;
refused where its reading model does not hold."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus.registry import make_apparatus
from alignrl.config.task_options import TaskOptions
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.ending import EpisodeEnds, resample_for
from alignrl.envs.option_table import POSTERIOR_PROBE_RULES
from alignrl.envs.task import get_task
from alignrl.posterior.inference import (
    PROBE_RULES,
    SCALE_FREE,
    SCORED_STATES,
    STOP_STATES,
    FamilyPosterior,
)
from alignrl.posterior.models import focus_box

WALK = [0.9, -0.6, 0.4, -0.3]  # probes on both sides of focus, from the episode's start


def _task(**options):
    options = {"approach_from_below": True, "action_power": 2.0, "move_floor": 0.02, **options}
    return TaskOptions(finish_at_posterior=True, **options).apply(get_task("focus"))


def _started(task, seed: int = 3):
    unit = make_apparatus("family:focus", {"analytic": True}, seed=seed)
    episodes = AlignmentEpisodes([unit], task, history=8)
    slot = np.array([0])
    episodes.begin(slot, [21])
    episodes.misalign(slot, np.array([0.0]))
    return episodes, slot, unit


def _walked(task, seed: int = 3):
    episodes, slot, unit = _started(task, seed)
    for change in WALK:
        episodes.step(slot, np.array([[change, -1.0]]))
    return episodes, slot, unit


def _posterior_best(episodes) -> float:
    """What a FamilyPosterior of its own says of episode 0's readings (its units)."""
    posterior = FamilyPosterior(focus_box(), **SCALE_FREE)
    posterior.begin()
    low, span = float(episodes.low[0, 0]), float(episodes.span[0, 0])
    for reading in episodes.ends.readings[0]:
        posterior.observe((float(reading.setting[0]) - low) / span, reading.width)
    return low + posterior.final()[0] * span


def test_a_stop_goes_back_to_the_posteriors_best_setting_without_an_image() -> None:
    episodes, slot, unit = _walked(_task(stop_at_best=True))
    assert len(episodes.ends.readings[0]) == 1 + len(WALK)
    expected, acquisitions = _posterior_best(episodes), int(episodes.acquisitions[0])
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert episodes.info[0].ended_at_fit
    assert float(unit.read()["defocus"]) == pytest.approx(expected)
    assert episodes.acquisitions[0] == acquisitions


def test_a_last_move_starts_at_the_posteriors_best_setting() -> None:
    episodes, slot, unit = _walked(_task(final_move=True, final_move_reach=0.2))
    origin = float(episodes.stop_origins(slot)[0, 0])
    assert origin == pytest.approx(_posterior_best(episodes))
    assert origin != float(episodes.setting[0, 0])
    episodes.step(slot, np.array([[0.0, 1.0]]))  # a stop of 0: ends at the posterior's best
    assert float(unit.read()["defocus"]) == pytest.approx(origin)


def test_the_posterior_ends_nearer_focus_than_the_narrowest_reading() -> None:
    """The same walks on six of the family's columns: ended at the posterior's best setting
    they lie nearer their optima, in all, than at their narrowest readings."""
    plain = TaskOptions(
        stop_at_best=True, approach_from_below=True, action_power=2.0, move_floor=0.02
    ).apply(get_task("focus"))
    errors = {}
    for name, task in {"posterior": _task(stop_at_best=True), "narrowest": plain}.items():
        total = 0.0
        for seed in range(6):
            episodes, slot, unit = _walked(task, seed=seed)
            episodes.step(slot, np.array([[0.0, 1.0]]))
            total += abs(unit.focus_error()) / float(episodes.span[0, 0])
        errors[name] = total
    assert errors["posterior"] < 0.5 * errors["narrowest"]


def _towards_the_posterior(episodes) -> np.ndarray:
    """A probe of episode 0 towards where its posterior puts the best setting (the task's
    action_power 2 and floor 0.02: at most a whole step, nothing within the floor)."""
    span = float(episodes.span[0, 0])
    move = episodes.ends.best(0)[0] - (float(episodes.setting[0, 0] - episodes.low[0, 0])) / span
    reach = max(abs(move) - 0.02, 0.0) / (float(episodes.max_step[0, 0]) / span)
    return np.array([[float(np.sign(move) * min(np.sqrt(reach), 1.0)), -1.0]])


def test_a_sure_posterior_ends_the_episode_where_it_puts_the_best_setting() -> None:
    """stop_when_sure: the policy never stops; the episode ends on the step after which the
    posterior's best setting passes with the chance asked, there, and not before."""
    for options in ({"stop_at_best": True}, {"final_move": True}):
        task = _task(stop_when_sure=0.7, **options)
        episodes, slot, unit = _started(task)
        chances = []
        while episodes.active[0]:
            chances.append(episodes.ends.best(0)[1])
            episodes.step(slot, _towards_the_posterior(episodes))
        assert 2 <= episodes.steps[0] < task.episode_steps, options  # before the step limit
        assert max(chances) < 0.7 <= episodes.ends.best(0)[1]
        expected = _posterior_best(episodes)
        assert float(unit.read()["defocus"]) == pytest.approx(expected), options
    plain, slot, _ = _started(_task(stop_at_best=True))
    for _ in range(6):  # without it, the same policy goes on
        assert not plain.step(slot, _towards_the_posterior(plain))[1][0]


@pytest.mark.parametrize(
    ("options", "task"),
    [
        ({"approach_from_below": False, "stop_at_best": True}, "focus"),  # its reading model
        ({"stop_at_best": True, "finish_at_fit": True}, "focus"),  # one estimate or the other
        ({}, "focus"),  # neither a way back nor a last move
        ({"final_move": True}, "stigmation"),  # a focus curve's posterior
    ],
)
def test_finishing_at_the_posterior_is_refused_where_its_model_does_not_hold(options, task):
    options = {"approach_from_below": True, **options}
    with pytest.raises(ValueError, match="finish_at_posterior"):
        TaskOptions(finish_at_posterior=True, **options).apply(get_task(task))


def test_stopping_when_sure_needs_the_posterior_and_a_chance_below_one() -> None:
    with pytest.raises(ValueError, match="stop_when_sure"):
        TaskOptions(stop_at_best=True, stop_when_sure=0.9).apply(get_task("focus"))
    with pytest.raises(ValueError, match="stop_when_sure"):
        _task(stop_at_best=True, stop_when_sure=1.0)


def test_the_posterior_draws_as_many_columns_as_the_task_says() -> None:
    """posterior_draws: the episode's posterior is one of that many columns, judging 8 and 80
    states per column (STATES_PER_COLUMN), and its end is what a FamilyPosterior of as many
    columns and states says of the same readings."""
    task = _task(stop_at_best=True, posterior_draws=64)
    episodes, slot, unit = _walked(task)
    assert episodes.ends._posterior(0).models.count == 64
    assert episodes.ends._posterior(0).resample == (512, 5120)
    posterior = FamilyPosterior(focus_box(), draws=64, resample=(512, 5120), **SCALE_FREE)
    posterior.begin()
    low, span = float(episodes.low[0, 0]), float(episodes.span[0, 0])
    for reading in episodes.ends.readings[0]:
        posterior.observe((float(reading.setting[0]) - low) / span, reading.width)
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert float(unit.read()["defocus"]) == pytest.approx(low + posterior.final()[0] * span)
    assert float(unit.read()["defocus"]) != pytest.approx(_posterior_best(episodes))


def test_an_episodes_posterior_judges_states_in_proportion_to_its_columns_up_to_a_cap() -> None:
    """From 250 columns on (the default 256, the champion's 1,024) every posterior judges
    the same SCORED_STATES and STOP_STATES; fewer columns, fewer states."""
    assert (SCORED_STATES, STOP_STATES) == (2000, 20000)
    for draws, resample in [(16, (128, 1280)), (256, (2000, 20000))]:
        ends = EpisodeEnds(1, 1, _task(stop_at_best=True, posterior_draws=draws))
        assert ends._posterior(0).resample == resample_for(draws) == resample
    with pytest.raises(ValueError, match="resample"):
        FamilyPosterior(focus_box(), draws=16, resample=(0, 100))


def test_posterior_draws_needs_the_posterior_and_a_sane_count() -> None:
    with pytest.raises(ValueError, match="posterior_draws"):
        TaskOptions(stop_at_best=True, posterior_draws=1024).apply(get_task("focus"))
    with pytest.raises(ValueError, match="posterior_draws"):
        _task(stop_at_best=True, posterior_draws=8)
    with pytest.raises(ValueError, match="posterior_draws"):
        TaskOptions(posterior_draws=10_000)


def test_an_unsure_posterior_turns_a_stop_into_a_reading_where_it_would_probe() -> None:
    """probe_until_sure: a policy that stops at once reads where its posterior would probe
    next, again and again, until that posterior is sure enough (or the steps run out); then
    the stop is taken and ends at the posterior's best setting."""
    task = _task(stop_at_best=True, probe_until_sure=0.9)
    episodes, slot, unit = _started(task)
    stop = np.array([[0.0, 1.0]])
    low, span = float(episodes.low[0, 0]), float(episodes.span[0, 0])
    probes = 0
    while episodes.ends.best(0)[1] < 0.9:
        expected = low + episodes.ends._posterior(0).probe() * span
        episodes.step(slot, stop)
        probes += 1
        assert episodes.active[0]  # a reading there, and the episode goes on
        assert float(episodes.setting[0, 0]) == pytest.approx(expected)
        assert episodes.acquisitions[0] == 1 + probes
    assert 2 <= probes < task.episode_steps  # sure before the step limit
    acquisitions = int(episodes.acquisitions[0])
    assert episodes.step(slot, stop)[1][0]  # sure now: the stop is taken, no image
    assert episodes.acquisitions[0] == acquisitions
    assert episodes.ends.best(0)[1] >= 0.9
    assert float(unit.read()["defocus"]) == pytest.approx(_posterior_best(episodes))
    plain, slot, _ = _started(_task(stop_at_best=True))
    assert plain.step(slot, stop)[1][0]  # without it, the same stop ends the episode


def test_probing_until_sure_needs_the_posterior_and_a_chance_below_one() -> None:
    with pytest.raises(ValueError, match="probe_until_sure"):
        TaskOptions(stop_at_best=True, probe_until_sure=0.9).apply(get_task("focus"))
    with pytest.raises(ValueError, match="probe_until_sure"):
        _task(stop_at_best=True, probe_until_sure=1.0)


def test_the_posterior_walks_from_the_reading_the_task_says() -> None:
    """posterior_walk_after N: the policy's moves are taken for the first N readings (the
    opening one counts); from then on every reading is where the posterior would probe next,
    whatever the policy asks, and a stop still ends the episode at the posterior's best."""
    task = _task(stop_at_best=True, posterior_walk_after=3)
    episodes, slot, unit = _started(task)
    low, span = float(episodes.low[0, 0]), float(episodes.span[0, 0])
    asked = np.array([[0.9, -1.0]])  # far up, every time
    for _ in range(2):  # readings 2 and 3: where the policy asks
        before = float(episodes.setting[0, 0])
        episodes.step(slot, asked)
        assert float(episodes.setting[0, 0]) > before
    settings = []
    for _ in range(3):  # readings 4 to 6: where the posterior would probe
        expected = low + episodes.ends._posterior(0).probe() * span
        episodes.step(slot, asked)
        settings.append(float(episodes.setting[0, 0]))
        assert settings[-1] == pytest.approx(expected)
    assert episodes.acquisitions[0] == 6
    policy_walk, _, _ = _started(_task(stop_at_best=True))
    for _ in range(5):
        policy_walk.step(slot, asked)
    assert float(policy_walk.setting[0, 0]) not in settings  # the policy alone went elsewhere
    assert episodes.step(slot, np.array([[0.0, 1.0]]))[1][0]
    assert float(unit.read()["defocus"]) == pytest.approx(_posterior_best(episodes))


def test_the_posterior_walks_while_nothing_is_measured_when_asked() -> None:
    """posterior_walk_unmeasured: while no reading of the episode has been measured (every
    frame so far without edges), the move goes where the posterior would probe next; once
    one is measured the policy moves again. Without the option the policy moves throughout."""
    asked = np.array([[0.9, -1.0]])  # far up, every time
    moved = {}
    for unmeasured in (False, True):
        task = _task(
            stop_at_best=True, posterior_no_edges=True, posterior_walk_unmeasured=unmeasured
        )
        episodes, slot, _ = _started(task)
        low, span = float(episodes.low[0, 0]), float(episodes.span[0, 0])
        episodes.ends.readings[0] = []  # as though the opening frame had shown no edges
        probe = low + episodes.ends._posterior(0).probe() * span
        before = float(episodes.setting[0, 0])
        episodes.step(slot, asked)
        moved[unmeasured] = float(episodes.setting[0, 0])
        assert len(episodes.ends.readings[0]) == 1  # this one was measured
        if not unmeasured:
            assert moved[unmeasured] > before  # the policy's move, up
        else:
            assert moved[unmeasured] == pytest.approx(probe) and probe < before
            before = moved[unmeasured]
            episodes.step(slot, asked)  # a reading measured: the policy's move again
            assert float(episodes.setting[0, 0]) > before
    assert moved[False] != pytest.approx(moved[True])


def test_frames_without_edges_reach_the_posterior_only_when_asked() -> None:
    """posterior_no_edges: a reading without edges is news for the posterior (focus is far
    from there): its best setting moves; without the option it is left out, as before."""
    best = {}
    for no_edges in (False, True):
        episodes, slot, _ = _walked(_task(stop_at_best=True, posterior_no_edges=no_edges))
        readings = len(episodes.ends.readings[0])
        episodes.ends.note(
            slot,
            episodes.setting[slot] * 0 + episodes.low[slot],
            np.array([np.nan]),
            np.array([False]),
            np.array([False]),
            np.zeros((1, 1)),
        )
        assert len(episodes.ends.readings[0]) == readings  # never a measured reading
        best[no_edges] = episodes.ends.best(0)
    walked, _, _ = _walked(_task(stop_at_best=True))
    assert best[False] == walked.ends.best(0)
    assert best[True] != best[False]


def test_far_noise_reaches_the_episodes_posterior() -> None:
    episodes, _, _ = _walked(_task(stop_at_best=True, posterior_far_noise=0.1))
    assert episodes.ends._posterior(0).far_noise == 0.1
    assert episodes.ends._posterior(0).models.far_noise == 0.1
    plain, _, _ = _walked(_task(stop_at_best=True))
    assert plain.ends._posterior(0).far_noise == 0.0


def test_the_episodes_posterior_levels_its_readings_off_where_the_task_says() -> None:
    episodes, _, _ = _walked(_task(stop_at_best=True, posterior_saturation_px=[10, 80]))
    assert episodes.ends.settings.saturation_px == (10.0, 80.0)
    saturation = episodes.ends._posterior(0).models.saturation
    assert 10.0 - 1e-9 <= saturation.min() < 0.9 * focus_box().saturation_px[0]
    assert saturation.max() <= 80.0 + 1e-9
    plain, _, _ = _walked(_task(stop_at_best=True))
    assert plain.ends._posterior(0).models.saturation.min() >= focus_box().saturation_px[0] - 1e-9


@pytest.mark.parametrize(
    ("option", "bad"),
    [
        ("posterior_far_noise", 1.5),
        ("posterior_walk_after", 99),
        ("posterior_walk_after", -1),
        ("posterior_probe_rule", "information"),
        ("posterior_saturation_px", (80.0, 10.0)),
        ("posterior_saturation_px", (0.0, 80.0)),
        ("posterior_saturation_px", (10.0, float("inf"))),
    ],
)
def test_the_posteriors_settings_are_refused_out_of_range(option, bad) -> None:
    assert POSTERIOR_PROBE_RULES == PROBE_RULES  # every rule the posterior has, and no other
    with pytest.raises(ValueError, match=option):
        TaskOptions(
            finish_at_posterior=True, stop_at_best=True, approach_from_below=True, **{option: bad}
        ).apply(get_task("focus"))


NEEDING_THE_POSTERIOR = [
    {"posterior_probe_rule": "entropy"},
    {"posterior_saturation_px": (10.0, 80.0)},
    {"posterior_far_noise": 0.1},
    {"posterior_walk_after": 3},
    {"posterior_walk_unmeasured": True},
    {"posterior_no_edges": True},
]


@pytest.mark.parametrize("option", NEEDING_THE_POSTERIOR)
def test_the_posteriors_settings_need_the_posterior(option) -> None:
    with pytest.raises(ValueError, match=next(iter(option))):
        TaskOptions(stop_at_best=True, **option).apply(get_task("focus"))


@pytest.mark.parametrize(
    ("options", "reason"),
    [
        ({"probe_until_sure": 0.9}, "the policy stopped"),
        ({"probe_until_sure": 0.9, "stop_when_sure": 0.9}, "its posterior was sure"),
    ],
)
def test_align_goes_on_while_the_posterior_turns_stops_into_readings(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], options, reason
) -> None:
    """`alignrl align` with a policy that stops at once: an unsure stop is a reading, and the
    alignment goes on (not left where that reading was taken) until the stop is taken, or a
    sure posterior ends it; the report says which."""
    import json

    from alignrl.cli import main
    from alignrl.deploy import policy as policy_module
    from alignrl.deploy.policy import DeployablePolicy

    task = _task(stop_at_best=True, **options)
    stopper = DeployablePolicy("stopper", lambda _: np.array([0.0, 1.0]), task, 8, "a test")
    monkeypatch.setattr(policy_module, "load_deployable", lambda spec: stopper)
    argv = ["align", "--policy", "stopper", "--apparatus", "family:focus", "--seed", "3"]
    assert main([*argv, "--apparatus-args", '{"analytic": true}', "--json"]) in (0, 1)
    result = json.loads(capsys.readouterr().out)
    assert 3 <= result["acquisitions"] <= task.episode_steps + 1  # went on past the 1st stop
    assert result["reason"].startswith(reason)
    assert result["success"]  # ended where the sure posterior puts focus


def test_the_way_back_to_the_posteriors_setting_arrives_from_below() -> None:
    """The posterior places its best setting as approached from below (FamilyPosterior.final).
    Where the narrowest reading is the column as found (no side known) and the way back goes
    down, it still arrives from below: past the setting by the overshoot, then up; before,
    it came straight down, on the other branch of a backlash, focused elsewhere."""
    task = _task(stop_at_best=True)
    unit = make_apparatus("instrument:val-backlash", {"analytic": True}, seed=0)
    episodes = AlignmentEpisodes([unit], task, history=8)
    slot = np.array([0])
    episodes.begin(slot, [1])
    episodes.misalign(slot, np.array([0.0]))  # found in focus (3.1 px): the narrowest reading
    episodes.step(slot, np.array([[0.6, -1.0]]))  # up, out of focus
    assert episodes.ends.narrowest(0).side[0] == 0
    above = float(unit.read()["defocus"])
    expected = _posterior_best(episodes)
    assert expected < above  # the way back goes down
    episodes.step(slot, np.array([[0.0, 1.0]]))
    assert episodes.info[0].ended_at_fit
    assert float(unit.read()["defocus"]) == pytest.approx(expected)
    assert episodes.ends.approach[0, 0] == 1.0  # the last change was up: from below

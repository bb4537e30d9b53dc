"""The task options that shape a move: `action_power`, a knob change of max_step x sign(a)
|a|^power, and `move_floor`, every move at least that share of the interval further. The same
in the episodes (alignrl/envs/core.py), in the exported graph's knob_step and in the loaded
policy's probe (alignrl/deploy); refused outside [1, 4] and [0, 0.2]."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_SAC, write_experiment

from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.registry import make_apparatus
from alignrl.cli import main
from alignrl.config.task_options import TaskOptions
from alignrl.deploy.loading import load_exported
from alignrl.envs.core import AlignmentEpisodes, feature_layout
from alignrl.envs.task import get_task, knob_change
from alignrl.runs.sources import ExportError


def test_knob_changes_keep_their_sign_and_reach_and_are_finer_near_zero() -> None:
    actions = np.array([-1.0, -0.5, -0.1, 0.0, 0.1, 0.5, 1.0])
    np.testing.assert_allclose(knob_change(actions, 20.0), 20.0 * actions)
    squared = knob_change(actions, 20.0, 2.0)
    np.testing.assert_allclose(squared, [-20.0, -5.0, -0.2, 0.0, 0.2, 5.0, 20.0])
    assert np.all(np.diff(squared) > 0)  # still monotone: every change has one action
    # An action 0.01 off asks for a change 0.01 x max_step off (linear), but only
    # 2 x 0.1 x 0.01 = 0.002 x max_step off at a = 0.1 (power 2): a steep column's last move.
    linear_error = abs(knob_change(0.11, 1.0) - knob_change(0.1, 1.0))
    fine_error = abs(knob_change(0.11, 1.0, 2.0) - knob_change(0.1, 1.0, 2.0))
    assert fine_error < 0.25 * linear_error


def test_a_floor_moves_every_nonzero_action_at_least_that_far() -> None:
    actions = np.array([[-1.0, 0.5], [-1e-6, 0.0], [0.0, -0.25], [0.3, 1.0]])
    floor = np.array([0.5, 2.0])  # per knob, its units
    changes = knob_change(actions, np.array([10.0, 4.0]), 1.0, floor)
    expected = [[-10.5, 4.0], [-0.5 - 1e-5, 0.0], [0.0, -3.0], [3.5, 6.0]]
    np.testing.assert_allclose(changes, expected)
    assert np.all(
        np.abs(changes[actions != 0]) >= np.broadcast_to(floor, actions.shape)[actions != 0]
    )
    assert np.all(np.sign(changes) == np.sign(actions))  # no action turns a move around
    powered = knob_change(np.array([0.5]), 10.0, 2.0, 1.0)
    np.testing.assert_allclose(powered, [3.5])  # the floor adds to the powered change


@pytest.mark.parametrize(
    ("option", "value"),
    [
        *(("move_floor", floor) for floor in (-0.01, 0.25, float("nan"))),
        *(("action_power", power) for power in (0.5, 4.5, float("nan"))),
    ],
)
def test_a_shaping_option_out_of_its_range_is_refused(option: str, value: float) -> None:
    """move_floor in [0, 0.2], action_power in [1, 4]: by the task and by the config."""
    with pytest.raises(ValueError, match=f"{option} must be in"):
        dataclasses.replace(get_task("focus"), **{option: value})
    if np.isfinite(value):
        with pytest.raises(ValueError, match=option):
            TaskOptions(**{option: value})


@pytest.mark.parametrize(
    ("options", "share"),
    [  # the move as a share of the interval, for the action -0.4 at a quarter per action
        ({"action_power": 2.0}, -0.16 * 0.25),
        ({"move_floor": 0.02}, -0.4 * 0.25 - 0.02),
        ({"action_power": 2.0, "move_floor": 0.02}, -0.16 * 0.25 - 0.02),
    ],
)
def test_an_episode_moves_the_knob_as_its_task_shapes_the_action(options, share) -> None:
    task = TaskOptions(max_step_fraction=0.25, **options).apply(get_task("focus"))
    unit = make_apparatus("family:focus", {"analytic": True}, seed=3)
    episodes = AlignmentEpisodes([unit], task, history=4)
    slot = np.array([0])
    episodes.begin(slot, [11])
    episodes.misalign(slot, np.array([0.0]))  # the middle of the interval
    low, high = float(episodes.low[0, 0]), float(episodes.high[0, 0])
    before = float(episodes.setting[0, 0])
    episodes.step(slot, np.array([[-0.4, -1.0]]))
    moved = float(episodes.setting[0, 0]) - before
    assert moved == pytest.approx(share * (high - low), rel=1e-9)
    # The observation's last action is the action itself, not the change.
    action = feature_layout(1)["action"]
    np.testing.assert_allclose(episodes.history[0, -1, action], [-0.4, -1.0])


@pytest.mark.parametrize(
    ("option", "value"), [("action_power", 2.0), ("move_floor", 0.02)], ids=["power", "floor"]
)
def test_an_exported_policy_steps_as_its_task_says(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: float
) -> None:
    experiment = write_experiment(
        tmp_path,
        {
            "name": "powered",
            "envs": 2,
            "learner": {"algorithm": "sac", **SMALL_SAC},
            "task_options": {option: value},
            "budget": {"env_steps": 48, "eval_every": 48, "eval_scenarios": 2},
        },
    )
    runs = tmp_path / "runs"
    assert main(["train", str(experiment), "--runs-dir", str(runs), "--quiet"]) == 0
    batch = np.random.default_rng(5).normal(size=(64, 8, 7)).astype(np.float32)
    for export_format in ("safetensors", "torchscript"):
        out = tmp_path / export_format
        args = ["export", str(runs / "powered"), "--format", export_format, "--out", str(out)]
        assert main(args) == 0
        capsys.readouterr()
        policy = load_exported(out)
        assert getattr(policy.task, option) == value
        outputs = policy.run(batch)
        action = outputs["action"][:, :1].astype(np.float64)
        if option == "action_power":
            steps = np.sign(action) * action**2 * policy.max_step
        else:  # the interval is four max steps (a quarter of it per action)
            steps = action * policy.max_step + np.sign(action) * value * 4 * policy.max_step
        np.testing.assert_allclose(outputs["knob_step"], steps, rtol=1e-5, atol=1e-5)
        assert not np.allclose(outputs["knob_step"], action * policy.max_step, atol=1e-3)
    # A graph carries its shaping: a card whose option was edited away no longer matches the
    # steps the file asks for, and is refused before any instrument.
    card_path = tmp_path / "torchscript" / "card.json"
    card = json.loads(card_path.read_text())
    del card["task"]["options"][option]
    card_path.write_text(json.dumps(card))
    with pytest.raises(ExportError, match="scales its actions"):
        load_exported(card_path.parent)


def test_a_steep_validation_column_needs_the_focus_within_a_third_of_a_percent() -> None:
    """docs/physics.md's figure for val-steep: within 1.15x the best width only within about
    0.34 % of the interval (both sides together: the spec's span over 2), an action within
    about +-0.014 at a quarter of the interval per action."""
    column = make_apparatus("instrument:val-steep", {"analytic": True}, seed=0)
    column.reset(seed=0)
    width = column.draw.width
    errors = np.linspace(-0.01, 0.01, 40001) * width
    reading = np.array(
        [column._levelled(TEN_NINETY_PER_SIGMA * column.probe_sigma_px(e)) for e in errors]
    )
    within = errors[reading <= 1.15 * reading[len(errors) // 2]]  # the middle error is 0
    half_span = (within.max() - within.min()) / 2 / width
    assert half_span == pytest.approx(0.0034, abs=0.0002)
    assert half_span / 0.25 == pytest.approx(0.014, abs=0.001)


def test_an_export_may_set_how_a_trained_policy_acts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`alignrl export --set task_options.move_floor=...`: the card records the option and
    the command, the loaded policy acts with it; an option that changes what the policy
    observes, any other key, and a floor out of range are refused and nothing is written."""
    out = tmp_path / "floored"
    argv = ["export", "champion:focus-v2", "--format", "safetensors", "--out", str(out)]
    assert main([*argv, "--set", "task_options.move_floor=0.02"]) == 0
    assert "every move at least" in capsys.readouterr().out
    card = json.loads((out / "card.json").read_text())
    assert card["task"]["options"]["move_floor"] == 0.02
    assert "--set task_options.move_floor=0.02" in card["command"]
    policy = load_exported(out)
    assert policy.task.move_floor == 0.02 and policy.task.action_power == 2.0
    knobs = card["knobs"][0]
    outputs = policy.run(np.random.default_rng(1).normal(size=(32, 10, 7)).astype(np.float32))
    action = outputs["action"][:, :1].astype(np.float64)
    floor = 0.02 * (knobs["high"] - knobs["low"])
    steps = np.sign(action) * (action**2 * policy.max_step + floor)
    np.testing.assert_allclose(outputs["knob_step"], steps, rtol=1e-5, atol=1e-3)
    for assignment, named in [
        ("task_options.action_power=1", "changes only how the trained policy acts"),
        ("budget.env_steps=10", "changes only how the trained policy acts"),
        ("task_options.move_floor", "changes only how the trained policy acts"),
        ("task_options.move_floor=0.9", "task_options.move_floor"),
    ]:
        refused = tmp_path / "refused"
        assert main([*argv[:-1], str(refused), "--set", assignment]) == 2
        assert named in capsys.readouterr().err
        assert not refused.exists()

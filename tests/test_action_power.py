"""The task option `action_power`: a knob change of max_step x sign(a) |a|^power, the same in
the episodes (alignrl/envs/core.py), in the exported graph's knob_step and in the loaded
policy's probe (alignrl/deploy), and refused outside [1, 4]."""

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
from alignrl.config import TaskOptions
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


@pytest.mark.parametrize("power", [0.5, 4.5, float("nan")])
def test_a_power_outside_one_to_four_is_refused(power: float) -> None:
    with pytest.raises(ValueError, match="action_power must be in"):
        dataclasses.replace(get_task("focus"), action_power=power)
    if np.isfinite(power):
        with pytest.raises(ValueError, match="action_power"):
            TaskOptions(action_power=power)


def test_an_episode_moves_the_knob_by_the_powered_action() -> None:
    task = TaskOptions(action_power=2.0, max_step_fraction=0.25).apply(get_task("focus"))
    unit = make_apparatus("family:focus", {"analytic": True}, seed=3)
    episodes = AlignmentEpisodes([unit], task, history=4)
    slot = np.array([0])
    episodes.begin(slot, [11])
    episodes.misalign(slot, np.array([0.0]))  # the middle of the interval
    low, high = float(episodes.low[0, 0]), float(episodes.high[0, 0])
    before = float(episodes.setting[0, 0])
    episodes.step(slot, np.array([[-0.4, -1.0]]))
    moved = float(episodes.setting[0, 0]) - before
    assert moved == pytest.approx(-0.16 * 0.25 * (high - low), rel=1e-9)
    # The observation's last action is the action itself, not the change.
    action = feature_layout(1)["action"]
    np.testing.assert_allclose(episodes.history[0, -1, action], [-0.4, -1.0])


def test_an_exported_policy_steps_as_its_task_says(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    experiment = write_experiment(
        tmp_path,
        {
            "name": "powered",
            "envs": 2,
            "learner": {"algorithm": "sac", **SMALL_SAC},
            "task_options": {"action_power": 2.0},
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
        assert policy.task.action_power == 2.0
        outputs = policy.run(batch)
        action = outputs["action"][:, :1].astype(np.float64)
        steps = np.sign(action) * action**2 * policy.max_step
        np.testing.assert_allclose(outputs["knob_step"], steps, rtol=1e-5, atol=1e-5)
        assert not np.allclose(outputs["knob_step"], action * policy.max_step, atol=1e-3)
    # A graph carries its power: a card whose power was edited away no longer matches the
    # steps the file asks for, and is refused before any instrument.
    card_path = tmp_path / "torchscript" / "card.json"
    card = json.loads(card_path.read_text())
    del card["task"]["options"]["action_power"]
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

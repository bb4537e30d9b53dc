"""The ending as one typed record (alignrl/envs/endings.py): Task.ending, an Ending, with
its posterior's PosteriorSettings, validated once; the flat task options it is written as
(a run's task_options:, a card's task.options) parsed by ending_from_options and written back
by ending_options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from alignrl.config.task_options import TaskOptions
from alignrl.envs.endings import (
    ENDING_OPTIONS,
    Ending,
    PosteriorSettings,
    ending_from_options,
    ending_options,
    with_ending,
)
from alignrl.envs.task import get_task

CHAMPIONS = sorted(
    (Path(__file__).resolve().parents[1] / "alignrl" / "champions").glob("*/card.json")
)


@pytest.mark.parametrize("card", CHAMPIONS, ids=[card.parent.name for card in CHAMPIONS])
def test_a_cards_flat_options_round_trip_through_the_ending(card: Path) -> None:
    """card options -> Ending -> options: equal, and the task the card's options make holds
    that same Ending."""
    options = json.loads(card.read_text())["task"]["options"]
    flat = {name: value for name, value in options.items() if name in ENDING_OPTIONS}
    ending = ending_from_options(flat)
    written = ending_options(ending, every=True)
    for name, value in flat.items():
        assert written[name] == (tuple(value) if isinstance(value, list) else value), name
    assert ending_from_options(ending_options(ending)) == ending
    task_name = json.loads(card.read_text())["task"]["name"]
    assert TaskOptions(**options).apply(get_task(task_name)).ending == ending


def test_the_four_endings_from_their_flags() -> None:
    assert ending_from_options({}) == Ending()
    assert ending_from_options({"stop_at_best": True}).at == "narrowest"
    fit = ending_from_options({"stop_at_best": True, "finish_at_fit": True})
    assert (fit.at, fit.stop_at_best) == ("fit", True)
    moved = ending_from_options({"final_move": True, "finish_at_fit": True})
    assert (moved.at, moved.stop_at_best, moved.final_move) == ("fit", False, True)
    assert ending_options(moved) == {"finish_at_fit": True, "final_move": True}
    posterior = ending_from_options(
        {
            "stop_at_best": True,
            "finish_at_posterior": True,
            "approach_from_below": True,
            "posterior_draws": 64,
        }
    )
    assert posterior.posterior == PosteriorSettings(draws=64)
    assert ending_options(posterior)["posterior_draws"] == 64


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"finish_at_fit": True}, "finish_at_fit ends the way back"),
        ({"stop_at_best": True, "final_move": True}, "choose one"),
        ({"stop_at_best": True, "finish_at_fit": True, "finish_at_posterior": True}, "choose one"),
        ({"stop_at_best": True, "finish_at_posterior": True}, "approach_from_below"),
        ({"stop_at_best": True, "posterior_draws": 64}, "posterior_draws is a setting"),
        ({"stop_when_sure": 0.5}, "stop_when_sure is a setting"),
        ({"final_move_reach": 0.5}, "final_move_reach is the last move's share"),
        ({"backlash_overshoot": 0.6}, r"backlash_overshoot must be in \[0, 0.5\]"),
        ({"finish_window": 1.0}, "finish_window must be above 1"),
        ({"final_move": True, "final_move_reach": 0.0}, r"final_move_reach must be in \(0, 1\]"),
    ],
)
def test_an_ending_that_does_not_hold_is_refused_naming_the_option(options, fragment) -> None:
    with pytest.raises(ValueError, match=fragment):
        ending_from_options(options)


@pytest.mark.parametrize(
    ("settings", "fragment"),
    [
        ({"draws": 8}, r"posterior_draws must be in \[16, 4096\]"),
        ({"draws": 5000}, r"posterior_draws must be in \[16, 4096\]"),
        ({"far_noise": 1.5}, r"posterior_far_noise must be in \[0, 1\]"),
        ({"walk_after": -1}, r"posterior_walk_after must be in \[0, 100\]"),
        ({"probe_rule": "information"}, "posterior_probe_rule must be one of variance"),
        ({"stop_when_sure": 1.0}, r"stop_when_sure must be in \[0, 1\)"),
        ({"probe_until_sure": -0.1}, r"probe_until_sure must be in \[0, 1\)"),
        ({"saturation_px": (80.0, 10.0)}, "posterior_saturation_px"),
        ({"column": (1.0,)}, "posterior_column"),
    ],
)
def test_posterior_settings_are_refused_naming_the_option_and_its_bound(settings, fragment) -> None:
    with pytest.raises(ValueError, match=fragment):
        PosteriorSettings(**settings)


def test_the_record_holds_itself_together() -> None:
    with pytest.raises(ValueError, match="at must be one of last, narrowest, fit, posterior"):
        Ending(at="best")
    with pytest.raises(ValueError, match="posterior settings go with at='posterior'"):
        Ending(at="fit", posterior=PosteriorSettings())
    with pytest.raises(ValueError, match="posterior settings go with at='posterior'"):
        Ending(at="posterior", approach_from_below=True)
    with pytest.raises(ValueError, match="final_move ends where"):
        Ending(at="narrowest", final_move=True)


def test_the_task_refuses_an_ending_it_cannot_have() -> None:
    with pytest.raises(ValueError, match="stop_at_best returns to the narrowest reading"):
        with_ending(get_task("stigmation"), stop_at_best=True)
    with pytest.raises(ValueError, match="finish_at_fit ends at a focus-curve fit along one knob"):
        with_ending(get_task("stigmation"), final_move=True, finish_at_fit=True)
    with pytest.raises(ValueError, match=r"posterior_walk_after.*at most episode_steps=10"):
        with_ending(
            get_task("focus"),
            stop_at_best=True,
            finish_at_posterior=True,
            approach_from_below=True,
            posterior_walk_after=11,
        )

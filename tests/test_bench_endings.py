"""benchmarks/endings.py: one policy's alignments ended several ways on the same sessions,
never on the held-out set."""

from __future__ import annotations

import dataclasses

import pytest

import benchmarks.endings as endings_module
from alignrl.deploy.policy import load_deployable
from alignrl.envs.endings import with_ending
from alignrl.envs.task import get_task
from benchmarks.endings import endings, floors, main


@pytest.fixture
def light_champion(monkeypatch: pytest.MonkeyPatch) -> None:
    """champion:focus-v2 with a posterior of 16 columns (the least a task takes) in place of
    its 1,024: the same tables, in far less computing (its posterior is asked at every reading
    of its walk)."""
    champion = load_deployable("champion:focus-v2")
    task = with_ending(champion.task, posterior_draws=16)
    light = dataclasses.replace(champion, task=task)
    monkeypatch.setattr(endings_module, "load_deployable", lambda spec: light)


def test_each_ending_changes_only_what_happens_once_the_policy_stops() -> None:
    trained = get_task("focus")
    compared = endings(trained, [3.0, 10.0])
    assert [label for label, _ in compared] == [
        "as trained",
        "narrowest, straight back",
        "narrowest",
        "fit within 3x",
        "fit within 10x",
        "as trained, every reading from below",
        "at the posterior, every reading from below",
    ]
    assert compared[0][1] is trained
    assert compared[1][1].ending.backlash_overshoot == 0 and compared[1][1].ending.at != "fit"
    assert [task.ending.finish_window for _, task in compared[3:5]] == [3.0, 10.0]
    assert compared[5][1] == with_ending(trained, approach_from_below=True)
    assert compared[6][1] == with_ending(
        compared[2][1], approach_from_below=True, finish_at_posterior=True
    )
    for _, task in compared[1:5]:
        assert task.ending.stop_at_best
        assert (task.knobs, task.episode_steps, task.action_power) == (
            trained.knobs,
            trained.episode_steps,
            trained.action_power,
        )


def test_the_endings_table_has_a_column_per_ending(
    capsys: pytest.CaptureFixture[str], light_champion: None
) -> None:
    argv = ["--policy", "champion:focus-v2", "--analytic", "--scenarios", "1", "--windows", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.startswith("| instrument"))
    cells = [cell.strip() for cell in header.strip("|").split("|")]
    assert cells == [
        "instrument",
        "as trained",
        "narrowest, straight back",
        "narrowest",
        "fit within 10x",
        "as trained, every reading from below",
        "at the posterior, every reading from below",
    ]
    assert "val-steep" in out and "**total**" in out


def test_floor_rows_change_only_how_far_each_move_goes(
    capsys: pytest.CaptureFixture[str], light_champion: None
) -> None:
    trained = get_task("focus")
    compared = floors(trained, [0.01, 0.02])
    assert [label for label, _ in compared] == ["moves at least 0.01", "moves at least 0.02"]
    assert [task for _, task in compared] == [
        dataclasses.replace(trained, move_floor=value) for value in (0.01, 0.02)
    ]
    ((label, below),) = floors(trained, [0.0], below=True)
    assert label == "moves at least 0, every reading from below"
    assert below == with_ending(trained, approach_from_below=True)
    argv = ["--policy", "champion:focus-v2", "--analytic", "--scenarios", "1", "--floors", "0.02"]
    assert main([*argv, "--floors-only", "--below"]) == 0
    header = next(line for line in capsys.readouterr().out.splitlines() if "| instrument" in line)
    assert [cell.strip() for cell in header.strip("|").split("|")] == [
        "instrument",
        "moves at least 0.02, every reading from below",
    ]
    assert main([*argv[:-1], "0.5"]) == 2
    assert "every floor must be in [0, 0.2]" in capsys.readouterr().err


def test_the_held_out_set_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--policy", "champion:focus-v2", "--set", "heldout"]) == 2
    assert "held out" in capsys.readouterr().err


def test_the_posteriors_options_leave_with_it() -> None:
    """A policy that asks its posterior more (the shipped champion's probe_until_sure) is
    compared with endings that ask none, and the ending at the posterior takes every stop."""
    from alignrl.config.task_options import TaskOptions

    trained = TaskOptions(
        approach_from_below=True,
        stop_at_best=True,
        finish_at_posterior=True,
        probe_until_sure=0.9,
        posterior_draws=64,
    ).apply(get_task("focus"))
    compared = dict(endings(trained, [3.0]))
    assert compared["as trained"] is trained
    for label in ("narrowest", "fit within 3x", "at the posterior, every reading from below"):
        task = compared[label]
        settings = task.ending.settings
        assert (settings.probe_until_sure, settings.stop_when_sure, settings.draws) == (0, 0, 256)
    assert compared["at the posterior, every reading from below"].ending.at == "posterior"
    assert compared["fit within 3x"].ending.at == "fit"
    ((_, fitted),) = floors(trained, [0.02])
    assert fitted.ending.at == "fit" and fitted.ending.posterior is None
    assert fitted.ending.settings.probe_until_sure == 0

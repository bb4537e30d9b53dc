"""benchmarks/endings.py: one policy's alignments ended several ways on the same sessions,
never on the held-out set."""

from __future__ import annotations

import dataclasses

import pytest

from alignrl.envs.task import get_task
from benchmarks.endings import endings, main


def test_each_ending_changes_only_what_happens_once_the_policy_stops() -> None:
    trained = get_task("focus")
    compared = endings(trained, [3.0, 10.0])
    assert [label for label, _ in compared] == [
        "as trained", "narrowest, straight back", "narrowest", "fit within 3x", "fit within 10x",
        "as trained, every reading from below",
    ]  # fmt: skip
    assert compared[0][1] is trained
    assert compared[1][1].backlash_overshoot == 0 and not compared[1][1].finish_at_fit
    assert [task.finish_window for _, task in compared[3:5]] == [3.0, 10.0]
    assert compared[5][1] == dataclasses.replace(trained, approach_from_below=True)
    for _, task in compared[1:5]:
        assert task.stop_at_best
        assert (task.knobs, task.episode_steps, task.action_power) == (
            trained.knobs, trained.episode_steps, trained.action_power,
        )  # fmt: skip


def test_the_endings_table_has_a_column_per_ending(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--policy", "champion:focus-v2", "--analytic", "--scenarios", "3", "--windows", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.startswith("| instrument"))
    cells = [cell.strip() for cell in header.strip("|").split("|")]
    assert cells == ["instrument", "as trained", "narrowest, straight back", "narrowest",
                     "fit within 10x", "as trained, every reading from below"]  # fmt: skip
    assert "val-steep" in out and "**total**" in out


def test_the_held_out_set_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--policy", "champion:focus-v2", "--set", "heldout"]) == 2
    assert "held out" in capsys.readouterr().err

"""benchmarks/reliability.py: the chance an aligner's ending posterior states after each
reading, against the verification at the setting it would end at."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from alignrl.apparatus.registry import make_apparatus
from alignrl.envs.task import get_task
from benchmarks.reliability import (
    Stated,
    binned,
    main,
    stated_chances,
    stopped_at,
    verified_at,
)


def test_readings_are_binned_by_the_chance_stated() -> None:
    chances = [0.1, 0.6, 0.97, 0.99, 1.0]
    passed = [False, True, True, False, True]
    pairs = enumerate(zip(chances, passed, strict=True))
    rows = [Stated(0, 2 + i, chance, ok, i == 4) for i, (chance, ok) in pairs]
    bins = binned(rows)
    assert [each.count for each in bins] == [1, 1, 0, 0, 1, 2]
    assert [each.found for each in bins][:2] == [0.0, 1.0]
    assert math.isnan(bins[2].found) and math.isnan(bins[3].stated)
    # the last bin is closed at 1: a posterior certain of its setting is counted
    assert bins[5].stated == pytest.approx(0.995) and bins[5].found == 0.5


def test_an_earlier_stop_ends_each_episode_at_its_first_reading_that_sure() -> None:
    rows = [
        Stated(0, 2, 0.5, False, False),
        Stated(0, 3, 0.92, True, False),
        Stated(0, 4, 0.99, True, True),
        Stated(1, 2, 0.96, False, False),
        Stated(1, 3, 0.985, True, True),
        Stated(2, 2, 0.91, False, False),
        Stated(2, 3, 0.97, False, False),
        Stated(2, 4, 0.6, False, True),  # the step limit: it ends where it stopped
    ]
    at_090 = stopped_at(rows, 0.9)
    assert (at_090.episodes, at_090.median_readings) == (3, 2)
    assert at_090.passed == pytest.approx(1 / 3)
    at_098 = stopped_at(rows, 0.98)
    assert at_098.median_readings == 4 and at_098.passed == pytest.approx(2 / 3)


def test_the_verification_passes_at_focus_from_below_and_not_far_from_it() -> None:
    column = make_apparatus("instrument:val-mid", {"analytic": True})
    column.reset(7)
    task = get_task("focus")
    low, high = column.knobs["defocus"]
    column.write({"defocus": low})  # below focus: the setting that focuses from below
    focus = (column.optimum()["defocus"] - low) / (high - low)
    threshold = task.success.relative * column.best_quality()
    assert verified_at(column, focus, task, threshold)
    assert not verified_at(column, 0.0 if focus > 0.5 else 1.0, task, threshold)
    # the twin is written, never the column
    assert column.read()["defocus"] == low


def test_every_reading_states_a_chance_and_each_episode_stops_once(light_export: Path) -> None:
    rows = stated_chances(str(light_export), "instrument:val-mid", episodes=2, seed=100)
    assert {row.episode for row in rows} == {0, 1}
    assert all(0.0 <= row.chance <= 1.0 for row in rows)
    for episode in (0, 1):
        mine = [row for row in rows if row.episode == episode]
        readings = [row.readings for row in mine]
        assert readings == sorted(set(readings))  # one row per reading, in order
        assert [row.stopped for row in mine] == [False] * (len(mine) - 1) + [True]
        # the champion stops once 98 % sure (or at its step limit): a sure stop passes
        assert mine[-1].chance >= 0.98 and mine[-1].passed


def test_the_benchmark_writes_its_readings_and_refuses_the_held_out_set(
    tmp_path: Path, light_export: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rel"
    argv = ["--policy", str(light_export), "--apparatus", "instrument:val-mid"]
    assert main([*argv, "--episodes", "1", "--out", str(out)]) == 0
    assert "| 0.98-1.00 |" in capsys.readouterr().out
    written = json.loads((out / "reliability.json").read_text())
    assert written["readings"] and len(written["bins"]) == 6
    assert [stop["level"] for stop in written["stops"]] == [0.9, 0.95, 0.98]
    assert (out / "reliability.png").stat().st_size > 0
    held = ["--apparatus", "instrument:near-bound", "--out", str(tmp_path / "held")]
    assert main(held) == 2
    assert "held out" in capsys.readouterr().err
    assert not (tmp_path / "held").exists()

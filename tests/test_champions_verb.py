"""`alignrl champions` (make run's first part): every shipped champion beside its task's
classical controllers, on the same columns from the same starts, none of them a column the
champion trained on."""

from __future__ import annotations

import contextlib
import io
import json

import pytest
from tqdm import tqdm

from alignrl.apparatus.instruments import instrument_names
from alignrl.cli import champions
from alignrl.cli.champions import COLUMN_NAME, FOCUS_CLASSICAL, HELD_OUT_SET, alignments
from alignrl.cli.main import main
from alignrl.evaluation.baselines import task_baselines


@pytest.fixture(scope="module")
def shown() -> tuple[dict, str]:
    """The verb's JSON and its text, one alignment per column: the sessions run once, then
    the verb prints them both ways."""
    measured = champions.measure(1, 4, tqdm(disable=True))
    found = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(champions, "measure", lambda scenarios, seed, bar: measured)
        for extra in (["--json"], []):
            out = io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
                argv = ["champions", "--scenarios", "1", "--seed", "4", "--quiet", *extra]
                assert main(argv) == 0
            found.append(out.getvalue())
    return json.loads(found[0]), found[1]


def test_focus_v2_and_the_classical_fits_align_the_same_held_out_columns(shown) -> None:
    payload, text = shown
    focus = payload["focus"]
    assert sorted(focus) == sorted(["focus-v2", *FOCUS_CLASSICAL])  # JSON keys sorted
    instruments = list(instrument_names(HELD_OUT_SET))
    for result in focus.values():
        assert result["set"] == HELD_OUT_SET and result["seed"] == 4
        assert [row["instrument"] for row in result["instruments"]] == instruments
        assert result["total"]["alignments"] == len(instruments)
    assert "| **total** " in text and "focus-v2 calibrated on ten alignments" in text
    assert "not run here" in payload["calibrated"]


def test_every_other_task_shows_its_champion_then_its_classical_controllers(shown) -> None:
    payload, text = shown
    for task, champion in (
        ("stigmation", "stigmation-v1"),
        ("aperture", "aperture-v1"),
        ("column", COLUMN_NAME),
    ):
        results = payload[task]
        assert sorted(results) == sorted([champion, *task_baselines(task)])
        held_out = f"heldout-{task}"  # columns the champion never trained on
        instruments = list(instrument_names(held_out))
        for result in results.values():
            assert result["set"] == held_out and result["seed"] == 4
            assert [row["instrument"] for row in result["instruments"]] == instruments
        assert f"{task} on set:{held_out}" in text
    focus = len(instrument_names(HELD_OUT_SET)) * (1 + len(FOCUS_CLASSICAL))
    others = sum(
        len(instrument_names(f"heldout-{task}")) * (1 + len(task_baselines(task)))
        for task in ("stigmation", "aperture", "column")
    )
    assert alignments(1) == focus + others  # what the progress bar counts


def test_a_scenario_count_out_of_range_is_refused(capsys) -> None:
    assert main(["champions", "--scenarios", "0", "--quiet"]) == 2
    assert "--scenarios must be in 1-1000" in capsys.readouterr().err


@pytest.mark.parametrize(("option", "value"), [("--seed", "-1"), ("--scenarios", "ten")])
def test_an_option_that_is_not_a_number_of_its_kind_is_refused_by_name(option, value, capsys):
    """The sessions' options read as every session verb reads them (alignrl/cli/common.py)."""
    with pytest.raises(SystemExit):
        main(["champions", option, value, "--quiet"])
    assert f"argument {option}: " in capsys.readouterr().err

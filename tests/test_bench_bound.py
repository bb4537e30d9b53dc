"""benchmarks/bound.py: the Bayesian autofocus over a set, as an oracle of each instrument,
its results written, read back, and shown beside other controllers' of the same sessions."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

import benchmarks.bound as bound
from alignrl.envs.ending import resample_for
from alignrl.evaluation.posterior import ROBUST
from benchmarks.bound import main


def _rows(out: str) -> dict[str, list[str]]:
    rows = {}
    for line in out.splitlines():
        if line.startswith("| ") and not line.startswith("| ---"):
            cells = [cell.strip() for cell in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_oracle_rows_are_written_read_back_and_shown_beside(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--kind", "oracle", "--set", "validation", "--analytic", "--scenarios", "2"]
    assert main([*argv, "--out", str(tmp_path / "bound")]) == 0
    first = _rows(capsys.readouterr().out)
    saved = json.loads((tmp_path / "bound" / "oracle.json").read_text())
    assert saved["controller"] == "oracle" and saved["set"] == "validation"
    assert [item["instrument"] for item in saved["instruments"]] == [
        "val-backlash",
        "val-low-bound",
        "val-mid",
        "val-shallow-hysteretic",
        "val-steep",
        "val-texture-noisy",
    ]
    assert first["instrument"] == ["oracle"]
    assert first["**total**"][0].startswith(f"{saved['total']['successes']}/12")

    # another controller's result of the same sessions, and one of other sessions
    beside = tmp_path / "heldout"
    beside.mkdir()
    (beside / "other.json").write_text(json.dumps({**saved, "controller": "other"}))
    (beside / "elsewhere.json").write_text(json.dumps({**saved, "controller": "x", "seed": 7}))
    argv += ["--out", str(tmp_path / "bound"), "--reuse", "--beside", str(beside)]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "oracle: read" in captured.err
    again = _rows(captured.out)
    assert again["instrument"] == ["other", "oracle"]
    assert again["**total**"][0] == again["**total**"][1] == first["**total**"][0]


@pytest.fixture
def made(monkeypatch: pytest.MonkeyPatch) -> list:
    """Every BayesianAutofocus benchmarks/bound.py makes, as it makes it; each then aligns with
    at most 64 columns (the robust kind draws 1,024), judging as many states as an episode's
    posterior of as many (resample_for): the same files and rows, whose figures these tests
    do not read, in less computing."""
    made = []

    class Recording(bound.BayesianAutofocus):
        def __post_init__(self) -> None:
            made.append(copy.copy(self))
            self.draws = min(self.draws, 64)
            self.resample = resample_for(self.draws)
            super().__post_init__()

    monkeypatch.setattr(bound, "BayesianAutofocus", Recording)
    return made


def test_a_probe_rule_names_its_result_and_reaches_the_posterior(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], made: list
) -> None:
    """--probe-rule chance: each kind's posterior probes by it, and its result is
    KIND-chance; the robust kind reads as posterior-robust does."""
    argv = ["--set", "validation", "--analytic", "--scenarios", "1", "--out", str(tmp_path)]
    assert main([*argv, "--kind", "oracle", "--kind", "robust", "--probe-rule", "chance"]) == 0
    assert sorted(path.name for path in tmp_path.glob("*.json")) == [
        "oracle-chance.json",
        "robust-chance.json",
    ]
    assert {posterior.probe_rule for posterior in made} == {"chance"}
    (robust,) = [posterior for posterior in made if posterior.name == "robust-chance"]
    assert {key: getattr(robust, key) for key in ROBUST} == ROBUST
    assert "robust-chance" in capsys.readouterr().out


def test_the_scale_free_oracle_reads_each_file_in_an_unknown_pixel_scale(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], made: list
) -> None:
    """--kind oracle-scale-free: one posterior per instrument over that instrument's own file,
    scale_free, beside the oracle's, which knows its pixels."""
    argv = ["--set", "validation", "--analytic", "--scenarios", "1", "--out", str(tmp_path)]
    assert main([*argv, "--kind", "oracle", "--kind", "oracle-scale-free"]) == 0
    assert sorted(path.name for path in tmp_path.glob("*.json")) == [
        "oracle-scale-free.json",
        "oracle.json",
    ]
    free = [posterior for posterior in made if posterior.name == "oracle-scale-free"]
    known = [posterior for posterior in made if posterior.name == "oracle"]
    assert len(free) == len(known) == 6
    assert all(posterior.scale_free and posterior.specimen_points == 1 for posterior in free)
    assert not any(posterior.scale_free for posterior in known)
    assert [posterior.family.name for posterior in free] == [
        posterior.family.name for posterior in known
    ]
    assert "oracle-scale-free" in capsys.readouterr().out

"""benchmarks/bound.py: the Bayesian autofocus over a set, as an oracle of each instrument,
its results written, read back, and shown beside other controllers' of the same sessions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

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
        "val-backlash", "val-low-bound", "val-mid", "val-shallow-hysteretic", "val-steep",
        "val-texture-noisy",
    ]  # fmt: skip
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

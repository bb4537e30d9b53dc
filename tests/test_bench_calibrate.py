"""benchmarks/calibrate.py: a policy calibrated on each instrument, then judged there."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.calibrate import main


def test_the_benchmark_calibrates_judges_and_reuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], light_export: Path
) -> None:
    argv = ["--policy", str(light_export), "--instrument", "narrow-interval", "--analytic"]
    argv += ["--alignments", "3", "--population", "8", "--rounds", "1", "--scenarios", "3"]
    argv += ["--out", str(tmp_path / "cal")]
    assert main(argv) == 0
    table = capsys.readouterr().out
    assert "| narrow-interval |" in table and "/3 (" in table
    judged = json.loads((tmp_path / "cal" / "narrow-interval" / "judged.json").read_text())
    assert judged["alignments"] == 3 and judged["scenarios"] == 3 and judged["steps"] >= 3
    assert (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    # --reuse reads the judged session back instead of calibrating again
    (tmp_path / "cal" / "narrow-interval" / "calibration.json").unlink()
    assert main([*argv, "--reuse"]) == 0
    assert not (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    assert "| narrow-interval |" in capsys.readouterr().out

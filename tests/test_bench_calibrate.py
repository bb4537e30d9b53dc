"""benchmarks/calibrate.py: a policy calibrated on each instrument, then judged there."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from alignrl.posterior.calibration import CALIBRATED_STOP, FAR_NOISE_SEARCHED
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
    assert judged["alignments"] == 3 and judged["scenarios"] == 3
    # every image the calibration took is a step and a reading it weighed: the alignments'
    # acquisitions and their verifications
    calibration = json.loads(
        (tmp_path / "cal" / "narrow-interval" / "calibration.json").read_text()
    )
    assert judged["steps"] == calibration["readings"] == sum(map(len, calibration["sweeps"]))
    # each alignment's verification (on its side), then the default two from above
    sides = [[side for _, _, side in sweep] for sweep in calibration["sweeps"]]
    assert calibration["from_above"] == 2 and all(each[-2:] == [-1, -1] for each in sides)
    assert all(each[-3] in (0.0, 1.0) for each in sides)
    # --reuse reads the judged session back instead of calibrating again
    (tmp_path / "cal" / "narrow-interval" / "calibration.json").unlink()
    assert main([*argv, "--reuse"]) == 0
    assert not (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    assert "| narrow-interval |" in capsys.readouterr().out
    # ... only a result of the same command: with other alignments it calibrates again
    changed = [*argv, "--reuse"]
    changed[changed.index("--alignments") + 1] = "2"
    assert main(changed) == 0
    assert (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    again = json.loads((tmp_path / "cal" / "narrow-interval" / "judged.json").read_text())
    assert again["alignments"] == 2
    # ... and only one judged with today's calibrated stop
    assert again["stop"] == CALIBRATED_STOP
    judged_path = tmp_path / "cal" / "narrow-interval" / "judged.json"
    judged_path.write_text(json.dumps({**again, "stop": 0.98}))
    (tmp_path / "cal" / "narrow-interval" / "calibration.json").unlink()
    assert main(changed) == 0
    assert (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    assert json.loads(judged_path.read_text())["stop"] == CALIBRATED_STOP
    # ... and with its far noise found as asked: searched by default, so one found with a
    # far noise given (as every result saved before the search) is judged again ...
    again = json.loads(judged_path.read_text())
    grid = list(FAR_NOISE_SEARCHED)
    assert again["far_noise_searched"] == grid and again["far_noise"] in grid
    judged_path.write_text(json.dumps({**again, "far_noise": 0.05, "far_noise_searched": None}))
    (tmp_path / "cal" / "narrow-interval" / "calibration.json").unlink()
    assert main(changed) == 0
    assert (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()
    assert json.loads(judged_path.read_text())["far_noise_searched"] == grid
    # ... and --far-noise fits with that one, and reads back only a result fitted with it
    assert main([*changed, "--far-noise", "0.07"]) == 0
    fixed = json.loads(judged_path.read_text())
    assert (fixed["far_noise"], fixed["far_noise_searched"]) == (0.07, None)
    calibration = json.loads(
        (tmp_path / "cal" / "narrow-interval" / "calibration.json").read_text()
    )
    assert (calibration["far_noise"], calibration["far_noise_searched"]) == (0.07, None)
    (tmp_path / "cal" / "narrow-interval" / "calibration.json").unlink()
    assert main([*changed, "--far-noise", "0.07"]) == 0
    assert not (tmp_path / "cal" / "narrow-interval" / "calibration.json").exists()

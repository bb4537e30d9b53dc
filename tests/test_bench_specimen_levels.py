"""benchmarks/specimen_levels.py: where each specimen's edge widths level off on frames."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.specimen_levels import fitted_level, main, specimen_level


def test_a_fit_recovers_the_level_its_widths_were_made_with() -> None:
    true = np.geomspace(2.0, 100.0, 12)
    level, error = fitted_level(true, 30.0 * np.tanh(true / 30.0))
    assert level == pytest.approx(30.0, rel=0.01) and error < 0.01
    level, _ = fitted_level(true, 60.0 * np.tanh(true / 60.0))
    assert level == pytest.approx(60.0, rel=0.01)


def test_a_grid_levels_off_below_the_training_box_and_a_texture_above_it() -> None:
    """The grid's frames level off below the box's 18 px, the texture's far above: what
    posterior_saturation_px's lower end of 10 px rests on."""
    grid = specimen_level("grid", draws=1, doses=(400.0,))
    texture = specimen_level("texture", draws=1, doses=(400.0,))
    assert 10.0 < grid.high_px < 18.0 < 30.0 < texture.low_px
    assert grid.fits == texture.fits == 1 and max(grid.rms_log_error, texture.rms_log_error) < 0.15
    assert grid.widest_px < texture.widest_px


def test_the_table_and_the_refusals(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--specimen", "grid", "--draws", "1", "--dose", "400"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("| specimen |") and "| grid |" in out
    assert main(["--specimen", "coins"]) == 2
    assert "no such specimen: coins" in capsys.readouterr().err
    assert main(["--draws", "0"]) == 2
    assert "--draws" in capsys.readouterr().err
    assert main(["--dose", "-5"]) == 2
    assert "--dose" in capsys.readouterr().err

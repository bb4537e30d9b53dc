"""benchmarks/image_levels.py: an instrument's images against its file's reading model, on
validation instruments only."""

from __future__ import annotations

import pytest

from benchmarks.image_levels import image_levels, main


def test_near_focus_images_read_as_the_model_and_far_a_grid_loses_its_edges() -> None:
    column, levels = image_levels("val-steep", frames=2, blurs=(5.0, 80.0))
    near, far = levels
    assert column.draw.specimen == "grid"
    assert near.images_px is not None and abs(near.images_px - near.analytic_px) < 0.5
    assert near.no_edges == 0 and near.frames == 2
    # The file's model still reads 52 px there with edges almost surely; the frames have none.
    assert far.analytic_px > 40 and far.no_edges_chance < 0.05
    assert far.images_px is None and far.no_edges == 2


def test_the_table_and_the_refusals(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--instrument", "near-bound"]) == 2
    assert "held out" in capsys.readouterr().err
    assert main(["--instrument", "val-nowhere"]) == 2
    assert "no such validation instrument" in capsys.readouterr().err
    assert main(["--instrument", "val-mid", "--frames", "0"]) == 2
    assert "--frames" in capsys.readouterr().err

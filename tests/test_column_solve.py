"""The model-based column (alignrl/evaluation/column_solve.py, `column-solve`): focus,
aperture, stigmators and focus, each stage solving with what the ones before learned; it reads
only what a driver gives, writes inside every interval, and refuses what it cannot align."""

from __future__ import annotations

import pytest
from conftest import WriteRecorder

from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import HyperbolaFit, get_baseline
from alignrl.evaluation.column_solve import ColumnSolve
from alignrl.evaluation.session import run_session

SCENARIOS = 6
TURNED = {
    "stigmator_rotation_deg": 130.0,
    "stigmator_coupling": 0.3,  # 0.5 asks more than the presets' stigmators reach
    "stigmator_mirror": True,
    "aperture_rotation_deg": 250.0,
    "aperture_mirror": True,
}


def _quiet(preset: str) -> dict:
    """Analytic readings without their scatter or drift."""
    calibration = load_sem_config(PRESET_DIR / f"{preset}.yaml").analytic_calibration.model_dump()
    for key in ("noise_rel", "specimen_rel", "directional_noise_rel", "directional_specimen_rel"):
        calibration[key] = [0.0] * len(calibration["knots_px"])
    return {"analytic": True, "analytic_calibration": calibration, "drift_v_per_acquisition": 0.0}


@pytest.mark.parametrize("response", [{}, TURNED])
def test_it_aligns_analytic_columns_whatever_the_response(response) -> None:
    apparatus = make_apparatus("synthetic", {**_quiet("synthetic"), **response})
    result = run_session(
        get_baseline("column-solve"), apparatus, get_task("column"), SCENARIOS, seed=3
    )
    assert result.successes >= SCENARIOS - 1, result
    assert result.median_acquisitions <= 24  # a mirrored aperture costs one more wobble


def test_every_write_stays_inside_its_interval() -> None:
    """A column started at the corners of every interval: the stigmators' and the aperture's
    steps turn back at their bounds, every defocus approach stays above the bottom."""
    apparatus = WriteRecorder(make_apparatus("synthetic-b", {"analytic": True, **TURNED}))
    apparatus.reset(seed=4)
    apparatus.write({"defocus": 1.0, "stigmator_x": 99.0, "stigmator_y": -99.0, "aperture_x": 59.0})
    get_baseline("column-solve").align_task(apparatus, get_task("column"), 60)
    assert len(apparatus.writes) > 10
    for values in apparatus.writes:
        for knob, value in values.items():
            low, high = apparatus.knobs[knob]
            assert low <= value <= high, (knob, value)


def test_it_refuses_a_task_without_its_knobs_and_runs_by_name() -> None:
    assert isinstance(get_baseline("column-solve"), ColumnSolve)
    for other in ("focus", "stigmation", "aperture"):
        with pytest.raises(ValueError, match="controller 'column-solve' aligns"):
            get_baseline("column-solve").check_task(get_task(other))
    get_baseline("column-solve").check_task(get_task("column"))
    with pytest.raises(ValueError, match="column-solve: switch_fraction"):
        ColumnSolve(focus=HyperbolaFit(), switch_fraction=0.5)

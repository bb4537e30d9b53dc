"""The model-based stigmation (alignrl/evaluation/model_based.py, `stigmator-solve`): it
identifies how the stigmators act from directional widths a little out of focus and solves
for the setting where the astigmatism vanishes, whatever their gain, units, rotation,
coupling or mirror; it reads only what a driver gives and writes inside every interval."""

from __future__ import annotations

import pytest

from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import get_baseline
from alignrl.evaluation.model_based import StigmatorSolve, WobbleSolve
from alignrl.evaluation.session import run_session

SCENARIOS = 30


def _quiet(preset: str) -> dict:
    """Analytic readings without their scatter or drift: what the identification does when
    the readings say exactly what the probe is."""
    calibration = load_sem_config(PRESET_DIR / f"{preset}.yaml").analytic_calibration.model_dump()
    for key in ("noise_rel", "specimen_rel", "directional_noise_rel", "directional_specimen_rel"):
        calibration[key] = [0.0] * len(calibration["knots_px"])
    return {"analytic": True, "analytic_calibration": calibration, "drift_v_per_acquisition": 0.0}


def _session(controller, preset: str, **args):
    apparatus = make_apparatus(preset, args)
    return run_session(controller, apparatus, get_task("stigmation"), SCENARIOS, seed=5)


@pytest.mark.parametrize(
    "response",
    [
        {},
        {"stigmator_rotation_deg": 60.0, "stigmator_coupling": 0.3, "stigmator_mirror": True},
        {"stigmator_interval_pct": [-10.0, 10.0], "stigmator_v_per_pct": 2.5},  # other units
    ],
)
def test_it_aligns_a_column_whatever_its_stigmators_response(response) -> None:
    solved = _session(StigmatorSolve(), "synthetic-b", **_quiet("synthetic-b"), **response)
    untouched = _session(_Untouched(), "synthetic-b", **_quiet("synthetic-b"), **response)
    assert solved.successes >= SCENARIOS - 3 > untouched.successes + 10, (solved, untouched)
    assert solved.median_acquisitions <= 13


@pytest.mark.parametrize(
    ("name", "controller", "other_task", "bad"),
    [
        ("stigmator-solve", StigmatorSolve, "focus", {"target_ratio": 1.0}),
        ("wobble-solve", WobbleSolve, "stigmation", {"step_fraction": 0.5}),
    ],
)
def test_each_is_a_controller_by_name_and_refuses_what_it_cannot_do(
    name, controller, other_task, bad
) -> None:
    assert isinstance(get_baseline(name), controller)
    with pytest.raises(ValueError, match=f"controller {name!r} aligns"):
        controller().check_task(get_task(other_task))
    with pytest.raises(ValueError, match=f"{name}: {next(iter(bad))}"):
        controller(**bad)


def test_every_write_stays_inside_its_interval_and_the_focus_comes_back() -> None:
    """Near the bottom of the defocus interval the offset goes above the focus instead; the
    stigmators' steps turn back at their bounds; the defocus ends where it was."""
    apparatus = _Recording(make_apparatus("synthetic-b", {"analytic": True}))
    apparatus.write({"defocus": 1.0, "stigmator_x": 99.0, "stigmator_y": -99.0})
    StigmatorSolve().align_task(apparatus, get_task("stigmation"), 40)
    assert apparatus.writes and apparatus.read()["defocus"] == 1.0
    for values in apparatus.writes:
        for knob, value in values.items():
            low, high = apparatus.knobs[knob]
            assert low <= value <= high, (knob, value)


class _Untouched:
    """Leaves the stigmators where the session put them."""

    name = "untouched"

    def check_task(self, task) -> None:
        return None

    def align_task(self, apparatus, task, budget) -> None:
        return None


class _Recording:
    def __init__(self, inner) -> None:
        self.inner, self.writes = inner, []
        self.knobs = inner.knobs

    def write(self, values) -> None:
        self.writes.append(dict(values))
        self.inner.write(values)

    def __getattr__(self, name):
        return getattr(self.inner, name)


# --- wobble-solve: the aperture from two wobbles --------------------------------------------


@pytest.mark.parametrize(
    ("response", "most"),
    [
        ({}, 6),  # two wobbles and one at the solution
        ({"aperture_rotation_deg": 130.0}, 6),
        ({"aperture_rotation_deg": 130.0, "aperture_mirror": True}, 10),  # a guess, then the fit
        ({"aperture_interval_um": [-6.0, 6.0], "aperture_offset_max_um": 4.0}, 6),  # other units
    ],
)
def test_wobble_solve_centres_the_aperture_whatever_the_image_does(response, most) -> None:
    apparatus = make_apparatus("synthetic-b", {"analytic": True, **response})
    solved = run_session(WobbleSolve(), apparatus, get_task("aperture"), SCENARIOS, seed=5)
    untouched = run_session(_Untouched(), apparatus, get_task("aperture"), SCENARIOS, seed=5)
    assert solved.successes == SCENARIOS > untouched.successes + 10, (solved, untouched)
    assert solved.median_acquisitions <= most

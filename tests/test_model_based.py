"""The model-based stigmation and aperture centring (alignrl/evaluation/model_based.py,
`stigmator-solve`, `wobble-solve`): each identifies how its knobs act (directional widths
out of focus; wobbles) and solves for the setting that aligns them, whatever their gain,
units, rotation, coupling or mirror; they read only what a driver gives and write inside
every interval."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import WriteRecorder

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import get_baseline
from alignrl.evaluation.model_based import (
    StigmatorSolve,
    WobbleSolve,
    _affine_wobbles,
    fit_response,
)
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
    assert solved.successes >= SCENARIOS - 2 > untouched.successes + 10, (solved, untouched)
    assert solved.median_acquisitions <= 8  # two for the offset, three to identify, the rounds


@pytest.mark.parametrize(
    ("name", "controller", "other_task", "bad"),
    [
        ("stigmator-solve", StigmatorSolve, "focus", {"offset_ratio": 1.0}),
        ("stigmator-solve", StigmatorSolve, "focus", {"step_fraction": 0.5}),
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


@pytest.mark.parametrize(
    "response",
    [{}, {"stigmator_rotation_deg": 60.0, "stigmator_coupling": 0.3, "stigmator_mirror": True}],
)
def test_the_fit_recovers_the_stigmators_matrix_and_their_optimum(response) -> None:
    """Quiet analytic readings at one offset: the fitted response is the column's matrix
    (SEMConfig.stigmator_response, turned, coupled, mirrored) up to one scale, within 0.1
    in every entry, and its zero the optimum within 2 % of the stigmators' half-interval."""
    quiet = {**_quiet("synthetic-b"), "hysteresis_v": 0.0}
    apparatus = make_apparatus("synthetic-b", {**quiet, **response}, seed=3)
    focus = apparatus.optimum()["defocus"]
    solve = StigmatorSolve()
    settings = ([0.0, 0.0], [30.0, 0.0], [0.0, 30.0], [20.0, 20.0])
    readings = [solve._read(apparatus, focus, 6.0, np.array(s)) for s in settings]
    offset, fitted = fit_response(readings, focus)
    matrix = apparatus.config.stigmator_response()
    matrix = np.eye(2) if matrix is None else matrix
    scale = float(np.sum(fitted * matrix) / np.sum(matrix * matrix))
    assert np.max(np.abs(fitted / scale - matrix)) < 0.1, (fitted / scale, matrix)
    optimum = apparatus.optimum()
    zero = np.linalg.solve(fitted, -offset)
    assert np.hypot(*(zero - [optimum["stigmator_x"], optimum["stigmator_y"]])) < 2.0


def test_every_write_stays_inside_its_interval_and_the_focus_comes_back() -> None:
    """Near the bottom of the defocus interval the offset goes above the focus instead; the
    stigmators' steps turn back at their bounds; the defocus ends where it was."""
    apparatus = WriteRecorder(make_apparatus("synthetic-b", {"analytic": True}))
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


def test_wobble_solve_writes_inside_every_interval_from_a_corner() -> None:
    """The aperture started at a corner of its travel, the image turned and mirrored: the
    identifying step turns back at the bound, every solution is clipped into the interval."""
    args = {"analytic": True, "aperture_rotation_deg": 200.0, "aperture_mirror": True}
    for seed in range(4):
        apparatus = WriteRecorder(make_apparatus("synthetic-b", args, seed=seed))
        apparatus.write({"aperture_x": 59.5, "aperture_y": -59.5})
        WobbleSolve().align_task(apparatus, get_task("aperture"), 40)
        assert len(apparatus.writes) > 3
        for values in apparatus.writes:
            for knob, value in values.items():
                low, high = apparatus.knobs[knob]
                assert low <= value <= high, (knob, value)


def test_wobbles_recover_the_apertures_response_turned_and_mirrored() -> None:
    """Three wobbles on a quiet analytic column: the affine fit's response is the image's
    turn and mirror against the aperture (SEMConfig.aperture_response) times one gain."""
    apparatus = make_apparatus(
        "synthetic-b",
        {**_quiet("synthetic-b"), "aperture_rotation_deg": 130.0, "aperture_mirror": True},
        seed=2,
    )
    task = get_task("aperture")
    wobbles = []
    for setting in ([0.0, 0.0], [20.0, 0.0], [0.0, 20.0]):
        apparatus.write({"aperture_x": setting[0], "aperture_y": setting[1]})
        wobbles.append((np.array(setting), apparatus.measure_wobble(5.0)))
    fitted = _affine_wobbles(wobbles)
    turn = apparatus.config.aperture_response()
    gain = float(np.sum(fitted * turn) / np.sum(turn * turn))
    assert gain < 0 and np.max(np.abs(fitted / gain - turn)) < 0.05, (fitted / gain, turn)
    assert task.wobble_amplitude(apparatus.knobs) == 6.0  # 5 % of synthetic-b's 120 V


def test_a_frame_that_fails_is_left_out_of_the_fit() -> None:
    """A directional frame without edges (strong astigmatism far from focus) is no end of
    the alignment: the fit takes the readings that came, and the stigmators still end
    aligned on quiet readings."""
    quiet = _quiet("synthetic-b")
    failing = _session(_FailingThirdFrame(StigmatorSolve()), "synthetic-b", **quiet)
    assert failing.successes >= SCENARIOS - 3, failing


class _FailingThirdFrame:
    """The controller, on an apparatus whose third directional frame has no edges."""

    def __init__(self, controller) -> None:
        self.controller, self.name = controller, "failing-third-frame"

    def check_task(self, task) -> None:
        self.controller.check_task(task)

    def align_task(self, apparatus, task, budget) -> None:
        self.controller.align_task(_ThirdFrameFails(apparatus), task, budget)


class _ThirdFrameFails:
    def __init__(self, inner) -> None:
        self.inner, self.frames = inner, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def measure_directional(self):
        self.frames += 1
        if self.frames == 3:
            raise NoEdgesError("no edges in this frame")
        return self.inner.measure_directional()

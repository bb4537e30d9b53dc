"""Classical autofocus: exact on a noise-free lens, measured floors on the held-out recordings,
clipped to the interval, blind and faulty measurements taken as blurred images."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fake_drivers import ParabolicLens

from alignrl.apparatus import make_apparatus
from alignrl.apparatus.focus_curve import fit_focus_curve
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import (
    BASELINES,
    GoldenSection,
    HillClimb,
    HyperbolaFit,
    get_baseline,
)
from alignrl.evaluation.controllers import Controller
from alignrl.evaluation.session import run_session

FOCUS = get_task("focus")
TEN_NINETY = 2.563
SPEC_PX = 1.15 * TEN_NINETY  # ParabolicLens has no best_quality(): give the spec absolutely


def lens(**options: object) -> ParabolicLens:
    return ParabolicLens(**options)  # type: ignore[arg-type]


# --- the focus-curve fit ------------------------------------------------------------------


def test_fit_recovers_an_exact_hyperbola() -> None:
    a, b, c = 0.04 * TEN_NINETY**2, 43.2, TEN_NINETY**2
    settings = np.array([10.0, 40.0, 45.0, 90.0])
    widths = np.sqrt(a * (settings - b) ** 2 + c)
    curve = fit_focus_curve(settings, widths)
    assert curve is not None
    assert (curve.slope, curve.optimum, curve.floor) == pytest.approx((a, b, c), rel=1e-9)
    assert curve.brackets  # readings on both sides of the optimum took part


def test_fit_refuses_what_has_no_focus() -> None:
    assert fit_focus_curve(np.array([10.0, 50.0]), np.array([5.0, 3.0])) is None
    blind = np.array([5.0, math.inf, 4.0])  # only two measured points
    assert fit_focus_curve(np.array([10.0, 50.0, 90.0]), blind) is None
    peaked = np.array([3.0, 6.0, 3.0])  # sharpest at both ends: no minimum between
    assert fit_focus_curve(np.array([10.0, 50.0, 90.0]), peaked) is None


# --- noise-free lens: every number by hand ----------------------------------------------------


def test_every_baseline_is_a_controller() -> None:
    for name, make in BASELINES.items():
        controller = make()
        assert isinstance(controller, Controller)
        assert controller.name == name


def test_golden_section_takes_nine_acquisitions_and_lands_within_half_its_bracket() -> None:
    result = run_session(GoldenSection(), lens(), FOCUS, scenarios=100, seed=3, spec_px=SPEC_PX)
    assert result.successes == 100
    # 1 + ceil(log(0.03) / log(0.618)) = 9; the final bracket is 3 V wide.
    assert all(record.acquisitions == 9 for record in result.records)
    assert all(abs(record.optimum_error) <= 1.5 for record in result.records)


def test_hyperbola_fit_is_exact_in_five_acquisitions() -> None:
    result = run_session(HyperbolaFit(), lens(), FOCUS, scenarios=100, seed=3, spec_px=SPEC_PX)
    assert result.successes == 100
    # 3 spread probes + 2 around the first vertex; the refit does not move: stop.
    assert all(record.acquisitions == 5 for record in result.records)
    assert all(abs(record.optimum_error) < 1e-6 for record in result.records)
    assert result.final_width_stats()["max"] == pytest.approx(TEN_NINETY)


def test_hill_climb_stops_within_half_a_step_after_distance_over_step_acquisitions() -> None:
    step_v = 4.0  # default 0.04 of the 100 V interval
    result = run_session(HillClimb(), lens(), FOCUS, scenarios=100, seed=3, spec_px=SPEC_PX)
    assert result.successes == 100
    for record in result.records:
        distance = abs(record.start - record.optimum)
        # start, at most two trial steps, the climb, the step that blurs
        assert record.acquisitions <= distance / step_v + 4
        assert abs(record.optimum_error) <= step_v / 2 + 1e-9


class HysteresisLens(ParabolicLens):
    """The field lags the voltage by `lag_v` against the direction of the last change."""

    lag_v = 1.5

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.direction = 0.0

    def write(self, values: dict[str, float]) -> None:
        before = self.voltage
        super().write(values)
        if self.voltage != before:
            self.direction = math.copysign(1.0, self.voltage - before)

    def field_error_v(self) -> float:
        return self.voltage - self.lag_v * self.direction - self.optimum_v

    def measure(self) -> float:
        self.calls += 1
        return TEN_NINETY * math.hypot(self.sigma0, self.gain * self.field_error_v())


def test_hyperbola_fit_defeats_hysteresis_by_approaching_from_below() -> None:
    apparatus = HysteresisLens()
    result = run_session(HyperbolaFit(), apparatus, FOCUS, scenarios=20, seed=4, spec_px=SPEC_PX)
    assert result.successes == 20
    # Every probe ends on an upward move, so the fitted vertex is where the field focuses
    # when approached from below, and the final setting is approached the same way.
    for record in result.records:
        assert record.final_setting - record.optimum == pytest.approx(HysteresisLens.lag_v)
    assert apparatus.field_error_v() == pytest.approx(0.0, abs=1e-6)


class EdgeLens(ParabolicLens):
    """The focus lies at `focus_v`, next to a bound of the interval."""

    focus_v = 99.0

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.optimum_v = self.focus_v


@pytest.mark.parametrize("focus_v", [1.0, 99.0])
@pytest.mark.parametrize("name", sorted(BASELINES))
def test_focus_at_a_bound_is_found_without_leaving_the_interval(name: str, focus_v: float) -> None:
    apparatus = EdgeLens()
    apparatus.focus_v = focus_v
    # ParabolicLens refuses a write outside [0, 100] with ValueError: the session would fail.
    result = run_session(
        get_baseline(name), apparatus, FOCUS, scenarios=10, seed=5, spec_px=SPEC_PX
    )
    assert result.successes == 10
    assert all(0.0 <= write["defocus"] <= 100.0 for write in apparatus.writes)


# --- blind and faulty measurements ----------------------------------------------------------


def test_blind_probes_read_as_blurred_and_never_crash() -> None:
    blind_v = 20.0
    for name in ("golden-section", "hyperbola"):
        apparatus = lens(blind_beyond_v=blind_v)
        result = run_session(get_baseline(name), apparatus, FOCUS, seed=6, spec_px=SPEC_PX)
        assert result.successes == 100, name
    blind_probes = sum(width is None for record in result.records for _, width in record.trajectory)
    assert blind_probes > 0  # the hyperbola's outer probes did go blind
    climb = run_session(HillClimb(), lens(blind_beyond_v=blind_v), FOCUS, seed=6, spec_px=SPEC_PX)
    for record in climb.records:
        # A climb that starts where the image has edges reaches focus; one that starts
        # blind a full step further out sees nothing change and stays (a defined failure).
        distance = abs(record.start - record.optimum)
        if distance <= blind_v:
            assert record.success
        elif distance > blind_v + 4.0:
            assert not record.success and record.final_setting == record.start


def test_driver_faults_cost_an_acquisition_and_do_not_crash() -> None:
    for name in sorted(BASELINES):
        apparatus = lens(fault_every=4)
        calls_before = apparatus.calls
        result = run_session(
            get_baseline(name), apparatus, FOCUS, scenarios=30, seed=7, spec_px=SPEC_PX
        )
        faults = sum(width is None for r in result.records for _, width in r.trajectory)
        assert faults > 0, name
        # Every acquisition, faulty or not, is counted: the controller's plus one verification.
        spent = sum(record.acquisitions for record in result.records) + result.scenarios
        assert apparatus.calls - calls_before == spent, name
        assert all(len(r.trajectory) == r.acquisitions for r in result.records)


# --- held-out recordings: measured floors ---------------------------------------------------

# Measured on csv:default split "test", 200 scenarios, seed 0 (2026-11-26): golden-section
# 200, hyperbola 200, hill-climb 190 (far starts see a saturated, flat edge width).
FLOORS = {"golden-section": 196, "hyperbola": 196, "hill-climb": 180}
MEDIAN_ACQUISITIONS = {"golden-section": 9, "hyperbola": 5, "hill-climb": 9}


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_baselines_reach_their_floor_on_held_out_recordings(name: str) -> None:
    apparatus = make_apparatus("csv:default", {"split": "test"})
    result = run_session(get_baseline(name), apparatus, FOCUS, scenarios=200, seed=0)
    assert result.successes >= FLOORS[name]
    assert result.median_acquisitions <= MEDIAN_ACQUISITIONS[name]
    assert result.budget_exhausted == 0


# --- parameters -------------------------------------------------------------------------------


def test_unknown_baseline_names_the_known_ones() -> None:
    with pytest.raises(ValueError, match="golden-section, hill-climb, hyperbola"):
        get_baseline("parabola")


@pytest.mark.parametrize(
    "make",
    [
        lambda: GoldenSection(tolerance_fraction=0.0),
        lambda: HillClimb(step_fraction=1.5),
        lambda: HyperbolaFit(probe_fractions=(0.2, 0.8)),
        lambda: HyperbolaFit(fit_points=2),
        lambda: HyperbolaFit(refine_fractions=(-1.0,)),
    ],
)
def test_bad_parameters_are_refused(make) -> None:
    with pytest.raises(ValueError):
        make()

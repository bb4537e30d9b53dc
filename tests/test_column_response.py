"""How a synthetic column's stigmators and aperture act in its image: turned against the
image's axes, coupled, mirrored (SEMConfig.stigmator_response, aperture_response; issue 62),
as real columns differ. The presets keep the identity, and with it their numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config
from alignrl.apparatus.synthetic import SyntheticSEM

STIGMATORS = ("stigmator_x", "stigmator_y")


def _column(analytic: bool = True, **response: object) -> SyntheticSEM:
    config = load_sem_config(PRESET_DIR / "synthetic-b.yaml", **response)
    return SyntheticSEM(config, seed=11, analytic=analytic)


def _residual_change(sem: SyntheticSEM, knob: str, step: float) -> np.ndarray:
    """How the astigmatism residual moves when `knob` moves by `step` from the optimum."""
    optimum = sem.optimum()
    sem.write({name: optimum[name] for name in STIGMATORS})
    before = sem.astigmatism_residual_v()
    sem.write({knob: optimum[knob] + step})
    return sem.astigmatism_residual_v() - before


def test_the_presets_keep_the_identity() -> None:
    for preset in ("synthetic", "synthetic-b"):
        config = load_sem_config(PRESET_DIR / f"{preset}.yaml")
        assert config.stigmator_response() is None and config.aperture_response() is None


@pytest.mark.parametrize(
    "response",
    [
        {"stigmator_rotation_deg": 63.0},
        {"stigmator_coupling": 0.4},
        {"stigmator_mirror": True},
        {"stigmator_rotation_deg": 150.0, "stigmator_coupling": -0.3, "stigmator_mirror": True},
    ],
)
def test_the_optimum_cancels_the_astigmatism_whatever_the_response(response) -> None:
    sem = _column(**response)
    optimum = sem.optimum()
    sem.write({knob: optimum[knob] for knob in STIGMATORS})
    assert np.allclose(sem.astigmatism_residual_v(), 0.0, atol=1e-9)
    sigma_u, sigma_v, _ = sem.probe_sigmas_px()
    assert sigma_u == pytest.approx(sigma_v)  # a round probe again
    low, high = sem.knobs["stigmator_x"]
    assert all(low <= optimum[knob] <= high for knob in STIGMATORS)


def test_turned_stigmators_act_along_an_axis_turned_twice_as_far() -> None:
    """An astigmatism along phi is the vector (cos 2 phi, sin 2 phi): stigmators turned by
    30 degrees against the image act 60 degrees round in that plane."""
    plain = _residual_change(_column(), "stigmator_x", 10.0)
    turned = _residual_change(_column(stigmator_rotation_deg=30.0), "stigmator_x", 10.0)
    angle = math.degrees(math.atan2(turned[1], turned[0]) - math.atan2(plain[1], plain[0]))
    assert angle % 360.0 == pytest.approx(60.0)
    assert np.hypot(*turned) == pytest.approx(np.hypot(*plain))


def test_coupled_stigmators_reach_the_other_axis_and_a_mirror_flips_one() -> None:
    plain = _residual_change(_column(), "stigmator_y", 10.0)
    coupled = _residual_change(_column(stigmator_coupling=0.4), "stigmator_y", 10.0)
    assert plain[0] == pytest.approx(0.0) and coupled[0] == pytest.approx(0.4 * plain[1])
    mirrored = _residual_change(_column(stigmator_mirror=True), "stigmator_y", 10.0)
    assert mirrored == pytest.approx(-plain)
    unmoved = _residual_change(_column(stigmator_mirror=True), "stigmator_x", 10.0)
    assert unmoved == pytest.approx(_residual_change(_column(), "stigmator_x", 10.0))


@pytest.mark.parametrize("analytic", [True, False])
def test_the_wobble_turns_and_mirrors_with_the_image(analytic: bool) -> None:
    """The same aperture offset shifts the image by as much, turned by the image's rotation
    against the aperture's axes and mirrored with it; the aperture's optimum is the axis."""

    def shift(knob: str = "aperture_x", **response: object) -> np.ndarray:
        sem = _column(analytic=analytic, **response)
        optimum = sem.optimum()
        sem.write({"defocus": optimum["defocus"] + 8.0, knob: optimum[knob] + 20.0})
        return sem.image_shift_px()

    plain = shift()
    assert plain[0] != 0.0 and plain[1] == pytest.approx(0.0)
    turned = shift(aperture_rotation_deg=120.0)
    angle = math.degrees(math.atan2(turned[1], turned[0]) - math.atan2(plain[1], plain[0]))
    assert angle % 360.0 == pytest.approx(120.0)
    assert np.hypot(*turned) == pytest.approx(np.hypot(*plain))
    along_y = shift("aperture_y")
    assert along_y == pytest.approx([0.0, plain[0]], abs=1e-12)
    assert shift("aperture_y", aperture_mirror=True) == pytest.approx(-along_y, abs=1e-12)
    assert shift(aperture_mirror=True) == pytest.approx(plain, abs=1e-12)
    sem = _column(analytic=analytic, aperture_rotation_deg=120.0)
    optimum = sem.optimum()
    sem.write({"aperture_x": optimum["aperture_x"], "aperture_y": optimum["aperture_y"]})
    assert sem.image_shift_px() == pytest.approx([0.0, 0.0], abs=1e-12)


def test_a_turned_aperture_wobble_reads_the_turned_shift() -> None:
    sem = _column(aperture_rotation_deg=200.0)
    optimum = sem.optimum()
    sem.write({"aperture_x": optimum["aperture_x"] - 30.0, "defocus": optimum["defocus"]})
    measured = sem.measure_wobble(5.0)
    expected = math.radians(200.0)  # the aperture 30 um short of the axis along x: d = +30
    assert math.atan2(measured[1], measured[0]) % (2 * math.pi) == pytest.approx(
        expected % (2 * math.pi), abs=0.15
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"stigmator_rotation_deg": 180.0}, "stigmator_rotation_deg"),
        ({"stigmator_coupling": 0.95}, "stigmator_coupling"),
        ({"aperture_rotation_deg": -1.0}, "aperture_rotation_deg"),
        ({"stigmator_mirror": "sometimes"}, "stigmator_mirror"),
        # coupled stigmators need more excitation than the interval holds
        ({"stigmator_coupling": 0.8, "astigmatism_max_v": 14.0}, r"must contain \+/- 280 %"),
    ],
)
def test_a_response_out_of_its_range_is_refused_by_name(change, message) -> None:
    with pytest.raises(ValueError, match=message):
        load_sem_config(PRESET_DIR / "synthetic-b.yaml", **change)


def test_a_hysteretic_drifting_stigmator_is_aligned_by_its_reported_optimum() -> None:
    """Stigmator hysteresis: the field lags the setting against its last change, so the
    setting that aligns depends on the side it is approached from, and `optimum()` says
    which; drift walks the stigmators' optimum on a stream of its own (the lens's and the
    readings' streams stay as they were)."""
    lagging = _column(stigmator_hysteresis_pct=4.0)
    lagging.write({"stigmator_x": 90.0, "stigmator_y": 90.0})  # approached from below
    target = lagging.optimum()
    lagging.write({k: target[k] for k in ("stigmator_x", "stigmator_y")})
    assert np.linalg.norm(lagging.astigmatism_residual_v()) < 1e-9
    plain = _column()
    plain.write({k: target[k] for k in ("stigmator_x", "stigmator_y")})
    assert np.linalg.norm(plain.astigmatism_residual_v()) > 0.5  # 4 % off without the lag
    drifting = _column(stigmator_drift_pct_per_acquisition=1.0)
    still = _column()
    readings = [(drifting.measure(), still.measure()) for _ in range(5)]
    assert [a for a, _ in readings[:1]] == [b for _, b in readings[:1]]  # the same frame first
    moved = drifting.optimum()["stigmator_x"] - still.optimum()["stigmator_x"]
    assert abs(moved) > 0.1 and drifting.optimum()["defocus"] == still.optimum()["defocus"]

"""Apparatus specs: presets, csv:, sem:, and a user's driver by import path; and the
capabilities (alignrl/apparatus/base.py) each kind of apparatus offers, shielded or not."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from alignrl.apparatus import (
    Apparatus,
    BatchedQueries,
    KnowsBestQuality,
    KnowsOptimum,
    MeasuresDirectional,
    MeasuresWobble,
    ReportsApplied,
    ScenarioSimulator,
    SimulatedApparatus,
    SyntheticSEM,
    answers_batched,
    knows_best_quality,
    knows_optimum,
    make_apparatus,
    offers_directional,
    offers_wobble,
    preset_names,
    reports_applied,
)
from alignrl.apparatus.recorder import sweep, sweep_plan
from alignrl.apparatus.registry import build_apparatus
from alignrl.apparatus.scenarios import ScenarioWriter
from alignrl.apparatus.shield import ShieldOptions
from alignrl.apparatus.training_shield import TrainingShield, shield_apparatus


def test_presets_are_listed_and_built() -> None:
    assert {"synthetic", "synthetic-b"} <= set(preset_names())
    sem = make_apparatus("synthetic-b")
    assert isinstance(sem, SyntheticSEM)
    assert isinstance(sem, SimulatedApparatus)
    assert sem.config.name == "synthetic-b"


def test_preset_arguments_override_instrument_parameters() -> None:
    sem = make_apparatus("synthetic", {"dose_electrons_per_px": 50.0})
    assert sem.config.dose_electrons_per_px == 50.0
    with pytest.raises(ValueError, match="dose_electrons_per_pixel"):
        make_apparatus("synthetic", {"dose_electrons_per_pixel": 50.0})


def test_sem_spec_reads_a_users_instrument_file(tmp_path: Path) -> None:
    config = tmp_path / "lab-sem.yaml"
    config.write_text("name: lab-sem\ndefocus_interval_v: [-40, 40]\noptimum_v: 0\n")
    sem = make_apparatus(f"sem:{config}")
    assert sem.knobs["defocus"] == (-40.0, 40.0)


def _tiny_recording(path: Path) -> None:
    lens = make_apparatus("fake_drivers:ParabolicLens")
    plan = sweep_plan(lens.knobs, step="constant")
    with ScenarioWriter(path, plan.max_pairs) as writer:
        for scenario in range(3):
            record = sweep(lens, plan, scenario, seed=scenario)
            assert record is not None
            writer.write(record)


def test_csv_spec_builds_the_scenario_simulator_with_arguments(tmp_path: Path) -> None:
    path = tmp_path / "three.csv"
    _tiny_recording(path)
    simulator = make_apparatus(f"csv:{path}", {"noise": 0.01})
    assert isinstance(simulator, ScenarioSimulator)
    assert simulator.noise == 0.01
    assert isinstance(simulator, Apparatus)
    with pytest.raises(FileNotFoundError, match=r"missing\.csv"):
        make_apparatus(f"csv:{tmp_path / 'missing.csv'}")


def test_import_path_loads_a_users_driver_with_keyword_arguments() -> None:
    lens = make_apparatus("fake_drivers:ParabolicLens", {"gain_px_per_v": 0.5})
    assert isinstance(lens, TrainingShield)  # a driver is a real instrument: always shielded
    assert lens.driver.gain == 0.5
    lens.write({"defocus": lens.optimum()["defocus"] + 10.0})
    assert lens.measure() == pytest.approx(2.563 * np.hypot(1.0, 5.0))


def test_the_documented_example_driver_loads_and_measures() -> None:
    microscope = make_apparatus("my_microscope:MyMicroscope", {"timeout_s": 2.0})
    assert "defocus" in microscope.knobs
    microscope.reset(1)
    low, high = microscope.knobs["defocus"]
    microscope.write({"defocus": 0.5 * (low + high)})
    assert microscope.measure() > 0
    with pytest.raises(ValueError):  # the driver itself refuses a value off its interval,
        microscope.driver.write({"defocus": high + 1.0})
    microscope.write({"defocus": high + 1.0})  # ... and the shield clamps it into it
    assert microscope.read()["defocus"] == high


@pytest.mark.parametrize(
    ("spec", "args", "fragment"),
    [
        ("fake_drivers:NoSuchClass", {}, "has no 'NoSuchClass'"),
        ("no_such_module_xyz:Driver", {}, "cannot import module 'no_such_module_xyz'"),
        ("fake_drivers:ParabolicLens", {"volts": 3}, "does not accept the arguments"),
        ("fake_drivers:NotAnApparatus", {}, "missing read, write, measure, image"),
        ("fake_drivers:EmptyInterval", {}, "empty or infinite interval"),
        ("not a spec", {}, "unknown apparatus 'not a spec'"),
        ("", {}, "non-empty"),
    ],
)
def test_bad_specs_are_refused_with_a_reason(spec: str, args: dict, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        make_apparatus(spec, args)


def test_a_typo_in_simulator_arguments_is_refused_with_the_accepted_ones(tmp_path: Path) -> None:
    path = tmp_path / "three.csv"
    _tiny_recording(path)
    with pytest.raises(ValueError, match=r"'nois'.*it takes: noise, split"):
        make_apparatus(f"csv:{path}", {"nois": 0.1})
    with pytest.raises(ValueError, match="seed cannot be an apparatus argument"):
        make_apparatus(f"csv:{path}", {"seed": 3})


def test_a_bad_preset_override_is_named_as_an_argument() -> None:
    with pytest.raises(ValueError, match="apparatus argument dose: Extra inputs"):
        make_apparatus("synthetic", {"dose": 3})


@pytest.mark.parametrize(
    ("args", "fragment"),
    [({"scenarios": 3}, "scenarios cannot be an apparatus argument"), ({"noise": "abc"}, "number")],
)
def test_simulator_arguments_are_checked(tmp_path: Path, args: dict, fragment: str) -> None:
    path = tmp_path / "three.csv"
    _tiny_recording(path)
    with pytest.raises(ValueError, match=fragment):
        make_apparatus(f"csv:{path}", args)


# --- capabilities -------------------------------------------------------------------------

CAPABILITIES: dict[str, tuple[type, Callable[[object], bool]]] = {
    "optimum": (KnowsOptimum, knows_optimum),
    "best_quality": (KnowsBestQuality, knows_best_quality),
    "batched": (BatchedQueries, lambda unit: answers_batched([unit])),
    "applied": (ReportsApplied, reports_applied),
    "directional": (MeasuresDirectional, offers_directional),
    "wobble": (MeasuresWobble, offers_wobble),
}
SHIELD_SIMULATORS = ShieldOptions(simulators=True)


@pytest.mark.parametrize(
    ("open_it", "expected"),
    [
        pytest.param(
            lambda: make_apparatus("csv:default"),
            {"optimum", "best_quality", "batched"},
            id="scenario simulator",
        ),
        pytest.param(
            lambda: make_apparatus("synthetic", {"analytic": True}),
            {"optimum", "best_quality", "directional", "wobble"},
            id="synthetic SEM",
        ),
        pytest.param(
            lambda: build_apparatus("fake_drivers:BlindLens"), set(), id="driver, no optimum"
        ),
        pytest.param(
            lambda: build_apparatus("fake_drivers:ParabolicLens"), {"optimum"}, id="driver"
        ),
        # Behind the shield: the secret passes where the apparatus has it, writes report what
        # they applied, the multi-knob measures go through the shield's own methods, and a
        # batched query (around the shield's checks) is never offered.
        pytest.param(
            lambda: make_apparatus("fake_drivers:BlindLens"),
            {"applied", "directional", "wobble"},
            id="shielded driver, no optimum",
        ),
        pytest.param(
            lambda: make_apparatus("fake_drivers:ParabolicLens"),
            {"optimum", "applied", "directional", "wobble"},
            id="shielded driver",
        ),
        pytest.param(
            lambda: make_apparatus("csv:default", shield=SHIELD_SIMULATORS),
            {"optimum", "best_quality", "applied", "directional", "wobble"},
            id="shielded scenario simulator",
        ),
        pytest.param(
            lambda: make_apparatus("synthetic", {"analytic": True}, shield=SHIELD_SIMULATORS),
            {"optimum", "best_quality", "applied", "directional", "wobble"},
            id="shielded synthetic SEM",
        ),
    ],
)
def test_each_capability_is_recognised(open_it: Callable[[], Apparatus], expected: set) -> None:
    unit = open_it()
    by_helper = {name for name, (_, helper) in CAPABILITIES.items() if helper(unit)}
    by_protocol = {
        name for name, (protocol, _) in CAPABILITIES.items() if isinstance(unit, protocol)
    }
    assert by_helper == expected
    assert by_protocol == expected  # the protocols and the helpers agree on every kind
    assert isinstance(unit, SimulatedApparatus) == ({"optimum", "best_quality"} <= expected)


def test_a_capability_set_to_none_is_switched_off() -> None:
    sem = SyntheticSEM()
    sem.best_quality = None  # type: ignore[assignment,method-assign]
    assert knows_optimum(sem) and not knows_best_quality(sem)
    shielded = shield_apparatus(sem)
    assert knows_optimum(shielded) and not knows_best_quality(shielded)
    assert not hasattr(shielded, "best_quality")  # the shield passes on only what there is


def test_the_shield_passes_the_secret_on_through_its_bounded_calls() -> None:
    lens = make_apparatus("fake_drivers:ParabolicLens")
    assert isinstance(lens, TrainingShield)
    lens.reset(4)
    assert lens.optimum() == lens.driver.optimum()
    assert lens.inner.abandoned is None and lens.inner._worker is not None  # on its thread
    replay = make_apparatus("csv:default", {"split": "test"}, shield=SHIELD_SIMULATORS)
    assert replay.indices is replay.driver.indices  # the rows evaluation sessions walk
    assert not hasattr(lens, "indices")

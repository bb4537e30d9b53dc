"""Families for every knob (issue 62): the stigmation, aperture and column boxes, their
instruments, and the wall around the held-out ones."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import yaml

from alignrl.apparatus.column_box import FLAGS, PARAMETERS, ColumnBox
from alignrl.apparatus.column_family import ColumnFamily, column_values
from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.instruments import (
    INSTRUMENT_DIR,
    held_out_reason,
    held_out_sets,
    load_set,
    set_names,
    task_set,
)
from alignrl.apparatus.registry import make_apparatus
from alignrl.apparatus.sem_config import PRESET_DIR, load_sem_config
from alignrl.cli.main import main
from alignrl.envs.task import get_task

KINDS = ("stigmation", "aperture", "column")


def _preset_parameters(name: str) -> dict[str, float]:
    """A preset in the boxes' unit-free terms (column_box.column_config, inverted)."""
    c = load_sem_config(PRESET_DIR / f"{name}.yaml")
    low, high = c.defocus_interval_v
    width, half_s, half_a = high - low, c.stigmator_interval_pct[1], c.aperture_interval_um[1]
    return {
        "defocus_interval_width": width,
        "defocus_interval_centre": 0.5 * (low + high),
        "optimum_fraction": (c.optimum_v - low) / width,
        "optimum_spread_fraction": c.optimum_spread_v / width,
        "blur_px_per_interval": c.gain_px_per_v * width,
        "probe_sigma0_px": c.probe_sigma0_px,
        "hysteresis_fraction": c.hysteresis_v / width,
        "drift_fraction": c.drift_v_per_acquisition / width,
        "stigmator_interval_width": 2 * half_s,
        "astigmatism_max_px": c.gain_px_per_v * c.astigmatism_max_v,
        "astigmatism_floor": 0.0,
        "astigmatism_reach": c.astigmatism_max_v / (c.stigmator_v_per_pct * half_s),
        "stigmator_rotation_deg": 0.0,
        "stigmator_coupling": 0.0,
        "aperture_interval_width": 2 * half_a,
        "aperture_offset_reach": c.aperture_offset_max_um / half_a,
        "aperture_offset_floor": 0.0,
        "wobble_shift_px_per_interval": c.aperture_shift_px_per_v_um * width * half_a,
        "aperture_blur_px": c.aperture_blur_px_per_um * half_a,
        "aperture_rotation_deg": 0.0,
        "dose_electrons_per_px": c.dose_electrons_per_px,
        "detector_noise": c.detector_noise,
        "reading_noise_factor": 1.0,
        "stigmator_hysteresis_fraction": c.stigmator_hysteresis_pct / (2 * half_s),
        "stigmator_drift_fraction": c.stigmator_drift_pct_per_acquisition / (2 * half_s),
    }


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("preset", ["synthetic", "synthetic-b"])
def test_the_presets_sit_inside_every_family(kind: str, preset: str) -> None:
    box = load_family(family_path(kind))
    values = _preset_parameters(preset)
    outside = [
        name
        for name in box.used()
        if not getattr(box, name)[0] - 1e-9 <= values[name] <= getattr(box, name)[1] + 1e-9
    ]
    assert outside == []


@pytest.mark.parametrize("kind", KINDS)
def test_a_family_draws_inside_its_box_and_the_same_seed_draws_the_same_column(kind) -> None:
    family = ColumnFamily(load_family(family_path(kind)), seed=0, analytic=True)
    box, seen = family.family, {flag: set() for flag in FLAGS}
    for seed in range(40):
        family.reset(seed)
        for name in box.used():
            low, high = getattr(box, name)
            assert (
                low - 1e-9 * max(1.0, abs(low)) <= family.values[name] <= high * (1 + 1e-9) + 1e-9
            )
        for flag in FLAGS:
            seen[flag].add(family.mirrors[flag])
        low, high = family.knobs["defocus"]
        width = family.values["defocus_interval_width"]
        assert high - low == pytest.approx(width)
        assert family.knobs["stigmator_x"][1] == pytest.approx(
            0.5 * family.values["stigmator_interval_width"]
        )
    assert seen == {flag: {False, True} for flag in FLAGS}
    first = family.knobs
    family.reset(7)
    again = dict(family.knobs), family.optimum()
    family.reset(8)
    family.reset(7)
    assert (dict(family.knobs), family.optimum()) == again
    assert dict(first) != dict(family.knobs)


def test_a_draw_meets_its_units_the_astigmatism_and_wobble_it_was_drawn_with() -> None:
    family = ColumnFamily(load_family(family_path("column")), seed=3, analytic=True)
    config, values = family.config, family.values
    gain = config.gain_px_per_v
    assert gain * config.astigmatism_max_v == pytest.approx(values["astigmatism_max_px"])
    reach = config.astigmatism_max_v / (
        config.stigmator_v_per_pct * (1 - abs(config.stigmator_coupling))
    )
    assert reach == pytest.approx(values["astigmatism_reach"] * config.stigmator_interval_pct[1])
    half_a = config.aperture_interval_um[1]
    width = values["defocus_interval_width"]
    assert config.aperture_shift_px_per_v_um * width * half_a == pytest.approx(
        values["wobble_shift_px_per_interval"]
    )
    # the optimum lies inside every interval, so the knobs can reach it
    for knob, value in family.optimum().items():
        low, high = family.knobs[knob]
        assert low <= value <= high


def test_the_column_family_is_the_product_of_the_stigmation_and_aperture_families() -> None:
    column = load_family(family_path("column"))
    stigmation = load_family(family_path("stigmation"))
    aperture = load_family(family_path("aperture"))
    for name, parameter in PARAMETERS.items():
        if parameter.group == "stigmators":
            assert getattr(column, name) == getattr(stigmation, name)
        elif parameter.group == "aperture":
            assert getattr(column, name) == getattr(aperture, name)
        else:
            assert getattr(column, name) == getattr(stigmation, name) == getattr(aperture, name)
    assert column.stigmator_mirror == stigmation.stigmator_mirror
    assert column.aperture_mirror == aperture.aperture_mirror


def _write(tmp_path, name: str, data: dict) -> str:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_a_product_whose_factors_disagree_on_the_focus_is_refused(tmp_path) -> None:
    stigmation = yaml.safe_load(family_path("stigmation").read_text())
    stigmation["blur_px_per_interval"] = [20.0, 30.0]
    factor = _write(tmp_path, "stig", stigmation)
    column = _write(tmp_path, "col", {"kind": "column", "product": [factor, "aperture"]})
    with pytest.raises(ValueError, match="disagree on blur_px_per_interval"):
        load_family(column)
    selfish = _write(tmp_path, "selfish", {"kind": "column", "product": [column, "aperture"]})
    with pytest.raises(ValueError, match="stigmation or aperture family"):
        load_family(selfish)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"stigmator_coupling": [-0.95, 0.4]}, "stigmator_coupling .* physical range"),
        ({"stigmator_wobble": 3}, "stigmator_wobble"),
        ({"astigmatism_max_px": [0.0, 5.0]}, "astigmatism_max_px .*log scale"),
        ({"optimum_fraction": [0.1, 0.9]}, "leaves the defocus interval"),
        ({"base": "nowhere"}, "no preset 'nowhere'"),
        ({"stigmator_mirror": "maybe"}, "stigmator_mirror"),
    ],
)
def test_a_bad_box_is_refused_naming_the_key(tmp_path, change, message) -> None:
    data = yaml.safe_load(family_path("stigmation").read_text())
    data.update(change)
    with pytest.raises(ValueError, match=message):
        load_family(_write(tmp_path, "bad", data))


def test_every_instrument_is_a_point_of_its_set_s_kind_and_each_set_has_six() -> None:
    for kind in KINDS:
        for prefix in ("validation", "heldout"):
            name = f"{prefix}-{kind}"
            instruments = load_set(name)
            assert len(instruments) >= 6, name
            for instrument_name, box in instruments:
                assert isinstance(box, ColumnBox) and box.kind == kind, instrument_name
                assert box.name == instrument_name  # the file's stem is its name
                assert box.ranged() == (), instrument_name  # every parameter its task reads
    assert set(held_out_sets()) == {"heldout", *(f"heldout-{kind}" for kind in KINDS)}
    assert task_set("heldout", "column-focus-stigmation") == "heldout-column"
    assert task_set("validation", "focus") == "validation"


def test_the_held_out_instruments_lie_outside_the_training_boxes() -> None:
    """Each held-out instrument has a parameter its task reads beyond its family's box (one
    inside it, or on its edge only, would be trained on)."""
    for kind in KINDS:
        box = load_family(family_path(kind))
        for name, instrument in load_set(f"heldout-{kind}"):
            beyond = [
                parameter
                for parameter in instrument.used()
                if not getattr(box, parameter)[0]
                <= getattr(instrument, parameter)[0]
                <= getattr(box, parameter)[1]
            ]
            assert beyond, f"{name} lies inside the {kind} family"


@pytest.mark.parametrize("kind", KINDS)
def test_the_training_families_reach_no_held_out_instrument(kind) -> None:
    assert held_out_reason(f"family:{kind}") is None


def test_every_way_to_a_held_out_column_instrument_is_refused(tmp_path) -> None:
    assert "held-out set" in held_out_reason("set:heldout-stigmation")
    assert "held-out instrument" in held_out_reason("instrument:col-low-dose")
    copy = tmp_path / "mine.yaml"
    shutil.copy(INSTRUMENT_DIR / "heldout-aperture" / "ap-weak-wobble.yaml", copy)
    data = yaml.safe_load(copy.read_text())
    data["name"], data["aperture_unit"] = "mine", "nm"
    copy.write_text(yaml.safe_dump(data))
    assert "simulates the held-out instrument 'ap-weak-wobble'" in held_out_reason(f"family:{copy}")
    box = yaml.safe_load(family_path("aperture").read_text())
    box["wobble_shift_px_per_interval"] = [10.0, 400.0]  # now it holds ap-weak-wobble
    assert "contains the held-out instrument 'ap-weak-wobble'" in held_out_reason(
        f"family:{_write(tmp_path, 'wider', box)}"
    )


def test_a_designer_places_the_column_and_a_twin_reads_alike() -> None:
    family = ColumnFamily(load_family(family_path("stigmation")), seed=2, analytic=True)
    names = family.design_names()
    assert "dose_electrons_per_px" not in names and "reading_noise_factor" in names
    assert "aperture_rotation_deg" not in names  # the stigmation task keeps the aperture aligned
    draw = family.design_draw()
    assert draw.shape == (len(names),) and np.all((draw >= 0) & (draw <= 1))
    corner = np.zeros(len(names))
    family.design(corner)
    for name in names:
        if name in PARAMETERS:
            assert family.values[name] == pytest.approx(getattr(family.family, name)[0])
    twin = family.twin()
    assert [family.measure() for _ in range(3)] == [twin.measure() for _ in range(3)]
    with pytest.raises(ValueError, match="finite fractions"):
        family.design(np.full(len(names), math.nan))


def test_the_mirror_fraction_picks_from_its_list() -> None:
    box = load_family(family_path("column"))
    fractions = {name: 0.5 for name in (*PARAMETERS, *FLAGS)}
    fractions["stigmator_mirror"], fractions["aperture_mirror"] = 0.2, 0.99
    _, mirrors = column_values(box, fractions)
    assert mirrors == {"stigmator_mirror": False, "aperture_mirror": True}


def test_the_wobble_swings_five_percent_of_the_objective_in_its_own_unit() -> None:
    column = make_apparatus("instrument:vcol-wide", {"analytic": True}, seed=1)
    task = get_task("aperture")
    low, high = column.knobs["defocus"]
    assert task.wobble_amplitude(column.knobs) == pytest.approx(0.05 * (high - low))
    assert task.wobble_amplitude({"defocus": (0.0, 100.0)}) == 5.0  # the synthetic preset's
    import dataclasses

    fixed = dataclasses.replace(task, wobble_amplitude_v=2.0)
    assert fixed.wobble_amplitude(column.knobs) == 2.0


def test_evaluate_a_task_on_its_held_out_set_prints_a_row_per_instrument(capsys) -> None:
    argv = ["evaluate", "--policy", "wobble-center", "--task", "aperture", "--set", "heldout"]
    assert main([*argv, "--analytic", "--scenarios", "2", "--quiet"]) == 0
    out = capsys.readouterr().out
    for name, _ in load_set("heldout-aperture"):
        assert f"| {name}" in out
    assert "**total**" in out and "on set:heldout-aperture" in out
    wrong = ["evaluate", "--policy", "wobble-center", "--task", "aperture"]
    assert main([*wrong, "--set", "heldout-stigmation", "--analytic", "--quiet"]) == 2
    assert "judged on aperture instruments" in capsys.readouterr().err
    assert "heldout-column" in set_names()


def test_docs_physics_shows_the_column_boxes_and_every_instrument_as_they_are() -> None:
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "physics.md").read_text()
    section = page.partition("## Families for every knob")[2].partition("\n## ")[0]
    rows = {}
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = cells
    assert set(rows) == {*PARAMETERS, *FLAGS}, set(rows) ^ {*PARAMETERS, *FLAGS}
    boxes = [load_family(family_path(kind)) for kind in KINDS]
    for name, parameter in PARAMETERS.items():
        shown = [float(part.replace("−", "-")) for part in rows[name][1].split(" – ")]
        for box in boxes:
            if name in box.used():
                assert (shown[0], shown[-1]) == pytest.approx(getattr(box, name)), name
        assert rows[name][2] == ("log" if parameter.log else "uniform"), name
    for flag in FLAGS:
        assert all(set(getattr(box, flag)) == {False, True} for box in boxes)
        assert rows[flag][1] == "false, true"
    for kind in KINDS:
        for prefix in ("heldout", "validation"):
            for name, box in load_set(f"{prefix}-{kind}"):
                assert f"| {prefix}-{kind} | `{name}` | {box.description} |" in page, name


def test_a_designer_duels_inside_the_stigmation_family() -> None:
    """Issue 22's designers design inside these boxes too: the misaligner answers a start
    per stigmator and a fraction per designed parameter, and the env is a PettingZoo AEC."""
    from pettingzoo.test import api_test

    from alignrl.envs.duel import MISALIGNER, env

    duel = env(
        apparatus="family:stigmation",
        apparatus_args={"analytic": True},
        task=get_task("stigmation"),
        design=True,
    )
    api_test(duel, num_cycles=10)
    names = ColumnFamily(load_family(family_path("stigmation")), analytic=True).design_names()
    assert duel.action_space(MISALIGNER).shape == (2 + len(names),)

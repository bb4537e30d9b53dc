"""The focus family's specimens on the synthetic SEM's image path, and in the column boxes
(issue 62: SEMConfig.specimen, ColumnBox.specimens; docs/physics.md, "Families for every
knob")."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus.column_box import (
    FLAGS,
    PARAMETERS,
    SPECIMEN_DRAW,
    ColumnBox,
    column_config,
    column_specimen,
)
from alignrl.apparatus.column_family import ColumnFamily, column_values, draw_column_fractions
from alignrl.apparatus.family_box import family_path, load_family
from alignrl.apparatus.sem_config import PRESET_DIR, SPECIMEN_KINDS, SEMConfig, load_sem_config
from alignrl.apparatus.specimens import SPECIMENS
from alignrl.apparatus.synthetic import SyntheticSEM

SMALL = {"image_size_px": 128, "particles": (4, 8)}  # a quicker frame, the same physics


def _box(kind: str, specimens: list[str]) -> ColumnBox:
    data = load_family(family_path(kind)).model_dump()
    data["specimens"] = specimens
    return ColumnBox.model_validate(data)


def test_the_kinds_are_gold_and_the_focus_familys() -> None:
    assert SPECIMEN_KINDS == ("gold", *SPECIMENS)
    assert SEMConfig().specimen == "gold"
    for name in ("synthetic", "synthetic-b"):
        assert load_sem_config(PRESET_DIR / f"{name}.yaml").specimen == "gold"


@pytest.mark.parametrize("kind", SPECIMEN_KINDS)
def test_every_kind_images_sharp_in_focus(kind: str) -> None:
    """In focus and aligned, every specimen reads near the probe's best edge width, and
    its frame is not the gold one."""
    sem = SyntheticSEM(SEMConfig(specimen=kind, **SMALL), seed=3)
    sem.write({"defocus": sem.optimum()["defocus"]})
    width = sem.measure()
    assert sem.best_quality() <= 1.3 * width and width <= 1.3 * sem.best_quality(), width
    if kind != "gold":
        gold = SyntheticSEM(SEMConfig(**SMALL), seed=3)
        gold.write({"defocus": gold.optimum()["defocus"]})
        gold.measure()
        assert not np.array_equal(sem.image(), gold.image())


def test_an_unknown_kind_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"(?s)specimen.*foam"):
        SEMConfig(specimen="foam")
    with pytest.raises(ValueError, match=r"(?s)specimen.*foam"):
        load_sem_config(PRESET_DIR / "synthetic.yaml", specimen="foam")
    with pytest.raises(ValueError, match=r"(?s)specimen.*foam"):
        _box("stigmation", ["gold", "foam"])
    with pytest.raises(ValueError, match="each kind once"):
        _box("stigmation", ["grid", "grid"])
    box = _box("aperture", ["grid", "texture"])
    values, mirrors = column_values(box, dict.fromkeys((*PARAMETERS, *FLAGS), 0.5))
    with pytest.raises(ValueError, match="'bars' is not one of the box's"):
        column_config(box, values, mirrors, "bars")


def test_gold_leaves_the_presets_frames_as_they_were() -> None:
    """The field at its default changes no bit: frames, readings and the stream after them."""
    for name in ("synthetic", "synthetic-b"):
        path = PRESET_DIR / f"{name}.yaml"
        before = SyntheticSEM(load_sem_config(path), seed=11)
        after = SyntheticSEM(load_sem_config(path, specimen="gold"), seed=11)
        for sem in (before, after):
            sem.write({"defocus": sem.optimum()["defocus"] + 4.0})
        assert before.measure() == after.measure()
        assert np.array_equal(before.image(), after.image())
        assert before.measure_directional()[1].tolist() == after.measure_directional()[1].tolist()


def test_a_kind_keeps_the_scenario_and_the_analytic_stream() -> None:
    """Another kind is drawn where gold is: the scenario (optimum, astigmatism, aperture)
    stays the seed's, and analytic readings ignore the kind bit for bit."""
    gold = SyntheticSEM(SEMConfig(**SMALL), seed=5)
    grid = SyntheticSEM(SEMConfig(specimen="grid", **SMALL), seed=5)
    assert gold.optimum() == grid.optimum()
    gold_a = SyntheticSEM(SEMConfig(**SMALL), seed=5, analytic=True)
    texture_a = SyntheticSEM(SEMConfig(specimen="texture", **SMALL), seed=5, analytic=True)
    assert [gold_a.measure() for _ in range(3)] == [texture_a.measure() for _ in range(3)]


def test_the_specimen_fraction_picks_from_the_boxs_list() -> None:
    box = _box("stigmation", ["gold", "particles", "texture"])
    assert [column_specimen(box, u) for u in (0.0, 0.3, 0.34, 0.99, 1.0, 1.5)] == [
        "gold",
        "gold",
        "particles",
        "texture",
        "texture",
        "texture",
    ]
    seen = set()
    for seed in range(40):
        rng = np.random.default_rng([seed, 1])
        fractions = draw_column_fractions(box, rng)
        values, mirrors = column_values(box, fractions)
        kind = column_specimen(box, fractions.get(SPECIMEN_DRAW, rng.random()))
        config = column_config(box, values, mirrors, kind)
        assert config.specimen == kind
        seen.add(kind)
    assert seen == {"gold", "particles", "texture"}
    values, mirrors = column_values(box, fractions)
    assert column_config(box, values, mirrors).specimen == "gold"  # unnamed: the first


def test_a_column_familys_draw_images_its_specimens_and_only_them() -> None:
    box = _box("aperture", ["grid", "texture"])
    seen = set()
    for seed in range(16):
        family = ColumnFamily(box, seed=seed, analytic=True)
        assert family.config.specimen in box.specimens
        seen.add(family.config.specimen)
    assert seen == {"grid", "texture"}


def test_the_shipped_boxes_name_their_specimens() -> None:
    for kind in ("stigmation", "aperture"):
        box = load_family(family_path(kind))
        assert set(box.specimens) <= set(SPECIMEN_KINDS)
        assert "gold" in box.specimens
        assert not {"fibres", "bars"} & set(box.specimens)  # held out

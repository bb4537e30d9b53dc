"""One copy of each mechanism (issue 20): spec judging (`Task.judge`, whose criteria are both
`within_spec` and align's verdict text), the curriculum from a config, atomic folder writes,
and a check over the source that each mechanism is written in its one home only."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from alignrl.checkpoints import publish_folder, staging_folder
from alignrl.config.run import CurriculumConfig
from alignrl.envs.curriculum import Curriculum
from alignrl.envs.task import TASKS, get_task

PACKAGE = Path(__file__).resolve().parent.parent / "alignrl"


def _within_as_before(task, width, threshold, directional, directional_threshold, wobble):
    """Task.within_spec as it was written before judge (the reference it must equal)."""
    with np.errstate(invalid="ignore"):
        within = np.ones(width.shape, bool)
        if task.judges("width"):
            within &= np.isfinite(width) & (width <= threshold)
        if task.judges("directional"):
            within &= np.all(directional <= directional_threshold[..., None], axis=-1)
        if task.judges("wobble"):
            within &= np.hypot(*np.moveaxis(wobble, -1, 0)) <= task.wobble_spec_px
    return within


@pytest.mark.parametrize("name", sorted(TASKS))
def test_within_spec_is_every_judged_criterion_met(name: str) -> None:
    task = get_task(name)
    rng = np.random.default_rng(len(name))
    n = 400
    width = rng.uniform(2.0, 4.0, n)
    threshold = np.full(n, 2.95)
    directional = rng.uniform(2.0, 4.0, (n, 4))
    directional_threshold = rng.uniform(3.0, 3.6, n)
    wobble = rng.normal(0.0, 0.4, (n, 2))
    for values in (width, directional, wobble):  # failed measures here and there
        values[rng.random(values.shape) < 0.05] = np.nan
    arguments = (width, threshold, directional, directional_threshold, wobble)
    within = task.within_spec(*arguments)
    np.testing.assert_array_equal(within, _within_as_before(task, *arguments))
    criteria = task.judge(*arguments)
    assert [c.measure for c in criteria] == [m for m in task.measures if task.judges(m)]
    np.testing.assert_array_equal(within, np.all([c.met for c in criteria], axis=0))
    assert 0 < within.sum() < n  # both outcomes occur


def test_the_criteria_in_words_as_align_prints_them() -> None:
    column = get_task("column")
    criteria = column.judge(
        np.array([2.85]),
        np.array([2.95]),
        np.array([[3.08, 2.9, 3.0, 2.7]]),
        np.array([3.33]),
        np.array([[0.0155, 0.0]]),
    )
    assert [c.words() for c in criteria] == [
        "final edge width 2.85 px <= spec 2.95 px",
        "widest directional width 3.08 px <= spec 3.33 px",
        "wobble shift 0.0155 px <= spec 0.5 px",
    ]
    failed = column.judge(np.array([3.1]), np.array([2.95]), None, np.array([3.33]), None)
    assert [c.words() for c in failed] == [
        "final edge width 3.1 px > spec 2.95 px",
        "the directional widths could not be measured",
        "the wobble could not be measured",
    ]
    assert not any(c.met[0] for c in failed)
    nan_bin = column.judge(
        np.array([2.8]),
        np.array([2.95]),
        np.array([[np.nan, 3, 3, 3]]),
        np.array([3.33]),
        np.array([[0.0, 0.0]]),
    )
    assert nan_bin[1].words() == "widest directional width nan px > spec 3.33 px"


def test_the_curriculum_of_a_config() -> None:
    assert Curriculum.from_config(CurriculumConfig()) is None  # disabled by default
    curriculum = Curriculum.from_config(
        CurriculumConfig(enabled=True, level=0.3, step=0.1, window=7, raise_at=0.7, lower_at=0.2)
    )
    assert curriculum == Curriculum(
        level=0.3, minimum=0.1, step=0.1, window=7, raise_at=0.7, lower_at=0.2
    )
    low = Curriculum.from_config(CurriculumConfig(enabled=True, level=0.05, step=0.1))
    assert low is not None and low.minimum == 0.05  # never below where it starts


def test_a_published_folder_replaces_the_old_one_whole(tmp_path: Path) -> None:
    out = tmp_path / "exports" / "policy"
    for text in ("first", "second"):
        staging = staging_folder(out)
        (staging / "card.json").write_text(text)
        publish_folder(staging, out)
        assert (out / "card.json").read_text() == text
    assert sorted(path.name for path in out.parent.iterdir()) == ["policy"]  # nothing aside


# Each mechanism and the one module (relative to alignrl/) allowed to write it out.
HOMES = {
    r"bit_generator\.state|[gs]et_rng_state": {"runs/state.py"},
    r"SummaryWriter": {"runs/state.py"},
    r"\bCurriculum\(": {"envs/curriculum.py"},
    r"purge_step": {"runs/state.py"},
    # Atomic and durable writes. The scenario recorder streams its rows to a pending file
    # that it renames at the end, and the audit log fsyncs each line it appends: both are
    # their own kind of file (apparatus/ imports nothing of the run directory).
    r"os\.(fsync|replace)|tempfile\.": {
        "checkpoints.py",
        "apparatus/scenarios.py",
        "apparatus/audit.py",
    },
}


@pytest.mark.parametrize("pattern", sorted(HOMES))
def test_each_mechanism_is_written_in_its_home_only(pattern: str) -> None:
    found = {
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if any(
            re.search(pattern, line) and not line.lstrip().startswith("#")
            for line in path.read_text().splitlines()
        )
    }
    assert found <= HOMES[pattern], f"{pattern} outside its home: {sorted(found - HOMES[pattern])}"

"""docs/configs.md carries, verbatim, the key tables docs/gen_configs.py prints from the models."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest
from pydantic import BaseModel, Field

from alignrl.config.experiment import ExperimentConfig
from alignrl.league.config import Roster

ROOT = Path(__file__).resolve().parents[1]


def _generator() -> ModuleType:
    # docs/ is not a package: load the script by its path.
    spec = importlib.util.spec_from_file_location("gen_configs", ROOT / "docs" / "gen_configs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_doc_holds_the_generated_tables() -> None:
    generated = _generator().markdown()
    if generated not in (ROOT / "docs" / "configs.md").read_text():
        pytest.fail(
            "docs/configs.md differs from the config models: run "
            "`.venv/bin/python docs/gen_configs.py --write` and commit the result"
        )


def test_rows_render_defaults_bounds_and_choices() -> None:
    # Expected rows written out by hand from the Field(...) declarations.
    rows = {row[0]: row[1:] for row in _generator().rows(ExperimentConfig)}
    assert rows["learner.learning_rate"] == ("`0.0003`", "0 < number < 1", "Adam step size")
    assert rows["history"] == ("`8`", "1 ≤ integer ≤ 64", "history rows the aligner sees")
    assert rows["learner.algorithm"][:2] == ("`sac`", "`sac`, `ppo`")
    assert rows["learner.tau"][:2] == ("`null`", "0 < number ≤ 1, or `null`")
    assert rows["learner.hidden"][:2] == (
        "`[256, 256]`",
        "list of integers, each 1 ≤ integer ≤ 8192",
    )
    assert rows["apparatus_args"][0] == "`{noise: 0.02, split: train}`"
    assert rows["name"][2] == "run name (runs/\\<name\\>/)"  # not an HTML tag
    assert rows["budget"][:2] == ("`{}`", "mapping of the `budget.*` keys below")

    roster = {row[0]: row[1:] for row in _generator().rows(Roster)}
    assert roster["members"][:2] == (
        "required",
        "list of 1 or more mappings of the `members[].*` keys below",
    )
    assert roster["members[].learner.epochs"][1] == "1 ≤ integer ≤ 100, or `null`"


def test_an_undocumented_field_is_refused() -> None:
    class Undocumented(BaseModel):
        documented: int = Field(1, description="has its line")
        silent: int = 2

    with pytest.raises(ValueError, match=r"Undocumented\.silent \(silent\) has no description"):
        list(_generator().rows(Undocumented))

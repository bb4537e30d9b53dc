"""The task options declared once (alignrl/envs/option_table.py): Task's validation, the
`task_options:` model (TaskOptions) and the options an export may set (ACTING_OPTIONS) all
come from the one table, so their bounds and meanings cannot disagree."""

from __future__ import annotations

import dataclasses
import re

import pytest
from pydantic import ValidationError

from alignrl.config.task_options import ActingOptions, TaskOptions
from alignrl.envs.endings import ENDING_OPTIONS, ending_from_options
from alignrl.envs.option_table import ACTING_OPTIONS, OPTIONS
from alignrl.envs.task import Task, get_task

# An ending every ending option may be set on
POSTERIOR_ENDING = {"stop_at_best": True, "finish_at_posterior": True, "approach_from_below": True}
BOUNDED = [
    (name, option) for name, option in OPTIONS.items() if option.low is not None or option.high
]


def _outside(option) -> list[float]:
    """Values just outside each of the option's bounds."""
    step = 1 if option.kind is int else 0.5
    values = []
    if option.low is not None:
        values.append(option.low if option.above else option.low - step)
    if option.high is not None:
        values.append(option.high if option.below else option.high + step)
    return [option.kind(value) for value in values]


def test_the_model_and_the_export_list_are_the_table() -> None:
    assert list(TaskOptions.model_fields) == list(OPTIONS)
    assert list(ActingOptions.model_fields) == list(ACTING_OPTIONS)
    assert set(ACTING_OPTIONS) <= set(OPTIONS)
    task_fields = {field.name for field in dataclasses.fields(Task)}
    for name, option in OPTIONS.items():
        field = TaskOptions.model_fields[name]
        assert field.description == option.meaning
        assert (option.part == "task") == (name in task_fields), name
        assert (option.part in ("ending", "posterior")) == (name in ENDING_OPTIONS), name


@pytest.mark.parametrize(("name", "option"), BOUNDED, ids=[name for name, _ in BOUNDED])
def test_task_and_file_refuse_the_same_values_naming_the_bound(name, option) -> None:
    values = _outside(option)
    assert values
    for value in values:
        with pytest.raises(ValidationError, match=name):
            TaskOptions(**{name: value})
        if option.part == "success":
            continue
        with pytest.raises(
            ValueError, match=re.escape(f"{name} must be {option.bounds}")
        ) as refused:
            if option.part == "task":
                Task(name="t", knobs=("defocus",), **{name: value})
            else:  # the ending's own record refuses it, wherever it comes from
                ending_from_options({**POSTERIOR_ENDING, name: value})
        assert option.bounds in str(refused.value) and option.meaning in str(refused.value)


def test_the_bounds_read_as_words() -> None:
    assert OPTIONS["backlash_overshoot"].bounds == "in [0, 0.5]"
    assert OPTIONS["stop_when_sure"].bounds == "in [0, 1)"
    assert OPTIONS["final_move_reach"].bounds == "in (0, 1]"
    assert OPTIONS["fit_window"].bounds == "above 1"
    assert OPTIONS["acquisition_cost"].bounds == "at least 0"
    assert OPTIONS["posterior_probe_rule"].bounds == "one of variance, chance, entropy"


def test_every_built_in_task_is_within_the_table() -> None:
    focus = get_task("focus")
    for name, option in OPTIONS.items():
        if option.part == "task":
            assert option.problem(name, getattr(focus, name)) is None, name

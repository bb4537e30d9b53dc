"""The `task_options:` and `acting_options:` sections of a run: changes to a named task
(alignrl.envs.task), `TaskOptions`, and those a trained policy may act with beyond its
training's, `ActingOptions`."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from pydantic import Field, create_model

from alignrl.config_reading import Count, _Strict
from alignrl.envs.endings import ENDING_OPTIONS, ending_from_options
from alignrl.envs.option_table import ACTING_OPTIONS, OPTIONS, Option

__all__ = ["ActingOptions", "TaskOptions"]


def _annotation(name: str, option: Option) -> Any:
    """The type a file's value of option `name` takes (None: unset)."""
    if option.choices:
        return Literal[option.choices] | None  # type: ignore[valid-type]
    kinds: dict[type, Any] = {bool: bool, int: Count, float: float}
    special: dict[str, Any] = {
        "posterior_saturation_px": tuple[float, float],  # (low, high) px
        "posterior_column": dict[str, float],  # a mapping in a file, a tuple in the task
    }
    return (special[name] if option.kind is tuple else kinds[option.kind]) | None


# Every field from the one table of task options (alignrl/envs/option_table.py): its type,
# bounds and description; unset (None) keeps the task's own value.
_FIELDS: dict[str, Any] = {
    name: (
        _annotation(name, option),
        Field(None, description=option.meaning, **option.pydantic_bounds()),
    )
    for name, option in OPTIONS.items()
}


class _TaskOptions(_Strict):
    """TaskOptions' method; its fields are _FIELDS."""

    def apply(self, task: Any) -> Any:
        """The task with these changes (a new object; the registry's task is untouched)."""
        from alignrl.posterior.calibration import column_values

        success_keys = ("success_relative", "success_absolute_px")
        changes = {
            name: value
            for name, value in self.model_dump().items()
            if value is not None and name not in success_keys
        }
        measured_by = {
            "directional_relative": "directional",
            "wobble_amplitude_v": "wobble",
            "wobble_spec_px": "wobble",
            "wobble_weight": "wobble",
        }
        for name, measure in measured_by.items():
            if changes.get(name) is not None and measure not in task.measures:
                raise ValueError(
                    f"task_options.{name}: task {task.name!r} takes no {measure} "
                    f"measure (it measures {', '.join(task.measures)})"
                )
        if self.posterior_column is not None:  # a mapping in a file, a tuple in the task
            changes["posterior_column"] = column_values(self.posterior_column)
        ending = {name: changes.pop(name) for name in ENDING_OPTIONS if name in changes}
        if ending:  # the flat names, parsed into the task's one Ending record
            changes["ending"] = ending_from_options(ending, task.ending)
        success = task.success
        if self.success_relative is not None:
            success = dataclasses.replace(success, relative=self.success_relative)
        if self.success_absolute_px is not None:
            success = dataclasses.replace(success, absolute_px=self.success_absolute_px)
        return dataclasses.replace(task, success=success, **changes)


TaskOptions = create_model(  # type: ignore[call-overload]
    "TaskOptions",
    __base__=_TaskOptions,
    __doc__="Changes to a named task; unset fields keep the task's own values.",
    **_FIELDS,
)

# What a trained policy may act with beyond its training's options (never what it observes).
_ACTING = {
    name: (TaskOptions.model_fields[name].annotation, TaskOptions.model_fields[name])
    for name in ACTING_OPTIONS
}
ActingOptions = create_model("ActingOptions", __base__=_Strict, **_ACTING)  # type: ignore[call-overload]

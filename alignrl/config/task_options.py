"""The `task_options:` and `acting_options:` sections of a run: changes to a named task
(alignrl.envs.task), `TaskOptions`, and those a trained policy may act with beyond its
training's, `ActingOptions`."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from pydantic import Field, create_model

from alignrl.config_reading import MAX_EPISODE_STEPS, Count, _Strict
from alignrl.envs.task import ACTING_OPTIONS, POSTERIOR_PROBE_RULES

__all__ = ["ActingOptions", "TaskOptions"]

ProbeRule = Literal[POSTERIOR_PROBE_RULES]  # type: ignore[valid-type]


class TaskOptions(_Strict):
    """Changes to a named task; unset fields keep the task's own values."""

    episode_steps: Count | None = Field(
        None, ge=1, le=MAX_EPISODE_STEPS, description="acquisitions after the first"
    )
    max_step_fraction: float | None = Field(None, gt=0, le=2, description="action scale")
    acquisition_cost: float | None = Field(None, ge=0, description="reward cost per image")
    out_of_bounds_penalty: float | None = Field(None, ge=0, description="bound penalty")
    final_reward_scale: float | None = Field(None, gt=0, description="final reward factor")
    final_reward_form: Literal["difference", "log_ratio"] | None = Field(
        None, description="final reward on widths in px (difference) or on their logs"
    )
    success_bonus: float | None = Field(None, ge=0, description="optional shaping at success")
    bonus_relative: float | None = Field(None, gt=1, description="bonus within x best width")
    verify_final: bool | None = Field(None, description="judge the end on one more image")
    quality_reference: Literal["fixed", "first"] | None = Field(
        None, description="quality relative to quality_ref_px (fixed) or the first width"
    )
    fit_features: bool | None = Field(None, description="3 features of a local focus-curve fit")
    fit_window: float | None = Field(None, gt=1, description="fit within x narrowest reading")
    action_power: float | None = Field(None, ge=1, le=4, description="step: sign(a)|a|^power")
    stop_at_best: bool | None = Field(None, description="end at the narrowest reading's setting")
    backlash_overshoot: float | None = Field(None, ge=0, le=0.5, description="way back: past by")
    finish_at_fit: bool | None = Field(None, description="way back to / last move from a fit")
    finish_at_posterior: bool | None = Field(None, description="as finish_at_fit: posterior")
    stop_when_sure: float | None = Field(None, ge=0, lt=1, description="posterior stops at")
    probe_until_sure: float | None = Field(None, ge=0, lt=1, description="stop taken from")
    posterior_draws: Count | None = Field(None, ge=16, le=4096, description="posterior's columns")
    posterior_far_noise: float | None = Field(None, ge=0, le=1, description="posterior's far_noise")
    posterior_walk_after: Count | None = Field(
        None, ge=0, le=100, description="posterior walks from"
    )
    posterior_walk_unmeasured: bool | None = Field(None, description="and while none measured")
    posterior_no_edges: bool | None = Field(None, description="posterior reads no-edge frames")
    posterior_from_below: bool | None = Field(None, description="posterior: readings from below")
    posterior_on_sides: bool | None = Field(None, description="posterior: readings on their sides")
    posterior_probe_rule: ProbeRule | None = Field(None, description="where its walk probes")
    posterior_saturation_px: tuple[float, float] | None = Field(None, description="level off, px")
    posterior_column: dict[str, float] | None = Field(None, description="calibrated column")
    finish_window: float | None = Field(None, gt=1, description="finish fit: within x narrowest")
    approach_from_below: bool | None = Field(None, description="every reading reached from below")
    move_floor: float | None = Field(None, ge=0, le=0.2, description="least move, of the interval")
    final_move: bool | None = Field(None, description="the stopping action's move ends it")
    final_move_reach: float | None = Field(None, gt=0, le=1, description="x max_step, last move")
    success_relative: float | None = Field(None, gt=1, description="threshold x best width")
    success_absolute_px: float | None = Field(None, gt=0, description="absolute spec, px")
    directional_relative: float | None = Field(None, gt=1, description="directional spec x best")
    wobble_amplitude_v: float | None = Field(None, gt=0, description="wobble swing each way, V")
    wobble_spec_px: float | None = Field(None, gt=0, description="spec of the wobble shift, px")
    wobble_weight: float | None = Field(None, ge=0, description="cost px per px of wobble shift")

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
        success = task.success
        if self.success_relative is not None:
            success = dataclasses.replace(success, relative=self.success_relative)
        if self.success_absolute_px is not None:
            success = dataclasses.replace(success, absolute_px=self.success_absolute_px)
        return dataclasses.replace(task, success=success, **changes)


# What a trained policy may act with beyond its training's options (never what it observes).
_ACTING = {
    name: (TaskOptions.model_fields[name].annotation, TaskOptions.model_fields[name])
    for name in ACTING_OPTIONS
}
ActingOptions = create_model("ActingOptions", __base__=_Strict, **_ACTING)  # type: ignore[call-overload]

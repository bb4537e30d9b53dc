"""What every run names (`RunConfig`): where it lives, its seed, the apparatus it trains and
is judged on, the task, the history, the torch settings, its curriculum and how it was
started; a training experiment (alignrl.config.experiment) and a league
(alignrl.league.config) add their keys."""

from __future__ import annotations

from typing import Any

from pydantic import Field, ValidationInfo, field_validator, model_validator

from alignrl.config.task_options import ActingOptions, TaskOptions
from alignrl.config_reading import SEED_LIMIT, Count, Episodes, _Strict, check_file_name
from alignrl.devices import DEVICE, check_device_available

__all__ = ["CurriculumConfig", "Provenance", "RunConfig"]


class CurriculumConfig(_Strict):
    enabled: bool = Field(False, description="raise the complexity as the aligner succeeds")
    level: float = Field(0.1, gt=0, le=1, description="starting complexity level")
    step: float = Field(0.1, gt=0, le=1, description="change of the level per promotion")
    window: Episodes = Field(200, ge=1, description="episodes judged per decision")
    raise_at: float = Field(0.8, ge=0, le=1, description="success rate that raises the level")
    lower_at: float = Field(0.3, ge=0, le=1, description="success rate that lowers it")


class Provenance(_Strict):
    """How a run was started, as the command that started it wrote it (not a setting: a
    resumed run keeps it, a file that gives it is recorded as given)."""

    command: str = Field("", description="the command line that started the run")
    overrides: list[str] = Field(
        default_factory=list, description="its --set key.path=value assignments, in order"
    )
    git_commit: str | None = Field(
        None,
        description="the commit of the alignrl checkout that ran it, +dirty with changes not "
        "committed; null where alignrl is not a git checkout",
    )


class RunConfig(_Strict):
    """What every run names: where it lives, its seed, the apparatus it trains and is judged
    on, the task, the history, the torch settings; experiments and leagues add their keys."""

    name: str = Field("experiment", min_length=1, description="run name (runs/<name>/)")
    seed: Count = Field(0, ge=0, lt=SEED_LIMIT, description="seeds networks, envs, sampling")
    provenance: Provenance | None = Field(
        None,
        description="how the run was started: command line, --set overrides, git commit "
        "(written by alignrl train, league run and adapt)",
    )
    apparatus: str = Field("csv:default", description="apparatus spec trained on")
    apparatus_args: dict[str, Any] = Field(
        default_factory=lambda: {"noise": 0.02, "split": "train"},
        description="arguments of the training apparatus",
    )
    eval_apparatus: str = Field("csv:default", description="apparatus spec of evaluations")
    eval_apparatus_args: dict[str, Any] = Field(
        default_factory=lambda: {"noise": 0.02, "split": "test"},
        description="arguments of the evaluation apparatus (held-out scenarios)",
    )
    task: str = Field("focus", description="task name (alignrl.envs.TASKS)")
    task_options: TaskOptions = Field(
        default_factory=lambda: TaskOptions(), description="changes to the named task"
    )
    acting_options: ActingOptions | None = Field(
        None,
        description="how the trained policy acts once loaded (export, evaluate, align, adapt),"
        " laid over task_options; training and its validation sessions act without them",
    )
    history: Count = Field(8, ge=1, le=64, description="history rows the aligner sees")
    envs: Count = Field(8, ge=1, le=1024, description="apparatus instances stepped together")
    complexity: float = Field(
        1.0, gt=0, le=1, description="misalignment window (share of interval), no curriculum"
    )
    device: str = Field("cpu", description="torch device: cpu, cuda, cuda:1, ...")
    threads: Count = Field(
        1, ge=1, le=256, description="torch CPU threads (small networks: 1 is fastest)"
    )

    curriculum: CurriculumConfig = Field(
        default_factory=CurriculumConfig, description="complexity that follows the successes"
    )

    def resolved_task(self) -> Any:
        """The Task object this run aligns."""
        from alignrl.envs.task import get_task

        return self.task_options.apply(get_task(self.task))

    @field_validator("name")
    @classmethod
    def _name_is_a_folder(cls, name: str) -> str:
        return check_file_name(name, "a run name")

    @field_validator("device")
    @classmethod
    def _a_torch_device(cls, device: str, info: ValidationInfo) -> str:
        if not DEVICE.fullmatch(device):
            shown = device if len(device) <= 40 else f"{device[:40]}..."
            raise ValueError(f"{shown!r} is not a torch device: use cpu, cuda, cuda:N or mps")
        if (info.context or {}).get("check_device"):
            check_device_available(device)
        return device

    @model_validator(mode="after")
    def _check(self) -> RunConfig:
        if self.curriculum.lower_at >= self.curriculum.raise_at:
            raise ValueError("curriculum.lower_at must be below curriculum.raise_at")
        for config in (self, self.acting()) if self.acting_options else (self,):
            config.resolved_task()  # an unknown task, or options it (as trained) cannot take
        if getattr(self, "adaptation", None) is None:  # adapting on a user's column is no choice
            self._refuse_held_out()
        return self

    def acting(self) -> Any:
        """This config as its trained policy acts: `acting_options` over `task_options`."""
        if self.acting_options is None:
            return self
        changes = self.acting_options.model_dump(exclude_none=True)
        options = TaskOptions(**{**self.task_options.model_dump(exclude_none=True), **changes})
        return self.model_copy(update={"task_options": options, "acting_options": None})

    def misaligner_shape(self) -> tuple[tuple[int, int], int]:
        """(input shape, action size) of this run's misaligners: one row [1, aligned settings
        (k), complexity] answered with a start per knob (a league whose misaligners design
        the instrument says otherwise: LeagueConfig)."""
        from alignrl.envs.duel import misaligner_input_shape

        knobs = len(self.resolved_task().knobs)
        return misaligner_input_shape(knobs), knobs

    def apparatus_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(key, spec, arguments) of every apparatus this run trains or chooses on."""
        return [
            ("apparatus", self.apparatus, self.apparatus_args),
            ("eval_apparatus", self.eval_apparatus, self.eval_apparatus_args),
        ]

    def _refuse_held_out(self) -> None:
        """The held-out instruments judge generalization: no run trains or chooses on them
        (alignrl/apparatus/instruments.py)."""
        from alignrl.apparatus.instruments import held_out_reason

        for key, spec, arguments in self.apparatus_specs():
            reason = held_out_reason(spec, arguments)
            if reason is not None:
                raise ValueError(
                    f"{key}: {reason}; held-out instruments are never trained or chosen on "
                    "(choose on set:validation; judge with alignrl evaluate --set heldout)"
                )

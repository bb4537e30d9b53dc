"""Typed experiment configs, loaded strictly from YAML (experiments/*.yaml).

Every field has a one-line doc and a default; an unknown key, a wrong type or an impossible
value is an error naming the file, the key path and what was expected. Configs are frozen:
code derives new values into new objects, never edits a loaded config."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    Field,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)

from alignrl.agents.learners import LEARNERS, learner_defaults, learner_title
from alignrl.apparatus.shield import DEFAULT_CALL_TIMEOUT_S
from alignrl.config_reading import (  # noqa: F401 (re-exported: config files are read here)
    MAX_EPISODE_STEPS,
    SEED_LIMIT,
    ConfigError,
    Count,
    EnvSteps,
    Episodes,
    Scenarios,
    _Strict,
    check_file_name,
    overridden,
    parse_config,
    read_layered,
    read_yaml,
)
from alignrl.devices import DEVICE, check_device_available
from alignrl.envs.hindsight import HINDSIGHT_OPTIMA, HindsightOptimum  # noqa: F401 (re-exported)
from alignrl.envs.task import ACTING_OPTIONS, POSTERIOR_PROBE_RULES

__all__ = [
    "AdaptationConfig",
    "BudgetConfig",
    "ConfigError",
    "CurriculumConfig",
    "ExperimentConfig",
    "LearnerConfig",
    "Provenance",
    "RunConfig",
    "TaskOptions",
    "check_file_name",
    "load_experiment",
    "overridden",
]


MAX_HIDDEN_WIDTH = 8192  # units of one hidden layer: a 8192 x 8192 layer is 256 MB already
MAX_HIDDEN_LAYERS = 16
MAX_BUFFER_SIZE = 10_000_000  # replay transitions: a few GB at a history of 8
MAX_UPDATES_PER_STEP = 16  # (SAC) gradient updates per env step
HiddenWidth = Annotated[Count, Field(ge=1, le=MAX_HIDDEN_WIDTH)]


# The learners' names, settings and defaults come from their registry
# (alignrl/agents/learners.py): a key set for a learner that has no such setting is an error,
# and a key left out takes the default of the learner's own config dataclass.


def _shared_default(name: str) -> Any:
    """The default of a key that several learners have, read from their configs: they must
    agree on it (one key of the file, one default)."""
    found = {learner: learner_defaults(learner)[name] for learner in LEARNERS
             if name in learner_defaults(learner)}  # fmt: skip
    if not found or len(set(map(repr, found.values()))) > 1:
        raise TypeError(f"learner key {name}: the learners' defaults disagree or miss: {found}")
    return next(iter(found.values()))


def _plain(value: Any) -> str:
    """A default as a description quotes it: 1.0 as 1, False as false."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def _own_setting(name: str, meaning: str, **bounds: Any) -> Any:
    """A key of some learners alone: null (the default) takes the learner's own default,
    which the description quotes ("(SAC) target follow rate, 0.005")."""
    owners = [learner for learner in LEARNERS if name in learner_defaults(learner)]
    default = _shared_default(name)
    tags = "/".join(learner_title(owner) for owner in owners)
    return Field(None, description=f"({tags}) {meaning}, {_plain(default)}", **bounds)


# The learners alignrl ships; one registered later (a plugin, a test) is accepted by name too.
LearnerName = Literal[tuple(LEARNERS)]  # type: ignore[valid-type]
ProbeRule = Literal[POSTERIOR_PROBE_RULES]  # type: ignore[valid-type]


class LearnerConfig(_Strict):
    """One member's learner. Fields marked (SAC) or (PPO) belong to that algorithm alone;
    left unset (null) they take the learner's default (docs/learners.md)."""

    algorithm: LearnerName = Field("sac", description="the learning algorithm")
    encoder: Literal["mlp", "gru", "gtrxl"] = Field(
        _shared_default("encoder"), description="history encoder"
    )
    encoder_kwargs: dict[str, Any] = Field(
        default_factory=dict, description="encoder settings, e.g. {d_model: 32} for gtrxl"
    )
    hidden: tuple[HiddenWidth, ...] = Field(
        _shared_default("hidden"),
        max_length=MAX_HIDDEN_LAYERS,
        description="hidden widths of the heads (critics join action and secret here)",
    )
    learning_rate: float = Field(
        _shared_default("learning_rate"), gt=0, lt=1, description="Adam step size"
    )
    gamma: float = Field(_shared_default("gamma"), gt=0, le=1, description="discount per step")
    batch_size: Count = Field(
        _shared_default("batch_size"), ge=1, le=MAX_BUFFER_SIZE,
        description="transitions per gradient step (PPO: minibatch)",
    )  # fmt: skip
    secret_critics: bool = Field(
        _shared_default("secret_critics"), description="critics see optimum - setting"
    )
    tau: float | None = _own_setting("tau", "target follow rate", gt=0, le=1)
    initial_alpha: float | None = _own_setting("initial_alpha", "initial entropy coef", gt=0)
    updates_per_step: float | None = _own_setting(
        "updates_per_step", "gradient updates per env step", gt=0, le=MAX_UPDATES_PER_STEP
    )
    buffer_size: Count | None = _own_setting(
        "buffer_size", "replay capacity", ge=1000, le=MAX_BUFFER_SIZE
    )
    learning_starts: EnvSteps | None = _own_setting("learning_starts", "steps before updates", ge=0)
    random_steps: EnvSteps | None = _own_setting("random_steps", "uniform random steps", ge=0)
    shared_critic_encoder: bool | None = _own_setting(
        "shared_critic_encoder", "Q1, Q2 and V read one history encoder"
    )
    gae_lambda: float | None = _own_setting("gae_lambda", "GAE lambda", ge=0, le=1)
    clip_range: float | None = _own_setting("clip_range", "ratio clip", gt=0, lt=1)
    entropy_coef: float | None = _own_setting("entropy_coef", "entropy bonus", ge=0)
    value_coef: float | None = _own_setting("value_coef", "value loss weight", gt=0)
    epochs: Count | None = _own_setting("epochs", "passes per rollout", ge=1, le=100)
    rollout_steps: Count | None = _own_setting(
        "rollout_steps", "steps per env slot", ge=1, le=MAX_BUFFER_SIZE
    )
    initial_log_std: float | None = _own_setting("initial_log_std", "initial log-std", ge=-5, le=1)

    @field_validator("algorithm", mode="wrap")
    @classmethod
    def _a_registered_learner(cls, value: Any, handler: Any) -> Any:
        if isinstance(value, str) and value in LEARNERS:
            return value  # also a learner registered after this model was built
        return handler(value)  # pydantic's own message, naming the choices

    @field_validator("hidden")
    @classmethod
    def _some_layer(cls, hidden: tuple[int, ...]) -> tuple[int, ...]:
        if not hidden:
            raise ValueError("give at least one hidden width, e.g. [256, 256]")
        return hidden

    @model_validator(mode="after")
    def _fields_of_the_algorithm(self) -> LearnerConfig:
        own = learner_defaults(self.algorithm)
        fields = {
            name: info for name, info in type(self).model_fields.items() if name != "algorithm"
        }
        # A key the learner does not have must keep its default (null for a learner's own key).
        wrong = [
            name
            for name, info in fields.items()
            if name not in own
            and getattr(self, name) != info.get_default(call_default_factory=True)
        ]
        if wrong:
            raise ValueError(
                f"{', '.join(wrong)} {'does' if len(wrong) == 1 else 'do'} not apply to "
                f"algorithm {self.algorithm}"
            )
        # A learner registered after this model was built must still agree with its defaults.
        disagree = [
            f"{name}={own[name]!r}"
            for name, info in fields.items()
            if name in own and info.default is not None
            and repr(own[name]) != repr(info.get_default(call_default_factory=True))
        ]  # fmt: skip
        if disagree:
            raise ValueError(
                f"learner {self.algorithm} defaults {', '.join(disagree)}, which this config "
                "defaults otherwise; a key has one default: change the learner's config"
            )
        if "buffer_size" in own:  # a learner with a replay: a batch must fit in it
            capacity = self.buffer_size or own["buffer_size"]
            if self.batch_size > capacity:
                raise ValueError(
                    f"batch_size {self.batch_size} exceeds the replay capacity (buffer_size "
                    f"{capacity}): no batch could ever be drawn"
                )
        return self

    def hyperparameters(self) -> dict[str, Any]:
        """The settings a member of this algorithm takes (alignrl.agents.MemberSpec); those
        left null take the learner's own default there."""
        own = learner_defaults(self.algorithm)
        values = {name: getattr(self, name) for name in type(self).model_fields if name in own}
        if "hidden" in values:
            values["hidden"] = list(values["hidden"])
        if "encoder_kwargs" in values:
            values["encoder_kwargs"] = dict(values["encoder_kwargs"])
        return {name: value for name, value in values.items() if value is not None}


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
        changes = {name: value for name, value in self.model_dump().items()
                   if value is not None and name not in success_keys}  # fmt: skip
        measured_by = {"directional_relative": "directional", "wobble_amplitude_v": "wobble",
                       "wobble_spec_px": "wobble", "wobble_weight": "wobble"}  # fmt: skip
        for name, measure in measured_by.items():
            if changes.get(name) is not None and measure not in task.measures:
                raise ValueError(f"task_options.{name}: task {task.name!r} takes no {measure} "
                                 f"measure (it measures {', '.join(task.measures)})")  # fmt: skip
        if self.posterior_column is not None:  # a mapping in a file, a tuple in the task
            changes["posterior_column"] = column_values(self.posterior_column)
        success = task.success
        if self.success_relative is not None:
            success = dataclasses.replace(success, relative=self.success_relative)
        if self.success_absolute_px is not None:
            success = dataclasses.replace(success, absolute_px=self.success_absolute_px)
        return dataclasses.replace(task, success=success, **changes)


# What a trained policy may act with beyond its training's options (never what it observes).
_ACTING = {name: (TaskOptions.model_fields[name].annotation, TaskOptions.model_fields[name])
           for name in ACTING_OPTIONS}  # fmt: skip
ActingOptions = create_model("ActingOptions", __base__=_Strict, **_ACTING)  # type: ignore[call-overload]


class CurriculumConfig(_Strict):
    enabled: bool = Field(False, description="raise the complexity as the aligner succeeds")
    level: float = Field(0.1, gt=0, le=1, description="starting complexity level")
    step: float = Field(0.1, gt=0, le=1, description="change of the level per promotion")
    window: Episodes = Field(200, ge=1, description="episodes judged per decision")
    raise_at: float = Field(0.8, ge=0, le=1, description="success rate that raises the level")
    lower_at: float = Field(0.3, ge=0, le=1, description="success rate that lowers it")


class BudgetConfig(_Strict):
    env_steps: EnvSteps = Field(
        30_000, ge=1, description="environment steps (acquisitions) to train"
    )
    eval_every: EnvSteps = Field(5000, ge=1, description="env steps between validation sessions")
    eval_scenarios: Scenarios = Field(100, ge=1, description="alignments per validation session")
    test_scenarios: Scenarios | None = Field(
        None, ge=0, description="alignments of the test session of best.pt at the end (another "
        "seed, never used for a choice); null: eval_scenarios; 0: none"
    )  # fmt: skip
    checkpoint_every: EnvSteps = Field(5000, ge=1, description="env steps between checkpoints")


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
        return [("apparatus", self.apparatus, self.apparatus_args),
                ("eval_apparatus", self.eval_apparatus, self.eval_apparatus_args)]  # fmt: skip

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


class AdaptationConfig(_Strict):
    """Where an adaptation run (`alignrl adapt`) came from, and the safety shield every one of
    its writes passes on the new apparatus (alignrl/apparatus/shield.py)."""

    source: str = Field(description="the pre-trained aligner's checkpoint file it started from")
    source_member: str = Field(description="the pre-trained member's id")
    source_steps: EnvSteps = Field(ge=0, description="env steps the aligner had seen before")
    limits: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="site limits per knob, instrument units (low, high)"
    )
    max_step: dict[str, float] = Field(
        default_factory=dict, description="largest change per write per knob, instrument units"
    )
    call_timeout_s: float = Field(
        DEFAULT_CALL_TIMEOUT_S,
        gt=0,
        allow_inf_nan=False,
        description="longest one driver call may take before it is abandoned and the run stops",
    )
    hindsight_secrets: bool = Field(
        True,
        description=(
            "on an apparatus that cannot tell its optimum (a real column), give the critics "
            "the secret in hindsight, found from each episode's readings (SAC); false: the "
            "critics see zeros there"
        ),
    )
    hindsight_optimum: HindsightOptimum = Field(
        "posterior",
        description=(
            "what stands in for an episode's optimum in hindsight: a draw from its posterior "
            "given its readings and the column's focus curve pooled over earlier episodes "
            "(one knob; else sharpest), or the setting of its sharpest reading"
        ),
    )
    critic_warmup_steps: EnvSteps = Field(
        0,
        ge=0,
        description=(
            "env steps at the start in which only the critics learn and the policy acts as "
            "the source did: on an apparatus that cannot tell the critics its secret "
            "(a real column) they first learn to judge from the history alone"
        ),
    )


class ExperimentConfig(RunConfig):
    learner: LearnerConfig = Field(
        default_factory=LearnerConfig, description="the learner: algorithm, encoder, settings"
    )
    budget: BudgetConfig = Field(
        default_factory=BudgetConfig, description="how long to train; when to evaluate and save"
    )
    adaptation: AdaptationConfig | None = Field(
        None, description="set by `alignrl adapt`: the pre-trained source and the shield"
    )


def parse_experiment(data: Any, source: str = "config") -> ExperimentConfig:
    return parse_config(ExperimentConfig, data, source)


def load_experiment(path: str | Path, overrides: Sequence[str] = ()) -> ExperimentConfig:
    """Read an experiment YAML strictly (unknown keys are errors), its `base:` chain merged
    in and the command line's `overrides` applied, to run it on this machine (its device
    must be one this machine has)."""
    layers = read_layered(Path(path), "experiment config")
    data, source = overridden(layers.data, layers.source, overrides)
    return parse_config(ExperimentConfig, data, source, check_device=True)


def dump_experiment(config: ExperimentConfig) -> str:
    """The resolved config as YAML (every field, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)

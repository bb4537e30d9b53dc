"""Typed experiment configs, loaded strictly from YAML (experiments/*.yaml).

Every field has a one-line doc and a default; an unknown key, a wrong type or an impossible
value is an error naming the file, the key path and what was expected. Configs are frozen:
code derives new values into new objects, never edits a loaded config.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, TypeVar, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

__all__ = [
    "AdaptationConfig",
    "BudgetConfig",
    "ConfigError",
    "CurriculumConfig",
    "ExperimentConfig",
    "LearnerConfig",
    "RunConfig",
    "TaskOptions",
    "load_experiment",
]


ModelT = TypeVar("ModelT", bound=BaseModel)


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the file and the key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


SAC_ONLY = ("tau", "initial_alpha", "updates_per_step", "buffer_size", "learning_starts",
            "random_steps", "shared_critic_encoder")  # fmt: skip
PPO_ONLY = ("gae_lambda", "clip_range", "entropy_coef", "value_coef", "epochs", "rollout_steps",
            "initial_log_std")  # fmt: skip


class LearnerConfig(_Strict):
    """One member's learner. Fields marked (SAC) or (PPO) belong to that algorithm alone;
    left unset (null) they take the learner's default (docs/learners.md)."""

    algorithm: Literal["sac", "ppo"] = Field("sac", description="the learning algorithm")
    encoder: Literal["mlp", "gru", "gtrxl"] = Field("mlp", description="history encoder")
    encoder_kwargs: dict[str, Any] = Field(
        default_factory=dict, description="encoder settings, e.g. {d_model: 32} for gtrxl"
    )
    hidden: tuple[int, ...] = Field(
        (256, 256), description="hidden widths of the heads (critics join action and secret here)"
    )
    learning_rate: float = Field(3e-4, gt=0, lt=1, description="Adam step size")
    gamma: float = Field(0.99, gt=0, le=1, description="discount per step")
    batch_size: int = Field(256, ge=1, description="transitions per gradient step (PPO: minibatch)")
    secret_critics: bool = Field(True, description="critics see optimum - setting")
    tau: float | None = Field(None, gt=0, le=1, description="(SAC) target follow rate, 0.005")
    initial_alpha: float | None = Field(None, gt=0, description="(SAC) initial entropy coef, 0.2")
    updates_per_step: float | None = Field(
        None, gt=0, le=16, description="(SAC) gradient updates per env step, 1"
    )
    buffer_size: int | None = Field(None, ge=1000, description="(SAC) replay capacity, 200000")
    learning_starts: int | None = Field(None, ge=0, description="(SAC) steps before updates, 1000")
    random_steps: int | None = Field(None, ge=0, description="(SAC) uniform random steps, 2000")
    shared_critic_encoder: bool | None = Field(
        None, description="(SAC) Q1, Q2 and V read one history encoder, false"
    )
    gae_lambda: float | None = Field(None, ge=0, le=1, description="(PPO) GAE lambda, 0.95")
    clip_range: float | None = Field(None, gt=0, lt=1, description="(PPO) ratio clip, 0.2")
    entropy_coef: float | None = Field(None, ge=0, description="(PPO) entropy bonus, 0")
    value_coef: float | None = Field(None, gt=0, description="(PPO) value loss weight, 0.5")
    epochs: int | None = Field(None, ge=1, le=100, description="(PPO) passes per rollout, 10")
    rollout_steps: int | None = Field(None, ge=1, description="(PPO) steps per env slot, 64")
    initial_log_std: float | None = Field(
        None, ge=-5, le=1, description="(PPO) initial policy log-std, -0.5"
    )

    @model_validator(mode="after")
    def _fields_of_the_algorithm(self) -> LearnerConfig:
        foreign = PPO_ONLY if self.algorithm == "sac" else SAC_ONLY
        wrong = [name for name in foreign if getattr(self, name) is not None]
        if wrong:
            raise ValueError(
                f"{', '.join(wrong)} {'does' if len(wrong) == 1 else 'do'} not apply to "
                f"algorithm {self.algorithm}"
            )
        return self

    def hyperparameters(self) -> dict[str, Any]:
        """The settings a member of this algorithm takes (alignrl.agents.MemberSpec)."""
        own = SAC_ONLY if self.algorithm == "sac" else PPO_ONLY
        shared = ("encoder", "encoder_kwargs", "hidden", "learning_rate", "gamma", "batch_size",
                  "secret_critics")  # fmt: skip
        values = {name: getattr(self, name) for name in (*shared, *own)}
        values["hidden"] = list(values["hidden"])
        values["encoder_kwargs"] = dict(values["encoder_kwargs"])
        return {name: value for name, value in values.items() if value is not None}


class TaskOptions(_Strict):
    """Changes to a named task; unset fields keep the task's own values."""

    episode_steps: int | None = Field(None, ge=1, description="acquisitions after the first")
    max_step_fraction: float | None = Field(None, gt=0, le=2, description="action scale")
    acquisition_cost: float | None = Field(None, ge=0, description="reward cost per image")
    out_of_bounds_penalty: float | None = Field(None, ge=0, description="bound penalty")
    final_reward_scale: float | None = Field(None, gt=0, description="final reward factor")
    success_bonus: float | None = Field(None, ge=0, description="optional shaping at success")
    bonus_relative: float | None = Field(
        None, gt=1, description="bonus only within this x best width (the spec unchanged)"
    )
    verify_final: bool | None = Field(
        None, description="judge final reward and bonus on one more image (as evaluation does)"
    )
    success_relative: float | None = Field(None, gt=1, description="threshold x best width")
    success_absolute_px: float | None = Field(None, gt=0, description="absolute spec, px")
    directional_relative: float | None = Field(
        None, gt=1, description="spec of every directional width, x best width"
    )
    wobble_amplitude_v: float | None = Field(None, gt=0, description="wobble swing each way, V")
    wobble_spec_px: float | None = Field(None, gt=0, description="spec of the wobble shift, px")
    wobble_weight: float | None = Field(
        None, ge=0, description="cost px per px of wobble shift (rewards)"
    )

    def apply(self, task: Any) -> Any:
        """The task with these changes (a new object; the registry's task is untouched)."""
        import dataclasses

        changes = {
            name: value
            for name, value in self.model_dump().items()
            if value is not None and name not in ("success_relative", "success_absolute_px")
        }
        for name, measure in (
            ("directional_relative", "directional"),
            ("wobble_amplitude_v", "wobble"),
            ("wobble_spec_px", "wobble"),
            ("wobble_weight", "wobble"),
        ):
            if changes.get(name) is not None and measure not in task.measures:
                raise ValueError(
                    f"task_options.{name}: task {task.name!r} takes no {measure} measure "
                    f"(it measures {', '.join(task.measures)})"
                )
        success = task.success
        if self.success_relative is not None:
            success = dataclasses.replace(success, relative=self.success_relative)
        if self.success_absolute_px is not None:
            success = dataclasses.replace(success, absolute_px=self.success_absolute_px)
        return dataclasses.replace(task, success=success, **changes)


class CurriculumConfig(_Strict):
    enabled: bool = Field(False, description="raise the complexity as the aligner succeeds")
    level: float = Field(0.1, gt=0, le=1, description="starting complexity level")
    step: float = Field(0.1, gt=0, le=1, description="change of the level per promotion")
    window: int = Field(200, ge=1, description="episodes judged per decision")
    raise_at: float = Field(0.8, ge=0, le=1, description="success rate that raises the level")
    lower_at: float = Field(0.3, ge=0, le=1, description="success rate that lowers it")


class BudgetConfig(_Strict):
    env_steps: int = Field(30_000, ge=1, description="environment steps (acquisitions) to train")
    eval_every: int = Field(5000, ge=1, description="env steps between evaluation sessions")
    eval_scenarios: int = Field(100, ge=1, description="alignments per evaluation session")
    checkpoint_every: int = Field(5000, ge=1, description="env steps between checkpoints")


class RunConfig(_Strict):
    """What every run names: where it lives, its seed, the apparatus it trains and is judged
    on, the task, the history, and the torch settings. Training experiments and leagues add
    their own keys."""

    name: str = Field("experiment", min_length=1, description="run name (runs/<name>/)")
    seed: int = Field(0, ge=0, description="seeds everything: networks, envs, sampling")
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
    history: int = Field(8, ge=1, le=64, description="history rows the aligner sees")
    envs: int = Field(8, ge=1, le=1024, description="apparatus instances stepped together")
    complexity: float = Field(
        1.0, gt=0, le=1, description="misalignment window (share of interval), no curriculum"
    )
    device: str = Field("cpu", description="torch device: cpu, cuda, cuda:1, ...")
    threads: int = Field(
        1, ge=1, le=256, description="torch CPU threads (small networks: 1 is fastest)"
    )

    curriculum: CurriculumConfig = Field(
        default_factory=CurriculumConfig, description="complexity that follows the successes"
    )

    def resolved_task(self) -> Any:
        """The Task object this run aligns."""
        from alignrl.envs.task import get_task

        return self.task_options.apply(get_task(self.task))

    @model_validator(mode="after")
    def _check(self) -> RunConfig:
        if not self.name.replace("-", "").replace("_", "").replace(".", "").isalnum():
            raise ValueError(f"name {self.name!r}: use letters, digits, '-', '_' and '.'")
        if self.curriculum.lower_at >= self.curriculum.raise_at:
            raise ValueError("curriculum.lower_at must be below curriculum.raise_at")
        self.resolved_task()  # an unknown task, or options it cannot take
        return self


# What stands in for an episode's optimum in hindsight (alignrl.adaptation.HindsightSecrets).
HindsightOptimum = Literal["posterior", "sharpest"]
HINDSIGHT_OPTIMA: tuple[str, ...] = get_args(HindsightOptimum)


class AdaptationConfig(_Strict):
    """Where an adaptation run (`alignrl adapt`) came from, and the safety shield every one of
    its writes passes on the new apparatus (alignrl/deploy/shield.py)."""

    source: str = Field(description="the pre-trained aligner's checkpoint file it started from")
    source_member: str = Field(description="the pre-trained member's id")
    source_steps: int = Field(ge=0, description="env steps the aligner had seen before")
    limits: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="site limits per knob, instrument units (low, high)"
    )
    max_step: dict[str, float] = Field(
        default_factory=dict, description="largest change per write per knob, instrument units"
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
    critic_warmup_steps: int = Field(
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


def _describe(error: ValidationError) -> str:
    lines = []
    for item in error.errors():
        key = ".".join(str(part) for part in item["loc"]) or "(top level)"
        found = item.get("input")
        shown = "" if isinstance(found, dict) else f" (found {found!r})"
        lines.append(f"{key}: {item['msg']}{shown}")
    return "; ".join(lines)


def parse_config(model: type[ModelT], data: Any, source: str) -> ModelT:
    """`data` (a YAML mapping) as a `model`; any problem is a ConfigError naming `source`,
    the key path and what was expected."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of settings at the top level")
    try:
        return model(**data)
    except ValidationError as error:
        raise ConfigError(f"{source}: {_describe(error)}") from None


def read_yaml(path: Path, what: str) -> Any:
    """A YAML file read with yaml.safe_load (an empty file is an empty mapping)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    return {} if data is None else data


def parse_experiment(data: Any, source: str = "config") -> ExperimentConfig:
    return parse_config(ExperimentConfig, data, source)


def load_experiment(path: str | Path) -> ExperimentConfig:
    """Read an experiment YAML strictly (yaml.safe_load; unknown keys are errors)."""
    path = Path(path)
    return parse_experiment(read_yaml(path, "experiment config"), str(path))


def dump_experiment(config: ExperimentConfig) -> str:
    """The resolved config as YAML (every field, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)

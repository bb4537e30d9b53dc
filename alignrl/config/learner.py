"""The `learner:` section of an experiment and of a roster's member: `LearnerConfig`.

The learners' names, settings and defaults come from their registry
(alignrl/agents/learners.py): a key set for a learner that has no such setting is an error,
and a key left out takes the default of the learner's own config dataclass. Configs are
frozen: code derives new values into new objects, never edits a loaded config.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from alignrl.agents.learners import LEARNERS, learner_defaults, learner_title
from alignrl.config_reading import Count, EnvSteps, _Strict

__all__ = [
    "MAX_BUFFER_SIZE",
    "MAX_HIDDEN_LAYERS",
    "MAX_HIDDEN_WIDTH",
    "MAX_UPDATES_PER_STEP",
    "LearnerConfig",
    "LearnerName",
]


MAX_HIDDEN_WIDTH = 8192  # units of one hidden layer: a 8192 x 8192 layer is 256 MB already
MAX_HIDDEN_LAYERS = 16
MAX_BUFFER_SIZE = 10_000_000  # replay transitions: a few GB at a history of 8
MAX_UPDATES_PER_STEP = 16  # (SAC) gradient updates per env step
HiddenWidth = Annotated[Count, Field(ge=1, le=MAX_HIDDEN_WIDTH)]


def _shared_default(name: str) -> Any:
    """The default of a key that several learners have, read from their configs: they must
    agree on it (one key of the file, one default)."""
    found = {
        learner: learner_defaults(learner)[name]
        for learner in LEARNERS
        if name in learner_defaults(learner)
    }
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
        _shared_default("batch_size"),
        ge=1,
        le=MAX_BUFFER_SIZE,
        description="transitions per gradient step (PPO: minibatch)",
    )
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
            if name in own
            and info.default is not None
            and repr(own[name]) != repr(info.get_default(call_default_factory=True))
        ]
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

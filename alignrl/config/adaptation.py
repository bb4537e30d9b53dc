"""The `adaptation:` section of a run that `alignrl adapt` started: where the pre-trained
aligner came from, the safety shield every write passes on the new apparatus, and the
critics' secret in hindsight."""

from __future__ import annotations

from pydantic import Field

from alignrl.apparatus.shield import DEFAULT_CALL_TIMEOUT_S
from alignrl.config_reading import EnvSteps, _Strict
from alignrl.envs.hindsight import HindsightOptimum

__all__ = ["AdaptationConfig"]


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

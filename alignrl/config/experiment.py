"""A training experiment (experiments/*.yaml, `alignrl train`): a run, its learner, its
budget and, for an adaptation, where it came from; loaded strictly from YAML.

Every field has a one-line doc and a default; an unknown key, a wrong type or an impossible
value is an error naming the file, the key path and what was expected. Configs are frozen:
code derives new values into new objects, never edits a loaded config."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import Field

from alignrl.config.adaptation import AdaptationConfig
from alignrl.config.learner import LearnerConfig
from alignrl.config.run import RunConfig
from alignrl.config_reading import (
    EnvSteps,
    Scenarios,
    _Strict,
    overridden,
    parse_config,
    read_layered,
)

__all__ = [
    "BudgetConfig",
    "ExperimentConfig",
    "dump_experiment",
    "load_experiment",
    "parse_experiment",
]


class BudgetConfig(_Strict):
    env_steps: EnvSteps = Field(
        30_000, ge=1, description="environment steps (acquisitions) to train"
    )
    eval_every: EnvSteps = Field(5000, ge=1, description="env steps between validation sessions")
    eval_scenarios: Scenarios = Field(100, ge=1, description="alignments per validation session")
    test_scenarios: Scenarios | None = Field(
        None,
        ge=0,
        description="alignments of the test session of best.pt at the end (another "
        "seed, never used for a choice); null: eval_scenarios; 0: none",
    )
    checkpoint_every: EnvSteps = Field(5000, ge=1, description="env steps between checkpoints")


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

"""How alignrl reads a config file: strictly, within bounds, and saying what is wrong where.

The experiment, league and roster models (alignrl/config/, alignrl/league/config.py) are
built from what this module gives them:

* `read_yaml` reads a file through alignrl.yaml_io (no duplicate keys, no alias bombs, a
  bounded size) and refuses text that is not YAML text (a NUL byte: a binary file?) naming
  the file, the line and the column; `read_layered` merges a chain of `base:` files;
  `overridden` lays the command line's `--set key.path=value` over the data;
* `parse_config` validates the data against a model: any problem is one ConfigError naming
  the file, the key path and what was expected, the value echoed in short;
* a count (`Count`) is a whole number (`true`, `8.0` or `"8"` are typos), and every count of
  a config has an upper bound, one named constant per kind (env steps, alignments, episodes,
  acquisitions of an alignment): far beyond any run a machine finishes, so that a count
  above one is a typo (`1e26`, a few zeros too many), refused naming the key, the value and
  the bound, never a run that would outlive its machine.

This module imports no other part of alignrl than the bottom ones (yaml_io, overlays), so
that every layer may read a config file with it.
"""

from __future__ import annotations

import numbers
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, TypeVar

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from alignrl.overlays import Layers, OverlayError, apply_overrides
from alignrl.overlays import resolve as resolve_overlays
from alignrl.yaml_io import YAMLInputError, read_yaml_file

__all__ = [
    "MAX_ENV_STEPS",
    "MAX_EPISODES",
    "MAX_EPISODE_STEPS",
    "MAX_SCENARIOS",
    "SEED_LIMIT",
    "ConfigError",
    "Count",
    "EnvSteps",
    "Episodes",
    "Scenarios",
    "check_file_name",
    "overridden",
    "parse_config",
    "read_layered",
    "read_yaml",
]

ModelT = TypeVar("ModelT", bound=BaseModel)


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the file and the key."""


class _Strict(BaseModel):
    # allow_inf_nan: `.inf` or `.nan` in a YAML is a typo, never a setting.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _whole_number(value: Any) -> Any:
    """A count is written as an integer: `true` is not 1, and `8.0`, `1e26` or `"8"` are
    typos (a float is refused, never truncated)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError("expected a whole number such as 8")
    return int(value)


Count = Annotated[int, BeforeValidator(_whole_number)]

SEED_LIMIT = 2**63  # seeds are stored as int64 (numpy, scenario files)
# The upper bounds of counts, one per kind. Training takes 10 to 600 env steps a second
# here (docs/benchmarks.md), a microscope one or two: 10^10 steps are 190 days at the
# fastest and centuries on a column. The shipped experiments and benchmarks ask for
# 2 x 10^5 steps at most and 100 alignments a session.
MAX_ENV_STEPS = 10**10  # env steps (acquisitions): budgets, intervals between, warm-ups
MAX_SCENARIOS = 10**6  # alignments of one evaluation session: days of the slowest policy
MAX_EPISODES = 10**6  # episodes judged at once (a curriculum's window)
MAX_EPISODE_STEPS = 1000  # acquisitions of one alignment (the column task: 20; a policy
# card refuses more too: alignrl/deploy/card_schema.py)
EnvSteps = Annotated[Count, Field(le=MAX_ENV_STEPS)]
Scenarios = Annotated[Count, Field(le=MAX_SCENARIOS)]
Episodes = Annotated[Count, Field(le=MAX_EPISODES)]

# A run name or member id becomes one folder or file name (runs/<name>/, members/<id>.pt).
FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def check_file_name(value: str, what: str) -> str:
    """`value` if it is one safe path component, else a ValueError saying what is allowed."""
    if not FILE_NAME.fullmatch(value):
        raise ValueError(
            f"{what} must be one folder name: 1 to 100 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit (no '/', no '..')"
        )
    return value


SHOWN_VALUE = 100  # characters of a rejected value echoed in a message
SHOWN_ERRORS = 10  # problems listed in one message


def _shown(value: Any, limit: int = SHOWN_VALUE) -> str:
    text = value if isinstance(value, str) else repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text) - limit} more)"


def _describe(error: ValidationError) -> str:
    """The problems of a validation, one per key path, each value echoed in short."""
    lines = []
    problems = error.errors()
    for item in problems[:SHOWN_ERRORS]:
        key = _shown(".".join(str(part) for part in item["loc"]) or "(top level)", 200)
        found = item.get("input")
        shown = "" if isinstance(found, dict) else f" (found {_shown(repr(found))})"
        message = item["msg"].removeprefix("Value error, ")
        lines.append(f"{key}: {_shown(message, 400)}{shown}")
    if len(problems) > SHOWN_ERRORS:
        lines.append(f"and {len(problems) - SHOWN_ERRORS} more problems")
    return "; ".join(lines)


def parse_config(model: type[ModelT], data: Any, source: str, check_device: bool = False) -> ModelT:
    """`data` (a YAML mapping) as a `model`; any problem is a ConfigError naming `source`,
    the key path and what was expected. `check_device`: also refuse a torch device this
    machine lacks (for a config about to run here)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of settings at the top level")
    try:
        return model.model_validate(data, context={"check_device": check_device})
    except ValidationError as error:
        raise ConfigError(f"{source}: {_describe(error)}") from None


def read_yaml(path: Path, what: str) -> Any:
    """A YAML file read strictly and within bounds (alignrl.yaml_io: no duplicate keys, no
    alias bombs); an empty file is an error, never a file of defaults."""
    try:
        data = read_yaml_file(path)
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {path} is a folder, not a YAML file") from None
    except YAMLInputError as error:
        raise ConfigError(str(error)) from None
    if data is None:
        raise ConfigError(f"{path}: empty {what}: write its settings (experiments/*.yaml)")
    return data


def read_layered(path: Path, what: str) -> Layers:
    """An experiment YAML with its chain of `base:` files merged in (alignrl/overlays.py),
    each file read as `read_yaml` reads it. A file without `base:` is read as it is; messages
    about an overlay name it and its bases (`Layers.source`)."""
    try:
        return resolve_overlays(path, lambda file: read_yaml(file, what))
    except OverlayError as error:
        raise ConfigError(str(error)) from None


def overridden(data: Any, source: str, overrides: Sequence[str]) -> tuple[Any, str]:
    """A config's data with the command line's `--set key.path=value` assignments applied
    (alignrl.overlays.apply_overrides), and its source as messages name it."""
    if not overrides:
        return data, source
    if not isinstance(data, dict):
        return data, source  # parse_config says what is wrong with it
    try:
        data = apply_overrides(data, list(overrides))
    except OverlayError as error:
        raise ConfigError(f"{source}: {error}") from None
    return data, f"{source} with --set {' '.join(overrides)}"

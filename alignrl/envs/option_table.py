"""The task options, declared once: each option's kind, bounds and meaning (`OPTIONS`).

Three things derive from this one table, so that they cannot disagree:

* `Task.__post_init__` (alignrl/envs/task.py) refuses a task whose option lies outside its
  bounds (`Option.problem`, the option and its bound named);
* the `task_options:` section of a run (alignrl/config/task_options.py, `TaskOptions`) is a
  pydantic model whose fields, their `ge`/`gt`/`le`/`lt` and descriptions, are built from
  it (`Option.pydantic_bounds`), and docs/configs.md is generated from that model;
* the options an export may set (`ACTING_OPTIONS`: how a trained policy's moves reach the
  column and how its episode ends, never what it observes) are those marked `acting`.

The options that only the task validates across each other (finish_at_posterior needs
approach_from_below, posterior_walk_after at most episode_steps, ...) stay in
`Task.__post_init__`; the two whose values are not numbers in bounds
(`posterior_saturation_px`, `posterior_column`) are checked there too, their meaning here.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

from alignrl.config_reading import MAX_EPISODE_STEPS

__all__ = [
    "ACTING_OPTIONS",
    "MAX_ACTION_POWER",
    "MAX_FAR_NOISE",
    "MAX_MOVE_FLOOR",
    "MAX_POSTERIOR_DRAWS",
    "MAX_WALK_AFTER",
    "MIN_POSTERIOR_DRAWS",
    "OPTIONS",
    "POSTERIOR_PROBE_RULES",
    "QUALITY_REFERENCES",
    "REWARD_FORMS",
    "Option",
]

QUALITY_REFERENCES = ("fixed", "first")  # what quality observations are relative to
REWARD_FORMS = ("difference", "log_ratio")  # how the final reward counts widths (rewards.py)
MAX_ACTION_POWER = 4.0  # above it the smallest useful changes need actions within a hair of 0
MAX_MOVE_FLOOR = 0.2  # a share of the interval: beyond it no column could be brought to focus
# The posterior of finish_at_posterior: the columns it draws (FamilyPosterior.draws)
MIN_POSTERIOR_DRAWS, MAX_POSTERIOR_DRAWS = 16, 4096
MAX_FAR_NOISE = 1.0  # its posterior_far_noise: beyond it a reading far from focus says nothing
MAX_WALK_AFTER = 100  # its posterior_walk_after, in a file (the task: at most episode_steps)
# Where its walk probes: FamilyPosterior's PROBE_RULES (alignrl/posterior/inference.py,
# left unimported here for its scipy; tests/test_finish_at_posterior.py holds them equal)
POSTERIOR_PROBE_RULES = ("variance", "chance", "entropy")


@dataclass(frozen=True)
class Option:
    """One task option: what kind of value it takes, within which bounds, and what it means.

    `kind`: bool, int, float, str (one of `choices`) or tuple (checked by its record).
    `low`/`high`: the bounds (None: none), excluded where `above`/`below`. `acting`: an
    export may set it (ACTING_OPTIONS). `part`: whose field it is: "task" (Task's own),
    "ending" (Task.ending's, alignrl/envs/endings.py), "posterior" (its PosteriorSettings')
    or "success" (Task.success's)."""

    kind: type
    meaning: str
    low: float | None = None
    high: float | None = None
    above: bool = False
    below: bool = False
    choices: tuple[str, ...] = ()
    acting: bool = False
    part: str = "task"

    @property
    def bounds(self) -> str:
        """The bounds in words: 'in [0, 0.5]', 'above 1', 'at least 0', 'one of a, b'."""
        if self.choices:
            return f"one of {', '.join(self.choices)}"
        low, high = _number(self.low), _number(self.high)
        if self.low is not None and self.high is not None:
            return f"in {'(' if self.above else '['}{low}, {high}{')' if self.below else ']'}"
        if self.low is not None:
            return f"above {low}" if self.above else f"at least {low}"
        if self.high is not None:
            return f"below {high}" if self.below else f"at most {high}"
        return "any value"

    def problem(self, name: str, value: Any) -> str | None:
        """What is wrong with `value` for option `name`, naming the option and its bound;
        None where it is within (a bool, a tuple and None are not checked here)."""
        if value is None or self.kind in (bool, tuple):
            return None
        if self.choices:
            good = value in self.choices
        else:
            good = isinstance(value, numbers.Real) and not math.isnan(value)
            if good and self.low is not None:
                good = value > self.low if self.above else value >= self.low
            if good and self.high is not None:
                good = value < self.high if self.below else value <= self.high
        if good:
            return None
        return f"{name} must be {self.bounds} ({self.meaning}), got {value!r}"

    def pydantic_bounds(self) -> dict[str, float]:
        """The bounds as pydantic Field arguments (ge/gt, le/lt)."""
        bounds: dict[str, float] = {}
        if self.low is not None and not self.choices:
            bounds["gt" if self.above else "ge"] = _plain(self.low)
        if self.high is not None and not self.choices:
            bounds["lt" if self.below else "le"] = _plain(self.high)
        return bounds


def _plain(value: float) -> float:
    """A whole bound as an int (docs/configs.md shows 4, not 4.0)."""
    return int(value) if float(value).is_integer() else value


def _number(value: float | None) -> str:
    return f"{value:g}" if value is not None else ""


# Every option a run's `task_options:` may set, in the order docs/configs.md lists them.
OPTIONS: dict[str, Option] = {
    "episode_steps": Option(int, "acquisitions after the first", 1, MAX_EPISODE_STEPS),
    "max_step_fraction": Option(float, "action scale", 0, 2, above=True),
    "acquisition_cost": Option(float, "reward cost per image", 0),
    "out_of_bounds_penalty": Option(float, "bound penalty", 0),
    "final_reward_scale": Option(float, "final reward factor", 0, above=True),
    "final_reward_form": Option(
        str,
        "final reward on widths in px (difference) or on their logs",
        choices=REWARD_FORMS,
    ),
    "success_bonus": Option(float, "optional shaping at success", 0),
    "bonus_relative": Option(float, "bonus within x best width", 1, above=True),
    "verify_final": Option(bool, "judge the end on one more image"),
    "quality_reference": Option(
        str,
        "quality relative to quality_ref_px (fixed) or the first width",
        choices=QUALITY_REFERENCES,
    ),
    "fit_features": Option(bool, "3 features of a local focus-curve fit"),
    "fit_window": Option(float, "fit within x narrowest reading", 1, above=True),
    "action_power": Option(float, "step: sign(a)|a|^power", 1, MAX_ACTION_POWER),
    "move_floor": Option(float, "least move, of the interval", 0, MAX_MOVE_FLOOR, acting=True),
    "stop_at_best": Option(
        bool, "end at the narrowest reading's setting", acting=True, part="ending"
    ),
    "backlash_overshoot": Option(float, "way back: past by", 0, 0.5, acting=True, part="ending"),
    "finish_at_fit": Option(bool, "way back to / last move from a fit", acting=True, part="ending"),
    "finish_at_posterior": Option(bool, "as finish_at_fit: posterior", acting=True, part="ending"),
    "stop_when_sure": Option(
        float, "posterior stops at", 0, 1, below=True, acting=True, part="posterior"
    ),
    "probe_until_sure": Option(
        float, "stop taken from", 0, 1, below=True, acting=True, part="posterior"
    ),
    "posterior_draws": Option(
        int,
        "posterior's columns",
        MIN_POSTERIOR_DRAWS,
        MAX_POSTERIOR_DRAWS,
        acting=True,
        part="posterior",
    ),
    "posterior_far_noise": Option(
        float, "posterior's far_noise", 0, MAX_FAR_NOISE, acting=True, part="posterior"
    ),
    "posterior_walk_after": Option(
        int, "posterior walks from", 0, MAX_WALK_AFTER, acting=True, part="posterior"
    ),
    "posterior_walk_unmeasured": Option(
        bool, "and while none measured", acting=True, part="posterior"
    ),
    "posterior_no_edges": Option(
        bool, "posterior reads no-edge frames", acting=True, part="posterior"
    ),
    "posterior_probe_rule": Option(
        str, "where its walk probes", choices=POSTERIOR_PROBE_RULES, acting=True, part="posterior"
    ),
    "posterior_saturation_px": Option(tuple, "level off, px", acting=True, part="posterior"),
    "posterior_column": Option(tuple, "calibrated column", acting=True, part="posterior"),
    "finish_window": Option(
        float, "finish fit: within x narrowest", 1, above=True, acting=True, part="ending"
    ),
    "approach_from_below": Option(
        bool, "every reading reached from below", acting=True, part="ending"
    ),
    "final_move": Option(bool, "the stopping action's move ends it", acting=True, part="ending"),
    "final_move_reach": Option(
        float, "x max_step, last move", 0, 1, above=True, acting=True, part="ending"
    ),
    "success_relative": Option(float, "threshold x best width", 1, above=True, part="success"),
    "success_absolute_px": Option(float, "absolute spec, px", 0, above=True, part="success"),
    "directional_relative": Option(float, "directional spec x best", 1, above=True),
    "wobble_amplitude_v": Option(
        float, "wobble swing each way, defocus units (default: 5 % of its interval)", 0, above=True
    ),
    "wobble_spec_px": Option(float, "spec of the wobble shift, px", 0, above=True),
    "wobble_weight": Option(float, "cost px per px of wobble shift", 0),
}

# The task options that change how a trained policy's moves reach the column and how its
# episode ends, never what it observes: an export may set them (alignrl export --set).
ACTING_OPTIONS = tuple(name for name, option in OPTIONS.items() if option.acting)

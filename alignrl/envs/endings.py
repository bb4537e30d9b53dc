"""How an episode ends, as one typed record: `Task.ending`, an `Ending`.

`Ending.at` says where an episode that ends (a stop, or the step limit) leaves its knob:

* "last": where its last step took it (the seed);
* "narrowest": back where its narrowest reading was taken, as a classical autofocus ends;
* "fit": back to the optimum a focus-curve fit of its readings places between them
  (alignrl/envs/fit_features.py, `bracketed_optimum`, within `finish_window` x the
  narrowest), else to the narrowest reading;
* "posterior": back to the setting a posterior over the focus training box holds most
  likely to pass (alignrl/posterior/inference.py), set by one `PosteriorSettings`.

With `final_move` the stopping action's own move ends the episode instead (at "fit" or
"posterior" that move starts from the estimate); "narrowest" and `final_move` exclude each
other. `backlash_overshoot` and `approach_from_below` say how the knob arrives
(alignrl/envs/ending.py). Each record validates itself once, in its `__post_init__`, each
bound from the one table of task options (alignrl/envs/option_table.py).

The serialized form is the flat task options of a run's `task_options:` and a card's
`task.options` (stop_at_best, finish_at_fit, finish_at_posterior, posterior_draws, ...):
`ending_from_options` parses them into the record, `ending_options` writes it back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any, TypeVar

from alignrl.envs.fit_features import FINISH_WINDOW
from alignrl.envs.option_table import OPTIONS

__all__ = [
    "ENDING_OPTIONS",
    "ENDS_AT",
    "POSTERIOR_DRAWS",
    "POSTERIOR_OPTIONS",
    "Ending",
    "PosteriorSettings",
    "ending_from_options",
    "ending_options",
    "with_ending",
]

ENDS_AT = ("last", "narrowest", "fit", "posterior")
POSTERIOR_DRAWS = 256  # the columns the posterior draws by default
# The flat option each PosteriorSettings field is written as
_POSTERIOR_NAMES = {
    "draws": "posterior_draws",
    "far_noise": "posterior_far_noise",
    "no_edges": "posterior_no_edges",
    "probe_rule": "posterior_probe_rule",
    "saturation_px": "posterior_saturation_px",
    "column": "posterior_column",
    "walk_after": "posterior_walk_after",
    "walk_unmeasured": "posterior_walk_unmeasured",
    "stop_when_sure": "stop_when_sure",
    "probe_until_sure": "probe_until_sure",
}
_CHOICES = ("stop_at_best", "finish_at_fit", "finish_at_posterior")
_PLAIN = ("final_move", "final_move_reach", "backlash_overshoot", "finish_window")
_PLAIN += ("approach_from_below",)
# Every flat task option that the ending is written as
ENDING_OPTIONS = _CHOICES + _PLAIN + tuple(_POSTERIOR_NAMES.values())


def _check(name: str, value: Any) -> None:
    problem = OPTIONS[name].problem(name, value)
    if problem is not None:
        raise ValueError(f"ending: {problem}")


@dataclass(frozen=True)
class PosteriorSettings:
    """The posterior an episode ends by (Ending.at "posterior"), its walk and its stop.

    draws: the columns it draws from the box (more: nearer the truth, at a cost in
    proportion); far_noise: its readings far from focus trusted less (FamilyPosterior.
    far_noise); no_edges: frames without edges tell it focus is far from there; probe_rule:
    where its walk probes ("variance", "entropy", "chance"); saturation_px: where its
    columns' readings level off, (low, high) px, in place of the box's (): the box's;
    column: the column calibrated on the microscope (alignrl/posterior/calibration.py:
    COLUMN_FIELDS' values in order), read in its own pixels, each reading on its side; ():
    the box. The walk: from the walk_after-th reading on (0: never) every move goes where
    the posterior would probe next, and with walk_unmeasured while nothing is measured. The
    stop: stop_when_sure ends an episode once its best setting passes with that chance (0:
    only the policy stops); probe_until_sure makes a stop before that chance a reading.
    """

    draws: int = POSTERIOR_DRAWS
    far_noise: float = 0.0
    no_edges: bool = False
    probe_rule: str = "variance"
    saturation_px: tuple[float, ...] = ()
    column: tuple[float, ...] = ()
    walk_after: int = 0
    walk_unmeasured: bool = False
    stop_when_sure: float = 0.0
    probe_until_sure: float = 0.0

    def __post_init__(self) -> None:
        for name, flat in _POSTERIOR_NAMES.items():
            _check(flat, getattr(self, name))
        saturation = self.saturation_px
        if saturation and not (
            len(saturation) == 2 and 0 < saturation[0] <= saturation[1] < math.inf
        ):
            raise ValueError(
                "ending: posterior_saturation_px, where its columns' readings level off, "
                f"must be (low, high) px with 0 < low <= high; got {saturation}"
            )
        problem = self._column_problem()
        if problem is not None:
            raise ValueError(
                "ending: posterior_column must be a column calibrated on the microscope "
                f"(alignrl calibrate): {problem}"
            )

    def _column_problem(self) -> str | None:
        """What is wrong with `column`, or None (the box, or a calibrated column)."""
        if not self.column:
            return None
        from alignrl.posterior.calibration import COLUMN_FIELDS, column_problem

        if len(self.column) != len(COLUMN_FIELDS):
            return f"{len(COLUMN_FIELDS)} values ({', '.join(COLUMN_FIELDS)})"
        return column_problem(dict(zip(COLUMN_FIELDS, self.column, strict=True)))


@dataclass(frozen=True)
class Ending:
    """Where and how an episode ends (module docstring)."""

    at: str = "last"
    # The stopping action's knob components are one last move, written without an
    # acquisition, final_move_reach x max_step at most (its start: the estimate at "fit"
    # and "posterior", else the present setting).
    final_move: bool = False
    final_move_reach: float = 1.0
    # The way back arrives from the side the narrowest reading was approached from, going
    # past the target first by this share of the interval where it would come from the
    # other side (backlash and lens hysteresis); 0: one write.
    backlash_overshoot: float = 0.02
    finish_window: float = FINISH_WINDOW  # "fit": the readings within this x the narrowest
    # Every reading's setting is reached from below: a step down first goes past its target
    # by backlash_overshoot x the interval and comes back up.
    approach_from_below: bool = False
    posterior: PosteriorSettings | None = None  # at "posterior", and there alone

    def __post_init__(self) -> None:
        if self.at not in ENDS_AT:
            raise ValueError(f"ending: at must be one of {', '.join(ENDS_AT)}; got {self.at!r}")
        for name in _PLAIN:
            _check(name, getattr(self, name))
        if self.final_move_reach != 1.0 and not self.final_move:
            raise ValueError(
                "ending: final_move_reach is the last move's share of max_step, with "
                f"final_move; got {self.final_move_reach} (final_move=False)"
            )
        if self.final_move and self.at == "narrowest":
            raise ValueError(
                "ending: final_move ends where the stopping action moves, stop_at_best at "
                "the narrowest reading: choose one"
            )
        if (self.posterior is not None) != (self.at == "posterior"):
            raise ValueError(
                f"ending: posterior settings go with at='posterior' alone; got at={self.at!r}"
                f" and posterior={self.posterior}"
            )
        if self.at == "posterior" and not self.approach_from_below:
            raise ValueError(
                "ending: finish_at_posterior needs every reading approached from below "
                "(approach_from_below), as its reading model has them"
            )

    @property
    def settings(self) -> PosteriorSettings:
        """The posterior's settings, its defaults where the ending has none."""
        return self.posterior or _NO_POSTERIOR

    @property
    def stop_at_best(self) -> bool:
        """Whether an ending episode goes back (to the narrowest reading or an estimate)."""
        return self.at != "last" and not self.final_move

    @property
    def at_estimate(self) -> bool:
        """Whether it ends at an estimate from its readings ("fit" or "posterior")."""
        return self.at in ("fit", "posterior")

    @property
    def notes_readings(self) -> bool:
        """Whether the episode's readings are kept for its end."""
        return self.at != "last"

    @property
    def tracks_sides(self) -> bool:
        """Whether the side each knob was written from is kept (the way back, or every
        reading approached from below)."""
        return self.stop_at_best or self.approach_from_below


_NO_POSTERIOR = PosteriorSettings()


def ending_from_options(options: Mapping[str, Any], base: Ending | None = None) -> Ending:
    """The Ending that the flat task options (`ENDING_OPTIONS`; any other key is left
    alone) make, laid over `base` (None: the default ending). ValueError naming the option
    where they do not go together."""
    flat = {**ending_options(base or Ending(), every=True)}
    flat.update({name: value for name, value in options.items() if name in ENDING_OPTIONS})
    best, fit, posterior = (bool(flat[name]) for name in _CHOICES)
    if fit and posterior:
        raise ValueError("ending: finish_at_fit and finish_at_posterior: choose one")
    at = "posterior" if posterior else "fit" if fit else "narrowest" if best else "last"
    if at in ("fit", "posterior") and not (best or flat["final_move"]):
        name = "finish_at_posterior" if posterior else "finish_at_fit"
        raise ValueError(
            f"ending: {name} ends the way back to the narrowest reading (stop_at_best), or "
            "starts the last move (final_move), at its estimate; neither is set"
        )
    if best and flat["final_move"]:
        raise ValueError(
            "ending: final_move ends where the stopping action moves, stop_at_best at the "
            "narrowest reading: choose one"
        )
    settings = {
        name: flat[flat_name]
        for name, flat_name in _POSTERIOR_NAMES.items()
        if flat[flat_name] is not None
    }
    for name in ("saturation_px", "column"):
        settings[name] = tuple(settings.get(name) or ())
    if at != "posterior":
        defaults = PosteriorSettings()
        for name, value in settings.items():
            if value != getattr(defaults, name):
                raise ValueError(
                    f"ending: {_POSTERIOR_NAMES[name]} is a setting of the posterior of "
                    f"finish_at_posterior; got {value} (finish_at_posterior=False)"
                )
    return Ending(
        at=at,
        **{name: flat[name] for name in _PLAIN},
        posterior=PosteriorSettings(**settings) if at == "posterior" else None,
    )


def ending_options(ending: Ending, every: bool = False) -> dict[str, Any]:
    """The flat task options `ending` is written as (the inverse of ending_from_options):
    those that differ from the default ending, or with `every` all of ENDING_OPTIONS."""
    flat: dict[str, Any] = {
        "stop_at_best": ending.at == "narrowest" or (ending.at_estimate and not ending.final_move),
        "finish_at_fit": ending.at == "fit",
        "finish_at_posterior": ending.at == "posterior",
    }
    flat.update({name: getattr(ending, name) for name in _PLAIN})
    settings = ending.settings
    flat.update(
        {_POSTERIOR_NAMES[each.name]: getattr(settings, each.name) for each in fields(settings)}
    )
    if every:
        return flat
    default = ending_options(Ending(), every=True)
    return {name: value for name, value in flat.items() if value != default[name]}


# The flat options of the posterior's settings at their defaults (each needs
# finish_at_posterior): laid over an ending, they take its posterior's settings away.
POSTERIOR_OPTIONS = {
    name: value
    for name, value in ending_options(Ending(), every=True).items()
    if name in _POSTERIOR_NAMES.values()
}

_Task = TypeVar("_Task")


def with_ending(task: _Task, **options: Any) -> _Task:
    """`task` (a Task) with the flat ending options `options` laid over its ending
    (ending_from_options), e.g. with_ending(task, stop_at_best=True)."""
    ending = ending_from_options(options, task.ending)  # type: ignore[attr-defined]
    return replace(task, ending=ending)  # type: ignore[type-var]

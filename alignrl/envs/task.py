"""Alignment tasks: which knobs an aligner controls, how far one action moves them, how long
an episode may last, and what counts as aligned (seed sections 4.3 and 6.2).

A task is a frozen record; `TASKS` maps names to the built-in ones, so a new task is one
entry. Knob changes are in the apparatus's units (volts for lenses, percent of full excitation
for stigmators, micrometres for the aperture).

What a task measures after each action (`measures`):
* "width": the average edge width of one image (px), every task's first quality;
* "directional": the edge widths in four orientation bins of the edge normal, from the same
  image (alignrl/apparatus/quality.py): what shows the axis of an astigmatic probe;
* "wobble": the image shift (px) between frames acquired at defocus +d and -d, the symptom of
  an off-axis objective aperture. It costs two more acquisitions, counted as such.
Success needs every measured quality within its spec: the width within the success rule, every
directional width within `directional_relative` x the best width, the wobble shift at most
`wobble_spec_px`. `Task.judge` gives each judged measure against its spec (a `Criterion`, which
`align` prints); `Task.within_spec` is all of them met, as training and sessions count success.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from alignrl.envs.fit_features import FINISH_WINDOW, FIT_FEATURES
from alignrl.envs.success import Criterion, SuccessRule

__all__ = [
    "ACTING_OPTIONS",
    "MEASURES",
    "TASKS",
    "Criterion",
    "SuccessRule",
    "Task",
    "get_task",
    "knob_change",
]

MEASURES = ("width", "directional", "wobble")
DIRECTIONAL_BINS = 4  # edge-normal orientation bins of quality.directional_widths
QUALITY_REFERENCES = ("fixed", "first")  # what quality observations are relative to
REWARD_FORMS = ("difference", "log_ratio")  # how the final reward counts widths (rewards.py)
MAX_ACTION_POWER = 4.0  # above it the smallest useful changes need actions within a hair of 0
# The task options that change how a trained policy's moves reach the column and how its
# episode ends, never what it observes: an export may set them (alignrl export --set).
ACTING_OPTIONS = (
    "move_floor", "stop_at_best", "backlash_overshoot", "finish_at_fit", "finish_at_posterior",
    "stop_when_sure", "probe_until_sure", "posterior_draws", "posterior_far_noise",
    "posterior_walk_after", "posterior_walk_unmeasured", "posterior_no_edges",
    "posterior_from_below", "posterior_on_sides", "posterior_probe_rule",
    "posterior_saturation_px", "posterior_column", "finish_window", "approach_from_below",
    "final_move", "final_move_reach",
)  # fmt: skip
# The posterior of finish_at_posterior: the columns it draws (FamilyPosterior.draws)
POSTERIOR_DRAWS, MIN_POSTERIOR_DRAWS, MAX_POSTERIOR_DRAWS = 256, 16, 4096
# Where its walk probes: FamilyPosterior's PROBE_RULES (alignrl/posterior/inference.py,
# left unimported here for its scipy; tests/test_finish_at_posterior.py holds them equal)
POSTERIOR_PROBE_RULES = ("variance", "chance", "entropy")
MAX_FAR_NOISE = 1.0  # its posterior_far_noise: beyond it a reading far from focus says nothing
MAX_MOVE_FLOOR = 0.2  # a share of the interval: beyond it no column could be brought to focus


def knob_change(
    actions: np.ndarray, max_step: np.ndarray, power: float = 1.0, floor: np.ndarray | float = 0.0
) -> np.ndarray:
    """sign(a) (|a|^power x max_step + floor): the knob change (its units) an action a in
    [-1, 1] asks for. Power 1 is linear; above it, the same reach with finer changes near 0.
    `floor` (its units, per knob; 0: none) is the least a move goes: a = 0 stays put, any other
    action goes at least that far. The exported graph computes the same
    (alignrl/deploy/graph.py: knob_step)."""
    actions = np.asarray(actions, np.float64)
    if power != 1.0:
        actions = np.sign(actions) * np.abs(actions) ** power
    change = actions * max_step
    if np.any(np.asarray(floor) != 0):
        change = change + np.sign(actions) * floor
    return change


@dataclass(frozen=True)
class Task:
    """What an aligner controls and how an episode runs."""

    name: str
    knobs: tuple[str, ...]
    max_step: Mapping[str, float] = field(default_factory=dict)  # per knob, units per action
    max_step_fraction: float = 0.25  # default max change per step: this share of the interval
    episode_steps: int = 10  # acquisitions after the first one, at most
    success: SuccessRule = field(default_factory=SuccessRule)
    out_of_bounds_penalty: float = 1.0  # reward -penalty for a step that hits an interval bound
    final_reward_scale: float = 1.0  # x (quality before - quality after), quality in px
    # "log_ratio": x log(quality before / quality after) instead, unit-free (rewards.py)
    final_reward_form: str = "difference"
    acquisition_cost: float = 0.0  # reward -cost per acquisition (the seed: none)
    success_bonus: float = 0.0  # optional shaping, off by default: + this when the spec is met
    # Pay the bonus only within this x the best width (tighter than the spec: a margin against
    # measurement noise); None: wherever the spec is met. Success itself keeps the spec. Where
    # the best width is unknown (an absolute spec on a real column) the margin keeps its ratio
    # to the spec: bonus_relative / success.relative x the spec.
    bonus_relative: float | None = None
    # Judge the final reward and the bonus on one more image at the final setting (as an
    # evaluation session's verification does), not on the reading the aligner stopped at: a
    # lucky noisy reading then earns nothing. Costs one acquisition per episode.
    verify_final: bool = False
    quality_ref_px: float = 2.5  # quality observations are log(width / this) ...
    # ... or, "first", log(width / the episode's first measured width): unit-free readings,
    # for policies that must run on any pixel scale (alignrl/envs/core.py)
    quality_reference: str = "fixed"
    no_edges_px: float = 25.0  # a frame without edges counts as this wide in rewards
    measures: tuple[str, ...] = ("width",)  # what each step measures (see the module doc)
    directional_relative: float = 1.3  # success: every directional width within this x best
    wobble_amplitude_v: float = 5.0  # the wobble swings the defocus this far each way, V
    wobble_spec_px: float = 0.5  # success: wobble shift magnitude at most this, px
    wobble_weight: float = 1.0  # the task's cost counts this many px of width per px of shift
    wobble_ref_px: float = 12.0  # wobble observations are tanh(shift / this)
    # The knobs outside the task that an episode starts misaligned: knob -> the largest offset
    # from its optimum (its units), drawn uniformly and kept within its interval. A stage of a
    # column alignment meets the column as the stages before it leave it (the aperture is
    # centred with the stigmators anywhere); empty: every other knob at its optimum.
    context: Mapping[str, float] = field(default_factory=dict)
    # How far from its optimum each named knob of the task starts at most (its units), where
    # the stage before leaves it near (the focus after the first column stage): caps the
    # misalignment window (complexity x interval) in training and the uniform start of an
    # evaluation session. Knobs not named start anywhere.
    start_reach: Mapping[str, float] = field(default_factory=dict)
    # The measures success is judged on; None: every measure the task takes. A stage that
    # cannot reach the width spec alone (the aperture with the stigmators anywhere) is judged
    # on what it does fix (the wobble), and the width is left to the stage after it.
    judged: tuple[str, ...] | None = None
    # Three more features per row, from a local fit of the focus curve to the window's
    # readings (alignrl/envs/fit_features.py): where it puts the optimum, in maximum steps,
    # and how much narrower it says the column gets. Single-knob tasks only.
    fit_features: bool = False
    fit_window: float = 3.0  # the fit takes the readings within this x the narrowest
    # A knob change is max_step x sign(a) |a|^action_power for the action's a in [-1, 1]:
    # 1 is linear (the seed); above 1 the same reach with finer changes near 0, where a
    # steep column's last moves must land within a fraction of a percent of the interval.
    action_power: float = 1.0
    # An episode that ends (stop or step limit) leaves the knob where its narrowest reading
    # was taken, as a classical autofocus does, not where the last step took it: a probe
    # beyond the best costs an acquisition but never the result. Width-only tasks.
    stop_at_best: bool = False
    # The way back to the narrowest reading arrives at each knob's setting from the side that
    # reading was approached from, going past it first by this share of the interval where
    # it would come back from the other side (backlash and lens hysteresis put the focus
    # elsewhere otherwise); 0 returns in one write.
    backlash_overshoot: float = 0.02
    # With stop_at_best: where a focus-curve fit of the episode's readings places the optimum
    # between readings (alignrl/envs/fit_features.py, bracketed_optimum), the way back goes
    # there instead of to the narrowest reading. No reading is taken there: the final one is
    # the verification's (verify_final), or the narrowest stands. With final_move: the
    # stopping action's move starts from that optimum, not from the present setting (the
    # policy corrects the fit). One-knob width tasks.
    finish_at_fit: bool = False
    # As finish_at_fit, with the setting that the scale-free Bayesian autofocus over the
    # focus training box (alignrl/posterior/inference.py) holds most likely to pass,
    # given the episode's measured readings, in place of the fit's optimum: the policy
    # probes and stops, the posterior says where it ends. Focus tasks approached from below
    # (its reading model); a fraction of a second of computing per episode end.
    finish_at_posterior: bool = False
    # With finish_at_posterior: an episode also ends (as a stop whose last move is 0) once
    # that best setting passes with this probability (a calibrated posterior_column's: x the
    # chance at the optimum itself, FamilyPosterior.relative_stop); 0: only the policy stops.
    stop_when_sure: float = 0.0
    # With finish_at_posterior: a stop is taken only once the posterior is that sure of its
    # best setting (as stop_when_sure); before, the stopping action reads once more where it would
    # probe next (and the policy acts on); 0: every stop is taken.
    probe_until_sure: float = 0.0
    # With finish_at_posterior: the columns that posterior draws from the box (and draws
    # again around the likely ones as readings come): more columns, a chance nearer the truth
    # where few readings are near focus, at a computing cost in proportion.
    posterior_draws: int = POSTERIOR_DRAWS
    # With finish_at_posterior: its readings far from focus trusted less (FamilyPosterior.
    # far_noise; posterior-robust's 0.1 for readings measured on images).
    posterior_far_noise: float = 0.0
    # With finish_at_posterior: from an episode's posterior_walk_after-th reading on (taken,
    # measured or not), every move goes where the posterior would probe next, not where the
    # policy asks (its stops stand as before); 0: the policy walks throughout.
    posterior_walk_after: int = 0
    # With finish_at_posterior: while no reading of the episode has been measured (every
    # frame so far without edges), every move goes where the posterior would probe next too:
    # the policy has no reading to act on, the posterior knows focus lies away from there.
    posterior_walk_unmeasured: bool = False
    # With finish_at_posterior: readings without edges tell the posterior that focus is far
    # from there (as posterior-robust reads them); else it is fed measured readings alone.
    posterior_no_edges: bool = False
    # With finish_at_posterior: the posterior reads only the readings approached from below,
    # not the opening one, taken on whichever branch of its backlash or hysteresis the column
    # was found (the narrowest reading may still be that one); False: every reading.
    posterior_from_below: bool = False
    # With finish_at_posterior: the posterior reads each reading on the side it was
    # approached from, the opening one (the column as found) on an unknown side: the mixture
    # of the backlash's branches (FamilyPosterior.observe, side 0); False: every reading as
    # approached from below.
    posterior_on_sides: bool = False
    # With finish_at_posterior: where its walk probes (FamilyPosterior.probe_rule): "variance",
    # the least expected variance of the optimum; "entropy", the least expected entropy of
    # it (the most expected information); "chance", the final setting's greatest chance.
    posterior_probe_rule: str = "variance"
    # With finish_at_posterior: where its columns' readings level off (px, low and high, drawn
    # log-uniformly) in place of the box's saturation_px, which its analytic readings follow:
    # edge widths measured on images level off from 15 px (grids, bars); (): the box's.
    posterior_saturation_px: tuple[float, ...] = ()
    # With finish_at_posterior: the posterior reads in the one column calibrated on the
    # microscope (alignrl/posterior/calibration.py: COLUMN_FIELDS' values in order, `alignrl
    # calibrate`), in that column's own pixels, not in the scale-free training box; (): the box.
    posterior_column: tuple[float, ...] = ()
    finish_window: float = FINISH_WINDOW  # that fit takes the readings within this x the narrowest
    # Every setting a reading is taken at is reached from below, as a microscopist approaches
    # focus from one side: a step down first goes past its target by backlash_overshoot x the
    # interval (kept inside it) and comes back up, so that backlash and lens hysteresis put
    # every reading, and the way back, on one branch of the focus curve. No acquisition on
    # the way (alignrl/envs/ending.py, EpisodeEnds.writes_to).
    approach_from_below: bool = False
    # Every move goes at least this share of the interval further in its own direction
    # (Task.knob_change): a policy trained on the box's columns stops short near a bound and
    # under-brackets steep ones with its last, shortest moves. 0: the seed's moves.
    move_floor: float = 0.0
    # The stopping action's knob components are one last move (as any move, but without the
    # floor), written without an acquisition: the policy says where its episode ends, between
    # its readings (a Bayesian autofocus ends at its posterior's best setting, not at a
    # reading). The final reading is the verification's (verify_final, or a session's); the
    # last reading stands until then. Not with stop_at_best, which says where instead.
    final_move: bool = False
    # The last move's reach as a share of max_step (action_power as any move's): below 1, a
    # finer last move for a policy that corrects an estimate (finish_at_fit) by a little.
    final_move_reach: float = 1.0

    def __post_init__(self) -> None:
        if not self.knobs:
            raise ValueError(f"task {self.name!r} names no knob")
        if self.episode_steps < 1:
            raise ValueError(f"task {self.name!r}: episode_steps must be at least 1")
        if not 0 < self.max_step_fraction <= 2:
            raise ValueError(f"task {self.name!r}: max_step_fraction must be in (0, 2]")
        if not 0 <= self.move_floor <= MAX_MOVE_FLOOR:
            raise ValueError(f"task {self.name!r}: move_floor must be in [0, {MAX_MOVE_FLOOR}]")
        for knob, step in self.max_step.items():
            if knob not in self.knobs:
                raise ValueError(f"task {self.name!r}: max_step names {knob!r}, not a task knob")
            if not step > 0:
                raise ValueError(f"task {self.name!r}: max_step of {knob!r} must be positive")
        if self.out_of_bounds_penalty < 0 or self.acquisition_cost < 0 or self.success_bonus < 0:
            raise ValueError(f"task {self.name!r}: penalties and costs are magnitudes (>= 0)")
        if self.bonus_relative is not None and not self.bonus_relative > 1:
            raise ValueError(f"task {self.name!r}: bonus_relative must be above 1 (x best width)")
        if not self.quality_ref_px > 0 or not self.no_edges_px > 0:
            raise ValueError(f"task {self.name!r}: quality_ref_px and no_edges_px must be > 0")
        if self.final_reward_form not in REWARD_FORMS:
            raise ValueError(
                f"task {self.name!r}: final_reward_form must be one of "
                f"{', '.join(REWARD_FORMS)}, got {self.final_reward_form!r}"
            )
        if self.quality_reference not in QUALITY_REFERENCES:
            raise ValueError(
                f"task {self.name!r}: quality_reference must be one of "
                f"{', '.join(QUALITY_REFERENCES)}, got {self.quality_reference!r}"
            )
        unknown = [name for name in self.measures if name not in MEASURES]
        if unknown or "width" not in self.measures or len(set(self.measures)) != len(self.measures):
            raise ValueError(
                f"task {self.name!r}: measures must name 'width' and any of "
                f"{', '.join(MEASURES[1:])}, each once; got {list(self.measures)}"
            )
        if self.fit_features and len(self.knobs) != 1:
            raise ValueError(
                f"task {self.name!r}: fit_features fits a focus curve along one knob; the task "
                f"moves {len(self.knobs)} ({', '.join(self.knobs)})"
            )
        if not self.fit_window > 1:
            raise ValueError(f"task {self.name!r}: fit_window must be above 1 (x narrowest)")
        if self.stop_at_best and self.measures != ("width",):
            raise ValueError(
                f"task {self.name!r}: stop_at_best returns to the narrowest reading, a task "
                f"that measures the width alone; it measures {', '.join(self.measures)}"
            )
        if self.finish_at_fit and not (
            (self.stop_at_best or self.final_move) and len(self.knobs) == 1
        ):
            raise ValueError(
                f"task {self.name!r}: finish_at_fit ends the way back to the narrowest reading "
                f"(stop_at_best), or starts the last move (final_move), at a focus-curve fit "
                f"along one knob; the task has stop_at_best={self.stop_at_best}, "
                f"final_move={self.final_move} and {len(self.knobs)} knobs"
            )
        if self.finish_at_posterior and not (
            (self.stop_at_best or self.final_move) and self.knobs == ("defocus",)
            and self.approach_from_below and not self.finish_at_fit
        ):  # fmt: skip
            raise ValueError(
                f"task {self.name!r}: finish_at_posterior ends the way back (stop_at_best), or "
                f"starts the last move (final_move), where the focus posterior puts the best "
                f"setting, in place of finish_at_fit; it needs the defocus knob alone, every "
                f"reading approached from below (approach_from_below) and no finish_at_fit; "
                f"the task has stop_at_best={self.stop_at_best}, final_move={self.final_move}, "
                f"knobs {', '.join(self.knobs)}, approach_from_below={self.approach_from_below}"
                f" and finish_at_fit={self.finish_at_fit}"
            )
        column = self._column_problem()
        for option, good, meaning in (
            ("stop_when_sure", 0 <= self.stop_when_sure < 1, "the chance, in [0, 1), at which "
             "it ends an episode"),
            ("probe_until_sure", 0 <= self.probe_until_sure < 1, "the chance, in [0, 1), it "
             "must give its best setting before a stop is taken"),
            ("posterior_draws", MIN_POSTERIOR_DRAWS <= self.posterior_draws <= MAX_POSTERIOR_DRAWS,
             f"how many columns it draws, {MIN_POSTERIOR_DRAWS}-{MAX_POSTERIOR_DRAWS}"),
            ("posterior_far_noise", 0 <= self.posterior_far_noise <= MAX_FAR_NOISE,
             f"how much less it trusts far readings, in [0, {MAX_FAR_NOISE:g}]"),
            ("posterior_walk_after", 0 <= self.posterior_walk_after <= self.episode_steps,
             f"the reading it walks from, in [0, episode_steps={self.episode_steps}]"),
            ("posterior_walk_unmeasured", True, "whether it walks while nothing is measured"),
            ("posterior_no_edges", True, "whether it reads frames without edges"),
            ("posterior_from_below", True, "whether it reads only readings from below"),
            ("posterior_on_sides", True, "whether it reads readings on their sides"),
            ("posterior_probe_rule", self.posterior_probe_rule in POSTERIOR_PROBE_RULES,
             f"where its walk probes, one of {', '.join(POSTERIOR_PROBE_RULES)}"),
            ("posterior_saturation_px", not (saturation := self.posterior_saturation_px) or (
                len(saturation) == 2 and 0 < saturation[0] <= saturation[1] < math.inf),
             "where its columns' readings level off, (low, high) px with 0 < low <= high"),
            ("posterior_column", column is None, "a column calibrated on the microscope "
             f"(alignrl calibrate){'' if column is None else ': ' + column}"),
        ):  # fmt: skip
            value = getattr(self, option)
            if not good or (value != POSTERIOR_OPTIONS[option] and not self.finish_at_posterior):
                raise ValueError(
                    f"task {self.name!r}: {option} is {meaning}, by the posterior of "
                    f"finish_at_posterior; got {value} "
                    f"(finish_at_posterior={self.finish_at_posterior})"
                )
        if not 0.0 < self.final_move_reach <= 1.0 or (
            self.final_move_reach != 1.0 and not self.final_move
        ):
            raise ValueError(
                f"task {self.name!r}: final_move_reach is the last move's share of max_step, "
                f"in (0, 1], with final_move; got {self.final_move_reach} "
                f"(final_move={self.final_move})"
            )
        if self.final_move and self.stop_at_best:
            raise ValueError(
                f"task {self.name!r}: final_move ends where the stopping action moves, "
                "stop_at_best at the narrowest reading: choose one"
            )
        if not self.finish_window > 1:
            raise ValueError(f"task {self.name!r}: finish_window must be above 1 (x narrowest)")
        if not 0.0 <= self.backlash_overshoot <= 0.5:
            raise ValueError(
                f"task {self.name!r}: backlash_overshoot must be in [0, 0.5] (a share of the "
                f"interval), got {self.backlash_overshoot}"
            )
        if not 1.0 <= self.action_power <= MAX_ACTION_POWER:
            raise ValueError(
                f"task {self.name!r}: action_power must be in [1, {MAX_ACTION_POWER:g}], "
                f"got {self.action_power}"
            )
        if not self.directional_relative > 1:
            raise ValueError(f"task {self.name!r}: directional_relative must be above 1")
        for name in ("wobble_amplitude_v", "wobble_spec_px", "wobble_ref_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"task {self.name!r}: {name} must be positive")
        if self.wobble_weight < 0:
            raise ValueError(f"task {self.name!r}: wobble_weight is a magnitude (>= 0)")
        for knob, offset in self.context.items():
            if knob in self.knobs:
                raise ValueError(
                    f"task {self.name!r}: context names {knob!r}, a knob the task moves itself"
                )
            if not (math.isfinite(offset) and offset > 0):
                raise ValueError(
                    f"task {self.name!r}: context offset of {knob!r} must be positive, got {offset}"
                )
        for knob, reach in self.start_reach.items():
            if knob not in self.knobs:
                raise ValueError(f"task {self.name!r}: start_reach names {knob!r}, not a task knob")
            if not (math.isfinite(reach) and reach > 0):
                raise ValueError(
                    f"task {self.name!r}: start_reach of {knob!r} must be positive, got {reach}"
                )
        if self.judged is not None:
            strange = [name for name in self.judged if name not in self.measures]
            if not self.judged or strange or len(set(self.judged)) != len(self.judged):
                raise ValueError(
                    f"task {self.name!r}: judged must name measures the task takes "
                    f"({', '.join(self.measures)}), each once; got {list(self.judged)}"
                )

    def _column_problem(self) -> str | None:
        """What is wrong with posterior_column, or None (the box, or a calibrated column)."""
        if not self.posterior_column:
            return None
        from alignrl.posterior.calibration import COLUMN_FIELDS, column_problem

        if len(self.posterior_column) != len(COLUMN_FIELDS):
            return f"{len(COLUMN_FIELDS)} values ({', '.join(COLUMN_FIELDS)})"
        return column_problem(dict(zip(COLUMN_FIELDS, self.posterior_column, strict=True)))

    def knob_change(
        self, actions: np.ndarray, max_step: np.ndarray, span: np.ndarray
    ) -> np.ndarray:
        """The knob changes (its units) that actions in [-1, 1] ask for on knobs whose
        intervals are `span` wide (`knob_change`, the floor move_floor x span)."""
        floor = self.move_floor * span if self.move_floor else 0.0  # the env step's hot path
        return knob_change(actions, max_step, self.action_power, floor)

    def for_acting(self) -> Task:
        """The task as an evaluation session or `align` runs a policy on it: without the
        training verification image (`verify_final`), since they verify themselves."""
        return dataclasses.replace(self, verify_final=False) if self.verify_final else self

    @property
    def ends_at_estimate(self) -> bool:
        """Whether episodes end at an estimate from their readings (finish_at_fit or
        finish_at_posterior: alignrl/envs/ending.py, EpisodeEnds.estimated)."""
        return self.finish_at_fit or self.finish_at_posterior

    @property
    def directional(self) -> bool:
        return "directional" in self.measures

    @property
    def wobble(self) -> bool:
        return "wobble" in self.measures

    def start_intervals(
        self, knobs: Mapping[str, tuple[float, float]], optimum: Mapping[str, float] | None
    ) -> list[tuple[float, float]]:
        """Where each task knob may start: its interval, narrowed to `start_reach` around the
        optimum where the apparatus knows it."""
        intervals = []
        for knob in self.knobs:
            low, high = knobs[knob]
            if optimum is not None and knob in self.start_reach:
                reach = self.start_reach[knob]
                low, high = max(low, optimum[knob] - reach), min(high, optimum[knob] + reach)
            intervals.append((float(low), float(high)))
        return intervals

    def judges(self, measure: str) -> bool:
        """Whether success needs `measure` within its spec."""
        return measure in (self.measures if self.judged is None else self.judged)

    @property
    def extra_features(self) -> int:
        """Observation features beyond the width: 4 directional widths, 2 wobble shifts, 3
        of the focus-curve fit."""
        return self.measure_features + FIT_FEATURES * self.fit_features

    @property
    def measure_features(self) -> int:
        """The extra features the measures give (directional widths, wobble shifts)."""
        return DIRECTIONAL_BINS * self.directional + 2 * self.wobble

    @property
    def acquisitions_per_step(self) -> int:
        """Images one measurement costs: one, and two more for a wobble."""
        return 1 + 2 * self.wobble

    def directional_threshold_px(self, width_threshold_px: float, best_px: float | None) -> float:
        """The spec of every directional width: `directional_relative` x the best width, or,
        where the best is unknown, that share of an absolute width spec."""
        if best_px is None or not math.isfinite(best_px):
            return self.directional_relative * width_threshold_px / self.success.relative
        return self.directional_relative * best_px

    def judge(
        self,
        width_px: np.ndarray,
        width_threshold_px: np.ndarray,
        directional_px: np.ndarray | None = None,
        directional_threshold_px: np.ndarray | None = None,
        wobble_px: np.ndarray | None = None,
    ) -> list[Criterion]:
        """Each measure the task judges, in the order of MEASURES, against its spec (batched:
        widths (n,), directional (n, 4), wobble (n, 2)); None: that measure was not taken.
        The measures the task does not take or judge are not looked at."""
        width = np.asarray(width_px, dtype=np.float64)
        unmeasured, unmet = np.full(width.shape, np.nan), np.zeros(width.shape, bool)
        criteria = []
        with np.errstate(invalid="ignore"):
            if self.judges("width"):
                spec = np.broadcast_to(np.asarray(width_threshold_px, np.float64), width.shape)
                met = np.isfinite(width) & (width <= spec)
                criteria.append(Criterion("width", width, spec, met))
            if self.judges("directional"):
                spec = np.broadcast_to(
                    np.asarray(directional_threshold_px, np.float64), width.shape
                )
                if directional_px is None:
                    criteria.append(
                        Criterion("directional", unmeasured, spec, unmet, measured=False)
                    )
                else:
                    # NaN in any bin (a failed measure) makes the widest NaN: not met.
                    widest = np.max(np.asarray(directional_px, dtype=np.float64), axis=-1)
                    criteria.append(Criterion("directional", widest, spec, widest <= spec))
            if self.judges("wobble"):
                spec = np.full(width.shape, self.wobble_spec_px)
                if wobble_px is None:
                    criteria.append(Criterion("wobble", unmeasured, spec, unmet, measured=False))
                else:
                    shift = np.hypot(*np.moveaxis(np.asarray(wobble_px, dtype=np.float64), -1, 0))
                    criteria.append(Criterion("wobble", shift, spec, shift <= spec))
        return criteria

    def within_spec(
        self,
        width_px: np.ndarray,
        width_threshold_px: np.ndarray,
        directional_px: np.ndarray | None = None,
        directional_threshold_px: np.ndarray | None = None,
        wobble_px: np.ndarray | None = None,
    ) -> np.ndarray:
        """Whether each measurement meets every judged spec of the task (`judge`, batched
        alike); NaN anywhere, a failed measure, is not within."""
        criteria = self.judge(
            width_px, width_threshold_px, directional_px, directional_threshold_px, wobble_px
        )
        within = np.ones(np.shape(width_px), bool)
        for criterion in criteria:
            within &= criterion.met
        return within

    def check_apparatus(self, knobs: Mapping[str, tuple[float, float]]) -> None:
        """Refuse an apparatus that lacks one of the task's knobs."""
        missing = [knob for knob in self.knobs if knob not in knobs]
        if missing:
            have = ", ".join(sorted(knobs)) or "none"
            raise ValueError(
                f"task {self.name!r} needs knob(s) {', '.join(missing)}; the apparatus has {have}"
            )

    def step_sizes(self, knobs: Mapping[str, tuple[float, float]]) -> tuple[float, ...]:
        """Largest change per action of each task knob, in the apparatus's units."""
        self.check_apparatus(knobs)
        return tuple(
            float(self.max_step.get(k, self.max_step_fraction * (knobs[k][1] - knobs[k][0])))
            for k in self.knobs
        )


# The options that ask that posterior, at their defaults (each needs finish_at_posterior)
POSTERIOR_OPTIONS = {
    option.name: option.default
    for option in dataclasses.fields(Task)
    if option.name in ("stop_when_sure", "probe_until_sure") or option.name.startswith("posterior_")
}

TASKS: dict[str, Task] = {
    "focus": Task(name="focus", knobs=("defocus",)),
    # Stigmators only, focus aligned: the mean width shows how far off, the directional
    # widths (of a slightly defocused probe) which way.
    "stigmation": Task(
        name="stigmation",
        knobs=("stigmator_x", "stigmator_y"),
        measures=("width", "directional"),
        episode_steps=12,
    ),
    # The aperture only: each step is an image and a wobble pair (three acquisitions), so a
    # step may cross the whole interval: one wobble says where the centre is.
    "aperture": Task(
        name="aperture",
        knobs=("aperture_x", "aperture_y"),
        measures=("width", "wobble"),
        max_step_fraction=1.0,
        episode_steps=8,
    ),
    # The whole column, in the order an operator works: aperture, focus, stigmators.
    "column": Task(
        name="column",
        knobs=("aperture_x", "aperture_y", "defocus", "stigmator_x", "stigmator_y"),
        measures=("width", "directional", "wobble"),
        max_step_fraction=0.5,
        episode_steps=20,
    ),
    # The column in two stages, each meeting the column as it is at that point (`context`):
    # 1. the aperture, with the stigmators anywhere in their interval, and the focus, since a
    #    wobble is only as precise as its frames are sharp (its scatter grows with the probe,
    #    docs/physics.md; aperture first with the defocus anywhere missed a quarter of the
    #    columns, all far out of focus). Judged on the wobble alone: the stigmators, and with
    #    them the width, are the next stage's.
    "column-focus-aperture": Task(
        name="column-focus-aperture",
        knobs=("defocus", "aperture_x", "aperture_y"),
        measures=("width", "wobble"),
        max_step={"defocus": 25.0},
        max_step_fraction=1.0,
        episode_steps=10,
        context={"stigmator_x": 200.0, "stigmator_y": 200.0},
        judged=("wobble",),
    ),
    # 2. the focus and the stigmators together, refocusing while stigmating as an operator
    #    does, with the aperture as stage 1 leaves it (within 2.5 um of the axis: a wobble
    #    shift within its 0.5 px spec is 2.7 um on `synthetic`), and the focus near: within
    #    40 V (stage 1 is judged on its wobble and focuses on the way; run twice it left the
    #    defocus within 12 V of focus for 90 % of 200 columns, 36 V at worst).
    "column-focus-stigmation": Task(
        name="column-focus-stigmation",
        knobs=("defocus", "stigmator_x", "stigmator_y"),
        measures=("width", "directional"),
        episode_steps=16,
        context={"aperture_x": 2.5, "aperture_y": 2.5},
        start_reach={"defocus": 40.0},
    ),
}


def get_task(name: str) -> Task:
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(
            f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}"
        ) from None

"""What a policy card (card.json) holds, and `check_card`, which reads one back strictly.

A card is data from a file, so nothing in it is believed unchecked: every field has its
type and range, the fields agree with each other (the knobs' steps with the task's rule, the
shapes with the member), and the thresholds it is judged on may tighten the task's own spec,
never loosen it. The knob intervals it lists are those the policy was trained on, for the
record: the shield's limits always come from the apparatus and the site limits. The record
of its evaluations is read for what it claims: the kind of session (validation or test) and
intervals that are rates. The card is written by alignrl.deploy.card (keys documented in
docs/deploy.md).

Knob values and steps are in the apparatus's units (volts for a lens); edge widths in pixels.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from alignrl.agents.agent import MemberSpec
from alignrl.apparatus.family_box import PHYSICAL
from alignrl.deploy.formats import EXPORT_FORMATS, ONNX_OPSET
from alignrl.deploy.graph import graph_signature
from alignrl.envs.core import feature_layout
from alignrl.envs.task import Task
from alignrl.evaluation.report import SESSION_KINDS
from alignrl.runs.sources import MAX_CARD_BYTES, ExportError, read_card_file

__all__ = [
    "CARD_FORMAT",
    "CARD_KEYS",
    "MAX_CARD_BYTES",
    "card_action",
    "card_feature_layout",
    "check_card",
    "read_card",
]

CARD_FORMAT = "alignrl-policy-card-1"  # card.json's "format": which keys it has and means

# The top-level keys of card.json, all always present (null where they do not apply);
# cards written before policy_sha256 existed (the shipped champions) lack it.
CARD_KEYS = (
    "format",
    "policy_file",
    "export_format",
    "policy_sha256",
    "created",
    "alignrl_version",
    "torch_version",
    "onnx_opset",
    "command",
    "member",
    "source",
    "task",
    "knobs",
    "history",
    "features",
    "feature_layout",
    "inputs",
    "outputs",
    "action",
    "normalisation",
    "memory",
    "training",
    "evaluations",
    "parity",
    "lineage",
)


def card_action(knobs: int) -> dict[str, Any]:
    """card.json's `action` of a policy of `knobs` knobs."""
    return {
        "size": knobs + 1,
        "knob_actions": list(range(knobs)),
        "stop_index": knobs,
        "stop_when": f"action[{knobs}] > 0",
        "range": [-1.0, 1.0],
        "deterministic": "tanh(mean of the policy), clipped to [-1, 1]",
    }


def card_feature_layout(knobs: int, extra_features: int) -> dict[str, list[int]]:
    """card.json's `feature_layout`: each feature's [start, stop) in a history row."""
    layout = feature_layout(knobs, extra_features)
    return {name: [part.start, part.stop] for name, part in layout.items()}


# --- reading a card back ----------------------------------------------------------------

OPTIONAL_CARD_KEYS = ("policy_sha256",)  # absent from cards written before it existed
MEMBER_CARD_KEYS = (
    *(field.name for field in dataclasses.fields(MemberSpec)),
    "architecture",
    "encoder",
    "steps_seen",
    "updates",
)
TASK_CARD_KEYS = ("name", "options", "knobs", "episode_steps", "success")
KNOB_CARD_KEYS = ("name", "low", "high", "max_step")
MEMORY_CARD_KEYS = ("kind", "length", "layers", "d_model", "note")
MAX_HISTORY = 4096  # rows of history: far beyond any encoder we train
MAX_EPISODE_STEPS = 1000  # an alignment of more steps is no alignment (the column task: 20)
MAX_STEP_FRACTION = 1.0  # one action moves a knob at most across its whole interval
# An absolute spec wider than this is no spec: the sharpest edge of the simulated columns is
# 2.56 px, a frame without edges counts as 25 px (Task.no_edges_px).
MAX_ABSOLUTE_SPEC_PX = 10.0
STEP_AGREEMENT = 1e-6  # relative: a card's max_step is its task's rule on its interval
# Knob values a card may name: an instrument family's interval centres and widths
# (PHYSICAL), an interval of the widest width at the farthest centre.
MAX_KNOB_VALUE = PHYSICAL["interval_centre"][1] + 0.5 * PHYSICAL["interval_width"][1]
# Task options that set a judged spec, and the Task field each one sets: a card may make
# them stricter than the task's own values, never looser.
JUDGED_OPTIONS = {
    "success_relative": ("success.relative", lambda task: task.success.relative),
    "directional_relative": ("directional_relative", lambda task: task.directional_relative),
    "wobble_spec_px": ("wobble_spec_px", lambda task: task.wobble_spec_px),
}


class _CardReader:
    """Strict reading of one card.json: each failure an ExportError naming the file and the
    field ("exports/x/card.json: knobs[0].max_step is 1e+09, ...")."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, field: str, problem: str) -> ExportError:
        return ExportError(f"{self.path}: {field} {problem}")

    def mapping(
        self, value: Any, field: str, keys: tuple[str, ...], optional: tuple[str, ...] = ()
    ) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(field, f"is a {type(value).__name__}, where a mapping belongs")
        missing = [key for key in keys if key not in value and key not in optional]
        if missing:
            raise ExportError(
                f"{self.path} is incomplete or inconsistent: {field} has no key {missing[0]!r}"
            )
        unknown = sorted(set(map(str, value)) - set(keys))
        if unknown:
            raise self.fail(
                field,
                f"has unknown key(s) {', '.join(map(repr, unknown))}; a card holds only "
                f"{', '.join(keys)}",
            )
        return value

    def number(
        self,
        value: Any,
        field: str,
        *,
        above: float | None = None,
        at_least: float | None = None,
        at_most: float | None = None,
    ) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(field, f"is {_shown(value)}, not a number")
        try:
            value = float(value)
        except OverflowError:  # an integer of hundreds of digits
            raise self.fail(field, f"is a number of {len(str(value))} digits") from None
        if not math.isfinite(value):
            raise self.fail(field, f"is {value}, not a finite number")
        if above is not None and not value > above:
            raise self.fail(field, f"is {value:g}: it must be more than {above:g}")
        if at_least is not None and not value >= at_least:
            raise self.fail(field, f"is {value:g}: it must be at least {at_least:g}")
        if at_most is not None and not value <= at_most:
            raise self.fail(field, f"is {value:g}: it must be at most {at_most:g}")
        return float(value)

    def integer(self, value: Any, field: str, low: int, high: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(field, f"is {_shown(value)}, not a whole number")
        if not low <= value <= high:
            raise self.fail(field, f"is {value}: it must be from {low} to {high}")
        return value

    def text(self, value: Any, field: str, nullable: bool = False) -> str | None:
        if value is None and nullable:
            return None
        if not isinstance(value, str):
            raise self.fail(field, f"is {_shown(value)}, not a string")
        return value

    def equal(self, value: Any, expected: Any, field: str, why: str) -> None:
        if value != expected:
            raise self.fail(field, f"is {_shown(value)}, where {why} gives {_shown(expected)}")


def _shown(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, float) else f"{value:g}"
    return text if len(text) <= 120 else text[:117] + "..."


def check_card(card: Any, path: Path) -> Task:
    """A card.json's content, checked strictly, and the Task it describes (the one its
    policy acts on and is judged on). ExportError naming `path` and the first field that is
    missing, unknown, of the wrong type, out of range, looser than the task's own spec, or
    at odds with another field."""
    read = _CardReader(path)
    if not isinstance(card, dict) or card.get("format") != CARD_FORMAT:
        found = card.get("format") if isinstance(card, dict) else type(card).__name__
        raise ExportError(f"{path}: card format {found!r} is not {CARD_FORMAT}")
    read.mapping(card, "card", CARD_KEYS, OPTIONAL_CARD_KEYS)
    export_format = read.text(card["export_format"], "export_format")
    if export_format not in EXPORT_FORMATS:
        raise read.fail(
            "export_format", f"{export_format!r} is not one of {', '.join(EXPORT_FORMATS)}"
        )
    read.equal(
        card["policy_file"], EXPORT_FORMATS[export_format], "policy_file", "its export_format"
    )
    digest = card.get("policy_sha256")
    if digest is not None and not (
        isinstance(digest, str) and len(digest) == 64 and set(digest) <= set("0123456789abcdef")
    ):
        raise read.fail("policy_sha256", f"is {_shown(digest)}, not a SHA-256 in hex")
    for name in ("created", "alignrl_version", "torch_version", "normalisation"):
        read.text(card[name], name)
    read.text(card["command"], "command", nullable=True)
    read.equal(
        card["onnx_opset"],
        ONNX_OPSET if export_format == "onnx" else None,
        "onnx_opset",
        "its export_format",
    )
    for name in ("source", "training", "evaluations", "parity", "lineage"):  # the record
        if not isinstance(card[name], dict):
            raise read.fail(name, f"is a {type(card[name]).__name__}, where a mapping belongs")
    if card["parity"].get("passed") is not True:
        raise read.fail("parity.passed", "is not true: an export that failed parity is no policy")
    _evaluations(read, card["evaluations"])

    task = _task(read, card["task"])
    spec = _member(read, card["member"])
    knobs = len(task.knobs)
    history = read.integer(card["history"], "history", 1, MAX_HISTORY)
    features = read.integer(card["features"], "features", 1, MAX_HISTORY)
    read.equal(features, 5 + 2 * knobs + task.extra_features, "features", f"task {task.name!r}")
    read.equal(
        spec.observation_shape,
        (history, features),
        "member.observation_shape",
        "history and features",
    )
    read.equal(
        spec.action_dim, knobs + 1, "member.action_dim", f"task {task.name!r}'s {knobs} knob(s)"
    )
    layout = card_feature_layout(knobs, task.extra_features)
    read.equal(card["feature_layout"], layout, "feature_layout", f"task {task.name!r}")
    read.equal(
        card["action"], card_action(knobs), "action", f"task {task.name!r}'s {knobs} knob(s)"
    )
    _knobs(read, card["knobs"], task)
    # The history window is every policy's whole memory (no Transformer-XL memory since
    # issue 61); the section stays in the card's format with this one content.
    memory = read.mapping(card["memory"], "memory", MEMORY_CARD_KEYS)
    read.equal(memory["kind"], "history-window", "memory.kind", "a policy without memory")
    for key in ("length", "layers", "d_model"):
        read.integer(memory[key], f"memory.{key}", 0, 0)
    read.text(memory["note"], "memory.note")
    signature = graph_signature(history, features, knobs)
    read.equal(card["inputs"], signature["inputs"], "inputs", "history and features")
    read.equal(card["outputs"], signature["outputs"], "outputs", "history and features")
    return task


def read_card(path: Path) -> tuple[dict[str, Any], Task]:
    """card.json at `path` as every reader reads it (alignrl.runs.sources.read_card_file: at
    most MAX_CARD_BYTES, refused by its size before it is parsed; no key twice in one object;
    no deeper than a card nests; posterior settings within physical bounds), then checked
    field by field (`check_card`): the card and the Task it describes. ExportError naming the
    file and what is wrong."""
    card = read_card_file(path)
    return card, check_card(card, path)


def _evaluations(read: _CardReader, evaluations: dict[str, Any]) -> None:
    """What the evaluations claim, where the card says it (older cards do not): the kind of
    session, the interval's confidence, and each row's interval (rates, low <= high), the
    session the checkpoint was chosen on among them."""
    session = evaluations.get("session")
    if session is not None and session not in SESSION_KINDS:
        kinds = " or ".join(SESSION_KINDS)
        raise read.fail("evaluations.session", f"is {_shown(session)}, not {kinds}")
    if "confidence" in evaluations:
        read.number(evaluations["confidence"], "evaluations.confidence", above=0, at_most=1)
    rows = evaluations.get("rows", [])
    if not isinstance(rows, list):
        raise read.fail("evaluations.rows", f"is a {type(rows).__name__}, not a list")
    chosen = evaluations.get("chosen_on")
    named = [(f"evaluations.rows[{index}]", row) for index, row in enumerate(rows)]
    for field, row in [*named, *([("evaluations.chosen_on", chosen)] if chosen else [])]:
        if not isinstance(row, dict):
            raise read.fail(field, f"is a {type(row).__name__}, where a mapping belongs")
        if "success_low" in row or "success_high" in row:
            low = read.number(row.get("success_low"), f"{field}.success_low", at_least=0)
            read.number(row.get("success_high"), f"{field}.success_high", at_least=low, at_most=1)


def _member(read: _CardReader, member: Any) -> MemberSpec:
    member = read.mapping(member, "member", MEMBER_CARD_KEYS)
    try:
        spec = MemberSpec.from_dict(
            {f.name: member[f.name] for f in dataclasses.fields(MemberSpec)}
        )
    except (TypeError, ValueError) as error:
        raise read.fail("member", f"is not a member spec: {error}") from None
    if spec.team != "aligner":
        raise read.fail("member.team", f"is {spec.team!r}: only an aligner is a policy")
    read.equal(
        member["architecture"], spec.architecture, "member.architecture", "member.hyperparameters"
    )
    read.equal(member["encoder"], spec.encoder, "member.encoder", "member.hyperparameters")
    for name in ("steps_seen", "updates"):
        read.integer(member[name], f"member.{name}", 0, 1 << 62)
    return spec


def _task(read: _CardReader, entry: Any) -> Task:
    """The task the card describes: its registry task with the card's options, which must
    keep the step within one interval and the judged spec as strict as the task's own."""
    from pydantic import ValidationError

    from alignrl.config.task_options import TaskOptions
    from alignrl.envs.task import get_task

    entry = read.mapping(entry, "task", TASK_CARD_KEYS)
    name = read.text(entry["name"], "task.name")
    try:
        own = get_task(str(name))
    except ValueError as error:
        raise read.fail("task.name", f"names no task: {error}") from None
    if not isinstance(entry["options"], dict):
        raise read.fail("task.options", f"is a {type(entry['options']).__name__}, not a mapping")
    _posterior_options(read, entry["options"])
    try:
        options = TaskOptions(**entry["options"])
        task = options.apply(own)
    except ValidationError as error:
        problem = error.errors()[0]
        where = ".".join(str(part) for part in problem["loc"])
        raise read.fail(f"task.options.{where}", f"is refused: {problem['msg']}") from None
    except (TypeError, ValueError) as error:
        raise read.fail("task.options", f"is refused: {error}") from None
    if options.max_step_fraction is not None:
        read.number(
            options.max_step_fraction,
            "task.options.max_step_fraction",
            above=0,
            at_most=MAX_STEP_FRACTION,
        )
    read.integer(task.episode_steps, "task.options.episode_steps", 1, MAX_EPISODE_STEPS)
    for option, (field, value_of) in JUDGED_OPTIONS.items():
        value = getattr(options, option)
        if value is not None and not value <= value_of(own):
            raise read.fail(
                f"task.options.{option}",
                f"is {value:g}, looser than task {own.name!r}'s own {field} {value_of(own):g}: "
                "a card may tighten the spec its policy is judged on, never loosen it",
            )
    absolute = options.success_absolute_px
    if absolute is not None:
        bound = own.success.absolute_px or MAX_ABSOLUTE_SPEC_PX
        read.number(absolute, "task.options.success_absolute_px", above=0, at_most=bound)
    read.equal(entry["knobs"], list(task.knobs), "task.knobs", f"task {name!r}")
    read.equal(entry["episode_steps"], task.episode_steps, "task.episode_steps", "task.options")
    success = {"relative": task.success.relative, "absolute_px": task.success.absolute_px}
    read.mapping(entry["success"], "task.success", ("relative", "absolute_px"))
    read.equal(entry["success"], success, "task.success", f"task {name!r} with task.options")
    return task


def _posterior_options(read: _CardReader, options: dict[str, Any]) -> None:
    """The posterior settings of a card's task options inside what an instrument family can
    give them (alignrl.posterior.calibration.posterior_options_problem: a calibrated column's
    every parameter, where its readings level off); the far noise, draws and chances are
    bounded by TaskOptions itself."""
    from alignrl.posterior.calibration import posterior_options_problem

    bound = posterior_options_problem(options)
    if bound is not None:
        raise read.fail(f"task.options.{bound[0]}", bound[1])


def _knobs(read: _CardReader, knobs: Any, task: Task) -> None:
    """Each knob's interval (what it was trained on) and max_step, which must be the task's
    step on that interval and not more than the interval's width."""
    if not isinstance(knobs, list) or len(knobs) != len(task.knobs):
        count = len(knobs) if isinstance(knobs, list) else _shown(knobs)
        raise read.fail("knobs", f"lists {count} knob(s); task {task.name!r} has {len(task.knobs)}")
    for index, (knob, name) in enumerate(zip(knobs, task.knobs, strict=True)):
        field = f"knobs[{index}]"
        read.mapping(knob, field, KNOB_CARD_KEYS)
        read.equal(knob["name"], name, f"{field}.name", f"task {task.name!r}")
        low = read.number(knob["low"], f"{field}.low", at_least=-MAX_KNOB_VALUE)
        high = read.number(knob["high"], f"{field}.high", above=low, at_most=MAX_KNOB_VALUE)
        width = high - low
        if width > PHYSICAL["interval_width"][1]:
            raise read.fail(
                field,
                f"({name}) is [{low:g}, {high:g}], {width:g} wide: wider than any "
                f"instrument's, at most {PHYSICAL['interval_width'][1]:g} knob units",
            )
        step = read.number(knob["max_step"], f"{field}.max_step", above=0)
        if step > width:
            raise read.fail(
                f"{field}.max_step",
                f"({name}) is {step:g}, more than the width {width:g} of its interval "
                f"[{low:g}, {high:g}]: one action never moves a knob further than that",
            )
        rule = float(task.max_step.get(name, task.max_step_fraction * width))
        if abs(step - rule) > STEP_AGREEMENT * max(abs(rule), 1.0):
            raise read.fail(
                f"{field}.max_step",
                f"({name}) is {step:g}, but task {task.name!r} steps {rule:g} on the interval "
                f"[{low:g}, {high:g}]: the card's interval or step was changed after the export",
            )

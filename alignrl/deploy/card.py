"""The model card of an exported policy: what the policy is, what it was trained and judged
on, and how to feed it, as `card.json` (for machines, keys in docs/deploy.md) and
`model_card.md` (the same for a person).

Knob values and steps are in the apparatus's units (volts for a lens); edge widths in pixels.
"""

from __future__ import annotations

import csv
import datetime
import json
import math
import shlex
from pathlib import Path
from typing import Any

import torch

from alignrl import __version__
from alignrl.deploy.export import (
    CARD_FORMAT,
    EXPORT_FORMATS,
    ONNX_OPSET,
    Parity,
    PolicyGraph,
    PolicySource,
)
from alignrl.envs.core import feature_layout
from alignrl.training import EVALUATION_SEED

__all__ = ["CARD_KEYS", "build_card", "read_rows", "render_model_card"]

# The top-level keys of card.json, all always present (null where they do not apply).
CARD_KEYS = (
    "format",
    "policy_file",
    "export_format",
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

# Task options that change what an evaluation session does (the others shape rewards only).
SESSION_TASK_OPTIONS = (
    "episode_steps",
    "max_step_fraction",
    "success_relative",
    "success_absolute_px",
)
NORMALISATION = (
    "none inside the policy: the history is fed exactly as the env produces it "
    "(alignrl/envs/core.py scales every feature), as Agent.act does; the action is "
    "tanh(mean), clipped to [-1, 1], and knob_step = action[:k] x max_step"
)


def read_rows(path: Path) -> list[dict[str, Any]]:
    """A metrics CSV as rows, numbers parsed (int where whole); [] where there is no file."""
    if not path.exists():
        return []
    with path.open(newline="") as handle:
        return [
            {key: _number(value) for key, value in row.items()} for row in csv.DictReader(handle)
        ]


def _number(text: str | None) -> Any:
    if text is None or text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        return text
    if not math.isfinite(value):  # card.json stays strict JSON: nan and inf stay text
        return text
    return int(value) if value.is_integer() and "." not in text and "e" not in text else value


def _today() -> str:
    """Now, UTC, to the second (the card's date)."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _memory(graph: PolicyGraph) -> dict[str, Any]:
    if not graph.memory_length:
        return {
            "kind": "history-window",
            "length": 0,
            "layers": 0,
            "d_model": 0,
            "note": f"the history window of {graph.history} rows is the policy's whole "
            "memory: nothing is carried from one call to the next",
        }
    return {
        "kind": "transformer-xl",
        "length": graph.memory_length,
        "layers": graph.memory_layers,
        "d_model": graph.encoder.d_model,
        "note": "feed memory_out_* and memory_valid_out back as memory_in_* and "
        "memory_valid_in at the next step, zeros at the start of each alignment; zeros at "
        "every step give Agent.act's actions, as the member was trained and evaluated",
    }


def _evaluations(source: PolicySource) -> dict[str, Any]:
    config, member = source.config, source.agent.id
    if source.run_dir is None:
        return {"source": None, "produced_by": None, "command": None, "note": None, "rows": []}
    path = source.run_dir / "metrics" / "evaluations.csv"
    rows = read_rows(path)
    if source.kind == "league":
        rows = [row for row in rows if str(row.get("member")) == member]
        scenarios = config.schedule.eval_scenarios
        produced_by = (
            f"alignrl league run ({source.run_dir}): an evaluation session of {scenarios} "
            f"held-out scenarios on {config.eval_apparatus} every "
            f"{config.schedule.evaluate_every} iterations, for the best rated aligners"
        )
    else:
        scenarios = config.budget.eval_scenarios
        produced_by = (
            f"alignrl train ({source.run_dir}): an evaluation session of {scenarios} held-out "
            f"scenarios on {config.eval_apparatus} every {config.budget.eval_every} env steps"
        )
    command = shlex.join(
        [
            *("alignrl", "evaluate", "--policy", str(source.member_file)),
            *("--apparatus", config.eval_apparatus),
            *("--apparatus-args", json.dumps(config.eval_apparatus_args, sort_keys=True)),
            *("--task", config.task, "--scenarios", str(scenarios)),
            *("--seed", str(EVALUATION_SEED)),
        ]
    )
    options = {
        name: value
        for name, value in config.task_options.model_dump(exclude_none=True).items()
        if name in SESSION_TASK_OPTIONS
    }
    note = (
        f"the run's task options {json.dumps(options, sort_keys=True)} change an evaluation "
        "session but are not options of alignrl evaluate: the command runs the task's defaults"
        if options
        else None
    )
    return {
        "source": str(path) if path.exists() else None,
        "produced_by": produced_by,
        "command": command,
        "note": note,
        "rows": rows,
    }


def _lineage(source: PolicySource) -> dict[str, Any]:
    """The member's parent and the population-based-training copies that led to it."""
    copies: list[dict[str, Any]] = []
    if source.run_dir is not None and source.kind == "league":
        rows = read_rows(source.run_dir / "metrics" / "lineage.csv")
        current, seen = source.agent.id, set()
        while current not in seen:
            seen.add(current)
            row = next((r for r in reversed(rows) if str(r.get("member")) == current), None)
            if row is None:
                break
            copies.append(row)
            current = str(row.get("parent"))
    return {"parent": source.agent.spec.parent, "copies": copies}


def build_card(
    source: PolicySource,
    graph: PolicyGraph,
    knobs: list[dict[str, Any]],
    export_format: str,
    parity: Parity,
    command: str | None = None,
) -> dict[str, Any]:
    """card.json of an export (keys: CARD_KEYS, documented in docs/deploy.md)."""
    agent, config, task = source.agent, source.config, source.task
    spec = agent.spec
    signature = graph.signature()
    k = graph.knobs
    card = {
        "format": CARD_FORMAT,
        "policy_file": EXPORT_FORMATS[export_format],
        "export_format": export_format,
        "created": _today(),
        "alignrl_version": __version__,
        "torch_version": torch.__version__,
        "onnx_opset": ONNX_OPSET if export_format == "onnx" else None,
        "command": command,
        "member": {
            **spec.to_dict(),  # the whole MemberSpec: a safetensors policy is rebuilt from it
            "architecture": spec.architecture,
            "encoder": spec.encoder,
            "steps_seen": agent.steps_seen,
            "updates": agent.updates,
        },
        "source": {
            "kind": source.kind,
            "chosen_as": source.chosen_as,
            "run": str(source.run_dir) if source.run_dir else None,
            "member_file": str(source.member_file),
            "config_file": str(source.config_file) if source.config_file else None,
        },
        "task": {
            "name": task.name,
            "options": config.task_options.model_dump(exclude_none=True),
            "knobs": list(task.knobs),
            "episode_steps": task.episode_steps,
            "success": {
                "relative": task.success.relative,
                "absolute_px": task.success.absolute_px,
            },
        },
        "knobs": knobs,
        "history": graph.history,
        "features": graph.features,
        "feature_layout": {
            name: [part.start, part.stop]
            for name, part in feature_layout(k, task.extra_features).items()
        },
        "inputs": signature["inputs"],
        "outputs": signature["outputs"],
        "action": {
            "size": k + 1,
            "knob_actions": list(range(k)),
            "stop_index": k,
            "stop_when": f"action[{k}] > 0",
            "range": [-1.0, 1.0],
            "deterministic": "tanh(mean of the policy), clipped to [-1, 1]",
        },
        "normalisation": NORMALISATION,
        "memory": _memory(graph),
        "training": {
            "apparatus": config.apparatus,
            "apparatus_args": config.apparatus_args,
            "eval_apparatus": config.eval_apparatus,
            "eval_apparatus_args": config.eval_apparatus_args,
            "settings": "run config" if source.config_file else "defaults (no run config found)",
            "steps_seen": agent.steps_seen,
            "updates": agent.updates,
            "env_steps": source.env_steps,
            "league_iteration": (source.best or {}).get("iteration"),
            "adapted_on": [],
        },
        "evaluations": _evaluations(source),
        "parity": parity.to_dict(),
        "lineage": _lineage(source),
    }
    return card


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value).replace("|", "\\|")


def _table(rows: list[dict[str, Any]], columns: list[str]) -> list[str]:
    return [
        "| " + " | ".join(columns) + " |",
        "| " + " | ".join("---" for _ in columns) + " |",
        *("| " + " | ".join(_cell(row.get(c)) for c in columns) + " |" for row in rows),
    ]


def _shape(entry: dict[str, Any]) -> str:
    return "(" + ", ".join(str(size) for size in entry["shape"]) + ")"


def render_model_card(card: dict[str, Any]) -> str:
    """model_card.md: the card for a person, from card.json's values."""
    member, training, task = card["member"], card["training"], card["task"]
    evaluations, parity, lineage = card["evaluations"], card["parity"], card["lineage"]
    lines = [
        f"# Model card: {member['id']}",
        "",
        f"An aligner of task `{task['name']}` (knobs: {', '.join(task['knobs'])}): "
        f"{member['algorithm'].upper()} with a {member['architecture']} history encoder, "
        f"exported as {card['export_format']} (`{card['policy_file']}`) on {card['created']} "
        f"by alignrl {card['alignrl_version']} (torch {card['torch_version']}).",
        "",
        f"- source: {card['source']['kind']} `{card['source']['member_file']}` "
        f"({card['source']['chosen_as']})",
        f"- exported with: `{card['command']}`" if card["command"] else "- exported from Python",
        "",
        "## Inputs and outputs",
        "",
        "| name | direction | dtype | shape |",
        "| --- | --- | --- | --- |",
        *(
            f"| `{entry['name']}` | {side} | {entry['dtype']} | {_shape(entry)} |"
            for side in ("inputs", "outputs")
            for entry in card[side]
        ),
        "",
        f"`history` is the env's history, oldest row first, zero padding in front; each row "
        f"is {card['features']} features laid out as "
        + ", ".join(f"{name} [{a}:{b}]" for name, (a, b) in card["feature_layout"].items())
        + f". `action` is in [-1, 1]: one value per knob, then the stop component "
        f"({card['action']['stop_when']} stops). `knob_step` is the knob change asked for, "
        "in the apparatus's units.",
        "",
        f"Normalisation: {card['normalisation']}.",
        "",
        f"Memory: {card['memory']['note']}.",
        "",
        "## Knobs and limits",
        "",
        *_table(card["knobs"], ["name", "low", "high", "max_step"]),
        "",
        f"Episodes last at most {task['episode_steps']} steps; an alignment succeeds at "
        + (
            f"an edge width of {task['success']['absolute_px']:g} px or less."
            if task["success"]["absolute_px"]
            else f"{task['success']['relative']:g} x the best edge width the apparatus reaches."
        ),
        "",
        "## Training",
        "",
        f"- apparatus: `{training['apparatus']}` {json.dumps(training['apparatus_args'])}",
        f"- evaluated on: `{training['eval_apparatus']}` "
        f"{json.dumps(training['eval_apparatus_args'])}",
        f"- settings: {training['settings']}"
        + (f" (`{card['source']['config_file']}`)" if card["source"]["config_file"] else ""),
        f"- task options: {json.dumps(task['options']) if task['options'] else 'none'}",
        f"- transitions seen: {training['steps_seen']}, learner updates: {training['updates']}",
    ]
    if training["env_steps"] is not None:
        lines.append(f"- env steps at the exported checkpoint: {training['env_steps']}")
    if training["league_iteration"] is not None:
        lines.append(f"- league iteration of its best evaluation: {training['league_iteration']}")
    adapted = training["adapted_on"]
    lines += [f"- adapted on: {json.dumps(adapted) if adapted else 'nothing yet'}", ""]
    lines += ["## Evaluations", ""]
    if evaluations["rows"]:
        columns = list(evaluations["rows"][0])
        lines += [
            f"From `{evaluations['source']}`, written by {evaluations['produced_by']}.",
            "",
            *_table(evaluations["rows"], columns),
            "",
            "The same session on the exported weights:",
            "",
            "```",
            evaluations["command"],
            "```",
        ]
        if evaluations["note"]:
            lines += ["", f"Note: {evaluations['note']}."]
    else:
        lines.append("No evaluation session recorded for this member.")
    lines += [
        "",
        "## Parity",
        "",
        f"The written file, run by {parity['runtime']}, against {parity['reference']} on "
        f"{parity['histories']} random histories: max |difference| "
        f"{parity['max_abs_difference']:.3g} (action), "
        f"{parity['knob_step_max_abs_difference']:.3g} (knob_step)"
        + (
            f", {parity['memory_max_abs_difference']:.3g} (with random memory)"
            if parity["memory_max_abs_difference"] is not None
            else ""
        )
        + f"; allowed {parity['tolerance']:g} (action) and {parity['knob_step_tolerance']:g} "
        "(knob_step: the same allowance times the largest max_step).",
        "",
        "## Lineage",
        "",
        f"Parent: {lineage['parent'] or 'none (a starting member)'}.",
    ]
    if lineage["copies"]:
        lines += ["", *_table(lineage["copies"], list(lineage["copies"][0]))]
    return "\n".join(lines) + "\n"

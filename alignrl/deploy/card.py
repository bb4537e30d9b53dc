"""The card of an exported policy, written: `build_card` gives card.json (for machines, keys
in docs/deploy.md) of a source and its export: what the policy is, what it was trained and
judged on (a run's evaluation sessions, its lineage), and how to feed it. What a card holds
and its strict reading back are in alignrl.deploy.card_schema (`check_card`); the same card
for a person, model_card.md, in alignrl.deploy.model_card (`render_model_card`).

An export of an export (a shipped champion, a folder `alignrl export` wrote) keeps the record
of the card it came with: its evaluations, lineage and training history.

The evaluations a card records are a run's own periodic sessions, those its best checkpoint
and its champion are chosen on: *validation* sessions (`evaluations.session`), whose best
figure flatters what it chose. The card says so, names the session the exported checkpoint
was chosen on (`evaluations.chosen_on`, where it was chosen by one), and gives every session's
successes with their 95 % Wilson interval (`success_low`, `success_high`: rates). A test
figure comes from a session that chose nothing: `alignrl evaluate` (docs/evaluation.md).

Knob values and steps are in the apparatus's units (volts for a lens); edge widths in pixels.
"""

from __future__ import annotations

import csv
import datetime
import json
import math
import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from alignrl import __version__
from alignrl.deploy.card_schema import (
    CARD_FORMAT,
    CARD_KEYS,
    card_action,
    card_feature_layout,
    check_card,
)
from alignrl.deploy.formats import EXPORT_FORMATS, ONNX_OPSET
from alignrl.deploy.graph import PolicyGraph
from alignrl.deploy.model_card import render_model_card
from alignrl.deploy.parity import Parity
from alignrl.intervals import CONFIDENCE, wilson
from alignrl.runs.sources import PolicySource
from alignrl.training import EVALUATION_SEED

__all__ = [  # check_card, render_model_card and the keys: re-exported for their importers
    "CARD_FORMAT",
    "CARD_KEYS",
    "build_card",
    "check_card",
    "read_rows",
    "render_model_card",
]

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
    "tanh(mean), clipped to [-1, 1], and knob_step = sign(a) (|a|^p x max_step + f) for a = "
    "action[:k], p the task's action_power and f its move_floor x the knob's interval (1 and "
    "0 unless task.options set them: a x max_step)"
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
    """card.json's `memory`: always the history window (the section stays in the card's
    format; card_schema refuses any other kind)."""
    return {
        "kind": "history-window",
        "length": 0,
        "layers": 0,
        "d_model": 0,
        "note": f"the history window of {graph.history} rows is the policy's whole "
        "memory: nothing is carried from one call to the next",
    }


def _shown(path: Path | str) -> str:
    """A source's path as a card records it: relative to the working directory where it lies
    under it (a card shipped in the package names no machine's folders), else as it is."""
    try:
        return str(Path(path).relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def _recorded(source: PolicySource, key: str) -> dict[str, Any] | None:
    """The part `key` of the card an exported source came with (None for runs and files)."""
    if source.card is None or not isinstance(source.card.get(key), dict):
        return None
    return source.card[key]


def _with_interval(row: Mapping[str, Any]) -> dict[str, Any]:
    """A session's row with the 95 % Wilson interval of its successes (rates), where it
    counts successes out of scenarios."""
    successes, scenarios = row.get("successes"), row.get("scenarios")
    if not (isinstance(successes, int) and isinstance(scenarios, int) and scenarios > 0):
        return dict(row)
    if not 0 <= successes <= scenarios:
        return dict(row)
    low, high = wilson(successes, scenarios)
    return {**row, "success_low": low, "success_high": high}


def _chosen_on(
    rows: list[dict[str, Any]],
    kind: str | None,
    member_file: str,
    iteration: Any,
    env_steps: Any,
) -> dict[str, Any] | None:
    """The row of the session the exported checkpoint was chosen on: a league keeps each
    member's best/ checkpoint from its best session (best.json's iteration), a training run
    its best.pt from its best session (at env_steps). None for any other checkpoint (a
    snapshot, last.pt, a member file outside a run): no session chose it."""
    path = Path(member_file)
    if kind == "league" and path.parent.name == "best":
        key, value = "iteration", iteration
    elif kind == "training" and path.name == "best.pt":
        key, value = "env_steps", env_steps
    else:
        return None
    found = [row for row in rows if value is not None and row.get(key) == value]
    return found[-1] if found else None


def _labelled(evaluations: dict[str, Any], chosen_on: dict[str, Any] | None) -> dict[str, Any]:
    """The evaluations of a card with what they are: validation sessions, each row's
    interval, the session the checkpoint was chosen on. A record that says it already (the
    card of an export) keeps its own."""
    rows = [_with_interval(row) for row in evaluations["rows"]]
    return {
        "session": "validation",
        "confidence": CONFIDENCE,
        **evaluations,
        "rows": rows,
        "chosen_on": evaluations.get("chosen_on", chosen_on and _with_interval(chosen_on)),
    }


def _evaluations(source: PolicySource) -> dict[str, Any]:
    recorded = _recorded(source, "evaluations")
    if recorded is not None:  # an export of an export: the sessions its card records
        card = source.card or {}
        was, training = card.get("source") or {}, card.get("training") or {}
        chosen_on = _chosen_on(
            [dict(row) for row in recorded.get("rows") or []],
            was.get("kind"),
            str(was.get("member_file") or ""),
            training.get("league_iteration"),
            training.get("env_steps"),
        )
        return _labelled(recorded, chosen_on)
    config, member = source.config, source.agent.id
    if source.run_dir is None:
        return _labelled(
            {"source": None, "produced_by": None, "command": None, "note": None, "rows": []},
            None,
        )
    path = source.run_dir / "metrics" / "evaluations.csv"
    rows = read_rows(path)
    sessions = source.sessions
    scenarios = sessions.scenarios if sessions else None
    every = f" every {sessions.every} {sessions.unit}" if sessions else ""
    held = f"{scenarios} held-out scenarios" if scenarios else "held-out scenarios"
    if source.kind == "league":
        rows = [row for row in rows if str(row.get("member")) == member]
        produced_by = (
            f"alignrl league run ({source.run_dir}): an evaluation session of {held} on "
            f"{config.eval_apparatus}{every}, for the best rated aligners"
        )
    else:
        produced_by = (
            f"alignrl train ({source.run_dir}): an evaluation session of {held} on "
            f"{config.eval_apparatus}{every}"
        )
    command = shlex.join(
        [
            *("alignrl", "evaluate", "--policy", str(source.member_file)),
            *("--apparatus", config.eval_apparatus),
            *("--apparatus-args", json.dumps(config.eval_apparatus_args, sort_keys=True)),
            *("--task", config.task),
            *(("--scenarios", str(scenarios)) if scenarios else ()),
            *("--seed", str(EVALUATION_SEED)),
        ]
    )
    options = {
        name: value
        for name, value in config.task_options.model_dump(exclude_none=True).items()
        if name in SESSION_TASK_OPTIONS
    }
    notes = []
    if options:
        notes.append(
            f"the run's task options {json.dumps(options, sort_keys=True)} change an evaluation "
            "session but are not options of alignrl evaluate: the command runs the task's "
            "defaults"
        )
    if source.acting_options:  # RunConfig.acting_options: the sessions acted without them
        notes.append(
            "the run's sessions acted with its training's task options, the policy acts with "
            f"its acting_options {json.dumps(source.acting_options, sort_keys=True)} laid over "
            "them (as the command runs it)"
        )
    note = "; ".join(notes) or None
    chosen_on = _chosen_on(
        rows,
        source.kind,
        str(source.member_file),
        (source.best or {}).get("iteration"),
        source.env_steps,
    )
    evaluations = {
        "source": str(path) if path.exists() else None,
        "produced_by": produced_by,
        "command": command,
        "note": note,
        "rows": rows,
    }
    return _labelled(evaluations, chosen_on)


def _lineage(source: PolicySource) -> dict[str, Any]:
    """The member's parent and the population-based-training copies that led to it."""
    recorded = _recorded(source, "lineage")
    if recorded is not None:
        return recorded
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


def _training(source: PolicySource) -> dict[str, Any]:
    """Where and how long the policy trained (an export's card says it for an export)."""
    config, recorded = source.config, _recorded(source, "training") or {}
    if source.card is not None:
        settings = f"the card of the export it came from ({_shown(source.config_file)})"
    elif source.config_file:
        settings = "run config"
    else:
        settings = "defaults (no run config found)"
    return {
        "apparatus": config.apparatus,
        "apparatus_args": config.apparatus_args,
        "eval_apparatus": config.eval_apparatus,
        "eval_apparatus_args": config.eval_apparatus_args,
        "settings": settings,
        "steps_seen": source.agent.steps_seen,
        "updates": source.updates,
        "env_steps": recorded.get("env_steps", source.env_steps),
        "league_iteration": recorded.get("league_iteration", (source.best or {}).get("iteration")),
        "adapted_on": recorded.get("adapted_on", []),
    }


def build_card(
    source: PolicySource,
    graph: PolicyGraph,
    knobs: list[dict[str, Any]],
    export_format: str,
    parity: Parity,
    command: str | None = None,
    policy_sha256: str | None = None,
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
        "policy_sha256": policy_sha256,
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
            "updates": source.updates,
        },
        "source": {
            "kind": source.kind,
            "chosen_as": source.chosen_as,
            "run": _shown(source.run_dir) if source.run_dir else None,
            "member_file": _shown(source.member_file),
            "config_file": _shown(source.config_file) if source.config_file else None,
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
        "feature_layout": card_feature_layout(k, task.extra_features),
        "inputs": signature["inputs"],
        "outputs": signature["outputs"],
        "action": card_action(k),
        "normalisation": NORMALISATION,
        "memory": _memory(graph),
        "training": _training(source),
        "evaluations": _evaluations(source),
        "parity": parity.to_dict(),
        "lineage": _lineage(source),
    }
    return card

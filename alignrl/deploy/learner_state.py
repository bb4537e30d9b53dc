"""The learner state of an exported aligner, written: `alignrl export --format safetensors
--with-learner-state` puts the member's critics, target critics, entropy coefficient and
optimizers beside its policy, as learner.safetensors and learner.json (no pickle; the format,
and how alignrl.runs.sources reads it back, in alignrl.runs.learner_state).

`write_checked` writes the pair into an export's staging folder and reads it back as a
source would, into a member built afresh from the spec: unless every tensor and every
counter comes back equal to the source's, nothing is published (ExportError).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from alignrl import __version__
from alignrl.agents.agent import Agent
from alignrl.checkpoints import atomic_write_text
from alignrl.deploy.formats import save_tensors, sha256_of
from alignrl.runs.learner_state import (
    LEARNER_FILE,
    LEARNER_FORMAT,
    LEARNER_RECORD,
    POLICY_FILE,
    RUN_KEYS,
    LearnerStateError,
    load_learner_state,
    split_state,
    state_difference,
)
from alignrl.runs.sources import ExportError, PolicySource

__all__ = ["run_record", "write_checked", "write_learner_state"]


def run_record(config: Any, agent: Agent) -> dict[str, Any]:
    """The run settings a source trained with, as plain JSON: the RUN_KEYS of its config
    (a run's, or the one an export's card gives), task_options as those set (as card.json's
    task.options), and its learner (the member's algorithm and hyperparameters)."""
    dumped = config.model_dump(mode="json")
    record = {key: dumped[key] for key in RUN_KEYS if key in dumped}
    if "task_options" in record:  # the options set, as card.json's task.options has them
        record["task_options"] = config.task_options.model_dump(mode="json", exclude_none=True)
    spec = agent.spec
    record["learner"] = {"algorithm": spec.algorithm, **spec.to_dict()["hyperparameters"]}
    return record


def write_learner_state(
    folder: Path,
    agent: Agent,
    run: Mapping[str, Any],
    knobs: list[dict[str, Any]],
    source: Mapping[str, Any],
) -> dict[str, Any]:
    """Write `agent`'s learner state as learner.safetensors and learner.json into `folder`
    (an export's staging folder, which already holds policy.safetensors); the record
    written. `run`: run_record of the source; `knobs`: its knob limits; `source`: where it
    came from (card.json's `source`)."""
    state = agent.state_dict(replay=False)
    try:
        tree, tensors = split_state(state["learner"])
    except LearnerStateError as error:
        raise ExportError(str(error)) from None
    weights = folder / LEARNER_FILE
    save_tensors(weights, tensors, {"format": LEARNER_FORMAT, "member": agent.id})
    record = {
        "format": LEARNER_FORMAT,
        "learner_file": LEARNER_FILE,
        "learner_sha256": sha256_of(weights),
        "policy_file": POLICY_FILE,
        "policy_sha256": sha256_of(folder / POLICY_FILE),
        "member": state["spec"],
        "steps_seen": int(state["steps_seen"]),
        "update_debt": float(state["update_debt"]),
        "updates": int(agent.updates),
        "tensors": len(tensors),
        "state": tree,
        "run": dict(run),
        "knobs": knobs,
        "source": dict(source),
        "written_by": {"alignrl": __version__, "torch": torch.__version__},
    }
    try:
        text = json.dumps(record, indent=2, allow_nan=False)
    except (TypeError, ValueError) as error:  # a run setting JSON cannot hold
        raise ExportError(f"the learner state of {agent.id!r} cannot be written: {error}") from None
    atomic_write_text(folder / LEARNER_RECORD, text + "\n")
    return record


def write_checked(
    source: PolicySource, folder: Path, knobs: list[dict[str, Any]], card: dict[str, Any]
) -> Path:
    """The learner state of `source` written into `folder` (an export's staging folder with
    its policy.safetensors), read back into a member rebuilt from its spec, as
    alignrl.runs.sources reads it, and compared with the source's tensor for tensor; the
    learner.safetensors written. ExportError where anything differs."""
    agent = source.agent
    write_learner_state(folder, agent, run_record(source.config, agent), knobs, card["source"])
    copy = Agent(agent.spec)
    try:
        load_learner_state(folder, copy, card)
    except LearnerStateError as error:
        raise ExportError(f"the learner state written cannot be read back: {error}") from None
    wanted = agent.state_dict(replay=False)
    difference = state_difference(copy.state_dict(replay=False), wanted, "member")
    if difference:
        raise ExportError(f"the learner state written differs from {agent.id!r}'s: {difference}")
    return folder / LEARNER_FILE

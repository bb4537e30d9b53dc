"""Which policy `alignrl align` and `alignrl evaluate` run: one string names any trained
aligner.

* a run directory of `alignrl train`: its `checkpoints/best.pt`;
* a league run directory: its champion, `best/<first member of best/best.json>.pt`;
* a checkpoint file: a league member (`.pt` saved by Agent.save) or a training checkpoint;
* an exported policy: a directory holding `card.json` and `policy.onnx`, `policy.pt` or
  `policy.safetensors`;
* `champion:NAME`: a shipped champion, the exported policy alignrl ships as package data
  (alignrl/champions/NAME/, safetensors: it runs on alignrl's own dependencies).

What a spec names is decided by `alignrl.runs.sources.locate_source`, as for `alignrl
export`, `adapt` and league warm starts, so a run aligns with the same policy, task and
history whether it is exported first or not. An exported folder or a champion runs through
`alignrl.deploy.loading.load_exported` (its card and policy file checked, any runtime); a
run or a checkpoint through the member `resolve_source` loads. Whatever the source, the
result acts the same: `act(history)` maps one history (H, F) of the environments' features
(alignrl/envs/core.py) to one action in [-1, 1]^(k+1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from alignrl.envs.task import Task
from alignrl.runs.sources import Location, PolicySpecError, locate_source, resolve_source

__all__ = ["DeployablePolicy", "PolicySpecError", "load_deployable"]


@dataclass(frozen=True)
class DeployablePolicy:
    """A deterministic aligner ready to run: `act(history (H, F)) -> action (k + 1,)`."""

    name: str
    act: Callable[[np.ndarray], np.ndarray]
    task: Task
    history: int
    source: str  # where it was loaded from, in words (for the audit log and reports)


def _exported(location: Location) -> DeployablePolicy:
    from alignrl.deploy.loading import load_exported  # torch / onnxruntime only when needed

    exported = load_exported(location.path)
    member = exported.card.get("member") or {}
    if location.kind == "champion":
        where = f"shipped champion {location.path.name} ({location.path})"
    else:
        where = f"exported policy {location.spec}"
    return DeployablePolicy(
        name=str(member.get("id") or location.path.name),
        act=exported.act,
        task=exported.task,
        history=int(exported.history),
        source=where,
    )


def _trained(location: Location) -> DeployablePolicy:
    source = resolve_source(location)
    agent = source.agent
    where = f"{source.kind} {source.run_dir}" if source.run_dir else source.kind
    return DeployablePolicy(
        name=agent.id,
        act=lambda history: agent.act(history, deterministic=True),
        task=source.task,
        history=int(source.config.history),
        source=f"{where}: {source.member_file} ({source.chosen_as})",
    )


def load_deployable(spec: str | Location) -> DeployablePolicy:
    """The policy a spec names (see the module docstring). PolicySpecError where it names
    nothing; the loaders' own errors (ExportError, CheckpointError: ValueErrors) where what
    it names is broken."""
    location = spec if isinstance(spec, Location) else locate_source(spec)
    return _exported(location) if location.exported else _trained(location)

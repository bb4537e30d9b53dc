"""Which policy `alignrl align` runs: one string names any trained aligner.

* a run directory of `alignrl train`: its `checkpoints/best.pt`;
* a league run directory: its champion, `best/<first member of best/best.json>.pt`;
* a checkpoint file: a league member (`.pt` saved by Agent.save) or a training checkpoint;
* an exported policy: a directory holding `card.json` and `policy.onnx`, `policy.pt` or
  `policy.safetensors`;
* `champion:NAME`: a shipped champion, the exported policy in populations/champions/NAME/
  (safetensors: it runs on alignrl's own dependencies).

Runs and checkpoint files are resolved as `alignrl export` resolves them
(`alignrl.runs.sources.resolve_source`), so a run aligns with the same policy, task and
history whether it is exported first or not. Whatever the source, the result acts the same:
`act(history)` maps one history (H, F) of the environments' features (alignrl/envs/core.py)
to one action in [-1, 1]^(k+1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from alignrl.envs.task import Task

__all__ = ["CHAMPIONS_DIR", "DeployablePolicy", "PolicySpecError", "load_deployable"]

CHAMPIONS_DIR = Path(__file__).resolve().parents[2] / "populations" / "champions"
CHAMPION_PREFIX = "champion:"


class PolicySpecError(ValueError):
    """A policy spec that names nothing usable."""


@dataclass(frozen=True)
class DeployablePolicy:
    """A deterministic aligner ready to run: `act(history (H, F)) -> action (k + 1,)`."""

    name: str
    act: Callable[[np.ndarray], np.ndarray]
    task: Task
    history: int
    source: str  # where it was loaded from, in words (for the audit log and reports)


def _exported(folder: Path, source: str) -> DeployablePolicy:
    from alignrl.deploy.loading import load_exported  # torch / onnxruntime only when needed

    exported = load_exported(folder)
    member = exported.card.get("member") or {}
    return DeployablePolicy(
        name=str(member.get("id") or folder.name),
        act=exported.act,
        task=exported.task,
        history=int(exported.history),
        source=source,
    )


def _champion(name: str) -> DeployablePolicy:
    folder = CHAMPIONS_DIR / name
    if not name or "/" in name or name.startswith(".") or not folder.is_dir():
        # Hidden folders are exports still being written (alignrl export stages beside --out).
        shipped = sorted(
            path.name
            for path in CHAMPIONS_DIR.glob("*")
            if path.is_dir() and not path.name.startswith(".")
        )
        known = ", ".join(shipped) if shipped else f"none ({CHAMPIONS_DIR} holds no champion)"
        raise PolicySpecError(f"no shipped champion {name!r}; shipped champions: {known}")
    return _exported(folder, f"shipped champion {name} ({folder})")


def _trained(path: Path) -> DeployablePolicy:
    from alignrl.runs.sources import resolve_source

    source = resolve_source(path)
    agent = source.agent
    where = f"{source.kind} {source.run_dir}" if source.run_dir else source.kind
    return DeployablePolicy(
        name=agent.id,
        act=lambda history: agent.act(history, deterministic=True),
        task=source.task,
        history=int(source.config.history),
        source=f"{where}: {source.member_file} ({source.chosen_as})",
    )


def load_deployable(spec: str) -> DeployablePolicy:
    """The policy a spec names (see the module docstring). PolicySpecError where it names
    nothing; the loaders' own errors (ExportError, CheckpointError: ValueErrors) where what
    it names is broken."""
    if spec.startswith(CHAMPION_PREFIX):
        return _champion(spec[len(CHAMPION_PREFIX) :])
    path = Path(spec)
    if path.is_dir() and (path / "card.json").exists():
        return _exported(path, f"exported policy {path}")
    if path.exists():
        return _trained(path)
    raise PolicySpecError(
        f"unknown policy {spec!r}: give a run directory (training or league), a checkpoint "
        "file (.pt), an exported policy directory, or champion:NAME"
    )

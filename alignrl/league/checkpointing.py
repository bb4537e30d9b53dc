"""A league's checkpoints, in runs/<name>/checkpoints/:

    LATEST                              names the newest complete checkpoint
    iteration-NNNNNN/members/<id>.pt    every active member, its experience included
    iteration-NNNNNN/league.pt          the league's own state (STATE_FORMAT), written last

A checkpoint is written members first and league state last, then LATEST names it; only then
are older folders removed, and the snapshot files its opponent pool does not list. So a kill
at any moment leaves LATEST naming a complete checkpoint and all it refers to, and a write
that fails (a full disk) leaves the previous checkpoint as it was. What a checkpoint holds
is the league loop's (alignrl.league.loop); this module only writes, reads and prunes it.
"""

from __future__ import annotations

import shutil
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

from alignrl.agents.agent import Agent
from alignrl.checkpoints import (
    CheckpointError,
    atomic_write_text,
    load_checkpoint,
    remove_partial_writes,
    save_checkpoint,
)

__all__ = [
    "STATE_FORMAT",
    "check_state_format",
    "latest_checkpoint",
    "read_checkpoint",
    "remove_partial_files",
    "remove_unreferenced",
    "write_checkpoint",
]

# 2: openskill ratings (mu, sigma) with anchors; 1 held Elo ratings, which cannot be resumed.
STATE_FORMAT = "alignrl-league-2"
# The folders of a league run that atomic writes go to (their killed temporaries are cleared).
WRITTEN_FOLDERS = ("checkpoints", "snapshots", "best", "metrics", "initial")


def latest_checkpoint(run_dir: Path) -> str | None:
    """The folder name LATEST gives, None before the first checkpoint."""
    latest = run_dir / "checkpoints" / "LATEST"
    return latest.read_text().strip() if latest.exists() else None


def write_checkpoint(
    run_dir: Path, iteration: int, members: Mapping[str, Agent], state: dict[str, Any]
) -> Path:
    """A new checkpoint folder for `iteration`: `members`, then `state` as league.pt, then
    LATEST naming it. A write that fails removes the new folder (unless LATEST names it)."""
    root = run_dir / "checkpoints"
    folder = root / f"iteration-{iteration:06d}"
    try:
        for member_id, agent in members.items():
            agent.save(folder / "members" / f"{member_id}.pt", replay=True)
        save_checkpoint(folder / "league.pt", state)
        atomic_write_text(root / "LATEST", folder.name + "\n")
    except OSError:
        if latest_checkpoint(run_dir) != folder.name:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder


def remove_unreferenced(run_dir: Path, snapshots: Collection[str]) -> None:
    """Checkpoint folders other than LATEST's, and snapshot files that are not among
    `snapshots` (those LATEST's opponent pool lists: the others were pruned from it, or
    frozen after it by a run that was killed)."""
    current = latest_checkpoint(run_dir)
    for folder in (run_dir / "checkpoints").glob("iteration-*"):
        if folder.name != current and folder.is_dir():
            shutil.rmtree(folder, ignore_errors=True)
    for path in (run_dir / "snapshots").glob("*.pt"):
        if path.stem not in snapshots:
            path.unlink(missing_ok=True)


def remove_partial_files(run_dir: Path) -> None:
    """The temporaries that writes killed midway left anywhere in the run directory."""
    for folder in WRITTEN_FOLDERS:
        remove_partial_writes(run_dir / folder)


def check_state_format(state: dict[str, Any], path: Path) -> None:
    """CheckpointError unless `state` is a league state this alignrl reads."""
    if state.get("format") != STATE_FORMAT:
        raise CheckpointError(
            f"{path}: league state format {state.get('format')!r}, this alignrl reads "
            f"{STATE_FORMAT!r} (a league of an earlier alignrl, rated by Elo, cannot be "
            "resumed or reported: start it again)"
        )


def read_checkpoint(
    folder: Path, envs: int, device: str
) -> tuple[dict[str, Any], dict[str, Agent]]:
    """The league state of the checkpoint `folder` and its members (each with `envs`
    experience slots on `device`)."""
    state = load_checkpoint(folder / "league.pt", device)
    check_state_format(state, folder / "league.pt")
    members = {
        member_id: Agent.load(folder / "members" / f"{member_id}.pt", envs, device)
        for member_id in state["members"]
    }
    return state, members

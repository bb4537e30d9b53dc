"""Atomic, safe checkpoint files for runs (runs/<name>/checkpoints/).

A write goes to a temporary file in the same folder, is flushed and fsynced, then renamed over
the target: a run killed at any moment leaves either the old file or the new one, never half
of one. Loading uses `torch.load(weights_only=True)`: tensors, numbers, strings and
containers only, never arbitrary pickled objects.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "CheckpointError",
    "atomic_write",
    "atomic_write_text",
    "load_checkpoint",
    "save_checkpoint",
]


class CheckpointError(ValueError):
    """A checkpoint that cannot be read: missing, truncated, or not ours."""


def _fsync_directory(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write: Any) -> None:
    """Create or replace `path` with what `write(handle)` writes to a binary handle, so that
    a reader (or a crash) sees the old file or the new one, never part of either."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", delete=False)
    try:
        with handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(handle.name, 0o666 & ~_umask())  # as open() would make it, not 0600
        os.replace(handle.name, path)
        _fsync_directory(path.parent)
    except BaseException:
        Path(handle.name).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write(Path(path), lambda handle: handle.write(text.encode("utf-8")))


def to_tensors(value: Any) -> Any:
    """numpy arrays -> tensors, recursively, so that weights_only loading accepts them."""
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, dict):
        return {key: to_tensors(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_tensors(item) for item in value)
    return value


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    atomic_write(Path(path), lambda handle: torch.save(to_tensors(state), handle))


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as error:  # any unreadable file: say which and why, never a traceback
        raise CheckpointError(
            f"checkpoint {path} cannot be read ({type(error).__name__}: {error}); it may be "
            "truncated or not an alignrl checkpoint"
        ) from None
    if not isinstance(state, dict) or "format" not in state:
        raise CheckpointError(f"checkpoint {path} is not an alignrl checkpoint")
    return state

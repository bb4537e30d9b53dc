"""Atomic, durable files for runs and exports, and safe checkpoint files.

Every file alignrl keeps is written here. A write goes to a temporary file in the same folder,
is flushed and fsynced, then renamed over the target: a run killed at any moment leaves either
the old file or the new one, never half of one (and perhaps a temporary
`.<name>.<random>.partial`, which `remove_partial_writes` clears). A folder written as a whole
(an exported policy) is staged beside its target and put in place with renames
(`staging_folder`, `publish_folder`). A write that fails on the disk (full, read-only) is an
OSError naming the target. Loading uses `torch.load(weights_only=True)`: tensors, numbers,
strings and containers only, never arbitrary pickled objects. Torch is imported only by the
checkpoint functions, so that torch-free modules (metrics, reports) can write files too.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

__all__ = [
    "CheckpointError",
    "atomic_write",
    "atomic_write_text",
    "current_umask",
    "fsync_directory",
    "fsync_file",
    "load_checkpoint",
    "naming_path",
    "publish_folder",
    "remove_partial_writes",
    "save_checkpoint",
    "staging_folder",
]

PARTIAL_SUFFIX = ".partial"
# What atomic_write leaves when killed: .<target>.<8 random characters>[.partial] (the
# suffix came later; runs killed before it still have the bare form).
_PARTIAL_NAME = re.compile(r"\..+\.[a-z0-9_]{8}(\.partial)?")


class CheckpointError(ValueError):
    """A checkpoint that cannot be read: missing, truncated, or not ours."""


def fsync_directory(folder: Path) -> None:
    """Make a rename or a new file in `folder` durable (where the platform allows it)."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def fsync_file(path: Path) -> None:
    """Make a file that a library wrote by name (torch.onnx.export, safetensors) durable."""
    with path.open("rb") as handle:
        os.fsync(handle.fileno())


def current_umask() -> int:
    """The umask new files and folders are made with (mkdir and open honour it)."""
    mask = os.umask(0)  # reading the umask means setting it: put it straight back
    os.umask(mask)
    return mask


def _os_errors(error: BaseException) -> Iterator[OSError]:
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError):
            yield error
        error = error.__cause__ or error.__context__


def naming_path(error: BaseException, path: str | Path) -> OSError | None:
    """The OSError behind `error` (torch.save reports a failed write as a RuntimeError whose
    context is the OSError), with `path` in its message where it named none; None if no
    OSError is behind it. "[Errno 28] No space left on device" alone does not say where."""
    for cause in _os_errors(error):
        if cause.filename is not None:
            return cause
        return OSError(cause.errno, cause.strerror or str(cause), str(path))
    return None


def atomic_write(path: Path, write: Any) -> None:
    """Create or replace `path` with what `write(handle)` writes to a binary handle, so that
    a reader (or a crash) sees the old file or the new one, never part of either."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = tempfile.NamedTemporaryFile(
            dir=path.parent, prefix=f".{path.name}.", suffix=PARTIAL_SUFFIX, delete=False
        )
    except OSError as error:
        raise naming_path(error, path) from None
    try:
        with handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(handle.name, 0o666 & ~current_umask())  # as open() would make it, not 0600
        os.replace(handle.name, path)
        fsync_directory(path.parent)
    except BaseException as error:
        Path(handle.name).unlink(missing_ok=True)
        disk = naming_path(error, path) if isinstance(error, Exception) else None
        if disk is None or disk is error:
            raise
        raise disk from error


def remove_partial_writes(folder: Path, recursive: bool = True) -> None:
    """Delete the temporaries that writes killed midway left in `folder` (and below, if
    `recursive`); call it only where no other process is writing."""
    if not folder.is_dir():
        return
    for path in folder.rglob(".*") if recursive else folder.glob(".*"):
        if path.is_file() and _PARTIAL_NAME.fullmatch(path.name):
            path.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write(Path(path), lambda handle: handle.write(text.encode("utf-8")))


def staging_folder(out: Path) -> Path:
    """A new empty folder beside `out` to write a folder's files into before
    `publish_folder` puts it in place; a kill leaves it as `.<name>.tmp-<random>`."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))


def publish_folder(staging: Path, out: Path) -> None:
    """Put the folder `staging` in place of `out` with renames: a reader sees the old folder
    or the new one, never a half-written one. `out` may be missing, empty or full."""
    staging.chmod(0o777 & ~current_umask())  # mkdtemp makes 0700; mkdir would not
    if out.is_dir() and any(out.iterdir()):
        aside = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
        os.replace(out, aside / out.name)
        os.replace(staging, out)
        shutil.rmtree(aside)
    else:
        if out.is_dir():
            out.rmdir()
        os.replace(staging, out)
    fsync_directory(out.parent)


def to_tensors(value: Any) -> Any:
    """numpy arrays -> tensors, recursively, so that weights_only loading accepts them."""
    import numpy as np
    import torch

    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, dict):
        return {key: to_tensors(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_tensors(item) for item in value)
    return value


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    import torch

    atomic_write(Path(path), lambda handle: torch.save(to_tensors(state), handle))


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    import torch

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

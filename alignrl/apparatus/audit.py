"""The audit log: one record per call to an instrument and per decision of the shield.

Records are dicts (the event, its time, and what happened); `JsonLinesAudit` appends them to
a file, one JSON object a line, written whole and fsynced before the call it records returns,
so a crash or a power cut loses nothing, and a full disk leaves no half record
(`AuditFailure`). `MemoryAudit` keeps them in memory.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from alignrl.apparatus.guard import ShieldStop

__all__ = [
    "MEMORY_AUDIT_RECORDS",
    "AuditFailure",
    "AuditSink",
    "JsonLinesAudit",
    "MemoryAudit",
    "plain",
]

# Audit records a run keeps in memory where no log file is given (the newest ones).
MEMORY_AUDIT_RECORDS = 10_000


class AuditSink(Protocol):
    """Where audit records go (a JSON-lines file in alignrl.deploy.align)."""

    def record(self, entry: dict[str, Any]) -> None: ...


class MemoryAudit:
    """Audit records kept in memory (tests, and callers that keep no file): all of them, or
    with `keep`, the newest `keep`."""

    def __init__(self, keep: int | None = None) -> None:
        self.entries: list[dict[str, Any]] = []
        self.keep = keep

    def record(self, entry: dict[str, Any]) -> None:
        self.entries.append(entry)
        if self.keep is not None and len(self.entries) >= 2 * self.keep:
            del self.entries[: -self.keep]


def plain(value: Any) -> Any:
    """`value` as strict JSON data: numpy numbers as Python numbers, NaN and infinities as
    the strings "nan", "inf", "-inf" (JSON has no such numbers)."""
    if isinstance(value, Mapping):
        return {str(key): plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [plain(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


class AuditFailure(ShieldStop):
    """A record could not be written whole (a full disk, a lost mount): work on the
    instrument stops, since a call that cannot be put on record is not made."""


class JsonLinesAudit:
    """The audit log as a JSON-lines file, appended to. Each record is written whole and
    fsynced before the call it records returns, so a crash or a power cut loses nothing.

    A record that cannot be written whole (no space left, say) is taken back: the file is cut
    to where it ended before, and a log this run created is removed rather than left empty.
    Then AuditFailure (a ShieldStop: the shield sends nothing more), naming the path, and
    every later record refused the same way.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise ValueError(f"--log {self.path} is a directory; give a file name")
        self._fd: int | None = None  # opened with the first record
        self._created = False  # this log made the file (an empty one is then removed)
        self._closed = False
        self._broken: str | None = None  # why a record could not be written

    def _open(self) -> int:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._created = not self.path.exists()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        return self._fd

    def record(self, entry: dict[str, Any]) -> None:
        if self._closed:
            raise ValueError(f"the audit log {self.path} is closed")
        if self._broken is not None:
            raise AuditFailure(self._broken)
        data = (json.dumps(plain(entry), allow_nan=False) + "\n").encode("utf-8")
        fd = self._fd if self._fd is not None else self._open()
        before = os.fstat(fd).st_size
        try:
            written = 0
            while written < len(data):
                written += os.write(fd, data[written:])
            os.fsync(fd)
        except OSError as error:
            self._take_back(fd, before)
            self._broken = (
                f"the audit log {self.path} could not be written "
                f"({error.strerror or error}): no call is made that is not on record"
            )
            raise AuditFailure(self._broken) from None

    def _take_back(self, fd: int, size: int) -> None:
        """Cut the file back to `size` (no half record); a file this log created and that is
        empty then is removed."""
        with contextlib.suppress(OSError):
            os.ftruncate(fd, size)
        if size == 0 and self._created:
            with contextlib.suppress(OSError):
                os.close(fd)
                self._fd = None
                self.path.unlink()

    def __getstate__(self) -> dict[str, Any]:
        # A recorder's worker processes each append to the same file with a handle of their
        # own (one write per record, so lines never interleave).
        return {**self.__dict__, "_fd": None}

    def close(self) -> None:
        self._closed = True
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> JsonLinesAudit:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

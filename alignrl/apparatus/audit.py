"""The audit log: one record per call to an instrument and per decision of the shield.

Records are dicts (the event, its time, and what happened); `JsonLinesAudit` appends them to
a file, one JSON object a line, flushed and fsynced before the call it records returns, so a
crash or a power cut loses nothing. `MemoryAudit` keeps them in memory.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

__all__ = ["MEMORY_AUDIT_RECORDS", "AuditSink", "JsonLinesAudit", "MemoryAudit", "plain"]

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


class JsonLinesAudit:
    """The audit log as a JSON-lines file, appended to. Each record is flushed and fsynced
    before the call it records returns, so a crash or a power cut loses nothing."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise ValueError(f"--log {self.path} is a directory; give a file name")
        self._file: TextIO | None = None  # opened with the first record
        self._closed = False

    def record(self, entry: dict[str, Any]) -> None:
        if self._closed:
            raise ValueError(f"the audit log {self.path} is closed")
        if self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self.path.open("a", encoding="utf-8")
        self._file.write(json.dumps(plain(entry), allow_nan=False) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())

    def __getstate__(self) -> dict[str, Any]:
        # A recorder's worker processes each append to the same file with a handle of their
        # own (one write per record, so lines never interleave).
        return {**self.__dict__, "_file": None}

    def close(self) -> None:
        self._closed = True
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> JsonLinesAudit:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

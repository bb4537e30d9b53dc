"""One process per run: a lock on the run directory, `RUN_DIR/.lock`.

`alignrl train`, `adapt`, `league run` and `league resume` hold it (`RunLock`, a context
manager) from before they read or write anything in the run until they are done with it, so a
second process working on the same run (a second `--resume`, a `train` or `league run` into the
same folder, a `--force` that would remove it) is refused at once with `RunLockedError`: one
line naming the run directory and the PID, host and start time of the process that holds it.
`status`, `leaderboard`, `report` and `export` take no lock: they read a run (and write only
their reports), also while it runs.

The lock is `flock(LOCK_EX | LOCK_NB)` on the file, which names its holder (one JSON line: pid,
host, start time, command). The operating system lets go of it when its holder ends in any way,
kill -9 included: a lock left by a killed process is taken over by the next one without a word
(`RunLock.stale` says whose it was). A holder that ends normally removes the file, and the
folders it made for a run that never started (an empty run directory). The file is a dotfile
at the top of the run directory, where no reader of a run looks (checkpoints, metrics,
snapshots and their partial writes live in folders below it).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["LOCK_FILE", "LockHolder", "RunLock", "RunLockedError"]

LOCK_FILE = ".lock"
_ATTEMPTS = 50  # a lock file removed or replaced between open and flock: open it again
_HOLDER_BYTES = 4096  # a holder record is one short line; a longer file is not one


@dataclass(frozen=True)
class LockHolder:
    """Who holds (or held) a run's lock, as its file says."""

    pid: int | None
    host: str
    started: str
    command: str = ""

    def __str__(self) -> str:
        pid = "an unknown PID" if self.pid is None else f"PID {self.pid}"
        text = f"{pid} on {self.host or 'an unknown host'}"
        if self.started:
            text += f" since {self.started}"
        if self.command:
            text += f" ({self.command})"
        return text


class RunLockedError(ValueError):
    """Another process holds the run's lock (a ValueError: the command line says it in one
    line, exit 2)."""

    def __init__(self, run_dir: Path, holder: LockHolder) -> None:
        self.run_dir, self.holder = run_dir, holder
        super().__init__(
            f"{run_dir} is in use by another alignrl process, {holder}: one process works on "
            f"a run at a time; wait for it to end or stop it (its lock: {run_dir / LOCK_FILE})"
        )


def _me() -> bytes:
    argv = sys.argv or ["python"]
    command = " ".join([Path(argv[0]).name, *argv[1:]])
    record = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "command": command if len(command) <= 200 else command[:197] + "...",
    }
    return (json.dumps(record) + "\n").encode()


def _holder(data: bytes) -> LockHolder | None:
    """The holder a lock file names; None for an empty file, an unknown holder for one that
    cannot be read (never an error: the lock is the flock, not the text)."""
    if not data.strip():
        return None
    try:
        record = json.loads(data.decode())
        pid = record.get("pid")
        return LockHolder(
            pid if isinstance(pid, int) else None,
            str(record.get("host", ""))[:100],
            str(record.get("started", ""))[:40],
            str(record.get("command", ""))[:200],
        )
    except (ValueError, AttributeError):
        return LockHolder(None, "", "")


def _read_holder(fd: int, wait_s: float = 0.5) -> LockHolder:
    """The holder named in the lock file open at `fd`, waiting briefly for one that took the
    lock an instant ago and has not written its name yet."""
    deadline = time.monotonic() + wait_s
    while True:
        holder = _holder(os.pread(fd, _HOLDER_BYTES, 0))
        if holder is not None or time.monotonic() > deadline:
            return holder or LockHolder(None, "", "")
        time.sleep(0.02)


def _same_file(fd: int, path: Path) -> bool:
    """Whether `path` is still the file open at `fd` (not removed, not replaced)."""
    try:
        here, there = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


def _naming(error: OSError, path: Path) -> OSError:
    return type(error)(error.errno, f"cannot lock the run: {error.strerror}", str(path))


class RunLock:
    """The lock of the run in `run_dir`, held from `acquire` (or entering the `with` block)
    to `release`. `create`: make the run directory where it does not exist (a new run);
    without it (a resume), a missing directory is not locked and the resume says what is
    missing. `created`: the folders this lock made (the run directory, and those above it
    that were missing), removed again on release where the run never wrote anything there."""

    def __init__(self, run_dir: str | Path, create: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_FILE
        self.create = create
        self.created: list[Path] = []  # the folders this lock made, the deepest first
        self.stale: LockHolder | None = None  # the holder of a lock its process left behind
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def only_the_lock(self) -> bool:
        """Whether the run directory holds nothing but the lock file: a folder this lock
        made, or one whose start was killed before it wrote anything."""
        if not self.run_dir.is_dir():
            return True
        return all(path.name == LOCK_FILE for path in self.run_dir.iterdir())

    def acquire(self) -> RunLock:
        """Take the lock, or RunLockedError naming its holder (and the folders this lock made
        for it are gone again)."""
        if self._fd is not None:
            raise RuntimeError(f"{self.path} is held already")
        try:
            return self._acquire()
        except BaseException:
            self._remove_created()
            raise

    def _acquire(self) -> RunLock:
        for _ in range(_ATTEMPTS):
            if not self.run_dir.is_dir():
                if not self.create:
                    return self  # no run to lock: reading it says so
                self._make_folders()
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except FileNotFoundError:
                continue  # its folder went in the meantime
            except OSError as error:
                raise _naming(error, self.path) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as error:
                holder = _read_holder(fd) if error.errno in (errno.EAGAIN, errno.EACCES) else None
                os.close(fd)
                if holder is None:
                    raise _naming(error, self.path) from None
                raise RunLockedError(self.run_dir, holder) from None
            if not _same_file(fd, self.path):  # released and removed by its holder meanwhile
                os.close(fd)
                continue
            try:
                self.stale = _holder(os.pread(fd, _HOLDER_BYTES, 0))
                os.ftruncate(fd, 0)
                os.pwrite(fd, _me(), 0)
            except OSError as error:
                os.close(fd)
                raise _naming(error, self.path) from None
            self._fd = fd
            return self
        raise OSError(errno.EAGAIN, "cannot lock the run: its lock file keeps changing", self.path)

    def _make_folders(self) -> None:
        missing = [p for p in (self.run_dir, *self.run_dir.parents) if not p.exists()]
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise _naming(error, self.run_dir) from None
        self.created = sorted(set(self.created) | set(missing), key=lambda p: -len(p.parts))

    def renew(self) -> None:
        """After the run directory was removed and made again under the lock (`--force`):
        hold the lock in the new directory (RunLockedError where another process was
        quicker). Nothing happens while the lock file is still the one held."""
        old = self._fd
        if old is None or _same_file(old, self.path):
            return
        self._fd = None
        try:
            self.acquire()
        finally:
            os.close(old)
        self.stale = None  # the file was made afresh, not left by anyone

    def release(self) -> None:
        """Let go: remove the lock file (while still holding it, so no one locks a file that
        is going), then the folders the lock made where they are empty."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if _same_file(fd, self.path):
                with contextlib.suppress(OSError):
                    self.path.unlink()
        finally:
            os.close(fd)
        self._remove_created()

    def _remove_created(self) -> None:
        for folder in self.created:
            with contextlib.suppress(OSError):  # not empty (the run started), or gone
                folder.rmdir()
        self.created = []

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def __del__(self) -> None:  # a lock dropped without release: the file descriptor goes
        fd, self._fd = getattr(self, "_fd", None), None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

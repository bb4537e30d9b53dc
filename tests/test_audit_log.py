"""The audit log on a full disk: a record is written whole or not at all, the error names the
log, nothing more reaches the driver, and the exit code is the shield's (3), not a config
error. The disk is filled by a stand-in for `os.write` that takes part of a record and then
answers ENOSPC, as a full file system does."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import Any

import pytest
from fake_drivers import HostileLens
from hostile import assert_refused, run_cli
from test_shielded_paths import _command, _moving_policy, member_file  # noqa: F401

import alignrl.apparatus.audit as audit_module
from alignrl.apparatus.audit import AuditFailure, JsonLinesAudit

EXIT_SHIELD_STOP = 3


@pytest.fixture(autouse=True)
def fresh_driver_records() -> None:
    HostileLens.received.clear()
    HostileLens.instances.clear()


def _disk_full_after(monkeypatch: pytest.MonkeyPatch, records: int) -> None:
    """After `records` whole records, every write takes a few bytes and then fails."""
    real_write = os.write
    calls = {"whole": 0}

    def write(fd: int, data: bytes) -> int:
        if calls["whole"] < records:
            calls["whole"] += 1
            return real_write(fd, data)
        if len(data) > 8:
            return real_write(fd, data[:8])  # a part of the record fits, then the disk is full
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(audit_module.os, "write", write)


def _records(log: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in log.read_text().splitlines()]  # each line whole


def test_a_record_that_does_not_fit_is_taken_back_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = JsonLinesAudit(tmp_path / "audit.jsonl")
    _disk_full_after(monkeypatch, 2)
    log.record({"event": "one"})
    log.record({"event": "two"})
    with pytest.raises(AuditFailure, match=r"audit\.jsonl could not be written \(No space"):
        log.record({"event": "three"})
    with pytest.raises(AuditFailure):  # and every later one, without touching the file
        log.record({"event": "four"})
    log.close()
    assert [record["event"] for record in _records(tmp_path / "audit.jsonl")] == ["one", "two"]


def test_a_log_whose_first_record_does_not_fit_is_not_left_empty(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _disk_full_after(monkeypatch, 0)
    log = JsonLinesAudit(tmp_path / "audit.jsonl")
    with pytest.raises(AuditFailure):
        log.record({"event": "start"})
    assert not (tmp_path / "audit.jsonl").exists()
    kept = tmp_path / "older.jsonl"  # an older log appended to keeps what it had
    kept.write_text('{"event": "earlier"}\n')
    with pytest.raises(AuditFailure):
        JsonLinesAudit(kept).record({"event": "start"})
    assert kept.read_text() == '{"event": "earlier"}\n'


@pytest.mark.parametrize("whole", [0, 6])
@pytest.mark.parametrize("verb", ["align", "evaluate-policy"])
def test_a_full_disk_stops_the_work_before_any_unrecorded_write(
    verb: str,
    whole: int,
    tmp_path: Path,
    member_file: Path,  # noqa: F811
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _moving_policy(monkeypatch, 0.5, -1.0)
    _disk_full_after(monkeypatch, whole)
    log = tmp_path / "audit.jsonl"
    outcome = run_cli([*_command(verb, tmp_path, member_file, {}), "--log", str(log)], capsys)
    assert_refused(outcome, EXIT_SHIELD_STOP, f"the audit log {log} could not be written")
    if whole == 0:
        assert not log.exists() and HostileLens.received == []
        return
    records = _records(log)
    assert len(records) == whole
    sent = [r for r in records if r["event"] in ("write", "restore") and r.get("sent")]
    assert len(HostileLens.received) == len(sent)  # every write that went is on record

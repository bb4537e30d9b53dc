"""benchmarks/abort.py: a command sent SIGTERM while its driver hangs, timed from the signal to
its exit; the exit code and what the driver received after it hung are shown beside."""

from __future__ import annotations

import pytest

from benchmarks.abort import main


def test_the_benchmark_times_an_abort_and_shows_nothing_was_sent_after_the_hang(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--repeats", "1", "--verbs", "align"]) == 0
    rows = capsys.readouterr().out.splitlines()
    verb, code, expected, seconds, received = rows[2].split()
    assert (verb, code, expected, received) == ("align", "3", "3", "0")
    assert 0 < float(seconds) < 30  # the hang never ends: a command that waited would not
    assert rows[-1].startswith("align: median")

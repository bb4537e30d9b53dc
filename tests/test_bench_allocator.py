"""benchmarks/allocator.py: one alignrl command run tuned and with glibc's defaults, alternating,
each run compared with the first."""

from __future__ import annotations

import pytest

from benchmarks.allocator import main


def test_the_benchmark_runs_a_command_both_ways_and_compares_what_it_prints(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--repeats", "1", "--", "--version"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[0] == "alignrl --version"
    assert [row.split()[0] for row in rows[2:4]] == ["tuned", "system"]
    assert all(row.endswith("yes") for row in rows[2:4])
    assert rows[-2].startswith("median tuned: wall") and rows[-1].startswith("median system")

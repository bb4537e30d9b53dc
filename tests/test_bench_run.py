"""benchmarks/run.py (`make bench`) rewrites the measured figures of docs/benchmarks.md and
keeps its part measured by hand as the page has it: one copy, never dropped."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.run import DOCS, MEASURED_BY_HAND, measured_by_hand


def test_the_part_measured_by_hand_is_kept_from_the_page(tmp_path: Path) -> None:
    out = tmp_path / "benchmarks.md"
    out.write_text(f"# Benchmarks\n\nold figures\n\n{MEASURED_BY_HAND}\n\n### A run\n\ntext\n\n")
    assert measured_by_hand(out) == f"{MEASURED_BY_HAND}\n\n### A run\n\ntext"
    # A page without it (or none yet) takes the project's own.
    assert measured_by_hand(tmp_path / "new.md") == measured_by_hand(DOCS)
    assert "### focus-v2 from its one file" in measured_by_hand(DOCS)


def test_no_part_to_keep_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import benchmarks.run as run

    monkeypatch.setattr(run, "DOCS", tmp_path / "missing.md")
    with pytest.raises(SystemExit, match="has a '## Measured by hand' part to keep"):
        measured_by_hand(tmp_path / "new.md")

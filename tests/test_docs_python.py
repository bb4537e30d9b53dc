"""docs/python.md is kept true by running it: its ```python blocks run in order, in one
namespace (as a reader pastes them into one interpreter), in a fresh folder; what each prints
must be what the page shows after it, and what they make must be there.

A block's shown output is the first plain block after it, before the next Python block. A
printed line matches a shown line word for word, except that a number matches any number,
True or False either of them, and an outcome of `alignrl align` (aligned, not-aligned)
either: 600 training steps decide those by chance, and the page says "for example".
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "python.md"

_BLOCK = re.compile(r"^```(\w*)\n(.*?)^```$", re.DOTALL | re.MULTILINE)
_FREE = re.compile(r"\d+(?:\.\d+)?|True|False|not-aligned|aligned")
_KINDS = {"True": "True|False", "False": "True|False"}


def examples() -> list[tuple[str, str | None]]:
    """(code, shown output or None) of every Python block of the page, in order."""
    found: list[tuple[str, str | None]] = []
    for match in _BLOCK.finditer(PAGE.read_text()):
        language, body = match.group(1), match.group(2)
        if language == "python":
            found.append((body, None))
        elif language == "" and found and found[-1][1] is None:
            found[-1] = (found[-1][0], body.rstrip("\n"))
    return found


def line_pattern(shown: str) -> re.Pattern[str]:
    """A shown line as a pattern: its numbers, booleans and outcomes free (module docstring)."""
    parts, end = [], 0
    for token in _FREE.finditer(shown):
        parts.append(re.escape(shown[end : token.start()]))
        word = token.group()
        if word in _KINDS:
            parts.append(f"(?:{_KINDS[word]})")
        elif word in ("aligned", "not-aligned"):
            parts.append("(?:not-aligned|aligned)")
        else:
            parts.append(r"-?\d+(?:\.\d+)?")
        end = token.end()
    parts.append(re.escape(shown[end:]))
    return re.compile("".join(parts))


def test_the_matching_rule_frees_numbers_booleans_and_outcomes_only() -> None:
    pattern = line_pattern("synthetic: not-aligned, exit code 1, success False, 2.5 px")
    assert pattern.fullmatch("synthetic: aligned, exit code 0, success True, 12.25 px")
    assert not pattern.fullmatch("synthetic: aligned, exit status 0, success True, 12.25 px")
    assert not pattern.fullmatch("synthetic: aborted, exit code 3, success False, 2.5 px")


def test_the_python_page_runs_as_shown(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = examples()
    assert len(blocks) >= 3 and all(shown is not None for _, shown in blocks)
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    for number, (code, shown) in enumerate(blocks, start=1):
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            exec(compile(code, f"docs/python.md, Python block {number}", "exec"), namespace)
        lines, expected = printed.getvalue().rstrip("\n").split("\n"), str(shown).split("\n")
        assert len(lines) == len(expected), f"block {number} printed:\n{printed.getvalue()}"
        for line, want in zip(lines, expected, strict=True):
            assert line_pattern(want).fullmatch(line), f"block {number}: {line!r}, page: {want!r}"
    # What the calls made: a run directory as `alignrl train` writes it, a session of the
    # scenarios asked for, the alignment's GIF (a frame per acquisition and the final image)
    # and audit log, the env's frame.
    run, session, result = namespace["run"], namespace["session"], namespace["result"]
    assert (tmp_path / "runs" / "quick" / "config.yaml").is_file()
    assert (tmp_path / "runs" / "quick" / "checkpoints" / "best.pt").is_file()
    assert run.path == Path("runs") / "quick"  # type: ignore[attr-defined]
    assert session.scenarios == 20  # type: ignore[attr-defined]
    with Image.open(tmp_path / "quick.gif") as gif:
        assert gif.n_frames == result.acquisitions + 1  # type: ignore[attr-defined]
    log = (tmp_path / "align.jsonl").read_text().splitlines()
    assert '"event": "start"' in log[0] and '"event": "end"' in log[-1]
    frame = namespace["frame"]
    assert frame.ndim == 3 and frame.shape[2] == 3  # type: ignore[attr-defined]

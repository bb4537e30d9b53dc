"""The harness of the hostile-input tests: run the `alignrl` command as a user would and
check what a hostile input must never do.

`run_cli(argv)` runs `alignrl.cli.main` in this process and returns its exit code and what it
printed; an exception escaping `main` (a traceback the user would see) fails the test with
that traceback, and so does main's last-resort handler (exit code EXIT_INTERNAL). `tree_state`
and `assert_unchanged` check that nothing already written changed.
"""

from __future__ import annotations

import hashlib
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from alignrl.cli import main

__all__ = [
    "Outcome",
    "assert_refused",
    "assert_unchanged",
    "evaluate_on",
    "run_cli",
    "tree_state",
]

EXIT_INTERNAL = 70  # main's last resort (EX_SOFTWARE): a bug, never a refusal


@dataclass(frozen=True)
class Outcome:
    code: int
    out: str
    err: str

    @property
    def text(self) -> str:
        return self.out + self.err


def evaluate_on(spec: str, *extra: str) -> list[str]:
    """The argv of a short `alignrl evaluate` of the hyperbola fit on apparatus `spec`."""
    return [
        "evaluate",
        "--policy",
        "hyperbola",
        "--apparatus",
        spec,
        "--scenarios",
        "2",
        "--quiet",
        *extra,
    ]


def run_cli(argv: Sequence[str], capsys: pytest.CaptureFixture[str]) -> Outcome:
    """`alignrl ARGV` in process; fails the test on an escaping exception or a traceback."""
    capsys.readouterr()
    try:
        code = main([str(arg) for arg in argv])
    except SystemExit as exit_:  # argparse's usage errors
        code = exit_.code if isinstance(exit_.code, int) else 2
    except BaseException:
        pytest.fail(f"alignrl {' '.join(map(str, argv))} raised:\n{traceback.format_exc()}")
    captured = capsys.readouterr()
    outcome = Outcome(int(code), captured.out, captured.err)
    assert "Traceback (most recent call last)" not in outcome.text, outcome.text
    assert outcome.code != EXIT_INTERNAL, f"internal error, not a refusal:\n{outcome.text}"
    return outcome


def assert_refused(outcome: Outcome, code: int, *names: str) -> None:
    """The documented exit code, and a message naming every one of `names` (file, row, key,
    driver call); a message of bounded length (never an echo of an unbounded value)."""
    assert outcome.code == code, f"exit {outcome.code}, expected {code}:\n{outcome.text}"
    for name in names:
        assert name in outcome.text, f"{name!r} not named in:\n{outcome.text}"
    assert len(outcome.err) < 20_000, f"a message of {len(outcome.err)} characters"


def tree_state(root: Path) -> dict[str, str]:
    """Every file under `root` by its relative path and content hash."""
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


def assert_unchanged(before: dict[str, str], root: Path) -> None:
    """No file in `before` changed or vanished under `root` (new files may have appeared)."""
    after = tree_state(root)
    changed = [name for name, digest in before.items() if after.get(name) != digest]
    assert not changed, f"already-written files changed or vanished: {changed}"

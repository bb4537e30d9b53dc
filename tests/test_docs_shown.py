"""What docs/cli.md and docs/deploy.md show is what the code does: the `--help` screens word
for word, and the Python example of deploy.md run as written."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from alignrl.cli import build_parser

CLI_DOC = Path(__file__).parent.parent / "docs" / "cli.md"


def _help_blocks() -> list[tuple[list[str], str]]:
    """(the verbs, the shown screen) of every fenced block that starts with 'usage: alignrl'."""
    blocks = []
    for block in re.findall(r"```\n(usage: alignrl.*?)```", CLI_DOC.read_text(), re.DOTALL):
        words = block.split("[-h]")[0].split()[2:]  # "usage: alignrl record [-h] ..."
        blocks.append((words, block))
    return blocks


BLOCKS = _help_blocks()


@pytest.mark.parametrize(
    ("verbs", "shown"), BLOCKS, ids=[" ".join(verbs) or "alignrl" for verbs, _ in BLOCKS]
)
def test_each_help_screen_in_the_docs_is_the_commands_own(
    verbs: list[str], shown: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(os.environ, "COLUMNS", "80")  # argparse wraps to the terminal's width
    parser = build_parser()
    for verb in verbs:  # down the subcommands: alignrl -> scenarios -> validate
        actions = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
        parser = actions[0].choices[verb]  # type: ignore[attr-defined]
    assert parser.format_help() == shown, f"docs/cli.md: `alignrl {' '.join(verbs)} --help`"


def test_the_python_example_of_deploy_md_runs_as_shown(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (CLI_DOC.parent / "deploy.md").read_text()
    section = text[text.index("### From Python") :]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)  # type: ignore[union-attr]
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "docs/deploy.md", "exec"), {})
    outcome, exit_code = capsys.readouterr().out.split()
    assert outcome in ("aligned", "not-aligned") and int(exit_code) in (0, 1)
    records = (tmp_path / "align.jsonl").read_text().splitlines()
    assert '"event": "start"' in records[0] and '"event": "end"' in records[-1]

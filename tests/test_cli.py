"""Command-line behaviour shared by the verbs: errors, JSON on failure, version."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from alignrl import __version__
from alignrl.cli import main


def test_validate_json_reports_an_invalid_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("scenario,seed\n")
    assert main(["scenarios", "validate", str(bad), "--json"]) == 2
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["valid"] is False and report["file"] == str(bad)
    assert "column 3" in report["error"]
    assert "alignrl: error:" in captured.err


def test_missing_file_is_a_clean_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scenarios", "validate", str(tmp_path / "none.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as leaving:
        main(["--version"])
    assert leaving.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_unknown_apparatus_is_a_clean_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x.csv"
    code = main(["record", "--apparatus", "nikon", "--scenarios", "1", "--out", str(out)])
    assert code == 2
    assert "unknown apparatus 'nikon'" in capsys.readouterr().err
    assert not out.exists()

"""benchmarks/imitate.py: steps collected in the plain task judge a network that makes its
last move from the fit (moved afterwards), and a collection refuses --teacher-ends without
a student."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.imitate import main
from benchmarks.imitation import Demonstrations, PosteriorTeacher, collect
from tests.test_imitation import _env, _small_posterior

FITEND = "benchmarks/configs/focus-v2-imitate-fitend.yaml"


def test_agreement_moves_plain_steps_from_the_fit_and_reports_last_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    env = _env(envs=2, history=10)
    data = collect(env, PosteriorTeacher(env, _small_posterior), episodes=12, seed=6)
    path = tmp_path / "plain.npz"
    data.save(str(path))
    argv = ["agreement", "--config", FITEND, "--data", str(path), "--epochs", "3"]
    assert main([*argv, "--set", "task_options.final_move_reach=0.5"]) == 0
    out = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("|")}
    assert "the network's" in rows and "none" in rows and "all" in rows
    assert "beyond one last move's reach" in out
    assert not Demonstrations.load(str(path)).ends_from_fit  # the file is left as it was


def test_teacher_ends_needs_a_student(tmp_path: Path) -> None:
    argv = ["collect", "--config", FITEND, "--episodes", "1", "--teacher-ends"]
    with pytest.raises(SystemExit, match="--student"):
        main([*argv, "--out", str(tmp_path / "x.npz")])

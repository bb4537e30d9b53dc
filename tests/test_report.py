"""`alignrl report`: training figures and report.md from a run directory's metrics CSVs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from alignrl.cli import main
from alignrl.config import ExperimentConfig, dump_experiment
from alignrl.plots import (
    FIGURES,
    ReportError,
    losses_figure,
    read_metrics_csv,
    rolling_mean,
    write_run_report,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SAC_UPDATES = "env_steps,updates,policy_loss,q1_loss,q2_loss,v_loss,entropy,alpha"
EPISODES = "env_steps,episode,return,success,acquisitions,complexity"
EVALUATIONS = (
    "env_steps,successes,scenarios,median_acquisitions,p90_acquisitions,median_final_px,seconds"
)


def make_run(root: Path, updates: list[str], episodes: list[str], evaluations: list[str]) -> Path:
    """A run directory as alignrl/training.py leaves it: config.yaml and three CSVs, each
    given as its lines (header first; an empty list leaves the file out)."""
    run = root / "t"
    (run / "metrics").mkdir(parents=True)
    (run / "config.yaml").write_text(dump_experiment(ExperimentConfig(name="t")))
    for name, lines in (
        ("updates", updates),
        ("episodes", episodes),
        ("evaluations", evaluations),
    ):
        if lines:
            (run / "metrics" / f"{name}.csv").write_text("".join(f"{line}\n" for line in lines))
    return run


def full_run(root: Path) -> Path:
    """150 episodes with a curriculum step at episode 75, 20 update rows, 3 evaluations (the
    last with no edges measured, as the trainer writes it: a blank median_final_px)."""
    episodes = [
        f"{8 * (i // 4 + 1)},{i + 1},{0.1 * i:.1f},{i % 2},{1 + i % 5},{0.1 if i < 75 else 0.2}"
        for i in range(150)
    ]
    updates = [f"{100 + 8 * i},{50 * (i + 1)},-0.5,1.5,1.4,0.3,1.2,0.19" for i in range(20)]
    evaluations = ["100,1,4,5.0,9.0,3.1,0.5", "200,3,4,3.0,6.5,2.8,0.4", "300,2,4,2.5,4.0,,0.4"]
    return make_run(
        root, [SAC_UPDATES, *updates], [EPISODES, *episodes], [EVALUATIONS, *evaluations]
    )


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {
        str(path.relative_to(folder)): (path.stat().st_size, path.stat().st_mtime_ns)
        for path in sorted(folder.rglob("*"))
        if path.is_file()
    }


@pytest.fixture(scope="module")
def reported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, tuple[int, int]]]:
    """A full run, its files before the report, and the report written once for all tests."""
    run = full_run(tmp_path_factory.mktemp("full"))
    before = snapshot(run)
    write_run_report(run)
    return run, before


def test_rolling_mean_of_a_known_sequence() -> None:
    values = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    # Window 3: the first two points average what there is so far.
    assert np.allclose(rolling_mean(values, 3), [1.0, 1.5, 2.0, 3.0, 4.0, 5.0])
    assert np.allclose(rolling_mean(values, 1), values)
    assert np.allclose(rolling_mean(values, 100), np.cumsum(values) / np.arange(1, 7))
    assert rolling_mean([], 5).shape == (0,)
    with pytest.raises(ValueError, match="window"):
        rolling_mean(values, 0)


def test_every_figure_is_a_png(reported: tuple[Path, dict]) -> None:
    run, _ = reported
    written = sorted(path.name for path in (run / "report").glob("*.png"))
    assert written == sorted(FIGURES)  # the curriculum moved, so complexity.png is there too
    for name in written:
        data = (run / "report" / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000, name
    assert not [path for path in (run / "report").iterdir() if path.name.startswith(".")]


def test_report_lists_evaluations_and_links_figures(reported: tuple[Path, dict]) -> None:
    run, _ = reported
    text = (run / "report" / "report.md").read_text()
    assert text.startswith("# Training report: t\n")
    assert "sac, encoder mlp" in text
    assert "304 env steps of a budget of 30000, 150 episodes, 1000 gradient updates" in text
    assert "**Last held-out evaluation:** 2/4 aligned at 300 env steps" in text
    assert "no final edge width measured" in text
    assert "(kept in checkpoints/best.pt): 3/4 aligned at 200 env steps" in text
    assert "| 100 | 1/4 | 5 | 9.0 | 3.10 | 0.5 |" in text
    assert "| 200 | 3/4 | 3 | 6.5 | 2.80 | 0.4 |" in text
    assert "| 300 | 2/4 | 2.5 | 4.0 | - | 0.4 |" in text
    for name in FIGURES:
        assert f"]({name})" in text
    assert "Not plotted" not in text


def test_report_touches_nothing_else_in_the_run(reported: tuple[Path, dict]) -> None:
    run, before = reported
    after = {name: state for name, state in snapshot(run).items() if not name.startswith("report")}
    assert after == before


def test_empty_metrics_still_give_a_report(tmp_path: Path) -> None:
    """A run killed before its first episode: headers only, and no updates.csv at all."""
    run = make_run(tmp_path, [], [EPISODES], [EVALUATIONS])
    report = write_run_report(run, tmp_path / "out")
    assert report.figures.written == []
    assert report.figures.skipped == {
        "reward.png": "metrics/episodes.csv has no rows yet",
        "losses.png": "metrics/updates.csv is missing",
        "success.png": "metrics/episodes.csv has no rows yet and metrics/evaluations.csv has "
        "no rows yet",
        "acquisitions.png": "metrics/episodes.csv has no rows yet and metrics/evaluations.csv "
        "has no rows yet",
        "complexity.png": "metrics/episodes.csv has no rows yet",
    }
    text = report.markdown.read_text()
    assert "0 env steps" in text and "none yet (metrics/evaluations.csv has no rows yet)" in text
    assert "## Not plotted" in text and "- losses.png: metrics/updates.csv is missing" in text
    assert not list((tmp_path / "out").glob("*.png"))


@pytest.mark.parametrize(
    ("table", "lines", "message"),
    [
        (
            "episodes",
            [EPISODES, "8,1,0.5,1,2,1.0", "8,2,abc,0,3,1.0"],
            r"episodes\.csv, line 3, column return: 'abc' is not a number",
        ),
        (
            "evaluations",
            ["env_steps,scenarios", "100,4"],
            r"evaluations\.csv: no column 'successes'",
        ),
        (
            "updates",
            [SAC_UPDATES, "100,50,-0.5,1.5,1.4,0.3,1.2"],
            r"updates\.csv, line 2: 7 fields, the header has 8",
        ),
    ],
)
def test_a_malformed_csv_names_the_file_and_the_place(
    tmp_path: Path, table: str, lines: list[str], message: str
) -> None:
    files = {"updates": [SAC_UPDATES], "episodes": [EPISODES], "evaluations": [EVALUATIONS]}
    files[table] = lines
    run = make_run(tmp_path, files["updates"], files["episodes"], files["evaluations"])
    with pytest.raises(ReportError, match=message):
        write_run_report(run)
    assert not (run / "report").exists()


def test_ppo_updates_get_one_panel_per_column(tmp_path: Path) -> None:
    path = tmp_path / "updates.csv"
    path.write_text(
        "env_steps,updates,policy_loss,value_loss,entropy,approx_kl,clip_fraction,explained_var\n"
        "2048,10,-0.01,0.8,1.4,0.004,0.12,0.3\n"
        "4096,20,-0.02,0.6,1.3,0.006,0.15,0.5\n"
    )
    figure = losses_figure(read_metrics_csv(path, ("env_steps", "updates")))
    titles = [axes.get_title() for axes in figure.axes]
    assert titles == [
        "Policy loss (seed fig. 6.1.2)",
        "Value loss",
        "Policy entropy (seed fig. 6.1.6)",
        "Approximate KL divergence",
        "Clipped fraction",
        "explained_var",  # unknown to the report: plotted under its own name
    ]


def test_cli_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    episodes = [f"{8 * (i + 1)},{i + 1},0.5,{i % 2},3,1.0" for i in range(10)]
    run = make_run(tmp_path, [SAC_UPDATES], [EPISODES, *episodes], [EVALUATIONS])
    out = tmp_path / "elsewhere"
    assert main(["report", str(run), "--out", str(out), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["report"] == str(out / "report.md") and (out / "report.md").exists()
    assert payload["figures"] == [
        str(out / name) for name in ("reward.png", "success.png", "acquisitions.png")
    ]
    assert all(Path(name).read_bytes().startswith(PNG_MAGIC) for name in payload["figures"])
    assert set(payload["skipped"]) == {"losses.png", "complexity.png"}

    assert main(["report", str(tmp_path)]) == 2
    assert "is not a run directory (no config.yaml)" in capsys.readouterr().err

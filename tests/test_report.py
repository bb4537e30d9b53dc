"""`alignrl report`: training figures, report.md and report.html from a run directory's metrics
CSVs; every success figure of a session with its 95 % Wilson interval, the test session
(metrics/test.csv) apart from the validation sessions that chose best.pt."""

from __future__ import annotations

import html
import json
import re
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np
import pandas as pd
import pytest
from matplotlib.container import ErrorbarContainer
from PIL import Image

import alignrl.plots
from alignrl.cli import main
from alignrl.config.experiment import ExperimentConfig, dump_experiment
from alignrl.intervals import wilson
from alignrl.plots import (
    FIGURES,
    draw_success,
    drawn_from,
    losses_figure,
    panel_figure,
    rolling_mean,
    rolling_success_interval,
)
from alignrl.run_tables import ReportError, read_metrics_csv
from alignrl.runs.report import write_run_report

PACKAGE = Path(__file__).resolve().parent.parent / "alignrl"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SAC_UPDATES = "env_steps,updates,policy_loss,q1_loss,q2_loss,v_loss,entropy,alpha"
EPISODES = "env_steps,episode,return,success,acquisitions,complexity"
EVALUATIONS = (
    "env_steps,successes,scenarios,median_acquisitions,p90_acquisitions,median_final_px,seconds"
)
TEST = (
    "env_steps,checkpoint_env_steps,seed,successes,scenarios,success_rate_low,"
    "success_rate_high,median_acquisitions,p90_acquisitions,median_final_px,seconds"
)
TESTED = "304,200,2000000,7,10,0.3968,0.8922,3.5,6.0,2.9,0.5"  # best.pt: 7/10 on the test seed


def make_run(
    root: Path,
    updates: list[str],
    episodes: list[str],
    evaluations: list[str],
    test: list[str] | None = None,
) -> Path:
    """A run directory as alignrl/training.py leaves it: config.yaml and the metrics CSVs,
    each given as its lines (header first; an empty list or None leaves the file out)."""
    run = root / "t"
    (run / "metrics").mkdir(parents=True)
    (run / "config.yaml").write_text(dump_experiment(ExperimentConfig(name="t")))
    for name, lines in (
        ("updates", updates),
        ("episodes", episodes),
        ("evaluations", evaluations),
        ("test", test or []),
    ):
        if lines:
            (run / "metrics" / f"{name}.csv").write_text("".join(f"{line}\n" for line in lines))
    return run


def full_run(root: Path) -> Path:
    """A finished run: 150 episodes with a curriculum step at episode 75, 20 update rows, 3
    validation sessions (the last with no edges measured, as the trainer writes it: a blank
    median_final_px) and the test session of best.pt (that of 200 env steps)."""
    episodes = [
        f"{8 * (i // 4 + 1)},{i + 1},{0.1 * i:.1f},{i % 2},{1 + i % 5},{0.1 if i < 75 else 0.2}"
        for i in range(150)
    ]
    updates = [f"{100 + 8 * i},{50 * (i + 1)},-0.5,1.5,1.4,0.3,1.2,0.19" for i in range(20)]
    evaluations = ["100,1,4,5.0,9.0,3.1,0.5", "200,3,4,3.0,6.5,2.8,0.4", "300,2,4,2.5,4.0,,0.4"]
    return make_run(
        root,
        [SAC_UPDATES, *updates],
        [EPISODES, *episodes],
        [EVALUATIONS, *evaluations],
        [TEST, TESTED],
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
    assert "**Last validation session:** 2/4 (15-85 %) aligned at 300 env steps" in text
    assert "no final edge width measured" in text
    assert "(kept in checkpoints/best.pt):** 3/4 (30-95 %) aligned at 200 env steps" in text
    assert "| 100 | 1/4 (5-70 %) | 5 | 9.0 | 3.10 | 0.5 |" in text
    assert "| 200 | 3/4 (30-95 %) | 3 | 6.5 | 2.80 | 0.4 |" in text
    assert "| 300 | 2/4 (15-85 %) | 2.5 | 4.0 | - | 0.4 |" in text
    # The test session, apart: its seed, the checkpoint it tested, its interval.
    assert (
        "**Test session:** 7/10 (40-89 %) aligned on seed 2000000 by best.pt of 200 env steps"
        in text
    )
    assert "| 2000000 | 200 | 7/10 (40-89 %) | 3.5 | 6.0 | 2.90 | 0.5 |" in text
    for name in FIGURES:
        assert f"]({name})" in text
    assert "Not plotted" not in text


def test_report_touches_nothing_else_in_the_run(reported: tuple[Path, dict]) -> None:
    run, before = reported
    after = {name: state for name, state in snapshot(run).items() if not name.startswith("report")}
    assert after == before


def test_a_report_written_again_redraws_only_what_changed(tmp_path: Path) -> None:
    """Each PNG carries a digest of what it was drawn from: written again from the same
    tables it is kept (the very file), from other tables, or where the PNG was damaged or
    replaced by hand, it is drawn anew."""
    run = full_run(tmp_path)
    first = write_run_report(run).figures.written
    files = {path.name: path.stat().st_ino for path in first}
    (digest,) = {drawn_from(path) for path in first}
    assert digest is not None
    (run / "report" / "losses.png").write_bytes(PNG_MAGIC + b"damaged")
    Image.new("RGB", (4, 4)).save(run / "report" / "reward.png")  # a PNG drawn elsewhere
    again = write_run_report(run).figures.written
    assert again == first and all(drawn_from(path) == digest for path in again)
    kept = {path.name for path in again if path.stat().st_ino == files[path.name]}
    assert kept == set(files) - {"losses.png", "reward.png"}
    files = {path.name: path.stat().st_ino for path in again}
    episodes = run / "metrics" / "episodes.csv"
    episodes.write_text(episodes.read_text() + "1208,151,0.5,1,2,0.2\n")  # one more episode
    redrawn = write_run_report(run).figures.written
    (changed,) = {drawn_from(path) for path in redrawn}
    assert changed not in (None, digest)
    assert not {path.name for path in redrawn if path.stat().st_ino == files[path.name]}


def test_a_figure_kept_as_it_was_is_not_drawn_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = full_run(tmp_path)
    first = write_run_report(run).figures.written

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a figure was drawn though its PNG was drawn from these tables")

    monkeypatch.setattr(alignrl.plots, "panel_figure", refuse)
    monkeypatch.setattr(alignrl.plots, "losses_figure", refuse)
    assert write_run_report(run).figures.written == first


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
    assert "## Not plotted" in text and "- **losses.png:** metrics/updates.csv is missing" in text
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
    assert payload["html"] == str(out / "report.html") and (out / "report.html").exists()
    assert payload["figures"] == [
        str(out / name) for name in ("reward.png", "success.png", "acquisitions.png")
    ]
    assert all(Path(name).read_bytes().startswith(PNG_MAGIC) for name in payload["figures"])
    assert set(payload["skipped"]) == {"losses.png", "complexity.png"}

    assert main(["report", str(run), "--out", str(out)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == f"{run}: report in {out / 'report.md'} and {out / 'report.html'}"

    assert main(["report", str(tmp_path)]) == 2
    assert "is not a run directory (no config.yaml)" in capsys.readouterr().err


def page_images(page: Path) -> list[str]:
    """The src of every <img> of an HTML page, as paths relative to it."""
    return [
        unquote(html.unescape(src)) for src in re.findall(r'<img src="([^"]+)"', page.read_text())
    ]


def test_the_html_report_says_what_the_markdown_says_and_its_figures_exist(
    reported: tuple[Path, dict],
) -> None:
    run, _ = reported
    folder = run / "report"
    page = (folder / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "<title>Training report: t</title>" in page
    markdown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (folder / "report.md").read_text())
    assert page_images(folder / "report.html") == markdown == list(FIGURES)
    for name in markdown:
        assert (folder / name).read_bytes().startswith(PNG_MAGIC), name
    # The same sessions, with their intervals, in both.
    assert "<td>2000000</td><td>200</td><td>7/10 (40-89 %)</td>" in page
    assert "<td>100</td><td>1/4 (5-70 %)</td>" in page


def test_a_run_not_finished_has_no_test_session_yet(tmp_path: Path) -> None:
    episodes = [f"{8 * (i + 1)},{i + 1},0.5,{i % 2},3,1.0" for i in range(10)]
    run = make_run(tmp_path, [SAC_UPDATES], [EPISODES, *episodes], [EVALUATIONS, "40,1,2,3,4,,1"])
    text = write_run_report(run).markdown.read_text()
    assert (
        "**Test session:** none yet: it runs when the training has finished "
        "(metrics/test.csv is missing)" in text
    )


def errorbars(axes: Any) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per labelled error bar series of `axes`: x, y, and the (low, high) ends of its bars."""
    found = {}
    for container in axes.containers:
        if not isinstance(container, ErrorbarContainer):
            continue
        data, _, (bars,) = container.lines
        ends = np.array([segment[:, 1] for segment in bars.get_segments()])
        x, y = (np.asarray(values, float) for values in data.get_data())
        found[container.get_label()] = (x, y, ends)
    return found


def test_every_session_point_carries_its_wilson_interval() -> None:
    episodes = pd.DataFrame({"env_steps": [8.0, 16.0], "success": [1.0, 0.0]})
    evaluations = pd.DataFrame(
        {"env_steps": [10.0, 20.0], "successes": [1, 4], "scenarios": [4, 4]}
    )
    test = pd.DataFrame(
        {
            "checkpoint_env_steps": [20.0],
            "seed": [2000000.0],
            "successes": [7.0],
            "scenarios": [10.0],
        }
    )
    figure = panel_figure(draw_success, episodes, evaluations, test=test)
    series = errorbars(figure.axes[0])
    x, y, ends = series["validation sessions (95 % interval)"]
    np.testing.assert_allclose(x, [10, 20])
    np.testing.assert_allclose(y, [25, 100])
    np.testing.assert_allclose(ends, 100 * np.array([wilson(1, 4), wilson(4, 4)]))
    assert ends[1, 1] == 100.0  # 4/4: the interval ends at 100 %, as Wilson's does
    x, y, ends = series["test session, seed 2000000 (95 % interval)"]
    np.testing.assert_allclose([x[0], y[0]], [20, 70])
    np.testing.assert_allclose(ends[0], [39.68, 89.22], atol=0.01)  # worked out by hand
    # The training curve's band: the interval of each window's successes (1 of 1, 1 of 2).
    (band,) = figure.axes[0].collections[:1]
    edge = band.get_paths()[0].vertices[:, 1]
    low, high = rolling_success_interval([1, 0], 100)
    np.testing.assert_allclose([low[1], high[1]], [0.0945, 0.9055], atol=1e-4)  # by hand
    for bound in (*low, *high):
        assert np.isclose(edge, 100 * bound).any(), bound


def test_the_rolling_interval_counts_the_windows_successes() -> None:
    low, high = rolling_success_interval([1, 0, 1, 1], window=2)
    # Windows: 1/1, 1/2, 1/2, 2/2.
    expected = np.array([wilson(1, 1), wilson(1, 2), wilson(1, 2), wilson(2, 2)])
    np.testing.assert_allclose(np.column_stack([low, high]), expected)
    assert high[0] == high[3] == 1.0 and 0.09 < low[1] < 0.1


def test_html_is_written_by_one_module() -> None:
    """The reports' HTML has one home, alignrl/report_document.py (training and league)."""
    writers = sorted(
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if re.search(r"<!DOCTYPE|<html|<img ", path.read_text())
    )
    assert writers == ["report_document.py"]

"""Evaluation sessions: the same scenarios and starts for every controller, acquisitions
counted and capped, one verification image judged against the threshold, clear errors for
what cannot be evaluated, and the `evaluate` / `baselines` verbs."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from fake_drivers import ParabolicLens

from alignrl.apparatus import Apparatus, NoEdgesError, make_apparatus
from alignrl.cli import main
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import BASELINES, GoldenSection, HyperbolaFit, get_baseline
from alignrl.evaluation.controllers import BudgetExhausted, CountingApparatus
from alignrl.evaluation.session import run_session

FOCUS = get_task("focus")
LENS = "fake_drivers:ParabolicLens"  # knows its optimum, not its best edge width
TEN_NINETY = 2.563
SPEC_PX = 1.15 * TEN_NINETY


class StayPut:
    """A controller that trusts the start: one acquisition, no change."""

    name = "stay-put"

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        try:
            apparatus.measure()
        except NoEdgesError:
            pass


class ProtocolOnly:
    """A driver with the bare Apparatus protocol: no optimum, no best edge width."""

    def __init__(self) -> None:
        self.inner = ParabolicLens()
        self.knobs = self.inner.knobs

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)

    def read(self) -> dict[str, float]:
        return self.inner.read()

    def write(self, values: Mapping[str, float]) -> None:
        self.inner.write(values)

    def measure(self) -> float:
        return self.inner.measure()

    def image(self) -> None:
        return None


class ReferencedLens(ParabolicLens):
    """ParabolicLens that also tells its best edge width, like a simulator."""

    def best_quality(self) -> float:
        return TEN_NINETY * self.sigma0


class CondenserOnly(ParabolicLens):
    """An apparatus whose only knob is not the focus task's."""

    def __init__(self) -> None:
        super().__init__()
        self.knobs = {"condenser": (0.0, 10.0)}


# --- the session ------------------------------------------------------------------------------


def test_every_controller_starts_from_the_same_settings() -> None:
    apparatus = make_apparatus("csv:default", {"split": "test"})
    sessions = [
        run_session(get_baseline(name), apparatus, FOCUS, scenarios=30, seed=11)
        for name in sorted(BASELINES)
    ]
    starts = [[record.start for record in session.records] for session in sessions]
    optima = [[record.optimum for record in session.records] for session in sessions]
    assert starts[0] == starts[1] == starts[2]
    assert optima[0] == optima[1] == optima[2]  # the same scenarios, too
    other = run_session(GoldenSection(), apparatus, FOCUS, scenarios=30, seed=12)
    assert [record.start for record in other.records] != starts[0]


def test_starts_cover_the_interval_independently_of_the_optimum() -> None:
    # ParabolicLens draws its optimum as the first uniform of default_rng(reset seed); a
    # start drawn from the same generator would sit at a fixed offset from it.
    apparatus = make_apparatus(LENS)
    result = run_session(StayPut(), apparatus, FOCUS, scenarios=300, seed=0, spec_px=SPEC_PX)
    starts = np.array([record.start for record in result.records])
    optima = np.array([record.optimum for record in result.records])
    assert 0.0 <= starts.min() < 5.0 and 95.0 < starts.max() <= 100.0
    assert abs(np.corrcoef(starts, optima)[0, 1]) < 0.2


def test_the_verification_image_is_acquired_once_and_not_counted() -> None:
    apparatus = ReferencedLens()
    calls = apparatus.calls
    result = run_session(HyperbolaFit(), apparatus, FOCUS, scenarios=10, seed=2)
    assert apparatus.calls - calls == sum(r.acquisitions for r in result.records) + 10
    for record in result.records:
        assert record.threshold_px == pytest.approx(1.15 * TEN_NINETY)
        assert record.success == (record.final_width_px <= record.threshold_px)


def test_summary_statistics_follow_the_records() -> None:
    apparatus = make_apparatus("csv:default", {"split": "test"})
    result = run_session(get_baseline("hill-climb"), apparatus, FOCUS, scenarios=60, seed=1)
    acquisitions = [record.acquisitions for record in result.records]
    widths = [record.final_width_px for record in result.records]
    assert result.scenarios == 60
    assert result.successes == sum(record.success for record in result.records)
    assert result.median_acquisitions == np.median(acquisitions)
    assert result.p90_acquisitions == np.percentile(acquisitions, 90)
    assert result.final_width_stats()["max"] == max(widths)
    errors = [abs(record.final_setting - record.optimum) for record in result.records]
    assert result.optimum_error_stats()["median"] == pytest.approx(np.median(errors))


def test_a_small_budget_ends_alignments_where_the_knob_is() -> None:
    apparatus = make_apparatus(LENS)
    result = run_session(GoldenSection(), apparatus, FOCUS, scenarios=20, budget=2, spec_px=SPEC_PX)
    assert result.budget_exhausted == 20
    for record in result.records:
        assert record.acquisitions == 2
        # The third probe was written but not acquired; the verification image is taken
        # wherever the knob was left.
        assert record.final_width_px is not None
        assert len(record.trajectory) == 2
    assert result.successes < 20


def test_a_verification_without_edges_is_a_failure() -> None:
    apparatus = make_apparatus(LENS, {"blind_beyond_v": 5.0})
    result = run_session(StayPut(), apparatus, FOCUS, scenarios=40, seed=3, spec_px=SPEC_PX)
    blind = [r for r in result.records if abs(r.start - r.optimum) > 5.0]
    assert blind and all(r.final_width_px is None and not r.success for r in blind)
    assert result.unmeasured == len(blind)
    assert all(width is None for r in blind for _, width in r.trajectory)


def test_a_task_knob_the_apparatus_lacks_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"needs knob\(s\) defocus; the apparatus has condenser"):
        run_session(GoldenSection(), CondenserOnly(), FOCUS, scenarios=1)


def test_a_relative_threshold_needs_an_apparatus_that_knows_its_best() -> None:
    with pytest.raises(ValueError, match="--spec-px"):
        run_session(GoldenSection(), make_apparatus(LENS), FOCUS, scenarios=1)
    result = run_session(GoldenSection(), ProtocolOnly(), FOCUS, scenarios=10, spec_px=3.0)
    assert result.successes == 10
    assert all(record.threshold_px == 3.0 and record.optimum is None for record in result.records)
    assert result.optimum_error_stats() is None


def test_an_unreachable_spec_is_refused_where_the_apparatus_knows_its_best() -> None:
    with pytest.raises(ValueError, match=r"sharper than this apparatus can focus in 3 of 3"):
        run_session(GoldenSection(), make_apparatus("synthetic"), FOCUS, scenarios=3, spec_px=0.5)
    # A real instrument cannot tell: the session runs, and nothing meets the spec.
    result = run_session(GoldenSection(), ProtocolOnly(), FOCUS, scenarios=5, spec_px=0.5)
    assert result.successes == 0 and result.scenarios == 5


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_spec_px_must_be_a_positive_width(bad: float) -> None:
    with pytest.raises(ValueError, match="positive edge width"):
        run_session(GoldenSection(), ReferencedLens(), FOCUS, scenarios=1, spec_px=bad)


def test_the_baselines_align_the_noisy_synthetic_column() -> None:
    apparatus = make_apparatus("synthetic")
    for controller in (GoldenSection(), HyperbolaFit()):
        result = run_session(controller, apparatus, FOCUS, scenarios=4, seed=0)
        assert result.successes == 4, controller.name
        assert result.final_width_stats()["max"] <= 1.15 * apparatus.best_quality()


# --- the acquisition counter ------------------------------------------------------------------


def test_counting_apparatus_counts_records_and_stops_at_the_budget() -> None:
    apparatus = ParabolicLens(blind_beyond_v=10.0)
    apparatus.reset(0)
    counting = CountingApparatus(apparatus, budget=3)
    counting.write({"defocus": apparatus.optimum_v})
    assert counting.measure() == pytest.approx(TEN_NINETY)
    counting.write({"defocus": 0.0})
    with pytest.raises(NoEdgesError):
        counting.measure()
    counting.write({"defocus": apparatus.optimum_v})
    counting.measure()
    with pytest.raises(BudgetExhausted):
        counting.measure()
    assert counting.acquisitions == 3 and apparatus.calls == 3
    assert [shot.width_px is None for shot in counting.trajectory] == [False, True, False]
    assert counting.trajectory[1].settings == {"defocus": 0.0}
    with pytest.raises(RuntimeError, match="session owns it"):
        counting.reset(1)
    with pytest.raises(ValueError, match="at least 1"):
        CountingApparatus(apparatus, budget=0)


# --- the command line -------------------------------------------------------------------------

SESSION_KEYS = {
    "controller",
    "apparatus",
    "scenarios",
    "successes",
    "median_acquisitions",
    "p90_acquisitions",
    "final_quality",
    "threshold_px",
    "seconds",
}


def test_evaluate_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plot = tmp_path / "plots" / "hyperbola.png"
    lens = "test_evaluation:ReferencedLens"
    argv = ["evaluate", "--policy", "hyperbola", "--apparatus", lens, "--scenarios", "12"]
    assert main([*argv, "--seed", "4", "--plot", str(plot), "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert SESSION_KEYS <= set(report)
    assert report["controller"] == "hyperbola" and report["apparatus"] == lens
    assert report["scenarios"] == 12 and report["successes"] == 12
    assert report["median_acquisitions"] == 5 and report["p90_acquisitions"] == 5
    assert set(report["final_quality"]) == {"median_px", "p90_px", "max_px", "unmeasured"}
    assert report["final_quality"]["max_px"] == pytest.approx(TEN_NINETY, abs=1e-3)
    assert report["threshold_px"] == pytest.approx(1.15 * TEN_NINETY, abs=1e-3)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_baselines_side_by_side(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["baselines", "--apparatus", "csv:default", "--scenarios", "20", "--quiet"]
    args = ["--apparatus-args", '{"split": "test"}', "--plot-dir", str(tmp_path)]
    assert main([*argv, *args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["apparatus"] == "csv:default" and report["scenarios"] == 20
    assert set(report["controllers"]) == set(BASELINES)
    for name, session in report["controllers"].items():
        assert SESSION_KEYS <= set(session)
        assert session["controller"] == name
        assert Path(session["plot"]).is_file()
    assert main([*argv, "--apparatus-args", '{"split": "test"}']) == 0
    table = capsys.readouterr().out
    for name in BASELINES:
        assert name in table
    assert "successes" in table and "20 scenarios" in table


def test_evaluate_refuses_an_unknown_policy(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["evaluate", "--policy", "autofocus", "--apparatus", LENS, "--scenarios", "3"]
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert "unknown policy 'autofocus'" in error
    assert "golden-section, hill-climb, hyperbola" in error


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--spec-px", "0.5", "--apparatus", "synthetic"], "sharper than this apparatus"),
        (["--apparatus", LENS], "give an absolute spec with --spec-px"),
        (["--apparatus", "test_evaluation:CondenserOnly"], "needs knob(s) defocus"),
        (["--apparatus", LENS, "--task", "astigmatism"], "unknown task 'astigmatism'"),
        (["--apparatus", LENS, "--scenarios", "0"], "--scenarios must be at least 1"),
        (["--apparatus", LENS, "--budget", "0"], "--budget must be at least 1"),
        (["--apparatus", LENS, "--apparatus-args", "{noise"], "not valid JSON"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(
    extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["evaluate", "--policy", "golden-section", "--scenarios", "2", "--quiet"]
    assert main([*argv, *extra]) == 2
    assert message in capsys.readouterr().err


def test_ctrl_c_ends_a_session_without_a_report(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--apparatus", LENS, "--apparatus-args", '{"interrupt_at_reset": 3}']
    argv = ["baselines", *args, "--spec-px", "3", "--scenarios", "5", "--quiet", "--json"]
    assert main(argv) == 130
    captured = capsys.readouterr()
    assert captured.out == "" and "interrupted" in captured.err

"""Evaluation sessions of the multi-knob tasks (stigmation, aperture, column): the same starts
for every controller, knobs outside the task at their optimum, every image counted (a wobble
is two), the verification judged on every measure of the task and not counted; focus
sessions exactly as before; the stigmator, aperture and column baselines; the CLI."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from fake_drivers import FiveKnobColumn, ParabolicLens

from alignrl.apparatus import Apparatus, make_apparatus
from alignrl.apparatus.measures import measure_directional, measure_wobble
from alignrl.apparatus.recorder import scenario_seed
from alignrl.cli import main
from alignrl.envs.core import feature_layout
from alignrl.envs.task import Task, get_task
from alignrl.evaluation.baselines import (
    CLASSICAL,
    TASK_BASELINES,
    ColumnSequence,
    StigmatorSearch,
    WobbleCenter,
    get_baseline,
    task_baselines,
)
from alignrl.evaluation.controllers import (
    BudgetExhausted,
    CountingApparatus,
    PolicyController,
    TaskController,
)
from alignrl.evaluation.session import default_budget, run_session

TEN_NINETY = 2.563
FOCUS, STIGMATION, APERTURE, COLUMN = (
    get_task(name) for name in ("focus", "stigmation", "aperture", "column")
)
NEW_TASKS = (STIGMATION, APERTURE, COLUMN)
COLUMN_SPEC = "test_evaluation_column:Column"


class Column(FiveKnobColumn):
    """The five-knob fake column with its image axes 30 degrees from the aperture's."""

    def __init__(self, rotation_deg: float = 30.0) -> None:
        super().__init__(rotation_deg)


class ImagedAperture(FiveKnobColumn):
    """A column without a native wobble: it gives images (a texture shifted by the aperture
    residual, px per um), so measures.measure_wobble acquires the two frames itself."""

    measure_wobble = None  # type: ignore[assignment]

    def __init__(self) -> None:
        super().__init__()
        self.texture = np.random.default_rng(7).random((64, 64))

    def measure(self) -> float:
        width = super().measure()
        swing = self.setting["defocus"] - self.best["defocus"]
        shift = np.round(self.shift_gain * swing * self.residual("aperture")).astype(int)
        self.frame = np.roll(self.texture, (int(shift[1]), int(shift[0])), axis=(0, 1))
        return width

    def image(self) -> np.ndarray:  # type: ignore[override]
        return self.frame


class NoDefocus(Column):
    """Aperture and stigmators, but no lens to wobble (the focus is fixed, and right) and no
    native wobble."""

    knobs: Mapping[str, tuple[float, float]] = {
        k: v for k, v in Column.knobs.items() if k != "defocus"
    }
    measure_wobble = None  # type: ignore[assignment]

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.setting["defocus"] = self.best["defocus"]

    def read(self) -> dict[str, float]:
        return {knob: value for knob, value in self.setting.items() if knob in self.knobs}


class Recorder:
    """A task controller that looks at the column as the session hands it over (through the
    test's own reference: controllers themselves never see the optimum) and stays put."""

    name = "recorder"

    def __init__(self, column: Column) -> None:
        self.column = column
        self.seen: list[tuple[dict[str, float], dict[str, float]]] = []

    def check_task(self, task: Task) -> None:
        pass

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        self.seen.append((self.column.read(), self.column.optimum()))


class Oracle:
    """Puts every knob at its optimum, except `offsets` (knob -> units off), without an
    acquisition."""

    name = "oracle"

    def __init__(self, column: Column, **offsets: float) -> None:
        self.column, self.offsets = column, offsets

    def check_task(self, task: Task) -> None:
        pass

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        best = self.column.optimum()
        apparatus.write({k: v + self.offsets.get(k, 0.0) for k, v in best.items()})


class Wobbler:
    """Wobbles until stopped: only the budget ends it."""

    name = "wobbler"

    def check_task(self, task: Task) -> None:
        pass

    def align_task(self, apparatus: Apparatus, task: Task, budget: int) -> None:
        while True:
            measure_wobble(apparatus, task.wobble_amplitude(apparatus.knobs))


# --- sessions of several knobs ----------------------------------------------------------------


def test_starts_are_the_same_for_every_controller_and_other_knobs_sit_at_their_optimum() -> None:
    column = Column()
    recorder = Recorder(column)
    watched = run_session(recorder, column, STIGMATION, scenarios=8, seed=5)
    searched = run_session(StigmatorSearch(), column, STIGMATION, scenarios=8, seed=5)
    assert [r.starts for r in watched.records] == [r.starts for r in searched.records]
    assert [r.optima for r in watched.records] == [r.optima for r in searched.records]
    for record, (settings, optimum) in zip(watched.records, recorder.seen, strict=True):
        assert set(record.starts) == {"stigmator_x", "stigmator_y"}
        for knob in ("defocus", "aperture_x", "aperture_y"):
            assert settings[knob] == optimum[knob]  # the session aligned what the task does not
        assert {k: settings[k] for k in record.starts} == record.starts
    other = run_session(recorder, column, STIGMATION, scenarios=8, seed=6)
    assert [r.starts for r in other.records] != [r.starts for r in watched.records]


def test_every_task_knob_starts_uniformly_over_its_interval() -> None:
    result = run_session(Recorder(Column()), Column(), COLUMN, scenarios=200, seed=1)
    for knob, (low, high) in Column.knobs.items():
        starts = np.array([record.starts[knob] for record in result.records])
        span = high - low
        assert low <= starts.min() < low + 0.05 * span and high - 0.05 * span < starts.max() <= high
    first, second = ([r.starts[k] for r in result.records] for k in COLUMN.knobs[:2])
    assert abs(np.corrcoef(first, second)[0, 1]) < 0.2


@pytest.mark.parametrize("seed", [0, 3, 11])
def test_focus_starts_are_the_ones_sessions_always_drew(seed: int) -> None:
    lens = ParabolicLens()
    result = run_session(
        Recorder(Column()), lens, FOCUS, scenarios=10, seed=seed, spec_px=1.15 * TEN_NINETY
    )
    for index, record in enumerate(result.records):
        # The formula before multi-knob sessions: one uniform of this generator.
        generator = np.random.default_rng([scenario_seed(seed, index), 1])
        assert record.start == float(generator.uniform(0.0, 100.0))
        assert record.starts == {"defocus": record.start}
        assert record.final_setting == record.start and record.trajectory == ()
    assert result.knob == "defocus" and result.budget == 50


def test_a_wobble_counts_two_acquisitions_and_the_verification_none() -> None:
    column = Column()
    before = column.images
    result = run_session(WobbleCenter(), column, APERTURE, scenarios=6, seed=2)
    # The verification: one image and one wobble (two) per scenario, not counted.
    assert column.images - before == sum(r.acquisitions for r in result.records) + 3 * 6
    for record in result.records:
        kinds = [shot.kind for shot in record.shots]
        assert len(kinds) == record.acquisitions and set(kinds) == {"wobble"}
        assert record.acquisitions % 2 == 0


def test_the_counter_counts_native_measures_and_offers_only_what_the_apparatus_has() -> None:
    column = Column()
    counting = CountingApparatus(column, budget=4)
    width, widths = measure_directional(counting)
    assert widths.shape == (4,) and counting.acquisitions == 1
    assert counting.trajectory[0].width_px == width
    shift = measure_wobble(counting, 5.0)
    assert shift.shape == (2,) and counting.acquisitions == 3
    with pytest.raises(BudgetExhausted, match="2 more needed"):
        measure_wobble(counting, 5.0)  # one acquisition left: a wobble needs two
    assert counting.acquisitions == 3 and column.images == 3
    lens = CountingApparatus(ParabolicLens(), budget=4)
    assert not hasattr(lens, "measure_wobble") and not hasattr(lens, "measure_directional")


def test_a_wobble_read_off_images_is_counted_image_by_image() -> None:
    column = ImagedAperture()
    column.write({"defocus": column.best["defocus"], "aperture_x": column.best["aperture_x"] + 50})
    counting = CountingApparatus(column, budget=10)
    shift = measure_wobble(counting, 5.0)
    assert counting.acquisitions == 2 and column.images == 2
    assert [shot.settings["defocus"] for shot in counting.trajectory] == [
        column.best["defocus"] + 5.0,
        column.best["defocus"] - 5.0,
    ]
    assert np.hypot(*shift) == pytest.approx(10.0, abs=1.0)  # 0.02 px/V/um x 10 V x 50 um
    assert column.read()["defocus"] == column.best["defocus"]  # written back


def test_the_budget_stops_a_wobble_that_does_not_fit() -> None:
    result = run_session(Wobbler(), Column(), APERTURE, scenarios=3, budget=7)
    assert result.budget_exhausted == 3 and result.budget == 7
    assert all(record.acquisitions == 6 for record in result.records)


def test_success_needs_every_measure_within_its_spec() -> None:
    column = Column()
    aligned = run_session(Oracle(column), column, COLUMN, scenarios=5)
    assert aligned.successes == 5
    # 5 um off axis: the probe barely widens (1.03 x best) but the image moves 1 px.
    off = run_session(Oracle(column, aperture_x=5.0), column, COLUMN, scenarios=5)
    assert off.successes == 0
    for record in off.records:
        assert record.final_width_px <= record.threshold_px
        assert max(record.final_directional_px) <= record.directional_threshold_px
        assert record.final_wobble_shift_px == pytest.approx(1.0)
        assert record.optimum_errors()["aperture_x"] == pytest.approx(5.0)
    # 3 V of astigmatism, focused on a line focus: the mean width is 1.08 x best, the
    # probe 1.17 x longer one way. A directional spec of 1.05 x best fails it.
    strict = dataclasses.replace(STIGMATION, directional_relative=1.05)
    astigmatic = Oracle(column, stigmator_x=15.0, defocus=1.5)
    elongated = run_session(astigmatic, column, strict, scenarios=5)
    for record in elongated.records:
        assert record.final_width_px <= record.threshold_px
        assert max(record.final_directional_px) > record.directional_threshold_px
        assert not record.success and record.final_wobble_px is None
    assert elongated.records[0].directional_threshold_px == pytest.approx(1.05 * TEN_NINETY)
    assert run_session(astigmatic, column, STIGMATION, scenarios=5).successes == 5


def test_a_record_of_several_knobs_refuses_one_knob_questions() -> None:
    result = run_session(Recorder(Column()), Column(), APERTURE, scenarios=1)
    record = result.records[0]
    assert record.knobs == ("aperture_x", "aperture_y")
    with pytest.raises(ValueError, match="use starts, final_settings and optima"):
        _ = record.start
    with pytest.raises(ValueError, match="aligns 2 knobs"):
        _ = result.knob
    assert result.optimum_error_stats() is None
    assert set(result.optimum_errors_stats()) == {"aperture_x", "aperture_y"}


def test_the_default_budget_lets_a_column_episode_finish() -> None:
    assert [default_budget(task) for task in (FOCUS, *NEW_TASKS)] == [50, 50, 50, 63]
    assert run_session(Recorder(Column()), Column(), COLUMN, scenarios=1).budget == 63


# --- trained policies -------------------------------------------------------------------------


@pytest.mark.parametrize(("task", "images"), [(COLUMN, 3), (STIGMATION, 1)])
def test_a_policy_drives_every_knob_and_its_wobbles_are_counted(task: Task, images: int) -> None:
    rng = np.random.default_rng(0)
    shapes = set()

    def act(history: np.ndarray) -> np.ndarray:
        shapes.add(history.shape)
        action = rng.uniform(-1, 1, len(task.knobs) + 1)
        action[-1] = -1.0  # never stop: the task's step limit ends the episode
        return action

    policy = PolicyController("random", act, task, history=4)
    column = Column()
    result = run_session(policy, column, task, scenarios=3, seed=1)
    k = len(task.knobs)
    assert shapes == {(4, 5 + 2 * k + task.extra_features)}
    assert feature_layout(k, task.extra_features)["knobs"] == slice(1, 1 + k)
    for record in result.records:
        assert record.acquisitions == images * (task.episode_steps + 1)
        assert not record.budget_exhausted
        assert any(record.final_settings[knob] != record.starts[knob] for knob in task.knobs)
    with pytest.raises(ValueError, match="task 'aperture' has aperture_x, aperture_y"):
        run_session(policy, column, APERTURE, scenarios=1)


# --- the baselines ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("task", "controller", "most"),
    [
        (STIGMATION, StigmatorSearch(), 21),  # 2 x 5 + 1, then a round of 3 + 2 x 3 + 1
        (APERTURE, WobbleCenter(), 8),  # wobble, two calibrations, one correction
        (COLUMN, ColumnSequence(), 39),  # focus 5, aperture 8, stigmators 21, touch-up 5
    ],
)
def test_each_baseline_aligns_a_clean_column(task: Task, controller, most: int) -> None:
    column = Column()
    result = run_session(controller, column, task, scenarios=20, seed=3)
    assert result.successes == 20
    assert result.budget_exhausted == 0 and result.p90_acquisitions <= most
    assert isinstance(controller, TaskController)
    for record in result.records:
        assert all(abs(error) < 1.0 for error in record.optimum_errors().values())


def test_wobble_center_calibrates_the_rotated_response() -> None:
    # Image and aperture axes 90 degrees apart: a correction along the shift would go astray.
    result = run_session(WobbleCenter(), Column(rotation_deg=90.0), APERTURE, scenarios=10)
    assert result.successes == 10 and result.median_acquisitions == 8


def test_wobble_center_works_from_images() -> None:
    result = run_session(WobbleCenter(), ImagedAperture(), APERTURE, scenarios=5, seed=1)
    assert result.successes == 5


@pytest.mark.parametrize(
    ("task", "name"),
    [
        ("stigmation", "stigmator-search"),
        ("aperture", "wobble-center"),
        ("column", "column-sequence"),
    ],
)
def test_the_baselines_align_the_analytic_synthetic_sem(task: str, name: str) -> None:
    apparatus = make_apparatus("synthetic", {"analytic": True})
    result = run_session(get_baseline(name), apparatus, get_task(task), scenarios=20, seed=0)
    assert result.successes >= 18, name
    assert result.budget_exhausted == 0


def test_the_registry_names_each_task_s_baselines() -> None:
    assert list(task_baselines("focus")) == ["golden-section", "hyperbola", "hill-climb"]
    assert {task: list(names) for task, names in TASK_BASELINES.items() if task != "focus"} == {
        "stigmation": ["stigmator-search", "stigmator-solve"],
        "aperture": ["wobble-center", "wobble-solve"],
        "column": ["column-sequence", "column-solve"],
    }
    baselines = {name for names in TASK_BASELINES.values() for name in names}
    # the focus posteriors run by name only (seconds of computing an alignment)
    model_based = {"posterior", "posterior-scale-free", "posterior-robust"}
    assert set(CLASSICAL) == baselines | model_based
    with pytest.raises(ValueError, match="no classical controllers for task 'astigmatism'"):
        task_baselines("astigmatism")
    for make, field in ((StigmatorSearch, "shrink"), (WobbleCenter, "target_fraction")):
        with pytest.raises(ValueError, match=field):
            make(**{field: 0.0})


@pytest.mark.parametrize(
    ("controller", "task", "message"),
    [
        (get_baseline("hyperbola"), COLUMN, "aligns one knob; task 'column' has 5"),
        (WobbleCenter(), STIGMATION, "'wobble-center' aligns aperture_x, aperture_y"),
        (ColumnSequence(), APERTURE, "task 'aperture' has aperture_x, aperture_y, not defocus"),
    ],
)
def test_a_controller_that_cannot_align_the_task_is_refused(controller, task, message) -> None:
    with pytest.raises(ValueError, match=message):
        run_session(controller, Column(), task, scenarios=1)


def test_a_wobble_the_apparatus_cannot_take_is_refused() -> None:
    with pytest.raises(ValueError, match="measures the wobble, which swings 'defocus'"):
        run_session(WobbleCenter(), NoDefocus(), APERTURE, scenarios=1)
    result = run_session(StigmatorSearch(), NoDefocus(), STIGMATION, scenarios=3)
    assert result.successes == 3  # no lens to refocus: the stigmators alone


# --- the command line -------------------------------------------------------------------------


def test_baselines_of_the_aperture_task_as_json(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["baselines", "--task", "aperture", "--apparatus", COLUMN_SPEC, "--scenarios", "6"]
    assert main([*argv, "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["task"] == "aperture" and report["scenarios"] == 6
    assert list(report["controllers"]) == ["wobble-center", "wobble-solve"]
    session = report["controllers"]["wobble-center"]
    assert session["successes"] == 6 and session["budget"] == 50
    assert session["task"] == "aperture" and session["knobs"] == ["aperture_x", "aperture_y"]
    assert session["knob"] is None and session["optimum_error_v"] is None
    assert set(session["optimum_errors"]) == {"aperture_x", "aperture_y"}
    assert set(session["optimum_errors"]["aperture_x"]) == {"median", "p90", "max"}
    wobble = session["final_wobble_px"]
    assert set(wobble) == {"median_px", "p90_px", "max_px", "unmeasured", "spec_px"}
    assert wobble["spec_px"] == 0.5 and wobble["max_px"] <= 0.5 and wobble["unmeasured"] == 0
    assert session["final_directional_px"] is None
    assert main([*argv, "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "classical aperture alignment" in table and "wobble median" in table
    assert "|V-Vopt|" not in table


def test_focus_json_gains_keys_and_keeps_its_own(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["evaluate", "--policy", "hyperbola", "--apparatus", "fake_drivers:ParabolicLens"]
    assert main([*argv, "--spec-px", "3", "--scenarios", "4", "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["knob"] == "defocus" and report["knobs"] == ["defocus"]
    assert report["task"] == "focus" and set(report["optimum_error_v"]) == {"median", "p90", "max"}
    assert report["optimum_errors"] == {"defocus": report["optimum_error_v"]}
    assert report["final_wobble_px"] is None and report["final_directional_px"] is None


def test_evaluate_a_column_with_its_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "column.png"
    argv = ["evaluate", "--policy", "column-sequence", "--task", "column"]
    args = ["--apparatus", COLUMN_SPEC, "--scenarios", "3", "--plot", str(plot), "--quiet"]
    assert main([*argv, *args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["successes"] == 3 and report["budget"] == 63
    assert set(report["final_directional_px"]) == {
        "median_px",
        "p90_px",
        "max_px",
        "unmeasured",
        "threshold_px",
    }
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["baselines", "--task", "astigmatism"], "unknown task 'astigmatism'"),
        (
            ["baselines", "--task", "stigmation", "--apparatus", "fake_drivers:ParabolicLens"],
            "task 'stigmation' needs knob(s) stigmator_x, stigmator_y; the apparatus has defocus",
        ),
        (
            ["evaluate", "--policy", "golden-section", "--task", "column"],
            "controller 'golden-section' aligns one knob; task 'column' has 5",
        ),
        (
            ["evaluate", "--policy", "stigmator-search", "--task", "aperture"],
            "'stigmator-search' aligns stigmator_x, stigmator_y",
        ),
        (["evaluate", "--policy", "wobble"], "wobble-center"),  # the list of known ones
    ],
)
def test_bad_input_exits_2_with_a_clear_message(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    defaults = ["--apparatus", COLUMN_SPEC] if "--apparatus" not in argv else []
    assert main([*argv, *defaults, "--scenarios", "2", "--quiet"]) == 2
    assert message in capsys.readouterr().err

"""The column in stages: tasks that meet the column as the stages before them leave it
(`Task.context`), judged on what they fix (`Task.judged`); a sequence of stage aligners
evaluated as one column alignment (`SequenceController`, `alignrl evaluate --policy A
--policy B --task column`)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from fake_drivers import FiveKnobColumn
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test

from alignrl.envs import AlignmentEnv, DuelEnv
from alignrl.envs.context import align_others
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import get_task
from alignrl.evaluation.controllers import PolicyController, SequenceController
from alignrl.evaluation.session import run_session

STAGES = ("column-focus-aperture", "column-focus-stigmation")
# The API checkers' advisory UserWarnings are not what these tests judge.
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.mark.parametrize("name", STAGES)
def test_the_stage_tasks_pass_the_api_checkers(name: str) -> None:
    check_env(AlignmentEnv(apparatus=FiveKnobColumn(), task=name, history=4))
    api_test(DuelEnv(apparatus=FiveKnobColumn(), task=name, history=4), num_cycles=40)


def test_the_stages_together_move_every_knob_of_the_column() -> None:
    knobs = {knob for name in STAGES for knob in get_task(name).knobs}
    assert knobs == set(get_task("column").knobs)
    # Each stage meets the knobs it does not move misaligned, the ones the stage after it
    # moves anywhere in their intervals.
    first, second = (get_task(name) for name in STAGES)
    assert set(first.context) == set(second.knobs) - set(first.knobs)
    assert set(second.context) == set(first.knobs) - set(second.knobs)


def test_context_knobs_start_off_their_optimum_within_the_offset_and_seeded() -> None:
    context = {"defocus": 4.0, "stigmator_x": 30.0}

    def start(seed: int) -> tuple[dict[str, float], dict[str, float]]:
        unit = FiveKnobColumn()
        unit.reset(seed)
        align_others(unit, ("aperture_x", "aperture_y"), context, seed)
        return unit.read(), unit.optimum()

    offsets = []
    for seed in range(40):
        now, best = start(seed)
        assert start(seed)[0] == now  # the scenario seed fixes the context
        for knob, limit in context.items():
            assert abs(now[knob] - best[knob]) <= limit
            offsets.append(abs(now[knob] - best[knob]) / limit)
        assert now["stigmator_y"] == best["stigmator_y"]  # not in the context: aligned
    assert np.mean(offsets) == pytest.approx(0.5, abs=0.1)  # uniform, not at the bounds
    assert min(offsets) > 0


def test_a_context_wider_than_the_interval_stays_inside_it() -> None:
    unit = FiveKnobColumn()
    for seed in range(30):
        unit.reset(seed)
        align_others(unit, ("aperture_x", "aperture_y"), {"defocus": 500.0}, seed)
        assert 0.0 <= unit.read()["defocus"] <= 100.0


def test_episodes_of_a_stage_start_in_its_context() -> None:
    task = get_task("column-focus-stigmation")
    episodes = AlignmentEpisodes([FiveKnobColumn() for _ in range(16)], task, history=4)
    index = np.arange(episodes.n)
    episodes.begin(index, list(range(100, 116)))
    residuals = []
    for unit in episodes.apparatus:
        now, best = unit.read(), unit.optimum()
        for knob in ("aperture_x", "aperture_y"):
            residuals.append(abs(now[knob] - best[knob]))
    assert max(residuals) <= 2.5 and np.mean(residuals) > 0.5


def test_the_aperture_stage_is_judged_on_the_wobble_alone() -> None:
    task = get_task("column-focus-aperture")
    wide, threshold = np.array([9.0]), np.array([2.9])
    assert task.within_spec(wide, threshold, wobble_px=np.array([[0.3, 0.2]]))[0]
    assert not task.within_spec(wide, threshold, wobble_px=np.array([[0.5, 0.2]]))[0]
    assert not task.within_spec(wide, threshold, wobble_px=np.array([[np.nan, 0.0]]))[0]
    # The whole aperture task judges the width as well.
    assert not get_task("aperture").within_spec(wide, threshold, wobble_px=np.array([[0, 0]]))[0]


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"context": {"defocus": 1.0}}, "a knob the task moves itself"),
        ({"context": {"stigmator_x": 0.0}}, "must be positive"),
        ({"context": {"stigmator_y": float("nan")}}, "must be positive"),
        ({"judged": ("directional",)}, "judged must name measures the task takes"),
        ({"judged": ()}, "judged must name"),
        ({"judged": ("wobble", "wobble")}, "each once"),
    ],
)
def test_bad_contexts_and_judged_measures_are_refused(changes: dict, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        dataclasses.replace(get_task("column-focus-aperture"), **changes)


# --- sequences of stage aligners --------------------------------------------------------------


def _oracle(task_name: str, unit: FiveKnobColumn) -> PolicyController:
    """A stage aligner that reads the secret off the column (the fake's optimum): one move
    to the optimum, then stop."""
    task = get_task(task_name)
    steps = np.array(task.step_sizes(unit.knobs))

    def act(history: np.ndarray) -> np.ndarray:
        best, now = unit.optimum(), unit.read()
        move = np.array([best[k] - now[k] for k in task.knobs]) / steps
        stop = 1.0 if np.all(np.abs(move) < 1e-9) else -1.0
        return np.append(np.clip(move, -1, 1), stop)

    return PolicyController(task_name, act, task, history=4)


def test_a_sequence_of_stage_aligners_aligns_the_whole_column() -> None:
    column = FiveKnobColumn()
    sequence = SequenceController(tuple(_oracle(name, column) for name in STAGES))
    result = run_session(sequence, column, get_task("column"), scenarios=5, seed=3)
    assert result.successes == 5
    # Each stage measures only what its task takes: wobble steps of 3 images, then focus and
    # stigmators at 1 image a step: well under the column's 63 (a wobble every step).
    assert all(record.acquisitions <= 25 for record in result.records), [
        record.acquisitions for record in result.records
    ]
    # Without its second stage the column is not aligned.
    half = SequenceController((_oracle("column-focus-aperture", column),))
    with pytest.raises(ValueError, match="moves stigmator_x, stigmator_y"):
        run_session(half, column, get_task("column"), scenarios=1)


def test_a_stage_moves_only_its_own_knobs() -> None:
    column = FiveKnobColumn()
    stage = _oracle("column-focus-aperture", column)
    column.reset(7)
    before = column.read()
    stage.align_task(column, stage.task, budget=50)
    after = column.read()
    assert after["aperture_x"] != before["aperture_x"]
    for knob in ("stigmator_x", "stigmator_y"):
        assert after[knob] == before[knob]


def test_a_sequence_that_moves_knobs_outside_the_task_is_refused() -> None:
    column = FiveKnobColumn()
    sequence = SequenceController(tuple(_oracle(name, column) for name in STAGES))
    with pytest.raises(ValueError, match="outside task 'aperture'"):
        sequence.check_task(get_task("aperture"))
    with pytest.raises(ValueError, match="at least one stage"):
        SequenceController(())


def test_evaluate_runs_several_trained_policies_in_sequence(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import alignrl.cli as cli
    import alignrl.cli.sessions as sessions

    loaded = []

    def controller(spec: str) -> PolicyController:
        task = get_task(spec.rsplit("/", 1)[-1])
        loaded.append(task.name)

        def act(history: np.ndarray) -> np.ndarray:
            return np.append(np.full(len(task.knobs), 0.1), 1.0)  # one small move, then stop

        return PolicyController(task.name, act, task, history=4)

    monkeypatch.setattr(sessions, "_trained_controller", controller)
    runs = [tmp_path / name for name in STAGES]
    for run in runs:
        run.mkdir()
    argv = ["evaluate", "--apparatus", "fake_drivers:FiveKnobColumn", "--scenarios", "2"]
    policies = [option for run in runs for option in ("--policy", str(run))]
    assert cli.main([*argv, *policies, "--task", "column", "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert loaded == list(STAGES)
    assert report["controller"] == "column-focus-aperture > column-focus-stigmation"
    assert report["scenarios"] == 2
    # Several policies need the task they are judged on; classical ones do not run in one.
    assert cli.main([*argv, *policies, "--quiet"]) == 2
    assert "need --task" in capsys.readouterr().err
    classical = ["--policy", "wobble-center", "--policy", str(runs[1]), "--task", "column"]
    assert cli.main([*argv, *classical, "--quiet"]) == 2
    assert "only trained aligners run in sequence" in capsys.readouterr().err
    unknown = ["--policy", str(runs[0]), "--policy", str(tmp_path / "nowhere"), "--task", "column"]
    assert cli.main([*argv, *unknown, "--quiet"]) == 2
    assert "unknown policy" in capsys.readouterr().err


def test_a_start_reach_caps_where_the_task_knobs_start_in_training_and_sessions() -> None:
    task = get_task("column-focus-stigmation")
    assert task.start_reach == {"defocus": 40.0}
    episodes = AlignmentEpisodes([FiveKnobColumn() for _ in range(32)], task, history=4)
    index = np.arange(episodes.n)
    episodes.begin(index, list(range(32)))
    episodes.misalign(index, np.random.default_rng(0).uniform(-1, 1, (episodes.n, 3)))
    offsets = np.abs(episodes.setting - episodes.aligned)
    assert offsets[:, 0].max() <= 40.0  # the defocus, within its reach
    assert offsets[:, 1:].max() > 60.0  # the stigmators, anywhere in their window
    # An evaluation session draws its starts the same way.
    stage = PolicyController(task.name, lambda h: np.array([0, 0, 0, 1.0]), task, history=4)
    result = run_session(stage, FiveKnobColumn(), task, scenarios=20, seed=4)
    for record in result.records:
        assert abs(record.starts["defocus"] - record.optima["defocus"]) <= 40.0 + 0.5
    assert max(abs(r.starts["stigmator_x"] - r.optima["stigmator_x"]) for r in result.records) > 60


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"start_reach": {"aperture_x": 1.0}}, "not a task knob"),
        ({"start_reach": {"defocus": -1.0}}, "must be positive"),
    ],
)
def test_bad_start_reaches_are_refused(changes: dict, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        dataclasses.replace(get_task("column-focus-stigmation"), **changes)

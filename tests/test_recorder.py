"""The scenario recorder: sweeps, failures, and recordings that survive interruption."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fake_drivers import ParabolicLens

from alignrl.apparatus import read_scenarios
from alignrl.apparatus.recorder import SweepPlan, scenario_seed, sweep, sweep_plan
from alignrl.cli import main

TESTS = Path(__file__).resolve().parent
LENS = "fake_drivers:ParabolicLens"


def lens(**args: object) -> ParabolicLens:
    return ParabolicLens(**args)  # type: ignore[arg-type]


def test_constant_sweep_covers_the_interval_in_equal_steps() -> None:
    apparatus = lens()
    plan = sweep_plan(apparatus.knobs, step="constant")
    record = sweep(apparatus, plan, scenario=4, seed=99)
    assert record is not None
    np.testing.assert_allclose(record.voltages, np.arange(0.0, 100.1, 2.0))
    assert record.scenario == 4 and record.seed == 99 and record.n_failed == 0
    expected = 2.563 * np.hypot(1.0, 0.2 * (record.voltages - apparatus.optimum_v))
    np.testing.assert_allclose(record.edge_widths, expected, atol=5e-5)  # stored to 1e-4 px
    assert plan.max_pairs == 51


def test_adaptive_sweep_is_finer_near_the_focus() -> None:
    apparatus = lens()
    plan = sweep_plan(apparatus.knobs, step="adaptive")
    record = sweep(apparatus, plan, scenario=0, seed=5)
    assert record is not None
    voltages = record.voltages
    assert voltages[0] == 0.0 and voltages[-1] == 100.0
    assert np.all(np.diff(voltages) > 0)
    steps = np.diff(voltages)
    distance = np.abs(voltages[:-1] - apparatus.optimum_v)
    assert steps[distance < 3.0].max() <= 1.5 * plan.min_step_v
    far = distance > 25.0
    far[-1] = False  # the last step is cut short to land on the upper bound
    assert steps[far].min() >= 4.0
    assert len(voltages) < 51  # fewer acquisitions than the constant 2 V sweep
    assert len(voltages) <= plan.max_pairs


def test_failed_acquisitions_are_counted_not_stored() -> None:
    apparatus = lens(blind_beyond_v=25.0)
    plan = sweep_plan(apparatus.knobs, step="constant")
    record = sweep(apparatus, plan, scenario=0, seed=3)
    assert record is not None
    grid = np.arange(0.0, 100.1, 2.0)
    blind = np.abs(grid - apparatus.optimum_v) > 25.0
    np.testing.assert_allclose(record.voltages, grid[~blind])
    assert record.n_failed == int(blind.sum())


def test_driver_faults_are_retried() -> None:
    plan = sweep_plan(lens().knobs, step="constant")
    clean = sweep(lens(), plan, scenario=0, seed=8)
    faulty = sweep(lens(fault_every=3), plan, scenario=0, seed=8)
    assert clean is not None and faulty is not None
    np.testing.assert_array_equal(clean.edge_widths, faulty.edge_widths)
    assert faulty.n_failed == 0


def test_a_scenario_with_too_few_points_is_skipped() -> None:
    apparatus = lens(blind_beyond_v=3.0)
    record = sweep(apparatus, sweep_plan(apparatus.knobs, step="constant"), 0, 1)
    assert not record.usable and len(record.voltages) < 5
    assert record.n_failed == 51 - len(record.voltages)


def test_sweep_plans_are_validated() -> None:
    with pytest.raises(ValueError, match="below"):
        SweepPlan("defocus", 10.0, 10.0)
    with pytest.raises(ValueError, match="min_step_v"):
        SweepPlan("defocus", 0.0, 1.0, min_step_v=2.0, max_step_v=1.0)
    with pytest.raises(ValueError, match="no knob 'focus'"):
        sweep_plan(lens().knobs, knob="focus")


def test_scenario_seeds_are_distinct_and_stable() -> None:
    seeds = [scenario_seed(0, i) for i in range(1000)]
    assert len(set(seeds)) == 1000
    assert scenario_seed(0, 17) == scenario_seed(0, 17) != scenario_seed(1, 17)


def record_cli(out: Path, *extra: str, apparatus: str = LENS) -> int:
    return main(
        [
            *("record", "--apparatus", apparatus, "--out", str(out)),
            *("--quiet", "--step", "constant", *extra),
        ]
    )


def test_record_command_writes_a_valid_file_and_reports_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "lens.csv"
    assert record_cli(out, "--scenarios", "6", "--seed", "3", "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert report["scenarios_written"] == 6 and report["scenarios_skipped"] == 0
    assert report["median_pairs"] == 51.0
    data = read_scenarios(out)
    assert list(data.scenario_ids) == list(range(6))
    assert list(data.seeds) == [scenario_seed(3, i) for i in range(6)]


def test_existing_output_is_never_overwritten_without_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "lens.csv"
    assert record_cli(out, "--scenarios", "2") == 0
    before = out.read_bytes()
    assert record_cli(out, "--scenarios", "3", "--seed", "9") == 2
    assert "already exists" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert record_cli(out, "--scenarios", "3", "--seed", "9", "--force") == 0
    assert out.read_bytes() != before


def test_interrupted_recording_keeps_finished_rows_and_append_completes_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    reference = tmp_path / "reference.csv"
    assert record_cli(reference, "--scenarios", "6") == 0
    out = tmp_path / "interrupted.csv"
    # The operator presses Ctrl-C while the third scenario starts (reset #3 of the driver).
    code = record_cli(out, "--scenarios", "6", "--apparatus-args", '{"interrupt_at_reset": 3}')
    assert code == 130
    assert "2 scenarios written" in capsys.readouterr().err
    assert len(read_scenarios(out)) == 2
    assert record_cli(out, "--scenarios", "6", "--append") == 0
    assert out.read_bytes() == reference.read_bytes()


def test_append_to_a_finished_recording_adds_nothing(tmp_path: Path) -> None:
    out = tmp_path / "done.csv"
    assert record_cli(out, "--scenarios", "3") == 0
    before = out.read_bytes()
    assert record_cli(out, "--scenarios", "3", "--append") == 0
    assert out.read_bytes() == before


def test_append_with_other_sweep_settings_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "lens.csv"
    assert record_cli(out, "--scenarios", "2") == 0
    before = out.read_bytes()
    code = main(
        [
            *("record", "--apparatus", LENS, "--out", str(out), "--quiet"),
            *("--scenarios", "4", "--step", "adaptive", "--append"),
        ]
    )
    assert code == 2
    assert "pair columns" in capsys.readouterr().err
    assert out.read_bytes() == before


def test_bad_apparatus_args_are_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "x.csv"
    assert record_cli(out, "--scenarios", "2", "--apparatus-args", "{oops") == 2
    assert "--apparatus-args" in capsys.readouterr().err
    assert not out.exists()


def test_parallel_workers_record_the_same_rows(tmp_path: Path) -> None:
    small = '{"image_size_px": 96}'
    serial, parallel = tmp_path / "serial.csv", tmp_path / "parallel.csv"
    args = ["--scenarios", "3", "--apparatus-args", small]
    assert record_cli(serial, *args, apparatus="synthetic") == 0
    assert record_cli(parallel, *args, "--workers", "2", apparatus="synthetic") == 0
    assert serial.read_bytes() == parallel.read_bytes()


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(TESTS)}


def _command(out: Path, delay_s: float) -> list[str]:
    return [
        sys.executable,
        "-m",
        "alignrl.cli",
        "record",
        "--apparatus",
        LENS,
        "--apparatus-args",
        json.dumps({"delay_s": delay_s}),
        "--scenarios",
        "12",
        "--step",
        "constant",
        "--out",
        str(out),
        "--quiet",
    ]


def _wait_for_rows(out: Path, rows: int, process: subprocess.Popen, limit_s: float = 60) -> None:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        if out.exists() and out.read_text().count("\n") >= rows + 1:
            return
        assert process.poll() is None, "the recorder ended before it could be interrupted"
        time.sleep(0.02)
    raise AssertionError(f"no {rows} rows in {out} after {limit_s} s")


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGINT])
def test_killed_recorder_loses_no_finished_row(tmp_path: Path, how: signal.Signals) -> None:
    reference = tmp_path / "reference.csv"
    subprocess.run(_command(reference, 0.0), env=_env(), check=True, timeout=120)
    out = tmp_path / "killed.csv"
    process = subprocess.Popen(_command(out, 0.004), env=_env(), stderr=subprocess.PIPE)
    _wait_for_rows(out, 3, process)
    process.send_signal(how)
    _, stderr = process.communicate(timeout=60)
    if how == signal.SIGINT:
        assert process.returncode == 130
        assert b"--append" in stderr
    kept = read_scenarios(out)  # every row that reached the file is complete and valid
    assert 3 <= len(kept) < 12
    resumed = subprocess.run(
        [*_command(out, 0.0), "--append"], env=_env(), timeout=120, capture_output=True
    )
    assert resumed.returncode == 0, resumed.stderr
    assert out.read_bytes() == reference.read_bytes()


def test_a_driver_fault_near_focus_does_not_coarsen_the_sweep() -> None:
    apparatus = lens(faulty_within_v=0.6)
    plan = sweep_plan(apparatus.knobs, step="adaptive")
    record = sweep(apparatus, plan, scenario=0, seed=5)
    swept = np.array([w["defocus"] for w in apparatus.writes[plan.prescan_points :]])
    near = np.abs(swept - apparatus.optimum_v) < 4.0
    assert near.sum() >= 6  # still 1 V steps around the focus, faults or not
    assert record.n_failed >= 1


def test_a_narrow_knob_interval_is_swept_on_a_fine_grid() -> None:
    apparatus = lens()
    apparatus.knobs = {"defocus": (0.0, 0.01)}
    plan = sweep_plan(apparatus.knobs, step="adaptive")
    record = sweep(apparatus, plan, scenario=0, seed=1)
    assert record.voltages[0] == 0.0 and record.voltages[-1] == 0.01
    assert np.all(np.diff(record.voltages) > 0)
    assert len(record.voltages) <= plan.max_pairs


def test_record_skips_unmeasurable_scenarios_and_keeps_json_clean(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "partly.csv"
    code = record_cli(
        out, "--scenarios", "12", "--json", "--apparatus-args", '{"blind_beyond_v": 4.5}'
    )
    captured = capsys.readouterr()
    report = json.loads(captured.out)  # the skip notices go to stderr, not into the JSON
    assert code == 0
    assert report["scenarios_skipped"] > 0 and report["scenarios_written"] > 0
    assert report["scenarios_skipped"] + report["scenarios_written"] == 12
    assert "not written" in captured.err
    assert len(read_scenarios(out)) == report["scenarios_written"]


def test_record_with_nothing_measurable_fails_and_leaves_no_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "blind.csv"
    code = record_cli(out, "--scenarios", "3", "--apparatus-args", '{"blind_beyond_v": 1}')
    assert code == 2
    assert "measurable points" in capsys.readouterr().err
    assert not out.exists()


def test_append_with_another_seed_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "lens.csv"
    assert record_cli(out, "--scenarios", "2", "--seed", "1") == 0
    before = out.read_bytes()
    assert record_cli(out, "--scenarios", "4", "--seed", "2", "--append") == 2
    assert "another --seed" in capsys.readouterr().err
    assert out.read_bytes() == before


def test_force_keeps_the_old_file_when_nothing_could_be_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "precious.csv"
    assert record_cli(out, "--scenarios", "2") == 0
    before = out.read_bytes()
    blind = '{"blind_beyond_v": 1}'
    assert record_cli(out, "--scenarios", "2", "--force", "--apparatus-args", blind) == 2
    assert "was not written" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert sorted(path.name for path in tmp_path.iterdir()) == ["precious.csv"]


def test_an_interrupt_before_the_first_row_leaves_no_file(tmp_path: Path) -> None:
    out = tmp_path / "early.csv"
    code = record_cli(out, "--scenarios", "3", "--apparatus-args", '{"interrupt_at_reset": 1}')
    assert code == 130
    assert list(tmp_path.iterdir()) == []


def test_a_folder_as_output_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert record_cli(tmp_path, "--scenarios", "1") == 2
    assert "is a folder" in capsys.readouterr().err

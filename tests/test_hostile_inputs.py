"""Issue 60, items 9 and 10: inputs that crashed (exit 70, a traceback) or were silently
accepted are refused, exit 2, in one message naming what and where.

* a YAML file with a NUL byte (experiment, league, roster, instrument family): the file, the
  line and the column;
* counts far beyond a machine's life (`budget.env_steps: 10**26`, `schedule.matches: 10**9`,
  ...): the key, the value and the bound; every shipped experiment and benchmark stays inside;
* instrument family parameters of 1e300 (a family file, `--apparatus-args` of `family:` and
  `instrument:`): the parameter, the value, the physical range and the file or argument;
* `python -m alignrl` run from the parent of a checkout folder named `alignrl`;
* a held-out instrument copied into a training config with a parameter moved by 1e-7.

Refusals happen while reading, before any training, so no case trains.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import SMALL_SAC, write_experiment
from hostile import assert_refused, evaluate_on, run_cli

from alignrl.apparatus.family_box import FAMILY_DIR
from alignrl.apparatus.instruments import HELD_OUT_SET, INSTRUMENT_DIR, held_out_reason
from alignrl.config.experiment import load_experiment
from alignrl.config_reading import (
    MAX_ENV_STEPS,
    MAX_EPISODE_STEPS,
    MAX_EPISODES,
    MAX_SCENARIOS,
    ConfigError,
    read_layered,
)
from alignrl.league.config import MAX_ITERATIONS, MAX_MATCHES, load_league
from alignrl.league.matchmaking import MAX_MEMBERS

ROOT = Path(__file__).resolve().parents[1]


def _train(path: Path, tmp_path: Path, *extra: str) -> list[str]:
    return ["train", path, "--runs-dir", tmp_path / "runs", "--quiet", *extra]


def _league_run(path: Path, tmp_path: Path, *extra: str) -> list[str]:
    return ["league", "run", path, "--runs-dir", tmp_path / "runs", "--quiet", *extra]


def _league(tmp_path: Path, aligners: Path | None = None) -> Path:
    """experiments/league-default.yaml with its rosters named by absolute path."""
    data = yaml.safe_load((ROOT / "experiments" / "league-default.yaml").read_text())
    data["aligners"] = str(aligners or ROOT / "populations" / "aligners.yaml")
    data["misaligners"] = str(ROOT / "populations" / "misaligners.yaml")
    path = tmp_path / "league.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _with_nul(source: Path, target: Path, line: int) -> Path:
    """`source` copied to `target` with a NUL byte after the second character of `line`."""
    lines = source.read_text().splitlines(keepends=True)
    lines[line - 1] = lines[line - 1][:2] + "\x00" + lines[line - 1][2:]
    target.write_text("".join(lines))
    return target


# --- a. NUL bytes --------------------------------------------------------------------------


def _nul_experiment(tmp_path: Path) -> tuple[list[str], Path]:
    path = _with_nul(ROOT / "experiments" / "focus-sac-mlp.yaml", tmp_path / "x.yaml", 5)
    return _train(path, tmp_path), path


def _nul_league(tmp_path: Path) -> tuple[list[str], Path]:
    path = _with_nul(_league(tmp_path), tmp_path / "league-nul.yaml", 5)
    return _league_run(path, tmp_path), path


def _nul_roster(tmp_path: Path) -> tuple[list[str], Path]:
    roster = _with_nul(ROOT / "populations" / "aligners.yaml", tmp_path / "aligners.yaml", 5)
    return _league_run(_league(tmp_path, roster), tmp_path), roster


def _nul_family(tmp_path: Path) -> tuple[list[str], Path]:
    path = _with_nul(FAMILY_DIR / "focus.yaml", tmp_path / "box.yaml", 5)
    return evaluate_on(f"family:{path}"), path


@pytest.mark.parametrize(
    "case",
    [_nul_experiment, _nul_league, _nul_roster, _nul_family],
    ids=lambda case: case.__name__.strip("_"),
)
def test_a_yaml_file_with_a_nul_byte_is_refused_naming_file_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case
) -> None:
    argv, named = case(tmp_path)
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, f"{named}: line 5, column 3", "U+0000", "NUL byte")
    assert len(outcome.err.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()


# --- b. Counts beyond a machine's life ------------------------------------------------------

BIG = 10**26
EXPERIMENT_COUNTS = [
    # (--set assignment, the key named, the bound named)
    (f"budget.env_steps={BIG}", "budget.env_steps", MAX_ENV_STEPS),
    ("budget.env_steps=1.0e+26", "budget.env_steps", "whole number"),
    (f"budget.env_steps={MAX_ENV_STEPS + 1}", "budget.env_steps", MAX_ENV_STEPS),
    (f"budget.eval_every={BIG}", "budget.eval_every", MAX_ENV_STEPS),
    (f"budget.checkpoint_every={BIG}", "budget.checkpoint_every", MAX_ENV_STEPS),
    (f"budget.eval_scenarios={10**9}", "budget.eval_scenarios", MAX_SCENARIOS),
    (f"budget.test_scenarios={10**9}", "budget.test_scenarios", MAX_SCENARIOS),
    (f"learner.learning_starts={BIG}", "learner.learning_starts", MAX_ENV_STEPS),
    (f"learner.random_steps={BIG}", "learner.random_steps", MAX_ENV_STEPS),
    (f"task_options.episode_steps={10**6}", "task_options.episode_steps", MAX_EPISODE_STEPS),
    (f"curriculum.window={10**9}", "curriculum.window", MAX_EPISODES),
]


@pytest.mark.parametrize(
    ("assignment", "key", "bound"), EXPERIMENT_COUNTS, ids=[a for a, _, _ in EXPERIMENT_COUNTS]
)
def test_experiment_counts_beyond_their_bound_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], assignment: str, key: str, bound
) -> None:
    path = ROOT / "experiments" / "focus-sac-mlp.yaml"
    outcome = run_cli(_train(path, tmp_path, "--set", assignment), capsys)
    value = assignment.partition("=")[2]
    assert_refused(outcome, 2, str(path), f"{key}: ", value, str(bound))
    assert not (tmp_path / "runs").exists()


def test_steps_given_on_the_command_line_are_bounded_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = ROOT / "experiments" / "focus-sac-mlp.yaml"
    outcome = run_cli(_train(path, tmp_path, "--steps", str(BIG)), capsys)
    assert_refused(outcome, 2, "budget.env_steps", str(BIG), str(MAX_ENV_STEPS))
    assert not (tmp_path / "runs").exists()


LEAGUE_COUNTS = [
    (f"schedule.matches={10**9}", "schedule.matches", MAX_MATCHES),
    (f"schedule.iterations={10**9}", "schedule.iterations", MAX_ITERATIONS),
    (f"schedule.iterations={BIG}", "schedule.iterations", MAX_ITERATIONS),
    (f"schedule.snapshot_every={10**9}", "schedule.snapshot_every", MAX_ITERATIONS),
    (f"schedule.aligner_steps={BIG}", "schedule.aligner_steps", MAX_ENV_STEPS),
    (f"schedule.eval_scenarios={10**9}", "schedule.eval_scenarios", MAX_SCENARIOS),
    (f"schedule.keep_best={10**6}", "schedule.keep_best", MAX_MEMBERS),
    (f"matchmaking.max_snapshots={10**6}", "matchmaking.max_snapshots", MAX_MEMBERS),
    (f"sessions.test_scenarios={10**9}", "sessions.test_scenarios", MAX_SCENARIOS),
]


@pytest.mark.parametrize(
    ("assignment", "key", "bound"), LEAGUE_COUNTS, ids=[a for a, _, _ in LEAGUE_COUNTS]
)
def test_league_counts_beyond_their_bound_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], assignment: str, key: str, bound: int
) -> None:
    path = _league(tmp_path)
    outcome = run_cli(_league_run(path, tmp_path, "--set", assignment), capsys)
    assert_refused(outcome, 2, str(path), f"{key}: ", assignment.partition("=")[2], str(bound))
    assert not (tmp_path / "runs").exists()


def _shipped_configs() -> list[Path]:
    return sorted([*ROOT.glob("experiments/*.yaml"), *ROOT.glob("benchmarks/configs/*.yaml")])


@pytest.mark.parametrize("path", _shipped_configs(), ids=lambda path: path.name)
def test_no_shipped_experiment_or_benchmark_reaches_a_bound(path: Path) -> None:
    data = read_layered(path, "experiment").data
    if "aligners" in data or "schedule" in data:
        load_league(path)
    else:
        load_experiment(path)


# --- c. Instrument family parameters ---------------------------------------------------------

FAMILY_ARGUMENTS = [
    # (spec, --apparatus-args, the parameter, its value as shown, the range as shown)
    ("family:focus", '{"interval_width": 1e300}', "interval_width", "1e+300", "[1e-06, 1e+06] V"),
    ("family:focus", '{"interval_centre": -1e300}', "interval_centre", "-1e+300", "[-1e+06, 1e"),
    ("family:focus", '{"interval_width": 1e-300}', "interval_width", "1e-300", "[1e-06, 1e+06]"),
    ("family:focus", '{"floor_sigma_px": 1e300}', "floor_sigma_px", "1e+300", "[0.1, 10000] px"),
    (
        "family:focus",
        '{"blur_px_per_interval": [10, 1e300]}',
        "blur_px_per_interval",
        "[10, 1e+300]",
        "[0.1, 10000] px",
    ),
    (
        "family:focus",
        '{"dose_electrons_per_px": 1e300}',
        "dose_electrons_per_px",
        "1e+300",
        "[0.01, 1e+09] electrons per px",
    ),
    ("family:focus", '{"detector_noise": 1e300}', "detector_noise", "1e+300", "[0, 10]"),
    ("family:focus", '{"asymmetry": 1e300}', "asymmetry", "1e+300", "[0.01, 100]"),
    ("instrument:val-mid", '{"interval_width": 1e300}', "interval_width", "1e+300", "[1e-06"),
    ("instrument:val-mid", '{"saturation_px": 1e300}', "saturation_px", "1e+300", "[0.1, 10000]"),
]


@pytest.mark.parametrize(
    ("spec", "arguments", "name", "value", "shown_range"),
    FAMILY_ARGUMENTS,
    ids=[f"{spec} {arguments}" for spec, arguments, *_ in FAMILY_ARGUMENTS],
)
def test_family_parameters_beyond_their_physical_range_are_refused(
    capsys: pytest.CaptureFixture[str],
    spec: str,
    arguments: str,
    name: str,
    value: str,
    shown_range: str,
) -> None:
    outcome = run_cli(evaluate_on(spec, "--apparatus-args", arguments), capsys)
    file = "focus.yaml" if spec.startswith("family") else "val-mid.yaml"
    assert_refused(
        outcome,
        2,
        file,
        f"apparatus arguments {name}",
        f"{name} {value}",
        "physical range",
        shown_range,
    )


def test_a_family_file_beyond_the_physical_range_is_refused_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    box = yaml.safe_load((FAMILY_DIR / "focus.yaml").read_text())
    path = tmp_path / "box.yaml"
    path.write_text(yaml.safe_dump({**box, "interval_width": [40.0, 1e300], "unit": "mA"}))
    outcome = run_cli(evaluate_on(f"family:{path}"), capsys)
    assert_refused(outcome, 2, f"{path}: interval_width [40, 1e+300]", "[1e-06, 1e+06] mA")
    assert "apparatus arguments" not in outcome.err
    # An integer of 400 digits is no float: refused as well, not an OverflowError.
    path.write_text(yaml.safe_dump({**box, "flat_fraction": "HUGE"}).replace("HUGE", "1" * 400))
    outcome = run_cli(evaluate_on(f"family:{path}"), capsys)
    assert_refused(outcome, 2, str(path), "flat_fraction", "400 digits")


def _python(arguments: list[str], cwd: Path, **environment: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *arguments],
        cwd=cwd,
        env={**os.environ, **environment},
        capture_output=True,
        text=True,
        timeout=300,
    )


# --- d. python -m alignrl from a checkout's parent folder -------------------------------------


@pytest.mark.parametrize("folder", ["alignrl", "main"])
@pytest.mark.parametrize("checkout", [True, False], ids=["checkout", "empty-folder"])
def test_python_m_alignrl_runs_from_a_checkouts_parent_folder(
    tmp_path: Path, folder: str, checkout: bool
) -> None:
    # A checkout cloned as `alignrl/` (or `main/`) in the working directory, or a folder of
    # that name that holds nothing: the command is the installed package's either way.
    if checkout:
        (tmp_path / folder).symlink_to(ROOT, target_is_directory=True)
    else:
        (tmp_path / folder).mkdir()
    result = _python(["-m", "alignrl", "--version"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("alignrl "), result.stdout
    assert "Traceback" not in result.stderr
    result = _python(["-m", "alignrl", "scenarios", "validate", "nothing.csv"], tmp_path)
    assert result.returncode == 2 and result.stderr.startswith("alignrl: error:"), result.stderr


# --- f. A held-out instrument copied with a parameter moved by a hair -----------------------


def _copy_of(name: str, folder: Path, **changes) -> Path:
    data = yaml.safe_load((INSTRUMENT_DIR / HELD_OUT_SET / f"{name}.yaml").read_text())
    path = folder / "my-column.yaml"
    path.write_text(yaml.safe_dump({**data, "name": "my-column", "description": "mine", **changes}))
    return path


NUDGES = [
    ("fast-drift", {"interval_width": 200.0 + 1e-7}),
    ("fast-drift", {"interval_centre": -300.0 - 1e-7}),
    ("fast-drift", {"optimum_fraction": [0.25 + 1e-7, 0.75]}),
    ("fast-drift", {"drift_fraction": 0.002 - 1e-7, "unit": "volt"}),
    ("narrow-interval", {"detector_noise": 0.01 + 1e-7, "image_size_px": 512}),
    ("fibres-low-dose", {"reading_noise_px": 0.1 + 1e-7, "hysteresis_fraction": 0.002 + 1e-9}),
]


@pytest.mark.parametrize(("name", "changes"), NUDGES, ids=[f"{n} {c}" for n, c in NUDGES])
def test_a_held_out_instrument_nudged_by_a_hair_is_still_held_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, changes: dict
) -> None:
    copy = _copy_of(name, tmp_path, **changes)
    assert name in str(held_out_reason(f"family:{copy}"))
    config = write_experiment(
        tmp_path,
        {
            "name": "nudged",
            "apparatus": f"family:{copy}",
            "apparatus_args": {"analytic": True},
            "eval_apparatus": "set:validation",
            "eval_apparatus_args": {"analytic": True},
            "learner": SMALL_SAC,
            "budget": {"env_steps": 64, "eval_every": 64, "eval_scenarios": 2},
        },
    )
    outcome = run_cli(_train(config, tmp_path), capsys)
    assert_refused(outcome, 2, str(config), "apparatus", repr(name), "held-out")
    assert not (tmp_path / "runs").exists()


def test_the_wall_sees_a_held_out_instrument_given_as_arguments_or_a_randomizing_family(
    tmp_path: Path,
) -> None:
    held_out = yaml.safe_load((INSTRUMENT_DIR / HELD_OUT_SET / "fast-drift.yaml").read_text())
    arguments = {
        key: value
        for key, value in held_out.items()
        if key not in ("kind", "name", "description", "unit")
    }
    arguments["interval_width"] += 1e-7
    assert "fast-drift" in str(held_out_reason("instrument:val-mid", arguments))
    copy = _copy_of("fast-drift", tmp_path, interval_width=200.0 + 1e-7)
    randomized = {"split": "train", "randomize": {"family": str(copy)}}
    assert "fast-drift" in str(held_out_reason("csv:default", randomized))
    with pytest.raises(ConfigError, match="fast-drift"):
        load_experiment(write_experiment(tmp_path, {"name": "r", "apparatus_args": randomized}))


def test_a_column_that_differs_from_every_held_out_one_is_not_held_out(tmp_path: Path) -> None:
    # A thousandth of the interval is a different column, not a copy (nor inside one).
    copy = _copy_of("fast-drift", tmp_path, interval_width=200.2)
    assert held_out_reason(f"family:{copy}") is None

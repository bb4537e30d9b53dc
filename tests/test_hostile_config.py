"""Hostile config and data input is refused where it is read: exit 2, one message naming the
file and the key (or row and column), nothing written, never a traceback or exit 70.

Every case runs the real `alignrl` command (tests/hostile.py) on a valid input with one thing
changed. Refusals happen while reading, before any training starts, so no case trains.
"""

from __future__ import annotations

import gzip
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from hostile import assert_refused, assert_unchanged, evaluate_on, run_cli, tree_state

from alignrl.apparatus.scenarios import MAX_TEXT_BYTES

ROOT = Path(__file__).resolve().parents[1]
BOMB_SECONDS = 2.0  # a generous safety bound: the refusal itself takes milliseconds


@pytest.fixture(scope="module", autouse=True)
def _imports_done() -> None:
    """Load the modules the verbs import lazily, so that timings measure the reading alone."""
    import alignrl.evaluation.session
    import alignrl.league.loop
    import alignrl.training  # noqa: F401


def _billion_laughs(key: str) -> str:
    """`key:` holding nine levels of nine aliases each: 9^9 strings once expanded."""
    levels = [f"  l0: &l0 [{', '.join(['lol'] * 9)}]"]
    levels += [f"  l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 10)]
    return f"{key}:\n" + "\n".join(levels) + "\n"


def _experiment(tmp_path: Path, change: str = "", drop: tuple[str, ...] = ()) -> Path:
    """experiments/focus-sac-mlp.yaml with the top-level keys `drop` removed and `change`
    appended."""
    lines = (ROOT / "experiments" / "focus-sac-mlp.yaml").read_text().splitlines()
    kept, skipping = [], False
    for line in lines:
        top = line[:1].isalpha()
        if top:
            skipping = line.split(":")[0] in drop
        if not skipping:
            kept.append(line)
    path = tmp_path / "experiment.yaml"
    path.write_text("\n".join(kept) + "\n" + change)
    return path


def _league(tmp_path: Path, change: dict | None = None, text: str = "") -> Path:
    """experiments/league-default.yaml with its rosters named by absolute path, `change`
    merged into its keys (one level deep) and `text` appended."""
    data = yaml.safe_load((ROOT / "experiments" / "league-default.yaml").read_text())
    data["aligners"] = str(ROOT / "populations" / "aligners.yaml")
    data["misaligners"] = str(ROOT / "populations" / "misaligners.yaml")
    for key, value in (change or {}).items():
        data[key] = {**data.get(key, {}), **value} if isinstance(value, dict) else value
    path = tmp_path / "league.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False) + text)
    return path


def _roster_league(tmp_path: Path, roster_text: str) -> Path:
    roster = tmp_path / "aligners.yaml"
    roster.write_text(roster_text)
    return _league(tmp_path, {"aligners": str(roster)})


def _preset(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "instrument.yaml"
    path.write_text((ROOT / "alignrl" / "apparatus" / "presets" / "synthetic.yaml").read_text())
    path.write_text(path.read_text() + text)
    return path


def _train(path: Path, tmp_path: Path) -> list[str]:
    return ["train", path, "--runs-dir", tmp_path / "runs", "--quiet"]


def _league_run(path: Path, tmp_path: Path) -> list[str]:
    return ["league", "run", path, "--runs-dir", tmp_path / "runs", "--quiet"]


# --- 1. YAML: alias bombs and duplicate keys ----------------------------------------------

ROSTER = (ROOT / "populations" / "aligners.yaml").read_text()

# name -> (write the hostile file into tmp_path, the command, the file the message names)
YamlCase = Callable[[Path], tuple[list[str], Path]]


def _bomb_experiment(tmp_path: Path) -> tuple[list[str], Path]:
    path = _experiment(tmp_path, _billion_laughs("apparatus_args"), drop=("apparatus_args",))
    return _train(path, tmp_path), path


def _bomb_league(tmp_path: Path) -> tuple[list[str], Path]:
    path = _league(tmp_path, text=_billion_laughs("laughs"))
    return _league_run(path, tmp_path), path


def _bomb_roster(tmp_path: Path) -> tuple[list[str], Path]:
    path = _roster_league(tmp_path, ROSTER + _billion_laughs("laughs"))
    return _league_run(path, tmp_path), tmp_path / "aligners.yaml"


def _bomb_preset(tmp_path: Path) -> tuple[list[str], Path]:
    path = _preset(tmp_path, _billion_laughs("laughs"))
    return evaluate_on(f"sem:{path}"), path


def _recursive_alias(tmp_path: Path) -> tuple[list[str], Path]:
    path = _experiment(tmp_path, "apparatus_args: &self {noise: *self}\n", ("apparatus_args",))
    return _train(path, tmp_path), path


@pytest.mark.parametrize(
    "case",
    [_bomb_experiment, _bomb_league, _bomb_roster, _bomb_preset, _recursive_alias],
    ids=lambda case: case.__name__.strip("_"),
)
def test_alias_bombs_are_refused_fast_and_briefly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: YamlCase
) -> None:
    argv, named = case(tmp_path)
    started = time.perf_counter()
    outcome = run_cli(argv, capsys)
    elapsed = time.perf_counter() - started
    assert_refused(outcome, 2, str(named), "line")
    assert "alias" in outcome.err
    assert elapsed < BOMB_SECONDS, f"refused after {elapsed:.2f} s"
    assert len(outcome.err) < 20_000
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("write", "verb", "key"),
    [
        (lambda tmp: _experiment(tmp, "learner:\n  batch_size: 8\n"), "train", "learner"),
        (lambda tmp: _league(tmp, text="history: 4\n"), "league", "history"),
        (
            lambda tmp: _roster_league(tmp, ROSTER + "team: misaligner\n"),
            "roster",
            "team",
        ),
        (lambda tmp: _preset(tmp, "optimum_v: 50.0\n"), "preset", "optimum_v"),
    ],
    ids=["experiment", "league", "roster", "preset"],
)
def test_duplicate_keys_are_refused_naming_the_key_and_line(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    write: Callable[[Path], Path],
    verb: str,
    key: str,
) -> None:
    path = write(tmp_path)
    argv = {
        "train": _train(path, tmp_path),
        "league": _league_run(path, tmp_path),
        "roster": _league_run(path, tmp_path),
        "preset": evaluate_on(f"sem:{path}"),
    }[verb]
    named = tmp_path / "aligners.yaml" if verb == "roster" else path
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, str(named), f"key {key!r} is given twice", "line")
    assert not (tmp_path / "runs").exists()


# --- 2. Empty files -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "verb", "what"),
    [
        ("", "train", "empty experiment config"),
        ("# only a comment\n", "train", "empty experiment config"),
        ("", "league", "empty league config"),
        ("", "roster", "empty roster"),
        ("", "preset", "empty synthetic SEM config"),
    ],
)
def test_empty_files_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, verb: str, what: str
) -> None:
    path = tmp_path / "empty.yaml"
    path.write_text(text)
    if verb == "roster":
        league = _league(tmp_path, {"aligners": str(path)})
        argv = _league_run(league, tmp_path)
    elif verb == "preset":
        argv = evaluate_on(f"sem:{path}")
    else:
        argv = (_train if verb == "train" else _league_run)(path, tmp_path)
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, f"{path}: {what}")
    assert not (tmp_path / "runs").exists()


# --- 3. Types and ranges --------------------------------------------------------------------

EXPERIMENT_VALUES = [
    # (top-level key replaced, its YAML, the key path named)
    ("envs", "envs: true", "envs"),
    ("envs", "envs: 8.0", "envs"),
    ("learner", "learner: {hidden: [0]}", "learner.hidden.0"),
    ("learner", "learner: {hidden: []}", "learner.hidden"),
    ("learner", "learner: {hidden: [-4]}", "learner.hidden.0"),
    ("learner", "learner: {batch_size: 1e9}", "learner.batch_size"),
    ("learner", "learner: {batch_size: 1000000000}", "learner.batch_size"),
    ("learner", "learner: {batch_size: 300000}", "buffer_size"),
    ("learner", "learner: {buffer_size: 100000000000}", "learner.buffer_size"),
    ("learner", "learner: {learning_rate: .nan}", "learner.learning_rate"),
    ("device", "device: potato", "device"),
    ("device", "device: cuda:999", "device"),
    ("seed", f"seed: {2**63}", "seed"),
    ("seed", "seed: -1", "seed"),
    ("history", "history: [8]", "history"),
]


@pytest.mark.parametrize(
    ("key", "line", "named"), EXPERIMENT_VALUES, ids=[line for _, line, _ in EXPERIMENT_VALUES]
)
def test_bad_experiment_values_name_the_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, line: str, named: str
) -> None:
    path = _experiment(tmp_path, line + "\n", drop=(key,))
    outcome = run_cli(_train(path, tmp_path), capsys)
    assert_refused(outcome, 2, str(path), named)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("perturb", [[0, 0], [-1, -1], [0.8, 1e9]])
def test_bad_pbt_factors_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], perturb: list[float]
) -> None:
    path = _league(tmp_path, {"pbt": {"perturb": perturb}})
    outcome = run_cli(_league_run(path, tmp_path), capsys)
    assert_refused(outcome, 2, str(path), "pbt.perturb")
    assert not (tmp_path / "runs").exists()


RECORD = ["record", "--apparatus", "synthetic", "--scenarios", "1", "--out", "OUT"]
ADAPT = ["adapt", "--from", "x", "--apparatus", "synthetic", "--steps", "10"]
BAD_OPTIONS = [
    (evaluate_on("csv:default", "--seed", str(2**63)), "--seed"),
    (evaluate_on("csv:default", "--seed", "-1"), "--seed"),
    (["baselines", "--apparatus", "csv:default", "--seed", "1e3"], "--seed"),
    (["align", "--policy", "x", "--apparatus", "synthetic", "--seed", "-5"], "--seed"),
    ([*RECORD, "--workers", "0"], "--workers"),
    ([*RECORD, "--workers", "-3"], "--workers"),
    ([*RECORD, "--seed", str(2**64)], "--seed"),
    ([*ADAPT, "--updates-per-step", "0"], "--updates-per-step"),
    ([*ADAPT, "--updates-per-step", "nan"], "--updates-per-step"),
    (evaluate_on("csv:default", "--apparatus-args", "[" * 100_000), "--apparatus-args"),
    (evaluate_on("csv:default", "--apparatus-args", "1" * 5000), "--apparatus-args"),
]


@pytest.mark.parametrize(
    ("argv", "option"),
    BAD_OPTIONS,
    ids=[f"{argv[0]} {option} {argv[-1][:12]}" for argv, option in BAD_OPTIONS],
)
def test_bad_options_are_one_line_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], option: str
) -> None:
    argv = [str(tmp_path / "out.csv") if arg == "OUT" else arg for arg in argv]
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, option)
    assert len(outcome.err.strip().splitlines()[-1]) < 500
    assert not (tmp_path / "out.csv").exists()


# --- 4. Run names ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name", ["../../etc", "../x", "a/b", ".", "..", ".hidden", "a\\b", "nul\x00byte", "x" * 101, ""]
)
@pytest.mark.parametrize("verb", ["train", "league"])
def test_run_names_stay_inside_the_runs_dir(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, verb: str
) -> None:
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "kept.txt").write_text("an earlier run\n")
    before = tree_state(tmp_path)
    config = _experiment(tmp_path) if verb == "train" else _league(tmp_path)
    argv = (_train if verb == "train" else _league_run)(config, tmp_path)
    outcome = run_cli([*argv, "--name", name], capsys)
    assert_refused(outcome, 2, "--name", "name: ")
    assert_unchanged(before, tmp_path)
    assert sorted(path.name for path in (tmp_path / "runs").iterdir()) == ["kept.txt"]
    assert not (tmp_path / "etc").exists() and not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", ["../x", ".hidden", "a b"])
@pytest.mark.parametrize("verb", ["train", "league"])
def test_run_names_in_the_config_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, verb: str
) -> None:
    if verb == "train":
        path = _experiment(tmp_path, f"name: {name!r}\n", drop=("name",))
        argv = _train(path, tmp_path)
    else:
        path = _league(tmp_path, {"name": name})
        argv = _league_run(path, tmp_path)
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, str(path), "name", "one folder name")
    assert not (tmp_path / "runs").exists()


def test_a_config_and_resume_together_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _experiment(tmp_path)
    outcome = run_cli([*_train(path, tmp_path), "--resume", tmp_path / "runs" / "old"], capsys)
    assert_refused(outcome, 2, "--resume", "not both")
    assert not (tmp_path / "runs").exists()


# --- 5. Scenario CSVs ------------------------------------------------------------------------

PAIRS = 7
HEADER = "scenario,seed,knob,low,high,n_pairs,n_failed," + ",".join(
    f"voltage_{i},edge_width_{i}" for i in range(1, PAIRS + 1)
)
VOLTAGES = ["10.0", "25.0", "40.0", "50.0", "60.0", "75.0", "90.0"]
WIDTHS = ["12.0", "8.0", "4.0", "2.6", "4.0", "8.0", "12.0"]


def _row(
    scenario: int = 2,
    seed: str = "1",
    low: str = "0.0",
    high: str = "100.0",
    voltages: list[str] = VOLTAGES,
    widths: list[str] = WIDTHS,
) -> str:
    pairs = [cell for pair in zip(voltages, widths, strict=True) for cell in pair]
    return ",".join([str(scenario), seed, "defocus", low, high, str(len(voltages)), "0", *pairs])


def _csv(tmp_path: Path, bad_row: str) -> Path:
    """A recording of ten good scenarios and, as row 3, the bad one."""
    rows = [_row(scenario) for scenario in range(10)]
    rows[2] = bad_row
    path = tmp_path / "scenarios.csv"
    path.write_text("\n".join([HEADER, *rows]) + "\n")
    return path


TINY = [f"{value:.17g}" for value in (1e-301, 2e-301, 3e-301, 4e-301, 5e-301, 6e-301, 7e-301)]
CLOSE = [f"{50 + step * 1e-10:.17g}" for step in range(PAIRS)]

CSV_ROWS = [
    # (the bad row, what the message names besides file and row)
    (_row(seed=str(2**63)), "column seed"),
    (_row(seed="-1"), "column seed"),
    (_row(scenario=2**64), "column scenario"),
    (_row(seed="9" * 5000), "column seed"),
    (_row(widths=[*WIDTHS[:2], "1e308", *WIDTHS[3:]]), "column edge_width_3"),
    (_row(widths=[*WIDTHS[:2], "inf", *WIDTHS[3:]]), "column edge_width_3"),
    (_row(low="-1e308", high="1e308"), "column low"),
    (_row(low="0", high="1e-300", voltages=TINY), "spans only"),
    (_row(voltages=CLOSE), "span only"),
    (_row(widths=[*WIDTHS[:6], "x" * 200_000]), "row 3"),
]


@pytest.mark.parametrize(("bad_row", "named"), CSV_ROWS, ids=[n for _, n in CSV_ROWS])
@pytest.mark.parametrize("verb", ["validate", "evaluate"])
def test_bad_scenario_rows_name_file_row_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], bad_row: str, named: str, verb: str
) -> None:
    path = _csv(tmp_path, bad_row)
    argv = ["scenarios", "validate", path] if verb == "validate" else evaluate_on(f"csv:{path}")
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, str(path), "row 3", named)


def test_a_gzip_bomb_is_refused_before_it_is_read_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    member = gzip.compress(b"0" * (1 << 20), mtime=0)  # 1 MB in about 1 KB
    path = tmp_path / "bomb.csv.gz"
    path.write_bytes(
        gzip.compress((HEADER + "\n").encode()) + member * ((MAX_TEXT_BYTES >> 20) + 8)
    )
    assert path.stat().st_size < 1_000_000
    started = time.perf_counter()
    outcome = run_cli(["scenarios", "validate", path], capsys)
    assert_refused(outcome, 2, str(path), "decompresses to more than")
    assert time.perf_counter() - started < 10 * BOMB_SECONDS


@pytest.mark.parametrize(
    ("arguments", "named"),
    [
        ('{"noise": "loud"}', "noise"),
        ('{"noise": 5}', "noise"),
        ('{"split": "validation"}', "split"),
        ('{"randomize": {"gain": [0, -1]}}', "randomize.gain"),
    ],
)
def test_bad_simulator_arguments_name_the_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: str, named: str
) -> None:
    path = _csv(tmp_path, _row())
    outcome = run_cli(evaluate_on(f"csv:{path}", "--apparatus-args", arguments), capsys)
    assert_refused(outcome, 2, str(path), named)

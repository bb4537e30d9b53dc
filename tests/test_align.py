"""`alignrl align`: which policies it loads, its exit codes, its --json keys and its audit log
file, end to end through `alignrl.cli.main` (the shield's rules: tests/test_shield.py)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_shield import RecordingDriver, constant, scripted, setting_seen

import alignrl.deploy.policy as policy_module
import alignrl.runs.sources as sources
from alignrl.agents.agent import Agent, MemberSpec
from alignrl.apparatus import ApparatusError
from alignrl.cli import main
from alignrl.deploy.align import align
from alignrl.deploy.policy import DeployablePolicy, PolicySpecError, load_deployable
from alignrl.envs.alignment import aligner_spaces

DRIVER = "test_shield:RecordingDriver"
JSON_KEYS = {
    "success",
    "final_width_px",
    "final_directional_px",
    "final_wobble_px",
    "threshold_px",
    "acquisitions",
    "writes",
    "clamped",
    "refused",
    "aborted",
    "reason",
    "start_setting",
    "final_setting",
    "dry_run",
    "log",
    "outcome",
    "exit_code",
    "restored",
    "policy",
    "apparatus",
}


class Unreachable:
    """A driver whose microscope does not answer."""

    def __init__(self) -> None:
        raise ApparatusError("no microscope answers at 10.0.0.7")


def tiny_member(team: str = "aligner", history: int = 8) -> Agent:
    observation, action = aligner_spaces(1, history)
    spec = MemberSpec(
        id=f"tiny-{team}",
        team=team,
        algorithm="sac",
        observation_shape=observation.shape,
        action_dim=action.shape[0],
        secret_dim=1,
        hyperparameters={"encoder": "mlp", "hidden": [16]},
    )
    return Agent(spec)


@pytest.fixture(scope="module")
def member_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("members") / "tiny.pt"
    tiny_member().save(path)
    return path


def align_cli(
    capsys: pytest.CaptureFixture[str], *options: str, driver_args: dict[str, Any] | None = None
) -> tuple[int, dict[str, Any]]:
    code = main(
        [
            "align",
            "--apparatus",
            DRIVER,
            "--apparatus-args",
            json.dumps(driver_args or {}),
            "--json",
            *options,
        ]
    )
    out = capsys.readouterr().out
    return code, json.loads(out) if out.strip() else {}


@pytest.fixture
def scripted_policy(monkeypatch: pytest.MonkeyPatch):
    """Make `--policy NAME` load the scripted policy NAME of this test module."""

    def seeker_of_the_driver() -> DeployablePolicy:
        def act(history: np.ndarray) -> list[float]:
            error_v = RecordingDriver.last.optimum_v() - setting_seen(history)  # type: ignore[union-attr]
            return [0.0, 1.0] if abs(error_v) < 0.3 else [np.clip(error_v / 25, -1, 1), -1.0]

        return scripted(act, "seeker")

    policies = {
        "seeker": seeker_of_the_driver,
        "stop": lambda: constant(0.0, 1.0),
        "up": lambda: constant(0.2, -1.0),
    }

    def load(spec: str) -> DeployablePolicy:
        if spec not in policies:
            raise PolicySpecError(f"unknown policy {spec!r}")
        return policies[spec]()

    monkeypatch.setattr(policy_module, "load_deployable", load)


# --- exit codes ---------------------------------------------------------------------------


def test_exit_0_when_the_spec_is_met(capsys: pytest.CaptureFixture[str], scripted_policy) -> None:
    code, result = align_cli(capsys, "--policy", "seeker", "--spec-px", "3.2")
    assert code == 0 and result["success"] is True and result["outcome"] == "aligned"
    assert result["final_width_px"] <= result["threshold_px"] == 3.2
    assert result["final_setting"]["defocus"] == pytest.approx(69.8, abs=0.3)


def test_exit_0_with_the_relative_spec_of_a_simulator(
    capsys: pytest.CaptureFixture[str], scripted_policy
) -> None:
    code, result = align_cli(capsys, "--policy", "seeker")
    best = RecordingDriver.last.inner.best_quality()  # type: ignore[union-attr]
    assert result["threshold_px"] == pytest.approx(1.15 * best)
    assert code == 0


def test_exit_1_when_the_spec_is_not_met(
    capsys: pytest.CaptureFixture[str], scripted_policy
) -> None:
    code, result = align_cli(capsys, "--policy", "stop", "--spec-px", "3.0")
    assert code == 1 and result["success"] is False and result["outcome"] == "not-aligned"
    assert result["final_width_px"] > 3.0 and result["writes"] == 0


def test_exit_1_and_spec_unknown_without_a_reference(
    capsys: pytest.CaptureFixture[str], scripted_policy
) -> None:
    code, result = align_cli(capsys, "--policy", "seeker", driver_args={"best_quality": False})
    assert code == 1 and result["outcome"] == "spec-unknown"
    assert result["threshold_px"] is None and result["final_width_px"] is not None
    assert "--spec-px" in result["reason"]


def test_exit_3_on_operator_abort_with_restore(
    capsys: pytest.CaptureFixture[str], scripted_policy
) -> None:
    code, result = align_cli(
        capsys, "--policy", "up", "--restore-on-abort", driver_args={"interrupt_at": 3}
    )
    assert code == 3 and result["aborted"] is True and result["restored"] is True
    driver = RecordingDriver.last
    assert driver.calls[driver.aborted_at :] == [("write", {"defocus": 50.0})]  # type: ignore[union-attr]


def test_exit_3_on_the_watchdog(capsys: pytest.CaptureFixture[str], scripted_policy) -> None:
    code, result = align_cli(capsys, "--policy", "up", "--max-acquisitions", "2")
    assert code == 3 and "2 acquisitions" in result["reason"] and result["acquisitions"] == 2


def test_exit_4_when_the_driver_fails(capsys: pytest.CaptureFixture[str], scripted_policy) -> None:
    code, result = align_cli(capsys, "--policy", "up", driver_args={"fail_write_at": 2})
    assert code == 4 and result["outcome"] == "driver-failure"
    assert main(["align", "--policy", "up", "--apparatus", "test_align:Unreachable"]) == 4
    assert "no microscope answers" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--limits", "{defocus: 1}"], "--limits: not valid JSON"),
        (["--limits", '{"defocus": [40, 140]}'], "not inside the apparatus's interval"),
        (["--limits", '{"defocus": [60, 40]}'], "must be below high"),
        (["--max-step", '{"defocus": 0}'], "must be a positive change"),
        (["--max-step", '{"stigmator_x": 1}'], "unknown knob 'stigmator_x'"),
        (["--spec-px", "-1"], "--spec-px must be a positive"),
        (["--timeout", "0"], "--timeout must be positive"),
        (["--max-acquisitions", "0"], "--max-acquisitions must be at least 1"),
        (["--task", "astigmatism"], "unknown task 'astigmatism'"),
        (["--task", "stigmation"], "aligns task 'focus', not 'stigmation'"),
        (["--limits", '{"defocus": [60, 70]}'], "starts outside the limits"),
    ],
)
def test_exit_2_on_bad_options_with_nothing_written(
    capsys: pytest.CaptureFixture[str],
    scripted_policy,
    tmp_path: Path,
    options: list[str],
    message: str,
) -> None:
    RecordingDriver.last = None
    log = tmp_path / "audit.jsonl"
    code = main(["align", "--policy", "up", "--apparatus", DRIVER, "--log", str(log), *options])
    captured = capsys.readouterr()
    assert code == 2
    assert message in captured.err + captured.out
    if RecordingDriver.last is not None:
        assert RecordingDriver.last.count("write") == 0
    # Only a refusal after reading the column leaves a log: start, read, refusal, end.
    if log.exists():
        events = [json.loads(line)["event"] for line in log.read_text().splitlines()]
        assert events == ["start", "read", "refused-start", "end"]


def test_exit_2_on_an_unknown_policy(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    missing = tmp_path / "no-such-run"
    assert main(["align", "--policy", str(missing), "--apparatus", DRIVER]) == 2
    assert "unknown policy" in capsys.readouterr().err
    assert main(["align", "--policy", "champion:nobody", "--apparatus", DRIVER]) == 2
    assert "shipped champions:" in capsys.readouterr().err


# --- the real thing: a saved member, the log file, the keys ---------------------------------


def test_align_a_saved_member_end_to_end(
    capsys: pytest.CaptureFixture[str], member_file: Path, tmp_path: Path
) -> None:
    log = tmp_path / "logs" / "audit.jsonl"
    code, result = align_cli(
        capsys,
        "--policy",
        str(member_file),
        "--limits",
        '{"defocus": [45, 55]}',
        "--max-step",
        '{"defocus": 1.5}',
        "--log",
        str(log),
        "--spec-px",
        "3.0",
        driver_args={"low": 45, "high": 55, "max_step": 1.5},
    )
    driver = RecordingDriver.last
    assert driver is not None and not driver.violations
    assert set(result) == JSON_KEYS and code == result["exit_code"] in (0, 1)
    assert result["policy"] == "tiny-aligner" and result["log"] == str(log)
    assert result["start_setting"] == {"defocus": 50.0}
    assert 45.0 <= result["final_setting"]["defocus"] <= 55.0
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert lines[0]["event"] == "start" and lines[-1]["event"] == "end"
    assert lines[0]["limits"]["defocus"] == {"low": 45.0, "high": 55.0, "max_step": 1.5}
    assert lines[-1]["result"] == result
    sent_writes = [e for e in lines if e["event"] == "write" and e["sent"]]
    assert len(sent_writes) == driver.count("write") == result["writes"]
    assert sum(e["event"] == "measure" for e in lines) == driver.count("measure")
    # A second alignment appends to the same log.
    align_cli(capsys, "--policy", str(member_file), "--log", str(log), "--dry-run")
    events = [json.loads(line)["event"] for line in log.read_text().splitlines()]
    assert events.count("start") == 2 and events.count("end") == 2


def test_dry_run_through_the_cli_writes_nothing(
    capsys: pytest.CaptureFixture[str], member_file: Path
) -> None:
    code, result = align_cli(capsys, "--policy", str(member_file), "--dry-run", "--spec-px", "3")
    assert RecordingDriver.last.count("write") == 0  # type: ignore[union-attr]
    assert result["dry_run"] is True and result["writes"] == 0
    assert result["final_setting"] == result["start_setting"]
    assert code == 1  # the unmoved column (50 V, focus at 69.8 V) is not within 3 px


def test_text_output_says_how_it_ended(capsys: pytest.CaptureFixture[str], scripted_policy) -> None:
    code = main(["align", "--policy", "stop", "--apparatus", DRIVER, "--spec-px", "3"])
    out = capsys.readouterr().out
    assert code == 1
    assert out.startswith("not-aligned: the policy stopped; final edge width")
    assert "start defocus 50; left at defocus 50" in out


# --- loading policies ---------------------------------------------------------------------


def test_a_member_file_loads_with_its_history_and_the_default_task(member_file: Path) -> None:
    policy = load_deployable(str(member_file))
    assert (policy.name, policy.history, policy.task.name) == ("tiny-aligner", 8, "focus")
    history = np.random.default_rng(0).uniform(-1, 1, (8, 7)).astype(np.float32)
    agent = Agent.load(member_file)
    np.testing.assert_allclose(policy.act(history), agent.act(history, deterministic=True))


def test_a_misaligner_is_not_a_policy(tmp_path: Path) -> None:
    path = tmp_path / "mis.pt"
    tiny_member("misaligner").save(path)
    with pytest.raises(ValueError, match="misaligner"):
        load_deployable(str(path))


def test_a_league_run_gives_its_champion(tmp_path: Path) -> None:
    run = tmp_path / "league"
    (run / "best").mkdir(parents=True)
    (run / "config.yaml").write_text(
        "name: league\nhistory: 8\ntask_options:\n  episode_steps: 6\n"
    )
    (run / "aligners.yaml").write_text("team: aligner\n")
    tiny_member().save(run / "best" / "tiny-aligner.pt")
    (run / "best" / "best.json").write_text(json.dumps([{"member": "tiny-aligner"}]))
    policy = load_deployable(str(run))
    assert policy.name == "tiny-aligner" and policy.task.episode_steps == 6
    assert str(run) in policy.source


def test_a_training_run_gives_its_best_checkpoint(tmp_path: Path) -> None:
    from alignrl.checkpoints import save_checkpoint
    from alignrl.config.experiment import dump_experiment, parse_experiment
    from alignrl.runs.training_runs import member_spec
    from alignrl.training import CHECKPOINT_FORMAT

    config = parse_experiment({"name": "trained", "history": 6}, "test")
    agent = Agent(member_spec(config))
    state = {
        "format": CHECKPOINT_FORMAT,
        "agent": agent.state_dict(),
        "config": dump_experiment(config),
    }
    save_checkpoint(tmp_path / "trained" / "checkpoints" / "best.pt", state)
    policy = load_deployable(str(tmp_path / "trained"))
    assert (policy.name, policy.history) == ("trained", 6)
    assert "checkpoints/best.pt" in policy.source


def test_a_shipped_champion_is_an_exported_policy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, member_file: Path
) -> None:
    from alignrl.deploy.export import export_policy
    from alignrl.runs.sources import resolve_source

    monkeypatch.setattr(sources, "CHAMPIONS", tmp_path / "champions")
    with pytest.raises(PolicySpecError, match="shipped champions: none"):
        load_deployable("champion:tiny")
    export_policy(
        resolve_source(member_file), tmp_path / "champions" / "tiny", "torchscript", histories=8
    )
    champion = load_deployable("champion:tiny")
    assert champion.name == "tiny-aligner" and champion.history == 8
    history = np.random.default_rng(1).uniform(-1, 1, (8, 7)).astype(np.float32)
    expected = Agent.load(member_file).act(history, deterministic=True)
    np.testing.assert_allclose(champion.act(history), expected, atol=1e-5)
    assert load_deployable(str(tmp_path / "champions" / "tiny")).name == "tiny-aligner"
    with pytest.raises(PolicySpecError, match="shipped champions: tiny"):
        load_deployable("champion:other")


def test_align_a_safetensors_champion_end_to_end(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    member_file: Path,
) -> None:
    champions = tmp_path / "champions"
    monkeypatch.setattr(sources, "CHAMPIONS", champions)
    out = champions / "tiny"
    assert main(["export", str(member_file), "--format", "safetensors", "--out", str(out)]) == 0
    capsys.readouterr()
    assert sorted(path.name for path in out.iterdir()) == [
        "card.json",
        "model_card.md",
        "policy.safetensors",
    ]
    code = main(["align", "--policy", "champion:tiny", "--apparatus", "synthetic", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert set(result) == JSON_KEYS and code == result["exit_code"] in (0, 1)  # untrained
    assert result["policy"] == "tiny-aligner" and result["acquisitions"] > 0
    # An unknown name lists the champions there are; an export being staged is none of them.
    (champions / ".other.tmp-1234").mkdir()
    assert main(["align", "--policy", "champion:nope", "--apparatus", "synthetic"]) == 2
    assert "no shipped champion 'nope'; shipped champions: tiny\n" in capsys.readouterr().err


def test_the_log_file_is_strict_json_even_for_a_nan_action(tmp_path: Path) -> None:
    from alignrl.apparatus.shield import JsonLinesAudit, resolve_limits
    from alignrl.deploy.align import align

    driver = RecordingDriver()
    path = tmp_path / "audit.jsonl"
    with JsonLinesAudit(path) as audit:
        result = align(constant(float("nan"), -1.0), driver, resolve_limits(driver.knobs), audit)
    assert result.exit_code == 3

    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} is not JSON")

    lines = [json.loads(line, parse_constant=refuse) for line in path.read_text().splitlines()]
    action = next(line for line in lines if line["event"] == "action")
    assert action["action"] == ["nan", -1.0] and action["decision"] == "refused"


# --- a column aligned by a sequence of task champions --------------------------------------


def _oracle(column: Any, task_name: str) -> DeployablePolicy:
    """A policy for `task_name` that steps its knobs towards the column's secret optimum."""
    from alignrl.envs.task import get_task

    task = get_task(task_name)
    steps = np.array(task.step_sizes(column.knobs))

    def act(history: np.ndarray) -> np.ndarray:
        error = np.array([column.best[k] - column.setting[k] for k in task.knobs])
        if np.all(np.abs(error) < 1e-6):
            return np.append(np.zeros(len(task.knobs)), 1.0)
        return np.append(np.clip(error / steps, -1, 1), -1.0)

    return DeployablePolicy(f"oracle-{task_name}", act, task, 4, "test")


def _misaligned_column() -> Any:
    from fake_drivers import FiveKnobColumn

    column = FiveKnobColumn()
    column.reset(4)
    return column


def test_a_sequence_of_task_champions_aligns_the_column_through_the_shield() -> None:
    from alignrl.apparatus.shield import MemoryAudit, resolve_limits
    from alignrl.envs.task import get_task

    column = _misaligned_column()
    audit = MemoryAudit()
    sequence = [_oracle(column, name) for name in ("aperture", "focus", "stigmation")]
    result = align(sequence, column, resolve_limits(column.knobs), audit, task=get_task("column"))
    assert result.outcome == "aligned", result.reason
    assert result.policy == "oracle-aperture -> oracle-focus -> oracle-stigmation"
    assert result.final_wobble_px is not None and len(result.final_directional_px) == 4
    stages = [entry["task"] for entry in audit.entries if entry["event"] == "stage"]
    assert stages == ["aperture", "focus", "stigmation"]
    # Every image counted: the aperture stage measures with a wobble (3 per measurement).
    counted = [e for e in audit.entries if e["event"] == "measure" and e["purpose"] != "final"]
    wobbles = sum("shift_px" in entry for entry in counted)
    assert wobbles >= 2  # the aperture stage's first measurement and one after its move
    assert result.acquisitions == (len(counted) - wobbles) + 2 * wobbles


def test_a_sequence_that_skips_the_stigmators_is_not_aligned() -> None:
    from alignrl.apparatus.shield import MemoryAudit, resolve_limits
    from alignrl.envs.task import get_task

    column = _misaligned_column()
    sequence = [_oracle(column, name) for name in ("aperture", "focus")]
    result = align(
        sequence, column, resolve_limits(column.knobs), MemoryAudit(), task=get_task("column")
    )
    assert result.outcome == "not-aligned"
    assert "final edge width" in result.reason and ">" in result.reason


def test_a_sequence_needs_a_task_that_covers_its_policies() -> None:
    from alignrl.apparatus.shield import MemoryAudit, resolve_limits
    from alignrl.envs.task import get_task

    column = _misaligned_column()
    limits = resolve_limits(column.knobs)
    sequence = [_oracle(column, "aperture"), _oracle(column, "focus")]
    with pytest.raises(ValueError, match="needs the task it is judged on"):
        align(sequence, column, limits, MemoryAudit())
    with pytest.raises(ValueError, match="which task 'stigmation' does not align"):
        align(sequence, column, limits, MemoryAudit(), task=get_task("stigmation"))


# --- --gif: the alignment as an animated GIF ----------------------------------------------


def test_align_writes_a_gif_of_each_acquisition_and_the_final_image(
    capsys: pytest.CaptureFixture[str], member_file: Path, tmp_path: Path
) -> None:
    from PIL import Image, ImageSequence

    out = tmp_path / "align.gif"
    argv = ["align", "--policy", str(member_file), "--apparatus", "synthetic", "--seed", "2"]
    code = main([*argv, "--gif", str(out), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert set(result) == JSON_KEYS | {"gif"} and code == result["exit_code"] in (0, 1)
    assert result["gif"] == str(out)
    with Image.open(out) as gif:
        frames = [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(gif)]
    # One frame per acquisition of the alignment, then the final (judging) image.
    assert len(frames) == result["acquisitions"] + 1
    assert all(np.any(a != b) for a, b in itertools.pairwise(frames))


def test_filming_sends_the_driver_nothing_more(
    capsys: pytest.CaptureFixture[str], scripted_policy, tmp_path: Path
) -> None:
    code, plain = align_cli(capsys, "--policy", "seeker", "--spec-px", "3.2")
    calls = RecordingDriver.last.calls  # type: ignore[union-attr]
    gif = tmp_path / "seeker.gif"
    filmed_code, filmed = align_cli(
        capsys, "--policy", "seeker", "--spec-px", "3.2", "--gif", str(gif)
    )
    assert RecordingDriver.last.calls == calls  # type: ignore[union-attr]
    assert (filmed_code, filmed.pop("gif")) == (code, str(gif)) and filmed == plain
    text = main(
        [
            "align",
            "--policy",
            "seeker",
            "--apparatus",
            DRIVER,
            "--spec-px",
            "3.2",
            "--gif",
            str(gif),
        ]
    )
    assert text == code and f"animation: {gif} (" in capsys.readouterr().out


def test_a_gif_path_in_a_missing_folder_is_refused_before_anything_happens(
    capsys: pytest.CaptureFixture[str], scripted_policy, tmp_path: Path
) -> None:
    RecordingDriver.last = None
    missing = tmp_path / "no-such-folder" / "a.gif"
    code = main(["align", "--policy", "seeker", "--apparatus", DRIVER, "--gif", str(missing)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "" and RecordingDriver.last is None  # never opened
    assert captured.err == (
        f"alignrl: error: --gif {tmp_path}/no-such-folder/a.gif: the folder "
        f"{tmp_path}/no-such-folder does not exist; create it first, or write the GIF elsewhere\n"
    )

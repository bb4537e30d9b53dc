"""Hostile policies: a tampered card.json, a policy file that is not its card's, a checkpoint
of the wrong shapes, with NaN weights, truncated, or missing a tensor. Each is refused by the
command that meets it (exit 2, one line naming the file and the field or tensor), never
believed, never a traceback; nothing already written changes, and no write reaches a driver.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import create_league, one_sac_each, write_league_files
from hostile import assert_refused, assert_unchanged, run_cli, tree_state
from test_align import tiny_member
from test_shield import RecordingDriver

from alignrl.checkpoints import load_checkpoint, save_checkpoint
from alignrl.deploy.export import export_policy
from alignrl.runs.sources import resolve_source

DRIVER = "test_shield:RecordingDriver"
ACTOR_HEAD = "learner.actor.head.0.weight"  # a tensor of every tiny SAC member


@pytest.fixture(scope="module")
def member_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("member") / "tiny.pt"
    tiny_member().save(path)
    return path


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory, member_file: Path) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("exports")
    source = resolve_source(member_file)
    return {
        fmt: export_policy(source, root / fmt, fmt, histories=8).out
        for fmt in ("safetensors", "torchscript")
    }


def align_refused(capsys: pytest.CaptureFixture[str], policy: Path, *names: str) -> None:
    """`alignrl align --policy POLICY` on the recording driver: refused, nothing written."""
    RecordingDriver.last = None
    before = tree_state(policy)
    outcome = run_cli(["align", "--policy", policy, "--apparatus", DRIVER, "--json"], capsys)
    assert_refused(outcome, 2, *names)
    assert RecordingDriver.last is None or RecordingDriver.last.count("write") == 0
    assert_unchanged(before, policy)


# --- card.json tampered -----------------------------------------------------------------


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(card: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        entry: Any = card
        for key in parents:
            entry = entry[int(key)] if isinstance(entry, list) else entry[key]
        if value is KeyError:
            del entry[last]
        else:
            entry[last] = value

    return change


def _widen(card: dict[str, Any]) -> None:
    card["knobs"][0].update(low=-1000.0, high=1000.0)


CARD_TAMPERS = {
    "widened interval": (_widen, "knobs[0].max_step"),
    "max_step 1e9": (_set("knobs.0.max_step", 1e9), "knobs[0].max_step"),
    "max_step NaN": (_set("knobs.0.max_step", float("nan")), "knobs[0].max_step"),
    "max_step -1": (_set("knobs.0.max_step", -1.0), "knobs[0].max_step"),
    "max_step_fraction 2": (
        _set("task.options", {"max_step_fraction": 2.0}),
        "task.options.max_step_fraction",
    ),
    "success_absolute_px 1000": (
        _set("task.options", {"success_absolute_px": 1000.0}),
        "task.options.success_absolute_px",
    ),
    "success.absolute_px 1000": (_set("task.success.absolute_px", 1000.0), "task.success"),
    "success_relative 5": (
        _set("task.options", {"success_relative": 5.0}),
        "task.options.success_relative",
    ),
    "episode_steps 1e6": (
        _set("task.options", {"episode_steps": 1_000_000}),
        "task.options.episode_steps",
    ),
    "unknown key": (_set("shield", "off"), "'shield'"),
    "unknown task option": (_set("task.options", {"limits": "none"}), "task.options.limits"),
    "missing key": (_set("knobs", KeyError), "'knobs'"),
    "wrong type": (_set("history", "8"), "history"),
    "older format": (_set("format", "alignrl-policy-card-0"), "card format"),
    "policy file elsewhere": (_set("policy_file", "../policy.safetensors"), "policy_file"),
    "a misaligner": (_set("member.team", "misaligner"), "member"),
    "history vs member": (_set("member.observation_shape", [6, 7]), "member.observation_shape"),
    "parity failed": (_set("parity.passed", False), "parity.passed"),
    "bad hash": (_set("policy_sha256", "not a hash"), "policy_sha256"),
}


@pytest.mark.parametrize("tamper", list(CARD_TAMPERS))
def test_a_tampered_card_is_refused(
    tamper: str, exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    change, field = CARD_TAMPERS[tamper]
    folder = shutil.copytree(exports["safetensors"], tmp_path / "policy")
    card = json.loads((folder / "card.json").read_text())
    change(card)
    (folder / "card.json").write_text(json.dumps(card))  # NaN as JSON's NaN, as a tamperer
    align_refused(capsys, folder, "card.json", field)


def test_a_card_that_widens_nothing_is_believed_the_same(
    exports: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    # The untampered export aligns (exit 0 or 1: untrained), so the refusals above are the
    # tampering's, not the harness's.
    RecordingDriver.last = None
    outcome = run_cli(
        ["align", "--policy", exports["safetensors"], "--apparatus", DRIVER, "--spec-px", "3"],
        capsys,
    )
    assert outcome.code in (0, 1), outcome.text
    assert RecordingDriver.last is not None and not RecordingDriver.last.violations


def test_a_graph_whose_steps_disagree_with_its_card_is_refused(
    exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Interval, step and rule edited consistently: only the graph's own max_step tells.
    folder = shutil.copytree(exports["torchscript"], tmp_path / "policy")
    card = json.loads((folder / "card.json").read_text())
    card["knobs"][0].update(low=0.0, high=400.0, max_step=100.0)
    (folder / "card.json").write_text(json.dumps(card))
    align_refused(capsys, folder, "policy.pt", "max_step")


def test_a_graph_of_another_history_is_refused(
    exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shutil.copytree(exports["torchscript"], tmp_path / "policy")
    card = json.loads((folder / "card.json").read_text())
    card["history"] = 6
    card["member"]["observation_shape"] = [6, 7]
    card["inputs"][0]["shape"] = ["batch", 6, 7]
    (folder / "card.json").write_text(json.dumps(card))
    align_refused(capsys, folder, "policy.pt", "does not run on the inputs")


def test_weights_of_another_member_are_refused(
    exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shutil.copytree(exports["safetensors"], tmp_path / "policy")
    other = tmp_path / "other.pt"
    tiny_member().save(other)  # the same network, other weights
    export_policy(resolve_source(other), tmp_path / "other", "safetensors", histories=8)
    shutil.copy(tmp_path / "other" / "policy.safetensors", folder / "policy.safetensors")
    align_refused(capsys, folder, "card.json", "policy_sha256")
    card = json.loads((folder / "card.json").read_text())
    card["member"]["hyperparameters"]["hidden"] = [32]
    (folder / "card.json").write_text(json.dumps(card))
    align_refused(capsys, folder, "policy.safetensors", "head.0.weight")


# --- non-finite weights in an exported file ------------------------------------------------


def _poison_safetensors(path: Path) -> None:
    from safetensors.torch import load_file, save_file

    weights = load_file(str(path))
    name = sorted(weights)[0]
    weights[name] = torch.full_like(weights[name], float("nan"))
    save_file(weights, str(path))


def _poison_torchscript(path: Path) -> None:
    module = torch.jit.load(str(path))
    with torch.no_grad():
        next(iter(module.parameters())).fill_(float("inf"))
    torch.jit.save(module, str(path))


@pytest.mark.parametrize("fmt", ["safetensors", "torchscript"])
def test_an_export_with_non_finite_weights_is_refused(
    fmt: str, exports: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shutil.copytree(exports[fmt], tmp_path / "policy")
    policy_file = next(folder.glob("policy.*"))
    {"safetensors": _poison_safetensors, "torchscript": _poison_torchscript}[fmt](policy_file)
    align_refused(capsys, folder, policy_file.name, "non-finite")


def test_an_onnx_export_with_non_finite_weights_is_refused(
    member_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from onnx import numpy_helper

    out = export_policy(resolve_source(member_file), tmp_path / "onnx", "onnx", histories=8).out
    model = onnx.load(str(out / "policy.onnx"))
    weight = max(model.graph.initializer, key=lambda entry: len(entry.raw_data))
    array = numpy_helper.to_array(weight).copy()
    array.flat[0] = float("nan")
    weight.CopyFrom(numpy_helper.from_array(array, weight.name))
    onnx.save(model, str(out / "policy.onnx"))
    align_refused(capsys, out, "policy.onnx", "non-finite")


# --- checkpoints of the wrong shapes -------------------------------------------------------


def _tensor(state: dict[str, Any]) -> dict[str, Any]:
    """The actor's tensors in a member state."""
    return state["learner"]["actor"]


def _wider(state: dict[str, Any]) -> None:
    weight = _tensor(state)["head.0.weight"]
    _tensor(state)["head.0.weight"] = torch.zeros(64, *weight.shape[1:])


def _missing(state: dict[str, Any]) -> None:
    del _tensor(state)["head.0.weight"]


def _unexpected(state: dict[str, Any]) -> None:
    _tensor(state)["head.9.weight"] = torch.zeros(2)


def _not_a_tensor(state: dict[str, Any]) -> None:
    _tensor(state)["head.0.weight"] = "weights"


def _nan(state: dict[str, Any]) -> None:
    _tensor(state)["head.0.weight"][0, 0] = float("nan")


def _spec_types(state: dict[str, Any]) -> None:
    state["spec"]["observation_shape"] = ["eight", 7]


MEMBER_TAMPERS = {
    "wrong shape": (_wider, [ACTOR_HEAD, "has shape (64,"]),
    "missing tensor": (_missing, [ACTOR_HEAD, "is missing"]),
    "unexpected tensor": (_unexpected, ["learner.actor.head.9.weight"]),
    "not a tensor": (_not_a_tensor, [ACTOR_HEAD, "is a str"]),
    "NaN weight": (_nan, [ACTOR_HEAD, "non-finite"]),
    "spec of wrong types": (_spec_types, ["observation_shape"]),
}


def _tamper_file(path: Path, change: Callable[[dict[str, Any]], None], key: str | None) -> None:
    state = load_checkpoint(path)
    change(state[key] if key else state)
    save_checkpoint(path, state)


@pytest.fixture(scope="module")
def training_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A training run's folder: config.yaml, checkpoints/last.pt and best.pt, no training."""
    from alignrl.config.experiment import parse_experiment
    from alignrl.training import Trainer

    settings = {
        "name": "tiny",
        "envs": 1,
        "learner": {"encoder_kwargs": {"hidden": [16]}, "hidden": [16]},
        "budget": {"env_steps": 8, "eval_every": 8, "eval_scenarios": 1, "checkpoint_every": 8},
    }
    runs = tmp_path_factory.mktemp("runs")
    trainer = Trainer.create(parse_experiment(settings, "test"), runs)
    trainer.checkpoint()
    last = runs / "tiny" / "checkpoints" / "last.pt"
    shutil.copy(last, last.with_name("best.pt"))
    return runs / "tiny"


TRAINING_COMMANDS = {
    "evaluate": lambda run, out: ["evaluate", "--policy", run, "--apparatus", "synthetic"],
    "align": lambda run, out: ["align", "--policy", run, "--apparatus", DRIVER],
    "export": lambda run, out: ["export", run, "--format", "safetensors", "--out", out / "x"],
    "adapt": lambda run, out: [
        *("adapt", "--from", run, "--apparatus", "synthetic", "--steps", "8"),
        *("--runs-dir", out / "runs"),
    ],
    "train --resume": lambda run, out: ["train", "--resume", run, "--quiet"],
}


@pytest.mark.parametrize("tamper", list(MEMBER_TAMPERS))
@pytest.mark.parametrize("command", list(TRAINING_COMMANDS))
def test_a_training_checkpoint_that_does_not_fit_is_refused(
    command: str,
    tamper: str,
    training_run: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    change, names = MEMBER_TAMPERS[tamper]
    run = shutil.copytree(training_run, tmp_path / "tiny")
    checkpoint = "last.pt" if command == "train --resume" else "best.pt"
    _tamper_file(run / "checkpoints" / checkpoint, change, "agent")
    before = tree_state(run)
    RecordingDriver.last = None
    outcome = run_cli(TRAINING_COMMANDS[command](run, tmp_path), capsys)
    assert_refused(outcome, 2, *names)
    assert_unchanged(before, run)
    assert not (tmp_path / "x").exists() and not (tmp_path / "runs").exists()
    assert RecordingDriver.last is None or RecordingDriver.last.count("write") == 0
    assert f"checkpoints/{checkpoint}" in outcome.text, outcome.text


def test_a_checkpoint_of_another_network_size_is_refused(
    training_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from alignrl.agents.agent import Agent, MemberSpec

    run = shutil.copytree(training_run, tmp_path / "tiny")
    best = run / "checkpoints" / "best.pt"
    state = load_checkpoint(best)
    spec = MemberSpec.from_dict(state["agent"]["spec"])
    bigger = {**spec.hyperparameters, "hidden": [64]}
    state["agent"] = Agent(MemberSpec(**{**spec.to_dict(), "hyperparameters": bigger})).state_dict()
    save_checkpoint(best, state)
    outcome = run_cli(["export", run, "--format", "safetensors", "--out", tmp_path / "x"], capsys)
    assert_refused(
        outcome, 2, "checkpoints/best.pt", ACTOR_HEAD, "(64, 16), the spec needs (16, 16)"
    )


def test_a_truncated_checkpoint_is_refused(
    training_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = shutil.copytree(training_run, tmp_path / "tiny")
    best = run / "checkpoints" / "best.pt"
    best.write_bytes(best.read_bytes()[:300])
    outcome = run_cli(["align", "--policy", run, "--apparatus", DRIVER], capsys)
    assert_refused(outcome, 2, "checkpoints/best.pt", "cannot be read")


# --- league members ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def league_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A league run's folder after its first checkpoint (nothing played)."""
    folder = tmp_path_factory.mktemp("league")
    small = {"encoder_kwargs": {"hidden": [16]}, "hidden": [16], "batch_size": 16}
    schedule = {"iterations": 1, "matches": 2, "eval_scenarios": 1, "checkpoint_every": 1}
    settings = {"name": "tiny", "envs": 2, "schedule": schedule}
    path = write_league_files(folder, **one_sac_each(small), settings=settings)
    league = create_league(path, folder / "runs")
    league.checkpoint()
    league.close()
    return folder / "runs" / "tiny"


@pytest.mark.parametrize("tamper", list(MEMBER_TAMPERS))
@pytest.mark.parametrize("command", ["leaderboard", "league resume", "export --member"])
def test_a_league_member_that_does_not_fit_is_refused(
    command: str,
    tamper: str,
    league_run: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    change, names = MEMBER_TAMPERS[tamper]
    run = shutil.copytree(league_run, tmp_path / "tiny")
    folder = run / "checkpoints" / (run / "checkpoints" / "LATEST").read_text().strip()
    member = folder / "members" / "a-sac.pt"
    _tamper_file(member, change, None)
    before = tree_state(run)
    argv = {
        "leaderboard": ["leaderboard", run],
        "league resume": ["league", "resume", run, "--quiet"],
        "export --member": [
            *("export", run, "--member", "a-sac", "--format", "safetensors"),
            *("--out", tmp_path / "x"),
        ],
    }[command]
    outcome = run_cli(argv, capsys)
    assert_refused(outcome, 2, "members/a-sac.pt", *names)
    assert_unchanged(before, run)
    assert not (tmp_path / "x").exists()

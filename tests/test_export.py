"""`alignrl export`: the exported policy acts exactly as the member does (ONNX, TorchScript and
safetensors; MLP-SAC, GTrXL-SAC and GRU-PPO), says what it is in its model card, and the
command refuses what it should (overwrites, misaligners, unknown members, corrupt files)."""

from __future__ import annotations

import csv
import datetime
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from alignrl import __version__
from alignrl.agents.agent import Agent, MemberSpec
from alignrl.cli import main
from alignrl.deploy.card import CARD_KEYS
from alignrl.deploy.export import export_policy
from alignrl.deploy.graph import random_histories
from alignrl.deploy.loading import load_exported
from alignrl.deploy.parity import PARITY_TOLERANCE
from alignrl.envs.alignment import aligner_spaces
from alignrl.league.config import load_league
from alignrl.league.loop import League
from alignrl.runs.sources import ExportError, resolve_source

HISTORY = 8  # the default run's history rows
OBSERVATION, ACTION = aligner_spaces(1, HISTORY)
DEFAULT_MAX_STEP_V = 25.0  # focus task: 0.25 of csv:default's 0-100 V interval
SMALL_SAC = {
    "encoder_kwargs": {"hidden": [16]},
    "hidden": [16],
    "batch_size": 16,
    "learning_starts": 16,
    "random_steps": 32,
    "buffer_size": 2000,
}
ARCHITECTURES = {
    "mlp-sac": ("sac", SMALL_SAC),
    "gtrxl-sac": (
        "sac",
        {**SMALL_SAC, "encoder": "gtrxl", "encoder_kwargs": {"d_model": 8, "heads": 2}},
    ),
    "gru-ppo": (
        "ppo",
        {
            "encoder": "gru",
            "encoder_kwargs": {"hidden": 8},
            "hidden": [16],
            "batch_size": 16,
            "rollout_steps": 4,
            "epochs": 1,
        },
    ),
}
FORMATS = ("onnx", "torchscript", "safetensors")


def needs_runtime(export_format: str) -> None:
    if export_format == "onnx":
        pytest.importorskip(
            "onnxruntime", reason="ONNX export needs the onnx extra: pip install 'alignrl[onnx]'"
        )


def make_member(member_id: str, algorithm: str, hyperparameters: dict, team: str = "aligner"):
    shape, actions = (OBSERVATION.shape, ACTION.shape[0]) if team == "aligner" else ((1, 3), 1)
    spec = MemberSpec(
        id=member_id,
        team=team,
        algorithm=algorithm,
        observation_shape=shape,
        action_dim=actions,
        secret_dim=1,
        hyperparameters=hyperparameters,
    )
    torch.manual_seed(0)
    agent = Agent(spec)
    # An untrained head's means sit near 0, where tanh is linear: scale its last layer so
    # that the actions spread over (-1, 1) and saturate, as a trained policy's do.
    learner = agent.learner
    policy = learner.actor if algorithm == "sac" else learner.policy
    with torch.no_grad():
        for parameter in policy.head[-1].parameters():
            parameter.mul_(8.0)
    return agent


def saved_member(tmp_path: Path, name: str) -> tuple[Agent, Path]:
    algorithm, hyperparameters = ARCHITECTURES[name]
    agent = make_member(name, algorithm, hyperparameters)
    path = tmp_path / f"{name}.pt"
    agent.save(path)
    return agent, path


def histories(count: int, seed: int = 7) -> np.ndarray:
    return random_histories(count, *OBSERVATION.shape, np.random.default_rng(seed))


# --- parity -----------------------------------------------------------------------------


@pytest.mark.parametrize("export_format", FORMATS)
@pytest.mark.parametrize("name", list(ARCHITECTURES))
def test_the_exported_policy_acts_as_the_member_does(
    tmp_path: Path, name: str, export_format: str
) -> None:
    needs_runtime(export_format)
    agent, path = saved_member(tmp_path, name)
    result = export_policy(resolve_source(path), tmp_path / "out", export_format)
    # The export checked the file it wrote on 1000 random histories, and says so.
    assert result.parity.histories == 1000
    assert result.parity.max_abs_difference <= PARITY_TOLERANCE
    assert result.card["parity"]["max_abs_difference"] == result.parity.max_abs_difference
    # Checked again here, on other histories, through the public loader.
    policy = load_exported(tmp_path / "out")
    batch = histories(1000)
    expected = agent.act(batch, deterministic=True)
    actions = policy.act(batch)
    assert actions.dtype == np.float64 and actions.shape == (1000, 2)
    assert np.max(np.abs(actions - expected)) <= PARITY_TOLERANCE
    assert np.all(np.abs(actions) <= 1.0) and np.abs(actions).max() > 0.5  # not all near 0
    # One history in, one action out.
    single = policy.act(batch[3])
    assert single.shape == (2,) and np.max(np.abs(single - expected[3])) <= PARITY_TOLERANCE
    # knob_step is the knob change the env would make of that action: action x max step.
    outputs = policy.run(batch)
    assert set(outputs) == {"action", "knob_step"}
    np.testing.assert_allclose(
        outputs["knob_step"], outputs["action"][:, :1] * DEFAULT_MAX_STEP_V, rtol=1e-6, atol=1e-6
    )
    assert policy.history == HISTORY and policy.task.name == "focus"
    np.testing.assert_array_equal(policy.max_step, [DEFAULT_MAX_STEP_V])


def test_random_histories_are_right_aligned_like_the_envs() -> None:
    batch = histories(2000)
    valid = batch[..., 0]
    assert set(np.unique(valid)) == {0.0, 1.0}
    # Once a row is valid, every newer row is too; padding rows are all zeros.
    assert np.all(np.diff(valid, axis=1) >= 0)
    assert np.all(batch[valid == 0.0] == 0.0)
    counts = valid.sum(axis=1)
    assert counts.min() == 0 and counts.max() == HISTORY  # a few all padding, some full
    assert 0 < np.mean(counts == 0) < 0.05
    assert np.all(batch >= OBSERVATION.low) and np.all(batch <= OBSERVATION.high)


# --- files and errors ---------------------------------------------------------------------


@pytest.mark.parametrize("export_format", FORMATS)
def test_a_corrupt_or_missing_policy_file_is_a_clear_error(
    tmp_path: Path, export_format: str
) -> None:
    needs_runtime(export_format)
    _, path = saved_member(tmp_path, "mlp-sac")
    result = export_policy(resolve_source(path), tmp_path / "out", export_format)
    result.policy_file.write_bytes(result.policy_file.read_bytes()[:200])  # truncated
    with pytest.raises(ExportError, match=rf"policy file {result.policy_file} cannot be loaded"):
        load_exported(tmp_path / "out")
    result.policy_file.unlink()
    with pytest.raises(ExportError, match=rf"policy file {result.policy_file} is missing"):
        load_exported(tmp_path / "out")
    (tmp_path / "out" / "card.json").write_text("{not json")
    with pytest.raises(ExportError, match=r"card\.json is not valid JSON"):
        load_exported(tmp_path / "out")
    with pytest.raises(ExportError, match="is not an exported policy"):
        load_exported(tmp_path)


def test_onnx_without_onnxruntime_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, path = saved_member(tmp_path, "mlp-sac")
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import onnxruntime -> ImportError
    with pytest.raises(ImportError, match=r"pip install 'alignrl\[onnx\]'"):
        export_policy(resolve_source(path), tmp_path / "out", "onnx")
    assert not (tmp_path / "out").exists()


def test_an_export_that_fails_its_parity_check_writes_nothing(tmp_path: Path) -> None:
    _, path = saved_member(tmp_path, "gru-ppo")
    out = tmp_path / "exports" / "policy"
    with pytest.raises(
        ExportError, match=r"differs from the PyTorch policy .* nothing was written"
    ):
        export_policy(resolve_source(path), out, "torchscript", tolerance=-1.0)
    assert not out.exists()
    assert list((tmp_path / "exports").iterdir()) == []  # no staging folder left behind


def test_a_misaligner_is_not_exported(tmp_path: Path) -> None:
    agent = make_member("m-sac", "sac", SMALL_SAC, team="misaligner")
    agent.save(tmp_path / "m-sac.pt")
    with pytest.raises(ExportError, match="'m-sac' is a misaligner; only aligners can be exported"):
        resolve_source(tmp_path / "m-sac.pt")


# --- the command on runs ----------------------------------------------------------------


@pytest.fixture(scope="module")
def league_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two iterations of a tiny league: one aligner in best/ (the champion), the others in
    the checkpoint only, a PBT copy with a parent, an evaluation session."""
    folder = tmp_path_factory.mktemp("league")
    members = [{"id": name, "learner": learner} for name, (_, learner) in ARCHITECTURES.items()]
    members[2]["learner"] = {**members[2]["learner"], "algorithm": "ppo"}
    rosters = {
        "aligners.yaml": {"team": "aligner", "members": members},
        "misaligners.yaml": {
            "team": "misaligner",
            "members": [{"id": "m-sac", "learner": SMALL_SAC}],
        },
    }
    for name, roster in rosters.items():
        (folder / name).write_text(yaml.safe_dump(roster))
    settings = {
        "name": "tiny",
        "envs": 4,
        "aligners": str(folder / "aligners.yaml"),
        "misaligners": str(folder / "misaligners.yaml"),
        "schedule": {
            "iterations": 2,
            "matches": 4,
            "snapshot_every": 100,
            "pbt_every": 1,  # a copy at iteration 1; none at the last (alignrl/league/loop.py)
            "evaluate_every": 2,
            "eval_scenarios": 2,
            "checkpoint_every": 2,
            "keep_best": 1,
        },
        "pbt": {"min_gap": 0.0},
    }
    (folder / "league.yaml").write_text(yaml.safe_dump(settings))
    config, aligners, misaligners = load_league(folder / "league.yaml")
    League.create(config, aligners, misaligners, folder / "runs").run(progress=False)
    return folder / "runs" / "tiny"


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_export_of_a_league_champion_end_to_end(
    league_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    needs_runtime("onnx")
    out = tmp_path / "champion"
    assert main(["export", str(league_run), "--format", "onnx", "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    champion = json.loads((league_run / "best" / "best.json").read_text())[0]["member"]
    assert report["member"] == champion and report["chosen_as"] == "champion"
    assert report["policy"] == str(out / "policy.onnx") and report["format"] == "onnx"
    assert report["parity_histories"] == 1000
    assert report["parity_max_abs_difference"] <= PARITY_TOLERANCE
    assert report["inputs"] == [
        {"name": "history", "dtype": "float32", "shape": ["batch", HISTORY, 7]}
    ]
    assert [entry["name"] for entry in report["outputs"]] == ["action", "knob_step"]
    assert report["memory"] == "history-window"
    assert sorted(path.name for path in out.iterdir()) == [
        "card.json",
        "model_card.md",
        "policy.onnx",
    ]
    # The model card says what is true of this member and run.
    card = json.loads((out / "card.json").read_text())
    assert tuple(card) == CARD_KEYS
    member = Agent.load(league_run / "best" / f"{champion}.pt")
    assert card["member"]["id"] == champion and card["member"]["team"] == "aligner"
    assert card["member"]["steps_seen"] == member.steps_seen
    assert card["training"]["updates"] == member.updates
    assert card["member"]["architecture"] == member.spec.architecture
    assert card["alignrl_version"] == __version__ and card["export_format"] == "onnx"
    assert card["created"][:10] == datetime.datetime.now(datetime.UTC).date().isoformat()
    assert card["knobs"] == [
        {"name": "defocus", "low": 0.0, "high": 100.0, "max_step": DEFAULT_MAX_STEP_V}
    ]
    assert card["training"]["apparatus"] == "csv:default"
    assert card["training"]["apparatus_args"] == {"noise": 0.02, "split": "train"}
    assert card["training"]["league_iteration"] == 2
    assert card["source"]["config_file"] == str(league_run / "config.yaml")
    rows = [row for row in read_csv(league_run / "metrics" / "evaluations.csv")]
    mine = [row for row in rows if row["member"] == champion]
    assert len(card["evaluations"]["rows"]) == len(mine) >= 1
    assert card["evaluations"]["rows"][0]["successes"] == int(mine[0]["successes"])
    assert card["evaluations"]["command"].startswith("alignrl evaluate --policy ")
    assert "--scenarios 2 --seed 1000000" in card["evaluations"]["command"]
    assert "the history window of 8 rows is the policy's whole memory" in card["memory"]["note"]
    assert card["parity"]["max_abs_difference"] == report["parity_max_abs_difference"]
    text = (out / "model_card.md").read_text()
    assert f"# Model card: {champion}" in text and card["evaluations"]["command"] in text
    # The exported file acts as the member does.
    batch = histories(200)
    policy = load_exported(out)
    assert np.max(np.abs(policy.act(batch) - member.act(batch))) <= PARITY_TOLERANCE
    # A second export into the same folder is refused, and the first is left as it was;
    # --force replaces it.
    before = (out / "policy.onnx").read_bytes()
    assert main(["export", str(league_run), "--format", "torchscript", "--out", str(out)]) == 2
    assert "is not empty" in capsys.readouterr().err
    assert (out / "policy.onnx").read_bytes() == before and not (out / "policy.pt").exists()
    code = main(
        ["export", str(league_run), "--format", "torchscript", "--out", str(out), "--force"]
    )
    assert code == 0
    assert "parity:" in capsys.readouterr().out
    assert sorted(path.name for path in out.iterdir()) == [
        "card.json",
        "model_card.md",
        "policy.pt",
    ]
    assert [path.name for path in tmp_path.iterdir()] == ["champion"]  # no leftovers


def test_an_export_without_out_lands_beside_its_run_or_under_runs(
    league_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Without --out nothing is written into the working directory itself: a run's policy
    goes to RUN/exports/MEMBER-FORMAT, a shipped champion's to runs/exports/NAME-FORMAT."""
    run = shutil.copytree(league_run, tmp_path / "elsewhere" / "tiny")
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert main(["export", str(run), "--format", "safetensors", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    beside = run / "exports" / f"{report['member']}-safetensors"
    assert report["out"] == str(beside) and (beside / "policy.safetensors").is_file()
    assert json.loads((beside / "card.json").read_text())["command"].endswith(f"--out {beside}")
    assert list(here.iterdir()) == []
    assert main(["export", "champion:focus-v1", "--format", "torchscript"]) == 0
    assert "runs/exports/focus-v1-torchscript/policy.pt" in capsys.readouterr().out
    assert sorted(path.relative_to(here) for path in here.rglob("*") if path.is_file()) == [
        Path("runs/exports/focus-v1-torchscript") / name
        for name in ("card.json", "model_card.md", "policy.pt")
    ]
    # The same export again is refused (exit 2), as for a given --out.
    assert main(["export", "champion:focus-v1", "--format", "torchscript"]) == 2
    assert "runs/exports/focus-v1-torchscript is not empty" in capsys.readouterr().err


def test_export_of_a_league_member_by_id(
    league_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A member not among the best: its file in the newest checkpoint. A PBT copy records
    # its parent.
    copy = read_csv(league_run / "metrics" / "lineage.csv")[0]
    out = tmp_path / "copy"
    args = ["export", str(league_run), "--member", copy["member"], "--format", "torchscript"]
    assert main([*args, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["member"] == copy["member"] and report["chosen_as"] == "--member"
    card = load_exported(out).card
    assert card["source"]["member_file"].endswith(f"members/{copy['member']}.pt")
    assert card["lineage"]["parent"] == copy["parent"]
    assert card["lineage"]["copies"][0]["member"] == copy["member"]
    # An unknown id is refused with the ids there are; a misaligner is refused.
    assert main([*args[:2], "--member", "nobody", "--format", "onnx", "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "has no member 'nobody'; its members:" in error and copy["member"] in error
    assert "m-sac" in error
    assert (
        main([*args[:2], "--member", "m-sac", "--format", "onnx", "--out", str(tmp_path / "m")])
        == 2
    )
    assert "only aligners can be exported" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_export_of_a_training_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    settings = {
        "name": "tiny",
        "envs": 2,
        "learner": {
            "algorithm": "ppo",
            "encoder": "gru",
            "encoder_kwargs": {"hidden": 8},
            "hidden": [16],
            "rollout_steps": 8,
            "batch_size": 16,
            "epochs": 1,
        },
        "task_options": {"max_step_fraction": 0.1},
        "budget": {"env_steps": 32, "eval_every": 16, "eval_scenarios": 2, "checkpoint_every": 32},
    }
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(settings))
    runs = tmp_path / "runs"
    assert main(["train", str(tmp_path / "tiny.yaml"), "--runs-dir", str(runs), "--quiet"]) == 0
    capsys.readouterr()
    out = tmp_path / "exported"
    args = ["export", str(runs / "tiny"), "--format", "torchscript", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "exported tiny (best checkpoint of" in printed and "at most 10 per action" in printed
    policy = load_exported(out / "policy.pt")  # the folder or its policy file
    card = policy.card
    assert card["source"]["kind"] == "training" and card["member"]["algorithm"] == "ppo"
    # The task is rebuilt with the run's options: a max step of 0.1 x 100 V.
    assert policy.task.max_step_fraction == 0.1 and card["knobs"][0]["max_step"] == 10.0
    rows = read_csv(runs / "tiny" / "metrics" / "evaluations.csv")
    assert [row["env_steps"] for row in card["evaluations"]["rows"]] == [
        int(row["env_steps"]) for row in rows
    ]
    assert card["evaluations"]["note"] and "max_step_fraction" in card["evaluations"]["note"]
    assert card["training"]["env_steps"] in {16, 32}
    from alignrl.runs.training_runs import load_policy

    agent, _ = load_policy(runs / "tiny")
    batch = histories(100)
    assert np.max(np.abs(policy.act(batch) - agent.act(batch))) <= PARITY_TOLERANCE
    outputs = policy.run(batch)
    np.testing.assert_allclose(outputs["knob_step"], outputs["action"][:, :1] * 10.0, atol=1e-5)
    # --member belongs to league runs.
    assert main([*args[:2], "--member", "x", *args[2:], "--force"]) == 2
    assert "--member picks a member of a league run" in capsys.readouterr().err


# --- safetensors: the weights alone ---------------------------------------------------------


@pytest.mark.parametrize("name", list(ARCHITECTURES))
def test_a_safetensors_policy_is_the_acting_network_alone(
    tmp_path: Path, name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from safetensors import safe_open

    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # needs nothing beyond alignrl's own
    agent, path = saved_member(tmp_path, name)
    result = export_policy(resolve_source(path), tmp_path / "out", "safetensors")
    assert result.policy_file == tmp_path / "out" / "policy.safetensors"
    assert sorted(p.name for p in result.out.iterdir()) == [
        "card.json",
        "model_card.md",
        "policy.safetensors",
    ]
    # As readable as the card beside it (safetensors itself writes 0600).
    mode = result.policy_file.stat().st_mode & 0o777
    assert mode == (result.out / "card.json").stat().st_mode & 0o777
    # The file: a JSON header and raw tensors (no pickle), the acting network's and no more.
    raw = result.policy_file.read_bytes()
    header_size = int.from_bytes(raw[:8], "little")
    assert raw[8:9] == b"{" and json.loads(raw[8 : 8 + header_size])
    acting = agent.policy_state()["policy"]
    with safe_open(str(result.policy_file), "pt") as handle:
        assert sorted(handle.keys()) == sorted(acting)
        assert handle.metadata() == {"format": "alignrl-policy-1", "member": name}
        for key in handle.keys():
            torch.testing.assert_close(handle.get_tensor(key), acting[key], rtol=0, atol=0)
    # The card carries the whole spec the network is rebuilt from.
    card = result.card
    assert card["export_format"] == "safetensors" and card["onnx_opset"] is None
    spec = agent.spec.to_dict()
    assert {key: card["member"][key] for key in spec} == spec
    # The same weights in the same network: the member's actions to the last bit.
    assert result.parity.max_abs_difference == 0.0
    policy = load_exported(tmp_path / "out")
    assert "Agent.act" in policy.runtime
    batch = histories(300, seed=11)
    np.testing.assert_array_equal(policy.act(batch), agent.act(batch, deterministic=True))
    np.testing.assert_array_equal(policy.act(batch[5]), agent.act(batch[5], deterministic=True))


def test_a_safetensors_file_that_does_not_fit_its_card_is_a_clear_error(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    agent, path = saved_member(tmp_path, "mlp-sac")
    result = export_policy(resolve_source(path), tmp_path / "out", "safetensors")
    policy_file, card_file = result.policy_file, tmp_path / "out" / "card.json"
    weights = agent.policy_state()["policy"]
    # Not a safetensors file at all.
    policy_file.write_bytes(b"\x80\x04 not tensors")
    with pytest.raises(ExportError, match=rf"policy file {policy_file} cannot be loaded as safe"):
        load_exported(tmp_path / "out")
    # A tensor too many, a tensor missing.
    save_file({**weights, "extra.weight": torch.zeros(2)}, str(policy_file))
    with pytest.raises(ExportError, match=r"holds tensor 'extra\.weight', which the network"):
        load_exported(tmp_path / "out")
    missing = next(iter(weights))
    save_file({k: v for k, v in weights.items() if k != missing}, str(policy_file))
    with pytest.raises(ExportError, match=rf"{policy_file} has no tensor '{missing}'"):
        load_exported(tmp_path / "out")
    # A card of another width than the file: the first tensor that differs is named.
    save_file(weights, str(policy_file))
    card = json.loads(card_file.read_text())
    card["member"]["hyperparameters"]["hidden"] = [32]
    card_file.write_text(json.dumps(card))
    with pytest.raises(
        ExportError,
        match=r"holds 'head\.0\.weight' as \(16, 16\) float32; the network described by its "
        r"card\.json needs \(32, 16\) float32",
    ):
        load_exported(tmp_path / "out")
    # A card without the spec cannot rebuild the network.
    del card["member"]["observation_shape"]
    card_file.write_text(json.dumps(card))
    with pytest.raises(ExportError, match=r"card\.json is incomplete .*'observation_shape'"):
        load_exported(tmp_path / "out")


def test_a_run_acts_with_its_acting_options_once_trained(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The experiment file says how its policy acts once trained (acting_options): training
    # and its validation sessions act without them, every load and export with them.
    settings = {
        "name": "acting",
        "envs": 2,
        "learner": {
            "algorithm": "ppo",
            "hidden": [16],
            "rollout_steps": 8,
            "batch_size": 16,
            "epochs": 1,
        },
        "task_options": {"max_step_fraction": 0.1, "stop_at_best": True},
        "acting_options": {"stop_at_best": False, "move_floor": 0.02},
        "budget": {"env_steps": 16, "eval_every": 16, "eval_scenarios": 2, "checkpoint_every": 16},
    }
    (tmp_path / "acting.yaml").write_text(yaml.safe_dump(settings))
    runs = tmp_path / "runs"
    assert main(["train", str(tmp_path / "acting.yaml"), "--runs-dir", str(runs), "--quiet"]) == 0
    from alignrl.runs.training_runs import load_policy

    _, trained = load_policy(runs / "acting")
    assert trained.resolved_task().ending.stop_at_best and trained.resolved_task().move_floor == 0
    source = resolve_source(runs / "acting")
    assert not source.task.ending.stop_at_best and source.task.move_floor == 0.02
    assert source.task.max_step_fraction == 0.1  # the training's options stay
    out = tmp_path / "exported"
    command = ["export", str(runs / "acting"), "--format", "safetensors", "--out", str(out)]
    assert main([*command, "--set", "task_options.move_floor=0.05"]) == 0  # --set wins
    capsys.readouterr()
    options = json.loads((out / "card.json").read_text())["task"]["options"]
    assert options["stop_at_best"] is False and options["move_floor"] == 0.05
    note = json.loads((out / "card.json").read_text())["evaluations"]["note"]
    assert 'acting_options {"move_floor": 0.02, "stop_at_best": false}' in note
    # Only the options that never change what the policy observes may be acting options.
    settings["acting_options"] = {"quality_reference": "first"}
    (tmp_path / "acting.yaml").write_text(yaml.safe_dump(settings))
    assert main(["train", str(tmp_path / "acting.yaml"), "--runs-dir", str(runs), "--quiet"]) == 2
    assert (
        "acting_options.quality_reference: Extra inputs are not permitted"
        in capsys.readouterr().err
    )

"""An export that can be adapted: `alignrl export --with-learner-state` ships the critics,
target critics, entropy coefficient and optimizers beside the policy, as safetensors and JSON
(no pickle), and `adapt --from`, a roster's `init_from` and `champion:NAME` train on from them,
on a driver that cannot tell its optimum too (the hindsight posterior stands in for it).

The source is a tiny SAC run trained for a few hundred env steps on the shipped recordings;
the driver without an optimum is `fake_drivers:BlindLens`, loaded by import path as a user's
driver is.
"""

from __future__ import annotations

import json
import pickle
import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from conftest import SMALL_PPO, SMALL_SAC, write_league
from fake_drivers import BlindLens
from safetensors.torch import load_file, save_file

import alignrl.runs.sources as sources
from alignrl.adaptation import check_adaptable
from alignrl.agents.agent import Agent, MemberSpec
from alignrl.checkpoints import load_checkpoint
from alignrl.cli import main
from alignrl.config.experiment import parse_experiment
from alignrl.deploy.export import export_policy
from alignrl.runs.learner_state import (
    LEARNER_FILE,
    LEARNER_RECORD,
    LearnerStateError,
    join_state,
    split_state,
)
from alignrl.runs.sources import ExportError, resolve_source
from alignrl.training import Trainer
from alignrl.transitions import Transition

BLIND = "fake_drivers:BlindLens"
SAC_PARTS = ("actor", "q1", "q2", "v", "v_target")  # networks; v_target: the target critic
OPTIMIZERS = ("actor_optimizer", "critic_optimizer", "alpha_optimizer")


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny SAC run past its warm-up: its optimizers hold running statistics."""
    root = tmp_path_factory.mktemp("run")
    settings = {
        "name": "tiny",
        "seed": 4,
        "envs": 4,
        "learner": SMALL_SAC,
        "budget": {"env_steps": 120, "eval_every": 120, "eval_scenarios": 2},
    }
    Trainer.create(parse_experiment(settings), root).run(progress=False)
    return root / "tiny"


@pytest.fixture(scope="module")
def exported(trained_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("export") / "tiny"
    argv = ["export", str(trained_run), "--format", "safetensors", "--with-learner-state"]
    assert main([*argv, "--out", str(out), "--json"]) == 0
    return out


def _copy(folder: Path, tmp_path: Path, name: str = "copy") -> Path:
    target = tmp_path / name
    shutil.copytree(folder, target)
    return target


def _assert_same_learner(agent: Agent, original: Agent) -> None:
    """Every tensor of the learner state equal, value for value, and the counters."""
    mine, theirs = agent.learner.state_dict(), original.learner.state_dict()
    for part in SAC_PARTS:
        for name, tensor in theirs[part].items():
            assert torch.equal(mine[part][name], tensor), (part, name)
    assert torch.equal(mine["log_alpha"], theirs["log_alpha"])
    for part in OPTIMIZERS:
        assert mine[part]["param_groups"] == theirs[part]["param_groups"], part
        assert mine[part]["state"].keys() == theirs[part]["state"].keys() != set(), part
        for index, statistics in theirs[part]["state"].items():
            for name, tensor in statistics.items():
                assert torch.equal(mine[part]["state"][index][name], tensor), (part, index, name)
    assert (agent.steps_seen, agent.updates) == (original.steps_seen, original.updates)
    assert agent.learner.update_debt == original.learner.update_debt


# --- export and load ------------------------------------------------------------------------


def test_an_export_with_its_learner_state_gives_the_whole_learner_back(
    trained_run: Path, exported: Path
) -> None:
    original = resolve_source(trained_run).agent
    assert original.updates > 0
    source = resolve_source(exported)
    assert (source.kind, source.learner_state) == ("export", True)
    assert source.learner_file == exported / LEARNER_FILE
    _assert_same_learner(source.agent, original)
    check_adaptable(source, str(exported))  # no refusal
    record = json.loads((exported / LEARNER_RECORD).read_text())
    assert record["member"] == original.spec.to_dict()
    assert record["run"]["task"] == "focus" and record["run"]["history"] == 8
    assert record["run"]["learner"]["algorithm"] == "sac"
    assert record["knobs"] == json.loads((exported / "card.json").read_text())["knobs"]
    card = json.loads((exported / "card.json").read_text())
    assert "--with-learner-state" in card["command"]


def test_the_export_holds_no_pickle_and_loads_without_unpickling(
    exported: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    names = sorted(path.name for path in exported.iterdir())
    assert names == [
        "card.json",
        "learner.json",
        LEARNER_FILE,
        "model_card.md",
        "policy.safetensors",
    ]
    for path in exported.iterdir():
        data = path.read_bytes()
        assert not data.startswith((b"\x80", b"PK")), path  # no pickle, no torch zip archive
        if path.suffix == ".json":  # strict JSON: no NaN or Infinity either
            json.loads(data, parse_constant=lambda constant: pytest.fail(constant))
        if path.suffix == ".safetensors":  # an 8-byte header length, then a JSON header
            (length,) = struct.unpack("<Q", data[:8])
            assert isinstance(json.loads(data[8 : 8 + length]), dict)

    def refused(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("an export is read without unpickling")

    for module, name in ((torch, "load"), (pickle, "load"), (pickle, "loads")):
        monkeypatch.setattr(module, name, refused)
    monkeypatch.setattr(pickle, "Unpickler", refused)
    assert resolve_source(exported).learner_state


def test_the_tree_of_a_state_splits_and_joins_again(tmp_path: Path) -> None:
    state = {
        "net": {"w": torch.ones(2, 3), "b": torch.zeros(3)},
        "optimizer": {
            "state": {0: {"step": torch.tensor(4.0)}},
            "param_groups": [
                {"betas": (0.9, 0.999), "params": [0], "foreach": None, "fused": True}
            ],
        },
        "updates": 7,
    }
    tree, tensors = split_state(state)
    assert tree["optimizer"]["state"] == {
        "$int_keys": {"0": {"step": {"$tensor": "optimizer/state/0/step"}}}
    }
    assert tree["optimizer"]["param_groups"][0]["betas"] == {"$tuple": [0.9, 0.999]}
    json.dumps(tree, allow_nan=False)  # plain JSON
    joined = join_state(tree, tensors, tmp_path / "l.json", tmp_path / "l.safetensors")
    assert joined["optimizer"]["param_groups"][0]["betas"] == (0.9, 0.999)
    assert list(joined["optimizer"]["state"]) == [0]
    assert torch.equal(joined["net"]["w"], state["net"]["w"]) and joined["updates"] == 7
    with pytest.raises(LearnerStateError, match=r"l\.safetensors holds tensor 'extra'"):
        join_state(
            tree,
            {**tensors, "extra": torch.ones(1)},
            tmp_path / "l.json",
            tmp_path / "l.safetensors",
        )
    with pytest.raises(LearnerStateError, match="learner state optimizer/param_groups/0/lr is nan"):
        split_state({"optimizer": {"param_groups": [{"lr": float("nan")}]}})


def test_a_ppo_member_exports_its_learner_state_too(tmp_path: Path) -> None:
    spec = MemberSpec(
        "p",
        "aligner",
        "ppo",
        (8, 7),
        2,
        1,
        {k: v for k, v in SMALL_PPO.items() if k != "algorithm"},
    )
    agent = Agent(spec)
    rng = np.random.default_rng(0)
    for _ in range(int(SMALL_PPO["rollout_steps"])):  # one rollout, one update
        observation = rng.uniform(-1, 1, (1, 8, 7)).astype(np.float32)
        action = agent.explore(observation, rng)
        none = np.zeros((1, 1), np.float32)
        reward, done = np.ones(1, np.float32), np.zeros(1, bool)
        agent.observe(Transition(observation, none, action, reward, observation, none, done))
    assert agent.learn(rng) and agent.updates > 0
    agent.save(tmp_path / "p.pt")
    out = export_policy(
        resolve_source(tmp_path / "p.pt"),
        tmp_path / "out",
        "safetensors",
        histories=8,
        note=lambda line: None,
        learner_state=True,
    ).out
    reloaded = resolve_source(out).agent
    mine, theirs = reloaded.learner.state_dict(), agent.learner.state_dict()
    for part in ("policy", "value"):
        assert all(torch.equal(mine[part][n], t) for n, t in theirs[part].items()), part
    for index, statistics in theirs["optimizer"]["state"].items():
        for name, tensor in statistics.items():
            assert torch.equal(mine["optimizer"]["state"][index][name], tensor), (index, name)
    assert reloaded.updates == agent.updates


# --- adapt, champion:NAME and init_from -----------------------------------------------------


def test_adapt_from_the_export_on_a_driver_that_cannot_tell_its_optimum(
    exported: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert BlindLens.optimum is None  # as a real column: the critics' secret is not known
    source = resolve_source(exported)
    argv = ["adapt", "--from", str(exported), "--apparatus", BLIND, "--spec-px", "3"]
    argv += ["--steps", "300", "--envs", "4", "--eval-scenarios", "3", "--name", "adapted"]
    assert main([*argv, "--runs-dir", str(tmp_path), "--quiet", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    run = tmp_path / "adapted"
    assert result["run"] == str(run) and result["env_steps"] >= 300
    config = yaml.safe_load((run / "config.yaml").read_text())
    adaptation = config["adaptation"]
    assert adaptation["hindsight_secrets"] is True
    assert adaptation["hindsight_optimum"] == "posterior"
    assert adaptation["source"] == str(exported / "policy.safetensors")
    assert adaptation["source_steps"] == source.agent.steps_seen
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    agent = last["agent"]
    learnt_from = agent["steps_seen"] - source.agent.steps_seen  # transitions: images less
    assert 200 <= learnt_from <= last["env_steps"]  # the episodes' verification images
    assert agent["learner"]["updates"] > source.agent.updates  # it trained on
    # The driver has no optimum: the secrets the critics learnt from stood in for it in
    # hindsight (without hindsight they are all zero).
    size = int(agent["replay"]["size"])
    assert 0 < size and np.abs(np.asarray(agent["replay"]["secret"][:size])).max() > 0.05
    # The config's source names the export again (its policy file names its folder).
    assert resolve_source(adaptation["source"]).learner_state


@pytest.fixture
def shipped(exported: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """The export shipped as a champion, `champion:tiny-v9`, in a champions folder of its
    own."""
    champions = tmp_path / "champions"
    _copy(exported, champions, "tiny-v9")
    monkeypatch.setattr(sources, "CHAMPIONS", champions)
    return "champion:tiny-v9"


def test_a_champion_with_its_learner_state_adapts_warm_starts_and_exports_again(
    shipped: str, trained_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from alignrl.league.config import load_league
    from alignrl.league.warm_starts import warm_starts

    original = resolve_source(trained_run).agent
    source = resolve_source(shipped)
    assert (source.kind, source.chosen_as, source.learner_state) == (
        "champion",
        "shipped champion",
        True,
    )
    argv = ["adapt", "--from", shipped, "--apparatus", BLIND, "--spec-px", "3", "--steps", "24"]
    argv += ["--envs", "4", "--eval-scenarios", "2", "--runs-dir", str(tmp_path / "runs")]
    assert main([*argv, "--quiet"]) == 0
    path = write_league(tmp_path, name="warm")
    roster = {"team": "aligner", "members": [{"id": "warm", "init_from": shipped}]}
    (tmp_path / "aligners.yaml").write_text(yaml.safe_dump(roster))
    config, aligners, _ = load_league(path)
    _, started = warm_starts(config, aligners)
    _assert_same_learner(started["warm"][0], original)
    again = tmp_path / "again"
    argv = [
        "export",
        shipped,
        "--format",
        "safetensors",
        "--with-learner-state",
        "--out",
        str(again),
    ]
    assert main(argv) == 0
    assert "learner:" in capsys.readouterr().out
    _assert_same_learner(resolve_source(again).agent, original)


def test_a_champion_without_its_learner_state_is_refused_as_before(
    trained_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source = resolve_source("champion:focus-v1")
    assert not source.learner_state and source.learner_file is None
    out = str(tmp_path / "x")
    argv = ["export", "champion:focus-v1", "--format", "safetensors", "--with-learner-state"]
    assert main([*argv, "--out", out]) == 2
    error = capsys.readouterr().err
    assert "champion:focus-v1 is a shipped champion without a learner state" in error
    assert "runs/league-default/best/mlp-sac.pt" in error
    argv = ["export", str(trained_run), "--format", "onnx", "--with-learner-state", "--out", out]
    assert main(argv) == 2
    assert "--with-learner-state needs --format safetensors" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


# --- damaged learner states -----------------------------------------------------------------


def _rewrite(folder: Path, change: Any) -> None:
    """learner.safetensors with `change(tensors)` applied (names kept as they were)."""
    tensors = load_file(str(folder / LEARNER_FILE))
    change(tensors)
    save_file(tensors, str(folder / LEARNER_FILE))


def _first(tensors: dict[str, torch.Tensor], prefix: str) -> str:
    return next(name for name in sorted(tensors) if name.startswith(prefix))


def _drop(tensors: dict[str, torch.Tensor]) -> None:
    del tensors[_first(tensors, "q1/")]


def _reshape(tensors: dict[str, torch.Tensor]) -> None:
    name = _first(tensors, "q2/")
    tensors[name] = torch.zeros(tensors[name].numel() + 1)


def _poison(tensors: dict[str, torch.Tensor]) -> None:
    name = _first(tensors, "v_target/")
    tensors[name] = torch.full_like(tensors[name], float("nan"))


def _nudge(tensors: dict[str, torch.Tensor]) -> None:
    tensors["log_alpha"] = tensors["log_alpha"] + 0.5  # finite and shaped right: the SHA says


def _edit_record(folder: Path, change: Any) -> None:
    record = json.loads((folder / LEARNER_RECORD).read_text())
    change(record)
    (folder / LEARNER_RECORD).write_text(json.dumps(record))


DAMAGES = {
    "truncated JSON": (
        lambda f: (f / LEARNER_RECORD).write_text((f / LEARNER_RECORD).read_text()[:200]),
        r"learner\.json is not valid JSON",
    ),
    "NaN in JSON": (
        lambda f: _edit_record(f, lambda r: r.update(update_debt=float("nan"))),
        r"learner\.json is not valid JSON \(NaN is not a JSON number",
    ),
    "no learner.json": (lambda f: (f / LEARNER_RECORD).unlink(), "but no learner.json"),
    "another member": (
        lambda f: _edit_record(f, lambda r: r["member"].update(id="someone")),
        r"learner\.json: member\.id is 'someone', but card\.json's member\.id is",
    ),
    "garbage tensors": (
        lambda f: (f / LEARNER_FILE).write_bytes(b"\x00" * 64),
        r"learner\.safetensors cannot be read as safetensors",
    ),
    "missing tensor": (
        lambda f: _rewrite(f, _drop),
        r"learner\.safetensors has no tensor 'q1/.*', which .*learner\.json names at state\.q1",
    ),
    "wrong shape": (
        lambda f: _rewrite(f, _reshape),
        r"learner\.safetensors does not fit the member .*learner\.q2\..* has shape",
    ),
    "NaN tensor": (
        lambda f: _rewrite(f, _poison),
        r"learner\.safetensors: tensor 'v_target/.*' contains non-finite values",
    ),
    "changed value": (
        lambda f: _rewrite(f, _nudge),
        r"learner\.json: learner_sha256 .* is not the SHA-256 of .*learner\.safetensors",
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_learner_state_is_named_never_half_loaded(
    damage: str, exported: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    change, message = DAMAGES[damage]
    folder = _copy(exported, tmp_path)
    change(folder)
    with pytest.raises(ExportError, match=message):
        resolve_source(folder)
    runs = tmp_path / "runs"
    argv = ["adapt", "--from", str(folder), "--apparatus", BLIND, "--steps", "10"]
    assert main([*argv, "--spec-px", "3", "--runs-dir", str(runs)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("alignrl: error: ") and "Traceback" not in error
    assert str(folder) in error and not runs.exists()

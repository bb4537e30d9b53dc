"""The shipped champions (alignrl/champions/, package data) align their task as their model
cards say, and `champion:NAME` is taken wherever a policy or a source is: evaluate, align,
export, adapt (refused for a champion that ships no critics) and a roster's init_from (refused
for the same reason), each decided by alignrl.runs.sources.

Each champion is run by `alignrl evaluate` on the apparatus its card says it was evaluated on,
on scenarios of a seed no card names: a champion whose weights, card or task went out of step
with the code (a changed feature layout, a renamed knob) fails here before a user meets it.
"""

from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import yaml

from alignrl.apparatus.instruments import load_set
from alignrl.apparatus.recorder import scenario_seed
from alignrl.cli import main
from alignrl.deploy.card import _shown
from alignrl.envs.task import get_task
from alignrl.runs.sources import CHAMPIONS, resolve_source, shipped_champions

CHAMPION_FOLDERS = [Path(str(CHAMPIONS / name)) for name in shipped_champions()]
SCENARIOS = 20
# Most cards' sessions of 100 are 96-100/100; a score of 20 at another seed may miss one or two
# (focus-v1 aligns 18 of seed 7's 20 recordings), an untrained aligner few or none. A champion
# whose card shows less (focus-v2 on the validation instruments) must reach 80 % of its
# card's best share.
PASS_SHARE = 0.9
SEED = 7
# On an instrument set (`set:NAME`; focus-v2's, on images, spends seconds of its posterior an
# alignment) the session is the fewest scenarios that reach each instrument, at a seed of the
# hundred from SEED that needs fewest (InstrumentSet.reset: the scenario's seed mod the set's
# size): seed 7's first 13 reach each of set:validation's six, seed 22's first 7 do.
MAX_SCENARIOS = 50


def pass_mark(card: dict, scenarios: int) -> int:
    """Of `scenarios`, the successes a champion must reach: PASS_SHARE, or below a best card
    session under 95/100, 80 % of that session's share."""
    rows = card["evaluations"]["rows"]
    best = max(row["successes"] / row["scenarios"] for row in rows)
    return math.ceil(PASS_SHARE * scenarios) if best >= 0.95 else int(0.8 * best * scenarios)


def _reaching(seed: int, count: int) -> int:
    """How many of `seed`'s first scenarios reach each of `count` instruments."""
    reached: set[int] = set()
    for index in range(MAX_SCENARIOS):
        reached.add(scenario_seed(seed, index) % count)
        if len(reached) == count:
            return index + 1
    return MAX_SCENARIOS


def session_for(apparatus: str) -> tuple[int, int]:
    """(scenarios, seed) of a champion's session: SCENARIOS at SEED; on an instrument set,
    the fewest scenarios that reach each instrument, at the first seed from SEED on that
    needs no more than a seed among the next hundred."""
    if not apparatus.startswith("set:"):
        return SCENARIOS, SEED
    count = len(load_set(apparatus.removeprefix("set:")))
    seed = min(range(SEED, SEED + 100), key=lambda seed: _reaching(seed, count))  # the first
    return _reaching(seed, count), seed


FOCUS = "champion:focus-v1"


def test_the_champions_are_shipped() -> None:
    # One per task alignrl ships a trained aligner for, and the column's two stages
    # (docs/deploy.md, docs/benchmarks.md).
    assert set(shipped_champions()) >= {
        "focus-v1",
        "focus-v2",
        "stigmation-v1",
        "aperture-v1",
        "column-focus-aperture-v1",
        "column-focus-stigmation-v1",
    }


def test_the_champions_are_package_data() -> None:
    # Read through importlib.resources from the imported package, never from the source tree.
    assert Path(str(CHAMPIONS)) == Path(str(resources.files("alignrl") / "champions"))
    for folder in CHAMPION_FOLDERS:
        assert {"card.json", "model_card.md", "policy.safetensors"} <= {
            path.name for path in folder.iterdir()
        }
    package = Path(str(resources.files("alignrl")))
    stale = [
        str(path.relative_to(package))
        for path in package.rglob("*.py")
        if "populations/champions" in path.read_text()
    ]
    assert not stale, f"modules naming the champions' old folder: {stale}"


def test_a_card_names_no_machines_folders(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A card records a source under the working directory relative to it (a card shipped in
    the package names no one's folders), one elsewhere as it is."""
    monkeypatch.chdir(tmp_path)
    assert _shown(tmp_path / "runs" / "a" / "best.pt") == str(Path("runs", "a", "best.pt"))
    assert _shown("/elsewhere/best.pt") == "/elsewhere/best.pt"
    for folder in CHAMPION_FOLDERS:
        source = json.loads((folder / "card.json").read_text())["source"]
        for key in ("run", "member_file", "config_file"):
            assert not Path(source.get(key) or "").is_absolute(), (folder.name, key)


@pytest.mark.parametrize("folder", CHAMPION_FOLDERS, ids=lambda path: path.name)
def test_a_shipped_champion_aligns_held_out_scenarios(
    folder: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    card = json.loads((folder / "card.json").read_text())
    training = card["training"]
    scenarios, seed = session_for(training["eval_apparatus"])
    command = [
        "evaluate",
        "--policy",
        f"champion:{folder.name}",
        "--apparatus",
        training["eval_apparatus"],
        "--apparatus-args",
        json.dumps(training["eval_apparatus_args"]),
        "--task",
        card["task"]["name"],
        "--scenarios",
        str(scenarios),
        "--seed",
        str(seed),
        "--json",
    ]
    assert main(command) == 0
    summary = json.loads(capsys.readouterr().out)
    session = summary[0] if isinstance(summary, list) else summary
    assert session["task"] == card["task"]["name"]
    assert session["knobs"] == [knob["name"] for knob in card["knobs"]]
    assert session["successes"] >= pass_mark(card, scenarios), session
    # In a few images: the policy stops once aligned instead of spending its episode.
    task = get_task(card["task"]["name"])
    most = 1 + card["task"]["episode_steps"] * task.acquisitions_per_step
    assert session["median_acquisitions"] < most, session


# --- champion:NAME in every verb ----------------------------------------------------------


def test_a_champion_resolves_to_its_card_and_weights() -> None:
    from alignrl.deploy.loading import load_exported

    source = resolve_source(FOCUS)
    card = json.loads((Path(str(CHAMPIONS)) / "focus-v1" / "card.json").read_text())
    assert (source.kind, source.chosen_as, source.run_dir) == ("champion", "shipped champion", None)
    assert not source.learner_state  # the acting network alone
    assert source.agent.id == card["member"]["id"] == "mlp-sac"
    assert source.agent.steps_seen == card["member"]["steps_seen"]
    assert source.updates == card["member"]["updates"]
    assert source.task.name == "focus" and source.config.history == card["history"]
    assert source.config.task_options.success_bonus == card["task"]["options"]["success_bonus"]
    assert source.knobs == card["knobs"]
    # The member it rebuilds acts as the exported policy that align and evaluate run.
    exported = load_exported(source.member_file.parent)
    histories = np.random.default_rng(5).uniform(-1, 1, (16, 8, 7)).astype(np.float32)
    np.testing.assert_allclose(
        source.agent.act(histories, deterministic=True), exported.act(histories), atol=1e-6
    )


def test_a_safetensors_export_resolves_only_as_its_card_says(tmp_path: Path) -> None:
    import shutil

    from alignrl.runs.sources import ExportError

    folder = tmp_path / "focus"
    shutil.copytree(Path(str(CHAMPIONS)) / "focus-v1", folder)
    source = resolve_source(folder)
    assert (source.kind, source.chosen_as) == ("export", "exported policy")
    assert source.member_file == folder / "policy.safetensors"
    card = json.loads((folder / "card.json").read_text())
    (folder / "card.json").write_text(json.dumps({**card, "policy_sha256": "0" * 64}))
    with pytest.raises(ExportError, match="is not the SHA-256 of"):
        resolve_source(folder)
    (folder / "card.json").write_text(json.dumps(card))
    aperture = Path(str(CHAMPIONS)) / "aperture-v1" / "policy.safetensors"
    shutil.copy2(aperture, folder / "policy.safetensors")  # another member's weights
    with pytest.raises(ExportError, match=r"does not fit the member its card\.json describes"):
        resolve_source(folder)


def test_align_runs_a_champion(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["align", "--policy", FOCUS, "--apparatus", "synthetic", "--seed", "2", "--json"]
    code = main(argv)
    result = json.loads(capsys.readouterr().out)
    assert result["policy"] == "mlp-sac" and code == result["exit_code"] == 0
    assert result["success"] and 0 < result["acquisitions"] <= 11


def _export_champion(tmp_path: Path, export_format: str, capsys: pytest.CaptureFixture[str]):
    from alignrl.deploy.loading import load_exported

    out = tmp_path / f"focus-{export_format}"
    argv = ["export", FOCUS, "--format", export_format, "--out", str(out), "--json"]
    assert main(argv) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["member"] == "mlp-sac" and summary["chosen_as"] == "shipped champion"
    exported = load_exported(out)
    original = json.loads((Path(str(CHAMPIONS)) / "focus-v1" / "card.json").read_text())
    card = exported.card
    assert card["export_format"] == export_format and card["source"]["kind"] == "champion"
    assert card["command"] == f"alignrl export {FOCUS} --format {export_format} --out {out}"
    # The record travels with the policy: sessions, lineage, training and knobs of the champion;
    # the sessions labelled for what they are (the league's validation sessions, each count
    # with its interval, the one that kept the champion named), none of their figures changed.
    evaluations, recorded = card["evaluations"], original["evaluations"]
    assert {key: evaluations[key] for key in recorded if key != "rows"} == {
        key: value for key, value in recorded.items() if key != "rows"
    }
    assert [
        {key: row[key] for key in old}
        for row, old in zip(evaluations["rows"], recorded["rows"], strict=True)
    ] == recorded["rows"]
    assert evaluations["session"] == "validation"
    assert evaluations["chosen_on"]["iteration"] == original["training"]["league_iteration"]
    assert card["lineage"] == original["lineage"]
    assert card["knobs"] == original["knobs"] and card["task"] == original["task"]
    assert card["training"]["updates"] == original["training"]["updates"]
    assert card["training"]["league_iteration"] == original["training"]["league_iteration"]
    histories = np.random.default_rng(6).uniform(-1, 1, (16, 8, 7)).astype(np.float32)
    champion = load_exported(Path(str(CHAMPIONS)) / "focus-v1")
    np.testing.assert_allclose(exported.act(histories), champion.act(histories), atol=2e-5)


def test_export_takes_a_champion_to_torchscript(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _export_champion(tmp_path, "torchscript", capsys)


def test_export_takes_a_champion_to_onnx(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("onnxruntime")
    _export_champion(tmp_path, "onnx", capsys)


def test_a_graph_export_holds_no_weights_to_train_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("onnxruntime")
    from alignrl.deploy.export import export_policy

    out = tmp_path / "focus-onnx"
    export_policy(resolve_source(FOCUS), out, "onnx", histories=50, tolerance=1e-4)
    # It runs, but cannot be exported again or trained on: say so, and what would do.
    assert main(["export", str(out), "--format", "safetensors", "--out", str(tmp_path / "x")]) == 2
    error = capsys.readouterr().err
    assert f"the export {out} is a graph export (onnx)" in error and "safetensors export" in error
    argv = ["adapt", "--from", str(out), "--apparatus", "synthetic-b", "--steps", "10"]
    assert main([*argv, "--runs-dir", str(tmp_path / "runs")]) == 2
    assert "is a graph export (onnx)" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "runs").exists()


def test_adapt_refuses_a_champion_saying_what_would_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    runs = tmp_path / "runs"
    argv = ["adapt", "--from", FOCUS, "--apparatus", "synthetic-b", "--steps", "10"]
    assert main([*argv, "--runs-dir", str(runs)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("alignrl: error: champion:focus-v1 is a shipped champion")
    assert "no critics" in error and "runs/league-default/best/mlp-sac.pt" in error
    assert f"alignrl align --policy {FOCUS} --apparatus SPEC" in error
    assert "Traceback" not in error and not runs.exists()


def _champion_league(tmp_path: Path, init_from: str) -> Path:
    from tests.test_league import SMALL_SAC, write_league

    path = write_league(tmp_path, name="warm")
    roster = {
        "team": "aligner",
        "members": [{"id": "warm", "init_from": init_from}, {"id": "fresh", "learner": SMALL_SAC}],
    }
    (tmp_path / "aligners.yaml").write_text(yaml.safe_dump(roster))
    return path


def test_a_warm_start_from_a_champion_is_refused_before_any_file(tmp_path: Path) -> None:
    from alignrl.config_reading import ConfigError
    from alignrl.league.config import load_league
    from alignrl.league.loop import League

    config, aligners, misaligners = load_league(_champion_league(tmp_path, FOCUS))
    with pytest.raises(ConfigError, match="aligner 'warm': init_from champion:focus-v1: ") as error:
        League.create(config, aligners, misaligners, tmp_path / "runs")
    assert "a warm start trains on from those" in str(error.value)
    assert "runs/league-default/best/mlp-sac.pt" in str(error.value)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("verb", ["evaluate", "align", "export", "adapt", "init_from"])
def test_an_unknown_champion_lists_the_shipped_ones(
    verb: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    expected = "no shipped champion 'focus-v9'; shipped champions: " + ", ".join(
        shipped_champions()
    )
    name = "champion:focus-v9"
    if verb == "init_from":
        from alignrl.config_reading import ConfigError
        from alignrl.league.config import load_league
        from alignrl.league.loop import League

        config, aligners, misaligners = load_league(_champion_league(tmp_path, name))
        with pytest.raises(ConfigError, match=expected):
            League.create(config, aligners, misaligners, tmp_path / "runs")
        return
    argv = {
        "evaluate": ["evaluate", "--policy", name, "--apparatus", "synthetic", "--scenarios", "1"],
        "align": ["align", "--policy", name, "--apparatus", "synthetic"],
        "export": ["export", name, "--format", "safetensors", "--out", str(tmp_path / "out")],
        "adapt": ["adapt", "--from", name, "--apparatus", "synthetic", "--steps", "10"],
    }[verb]
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert error == f"alignrl: error: {expected}\n"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("folder", CHAMPION_FOLDERS, ids=lambda folder: folder.name)
def test_every_shipped_card_says_its_figures_are_validation_sessions_with_intervals(
    folder: Path,
) -> None:
    """The figures a champion's card carries are the sessions that chose it (issue 23): the
    card says so, gives each row its 95 % interval, and its model card says it in words."""
    from alignrl.intervals import wilson

    evaluations = json.loads((folder / "card.json").read_text())["evaluations"]
    assert evaluations["session"] == "validation" and evaluations["confidence"] == 0.95
    for row in evaluations["rows"]:
        low, high = wilson(int(row["successes"]), int(row["scenarios"]))
        assert (row["success_low"], row["success_high"]) == pytest.approx((low, high))
    assert "These are **validation** sessions" in (folder / "model_card.md").read_text()

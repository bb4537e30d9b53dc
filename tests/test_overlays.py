"""Overlays (alignrl/overlays.py): a YAML that names its `base:` and changes a few keys resolves
to exactly the experiment it describes, strictly, for `alignrl train` and `alignrl league run`."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from alignrl.config.experiment import dump_experiment, load_experiment, parse_experiment
from alignrl.config_reading import ConfigError
from alignrl.league.config import load_league
from alignrl.overlays import merge

ROOT = Path(__file__).resolve().parents[1]

BASE = """\
name: base
apparatus_args: {noise: 0.02, split: train}
task_options: {success_bonus: 5.0}
learner:
  encoder: mlp
  encoder_kwargs: {hidden: [256]}
  hidden: [256, 256]
  learning_rate: 3.0e-4
budget: {env_steps: 30000, eval_every: 5000}
"""


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_merge_mappings_recursively_and_replace_lists_and_scalars() -> None:
    below = {"a": 1, "m": {"x": 1, "deep": {"p": 1, "q": 2}}, "lst": [1, 2, 3], "keep": "k"}
    above = {"a": 2, "m": {"deep": {"q": 9}, "y": 5}, "lst": [7]}
    assert merge(below, above) == {
        "a": 2,
        "m": {"x": 1, "deep": {"p": 1, "q": 9}, "y": 5},
        "lst": [7],
        "keep": "k",
    }
    # Neither input changed; a mapping over a scalar (or null over a mapping) replaces it.
    assert below["m"]["deep"] == {"p": 1, "q": 2} and above["m"] == {"deep": {"q": 9}, "y": 5}
    assert merge({"m": 3}, {"m": {"x": 1}}) == {"m": {"x": 1}}
    assert merge({"m": {"x": 1}}, {"m": None}) == {"m": None}


def test_an_overlay_changes_only_the_keys_it_names(tmp_path: Path) -> None:
    _write(tmp_path / "entry" / "base.yaml", BASE)
    overlay = _write(
        tmp_path / "bench" / "configs" / "over.yaml",
        "base: ../../entry/base.yaml\n"
        "name: over\n"
        "learner: {hidden: [64], encoder_kwargs: {dropout: 0.0}, updates_per_step: 2.0}\n"
        "budget: {env_steps: 500}\n",
    )
    config = load_experiment(overlay)
    base = load_experiment(tmp_path / "entry" / "base.yaml")
    assert config.name == "over"
    assert config.learner.hidden == (64,)  # a list replaces
    assert config.learner.encoder_kwargs == {"hidden": [256], "dropout": 0.0}  # a mapping merges
    assert config.learner.updates_per_step == 2.0
    assert config.learner.learning_rate == base.learner.learning_rate
    assert (config.budget.env_steps, config.budget.eval_every) == (500, 5000)
    assert config.task_options == base.task_options
    # The resolved config is a whole experiment: no `base:`, every key written out.
    dumped = dump_experiment(config)
    assert "base" not in yaml.safe_load(dumped)
    assert parse_experiment(yaml.safe_load(dumped)) == config


def test_chains_resolve_in_order(tmp_path: Path) -> None:
    _write(tmp_path / "base.yaml", BASE)
    _write(tmp_path / "one.yaml", "base: base.yaml\nname: one\nlearner: {learning_rate: 1.0e-3}\n")
    two = _write(tmp_path / "sub" / "two.yaml", "base: ../one.yaml\nname: two\nhistory: 4\n")
    config = load_experiment(two)
    assert (config.name, config.history, config.learner.learning_rate) == ("two", 4, 1e-3)
    assert config.learner.hidden == (256, 256)


def test_an_unknown_key_in_an_overlay_names_the_file_and_the_key_path(tmp_path: Path) -> None:
    _write(tmp_path / "base.yaml", BASE)
    overlay = _write(tmp_path / "over.yaml", "base: base.yaml\ntask_options: {sucess_bonus: 1.0}\n")
    with pytest.raises(ConfigError) as caught:
        load_experiment(overlay)
    message = str(caught.value)
    assert message.startswith(f"{overlay} (base {tmp_path / 'base.yaml'}): ")
    assert "task_options.sucess_bonus: Extra inputs are not permitted" in message


def test_a_missing_base_names_the_overlay_and_the_base(tmp_path: Path) -> None:
    overlay = _write(tmp_path / "over.yaml", "base: ../nowhere/base.yaml\nname: x\n")
    with pytest.raises(ConfigError, match=r"over\.yaml: base \.\./nowhere/base\.yaml does not"):
        load_experiment(overlay)
    not_a_path = _write(tmp_path / "bad.yaml", "base: [a.yaml]\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: base: expected the path"):
        load_experiment(not_a_path)


def test_a_cycle_is_refused(tmp_path: Path) -> None:
    a = _write(tmp_path / "a.yaml", "base: b.yaml\nname: a\n")
    _write(tmp_path / "b.yaml", "base: a.yaml\nname: b\n")
    with pytest.raises(
        ConfigError, match=r"b\.yaml: its base leads back to .*a\.yaml -> .*b\.yaml"
    ):
        load_experiment(a)
    itself = _write(tmp_path / "self.yaml", "base: ./self.yaml\n")
    with pytest.raises(ConfigError, match="leads back to"):
        load_experiment(itself)


def test_a_league_overlay_finds_rosters_as_its_base_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The repository's layout (entry/ for experiments/): populations/, an overlay two folders down;
    # run from a folder that has no populations/ of its own.
    repo = tmp_path / "repo"
    for team in ("aligners", "misaligners"):
        _write(
            repo / "populations" / f"{team}.yaml",
            (ROOT / "populations" / f"{team}.yaml").read_text(),
        )
    _write(
        repo / "populations" / "few.yaml", "team: aligner\nmembers:\n  - {id: one}\n  - {id: two}\n"
    )
    _write(
        repo / "entry" / "league.yaml",
        (ROOT / "experiments" / "league-default.yaml").read_text(),
    )
    inherits = _write(
        repo / "benchmarks" / "configs" / "short.yaml",
        "base: ../../entry/league.yaml\nname: short\nschedule: {iterations: 5}\n",
    )
    names = _write(
        repo / "benchmarks" / "configs" / "few.yaml",
        "base: short.yaml\nname: few\naligners: populations/few.yaml\n",
    )
    monkeypatch.chdir(_write(tmp_path / "elsewhere" / "x", "").parent)
    config, aligners, _ = load_league(inherits)
    assert (config.name, config.schedule.iterations, config.schedule.matches) == ("short", 5, 64)
    assert len(aligners.members) == 3
    config, aligners, _ = load_league(names)
    assert config.name == "few" and [m.id for m in aligners.members] == ["one", "two"]
    missing = _write(
        repo / "benchmarks" / "configs" / "gone.yaml",
        "base: few.yaml\naligners: populations/gone.yaml\n",
    )
    with pytest.raises(ConfigError, match=r"gone\.yaml \(base .*\): aligners: roster file"):
        load_league(missing)


SHIPPED = sorted([*ROOT.glob("experiments/*.yaml"), *ROOT.glob("benchmarks/configs/*.yaml")])


@pytest.mark.parametrize("path", SHIPPED, ids=lambda path: f"{path.parent.name}/{path.name}")
def test_every_shipped_experiment_and_overlay_loads(path: Path) -> None:
    if "aligners" in _chain_keys(path):  # a league names rosters, here or in a base
        config, aligners, misaligners = load_league(path)
        assert aligners.members and misaligners.members
    else:
        config = load_experiment(path)
    assert config.name == path.stem  # a run directory named after its file


def _chain_keys(path: Path) -> set[str]:
    keys: set[str] = set()
    while True:
        raw = yaml.safe_load(path.read_text())
        keys |= set(raw)
        if "base" not in raw:
            return keys
        path = path.parent / raw["base"]

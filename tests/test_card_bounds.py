"""A card is believed only within physical bounds, and read in one place (issue 60, items 8-10):
its posterior settings inside what an instrument family can give them, its learner.json
telling the same run, and card.json itself refused by size, by a key named twice and by
nesting, naming the file, before anything reads it further. Both readers of a card
(alignrl.deploy.loading for align and evaluate, alignrl.runs.sources for export, adapt and
calibrate) read it through `read_card`."""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hostile import assert_refused, run_cli
from test_calibration import COLUMN

from alignrl.deploy.card_schema import MAX_CARD_BYTES
from alignrl.deploy.export import export_policy
from alignrl.deploy.loading import load_exported
from alignrl.runs.sources import ExportError, resolve_source

READERS: dict[str, Callable[[Path], Any]] = {
    "load_exported": load_exported,
    "resolve_source": resolve_source,
}


def _edited(light: Path, tmp_path: Path, change: Callable[[dict[str, Any]], None]) -> Path:
    folder = shutil.copytree(light, tmp_path / "policy")
    card = json.loads((folder / "card.json").read_text())
    change(card)
    (folder / "card.json").write_text(json.dumps(card, indent=2))
    return folder


def _options(**options: Any) -> Callable[[dict[str, Any]], None]:
    return lambda card: card["task"]["options"].update(options)


# --- posterior settings within what a family can give ---------------------------------------

POSTERIORS = {
    "a blur of 1e300 px per interval": (
        _options(posterior_column={**COLUMN, "blur_px_per_interval": 1e300}),
        "task.options.posterior_column.blur_px_per_interval is 1e+300",
        "[0.1, 10000] px",
    ),
    "a probe of 1e-300 px in focus": (
        _options(posterior_column={**COLUMN, "floor_sigma_px": 1e-300}),
        "task.options.posterior_column.floor_sigma_px is 1e-300",
        "[0.1, 10000] px",
    ),
    "readings that level off at 1e300 px": (
        _options(posterior_saturation_px=[10.0, 1e300]),
        "task.options.posterior_saturation_px[1] is 1e+300",
        "[0.1, 10000] px",
    ),
}


@pytest.mark.parametrize("reader", list(READERS))
@pytest.mark.parametrize("case", list(POSTERIORS))
def test_posterior_settings_beyond_any_family_are_refused(
    case: str, reader: str, light: Path, tmp_path: Path
) -> None:
    change, field, bounds = POSTERIORS[case]
    folder = _edited(light, tmp_path, change)
    with pytest.raises(ExportError) as refused:
        READERS[reader](folder)
    message = str(refused.value)
    assert message.startswith(f"{folder / 'card.json'}: {field}"), message
    assert bounds in message and "\n" not in message and "input_value" not in message


def test_a_knob_interval_beyond_any_instrument_is_refused(light: Path, tmp_path: Path) -> None:
    def widened(card: dict[str, Any]) -> None:  # interval and step alike: the card agrees
        card["knobs"][0].update(low=-5e11, high=5e11, max_step=2.5e11)

    folder = _edited(light, tmp_path, widened)
    for name in ("learner.json", "learner.safetensors"):  # which would tell it otherwise
        (folder / name).unlink()
    said = f"{folder / 'card.json'}: knobs[0].low is -5e+11: it must be at least -1.5e+06"
    with pytest.raises(ExportError, match=re.escape(said)):
        load_exported(folder)
    with pytest.raises(ExportError, match=re.escape(said.split(": ", 1)[1])):  # its export
        export_policy(resolve_source(folder), tmp_path / "out", "safetensors")
    assert not (tmp_path / "out").exists()


# --- card.json against learner.json ---------------------------------------------------------

DISAGREEMENTS = {
    "training apparatus": (
        lambda card: card["training"].update(apparatus="synthetic"),
        "run.apparatus is 'family:focus', but card.json's training.apparatus is 'synthetic'",
    ),
    "a task option": (
        _options(posterior_far_noise=0.2),
        "run.task_options.posterior_far_noise is 0.1, but card.json's "
        "task.options.posterior_far_noise is 0.2",
    ),
    "where it came from": (
        lambda card: card["source"].update(kind="training"),
        "source.kind is 'champion', but card.json's source.kind is 'training'",
    ),
}


@pytest.mark.parametrize("reader", list(READERS))
@pytest.mark.parametrize("case", list(DISAGREEMENTS))
def test_a_card_and_its_learner_state_must_tell_the_same_run(
    case: str, reader: str, light: Path, tmp_path: Path
) -> None:
    change, said = DISAGREEMENTS[case]
    folder = _edited(light, tmp_path, change)
    with pytest.raises(ExportError) as refused:
        READERS[reader](folder)
    message = str(refused.value)
    assert message.startswith(f"{folder / 'learner.json'}: {said}"), message
    assert "{" not in message  # the field, never the two mappings dumped


# --- card.json as a file: size, keys, nesting -----------------------------------------------


def _huge(card: Path) -> None:
    with card.open("wb") as handle:  # sparse: 300 MB that take no disk
        handle.truncate(300 << 20)


def _twice(card: Path) -> None:
    text = card.read_text()
    format_line = text.splitlines()[1]  # '  "format": "alignrl-policy-card-1",'
    card.write_text("{\n" + format_line + text[1:])  # the same key, the same value: twice


def _nested(depth: int) -> Callable[[Path], None]:
    def write(card: Path) -> None:
        data = json.loads(card.read_text())
        text = json.dumps(data)[:-1]  # a lineage record nested `depth` deep
        deep = "[" * depth + "]" * depth
        card.write_text(text.replace('"lineage": {', f'"lineage": {{"deep": {deep}, ', 1) + "}")

    return write


FILES = {
    "300 MB": (_huge, ["314,572,800 bytes", f"{MAX_CARD_BYTES:,} bytes"]),
    "a key twice": (_twice, ["key 'format' is named twice"]),
    "nested 200,000 deep": (_nested(200_000), ["nests too deeply"]),
    "nested 100 deep": (_nested(100), ["nests more than 64 levels"]),
}
VERBS = {
    "export": lambda folder, tmp: ["export", folder, "--format", "safetensors", "--out", tmp / "x"],
    "evaluate": lambda folder, tmp: [
        "evaluate",
        "--policy",
        folder,
        "--apparatus",
        "fake_drivers:ParabolicLens",
        "--spec-px",
        "3",
        "--scenarios",
        "1",
        "--quiet",
    ],
}


@pytest.mark.parametrize("verb", list(VERBS))
@pytest.mark.parametrize("case", list(FILES))
def test_a_card_file_is_refused_before_it_is_believed(
    case: str, verb: str, light: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write, names = FILES[case]
    folder = shutil.copytree(light, tmp_path / "policy")
    write(folder / "card.json")
    outcome = run_cli(VERBS[verb](folder, tmp_path), capsys)
    assert_refused(outcome, 2, str(folder / "card.json"), *names)
    assert len(outcome.err.strip().splitlines()) == 1, outcome.err
    assert not (tmp_path / "x").exists()

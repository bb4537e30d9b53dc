"""A run's state beside its weights, kept and read in one place by the trainer, the league and
deploy:

    config.yaml   the resolved experiment (`run_config_data`, `read_training_config`)
    knobs.json    per task knob, its interval on the training apparatus and the largest change
                  one action makes, recorded when the run starts (`record_knobs`), so that an
                  export reads them from the run and never opens the instrument
                  (`recorded_knobs`)
    tensorboard/  TensorBoard events, opened on first use (`TensorBoardLog`)

and the random streams a checkpoint carries (`rng_state`, `restore_rng`). Intervals and steps
are in the apparatus's units (volts for lenses, percent for stigmators, micrometres for the
aperture).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from alignrl.checkpoints import atomic_write, atomic_write_text, remove_partial_writes
from alignrl.config.experiment import ExperimentConfig, parse_experiment
from alignrl.config_reading import ConfigError, read_yaml
from alignrl.envs.task import Task

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

__all__ = [
    "CONFIG_FILE",
    "KNOBS_FILE",
    "TensorBoardLog",
    "checked_knobs",
    "config_of_checkpoint",
    "cut_events",
    "flat_hparams",
    "knob_limits",
    "read_training_config",
    "record_knobs",
    "recorded_knobs",
    "restore_rng",
    "rng_state",
    "run_config_data",
    "run_hparams",
    "run_provenance",
    "with_provenance",
]

CONFIG_FILE = "config.yaml"
KNOBS_FILE = "knobs.json"
KNOBS_FORMAT = "alignrl-knobs-1"


# --- random streams -------------------------------------------------------------------------


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """The state of `rng` and of torch's CPU stream, under the keys a checkpoint keeps them."""
    return {"numpy_rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state()}


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def restore_rng(rng: np.random.Generator, state: Mapping[str, Any]) -> None:
    """Set `rng` and torch's CPU stream to what `rng_state` gave. A state that is missing or
    is not of these streams is a ValueError naming its key, and neither stream changes."""
    expected = type(rng.bit_generator).__name__
    numpy_state = state.get("numpy_rng")
    if not isinstance(numpy_state, Mapping) or numpy_state.get("bit_generator") != expected:
        raise ValueError(f"numpy_rng: not a {expected} generator state: {_shown(numpy_state)}")
    torch_state = state.get("torch_rng")
    size = torch.get_rng_state().shape
    if not (
        isinstance(torch_state, torch.Tensor)
        and torch_state.dtype == torch.uint8
        and torch_state.shape == size
    ):
        raise ValueError(
            f"torch_rng: not the state of torch's CPU generator ({size[0]} bytes as a uint8 "
            f"tensor): {_shown(torch_state)}"
        )
    before = rng.bit_generator.state
    try:
        rng.bit_generator.state = numpy_state
    except (KeyError, TypeError, ValueError) as error:
        rng.bit_generator.state = before
        raise ValueError(f"numpy_rng: not a {expected} generator state: {error}") from None
    torch.set_rng_state(torch_state)


# --- TensorBoard ----------------------------------------------------------------------------

EVENT_FILES = "*tfevents*"  # what TensorBoard reads as an event file (its io_wrapper)
# The hparams plugin's summary of a session's hyperparameters
# (tensorboard.plugins.hparams.metadata.SESSION_START_INFO_TAG).
HPARAMS_TAG = "_hparams_/session_start_info"


def _after_existing_events(folder: Path) -> None:
    """Wait (a second at most) until the clock has passed the second every event file in
    `folder` was opened in. TensorBoard reads a folder's files in name order, and a name
    starts with its writer's second (then host, process id and a counter, compared as text):
    a run resumed within the second its killed run opened would otherwise sort before it,
    and its points would show first."""
    seconds = []
    for path in folder.glob(EVENT_FILES):
        parts = path.name.split(".")
        if len(parts) > 3 and parts[3].isdigit():
            seconds.append(int(parts[3]))
    if seconds:
        wait = max(seconds) + 1 - time.time()
        if wait > 0:
            time.sleep(min(wait, 1.0))


class TensorBoardLog:
    """A run's TensorBoard events in `folder` (one TensorBoard run). The writer opens on first
    use (TensorBoard takes seconds to import).

    A resumed run calls `resume_after(step)` before it logs: the event files are cut back to
    the events at steps up to its checkpoint's (`cut_events`), as the metrics CSVs are, and the
    writer opens with purge_step past it. Both, because TensorBoard's readers differ: the
    Python one honours purge_step, the Rust data server (its default loader) ignores it and
    drops only the points a tag writes again, so an event the resumed run does not repeat
    (an episode that now ends at another step) would stay beside the new ones."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.purge_step: int | None = None
        self.has_hparams = False  # the run's hyperparameters are in its events
        self._writer: SummaryWriter | None = None

    def resume_after(self, step: int) -> None:
        """Drop every event after `step` (all of them for -1) before the first is written."""
        if self._writer is not None:
            raise RuntimeError(f"{self.folder}: resume_after must come before the first event")
        self.has_hparams = HPARAMS_TAG in cut_events(self.folder, step)
        self.purge_step = step + 1

    def _open(self) -> SummaryWriter:
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            _after_existing_events(self.folder)
            self._writer = SummaryWriter(str(self.folder), purge_step=self.purge_step)
        return self._writer

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self._open().add_scalar(tag, value, step)

    def add_scalars(self, prefix: str, values: Mapping[str, float | None], step: int) -> None:
        """`prefix/name` for each of `values` that is a number (None: not measured)."""
        for name, value in values.items():
            if value is not None:
                self.add_scalar(f"{prefix}/{name}", float(value), step)

    def add_histogram(self, tag: str, values: np.ndarray, step: int) -> None:
        self._open().add_histogram(tag, np.asarray(values, float), step)

    def add_hparams(self, hparams: Mapping[str, Any], step: int = 0) -> None:
        """The run's hyperparameters for TensorBoard's HParams dashboard, written once per run
        (a run that has them already, resumed, writes nothing). Only the session's start is
        written, no experiment summary: the dashboard then gathers the hyperparameters of
        every run it shows (runs with other keys side by side) and takes each run's scalars
        as its metrics."""
        if self.has_hparams:
            return
        from torch.utils.tensorboard.summary import hparams as hparams_summaries

        _, session_start, _ = hparams_summaries(dict(hparams), {})
        self._open().file_writer.add_summary(session_start, step)
        self.has_hparams = True

    def flush(self) -> None:
        """The events so far on disk (before a checkpoint: they are what it has seen)."""
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def cut_events(folder: Path, last_step: int) -> set[str]:
    """Cut each event file in `folder` back to its events at steps up to `last_step` (a file
    left without a summary goes; one that keeps everything is left as it is), and give the
    tags of the summaries kept. A record a kill tore, at the end of a file, goes too, as do
    the temporaries of a cut killed midway."""
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event

    remove_partial_writes(folder, recursive=False)
    kept_tags: set[str] = set()
    for path in sorted(folder.glob(EVENT_FILES)) if folder.is_dir() else []:
        if not path.is_file():
            continue
        size = path.stat().st_size
        records = [(raw, Event.FromString(raw)) for raw in RawEventFileLoader(str(path)).Load()]
        kept = [(raw, event) for raw, event in records if event.step <= last_step]
        tags = {value.tag for _, event in kept for value in event.summary.value}
        if not tags:
            path.unlink()
            continue
        kept_tags |= tags
        whole = sum(len(raw) + 16 for raw, _ in records) == size  # 16: a record's framing
        if len(kept) < len(records) or not whole:
            atomic_write(path, partial(_write_records, [raw for raw, _ in kept]))
    return kept_tags


def _write_records(records: list[bytes], handle: Any) -> None:
    """`records` (serialized events) framed as TensorBoard frames them, into `handle`."""
    from tensorboard.summary.writer.record_writer import RecordWriter

    writer = RecordWriter(handle)
    for raw in records:
        writer.write(raw)


# The settings of a run's config that are no hyperparameters: where it lives, how it started.
NOT_HPARAMS = ("name", "provenance")


def run_hparams(settings: Mapping[str, Any]) -> dict[str, float | str]:
    """A run's config (config.yaml, as data) as TensorBoard hyperparameters
    (`learner.learning_rate`, `budget.env_steps`, `schedule.iterations`, ...)."""
    return flat_hparams({k: v for k, v in settings.items() if k not in NOT_HPARAMS})


def flat_hparams(settings: Mapping[str, Any], prefix: str = "") -> dict[str, float | str]:
    """Settings as TensorBoard's hyperparameters: nested keys joined by '.', numbers and
    booleans as numbers, lists and text as text; null and empty settings left out."""
    flat: dict[str, float | str] = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flat_hparams(value, f"{name}."))
        elif isinstance(value, bool | int | float):
            # An integer too large for a float (a driver's argument of 400 digits) as text.
            flat[name] = float(value) if abs(value) < 2.0**1023 else str(value)
        elif isinstance(value, str):
            flat[name] = value
        elif isinstance(value, list | tuple) and value:
            flat[name] = json.dumps(value)
    return flat


# --- the run's config -----------------------------------------------------------------------


def run_config_data(run_dir: str | Path, kind: str = "run directory") -> dict[str, Any]:
    """A run's config.yaml as a mapping, read strictly and within bounds (alignrl.yaml_io).
    FileNotFoundError where `run_dir` has none ("runs/x is not a league run (no
    config.yaml)", with `kind` "league run"); ConfigError where it is no mapping."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} is not a {kind} (no {CONFIG_FILE})")
    data = read_yaml(path, "run config")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of settings at the top level")
    return data


def read_training_config(run_dir: str | Path) -> ExperimentConfig:
    """The experiment of an `alignrl train` (or `alignrl adapt`) run directory."""
    return parse_experiment(run_config_data(run_dir), str(Path(run_dir) / CONFIG_FILE))


def config_of_checkpoint(state: Mapping[str, Any], checkpoint: Path) -> ExperimentConfig:
    """The experiment a training checkpoint carries (last.pt and best.pt keep it as YAML)."""
    from alignrl.yaml_io import parse_yaml

    source = f"{checkpoint} (config)"
    return parse_experiment(parse_yaml(state["config"], source), source)


# --- knob intervals and steps ---------------------------------------------------------------


def knob_limits(task: Task, knobs: Mapping[str, tuple[float, float]]) -> list[dict[str, Any]]:
    """Per task knob: its interval on an apparatus with these `knobs` and the largest change
    one action makes (Task.step_sizes, as the env scales actions)."""
    steps = task.step_sizes(knobs)
    return [
        {
            "name": knob,
            "low": float(knobs[knob][0]),
            "high": float(knobs[knob][1]),
            "max_step": float(step),
        }
        for knob, step in zip(task.knobs, steps, strict=True)
    ]


def record_knobs(run_dir: Path, apparatus: str, limits: list[dict[str, Any]]) -> None:
    """Write knobs.json (atomically): `limits` as `knob_limits` gives them, and the spec of
    the apparatus they were read from."""
    record = {"format": KNOBS_FORMAT, "apparatus": apparatus, "knobs": limits}
    atomic_write_text(run_dir / KNOBS_FILE, json.dumps(record, indent=2) + "\n")


def recorded_knobs(run_dir: Path, task: Task) -> list[dict[str, Any]] | None:
    """The knob limits `run_dir` recorded when it started, checked against `task` (its knobs
    in order, finite intervals, positive steps); None where the run records none (it was
    made before alignrl recorded them). A record that does not fit is a ValueError naming
    the file and the entry."""
    path = run_dir / KNOBS_FILE
    if not path.exists():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(record, dict) or record.get("format") != KNOBS_FORMAT:
        raise ValueError(f"{path}: not a knob record (format {KNOBS_FORMAT} expected)")
    return checked_knobs(record.get("knobs"), task, str(path))


def checked_knobs(knobs: Any, task: Task, where: str) -> list[dict[str, Any]]:
    """`knobs` (a record's or a model card's list) if it describes `task`'s knobs in order,
    each with a finite interval (low < high) and a positive finite max_step."""
    if not isinstance(knobs, list) or len(knobs) != len(task.knobs):
        count = len(knobs) if isinstance(knobs, list) else _shown(knobs)
        raise ValueError(
            f"{where}: lists {count} knob(s); task {task.name!r} has {len(task.knobs)}"
        )
    checked = []
    for index, (entry, name) in enumerate(zip(knobs, task.knobs, strict=True)):
        if not isinstance(entry, dict) or entry.get("name") != name:
            raise ValueError(f"{where}: knobs[{index}] is not knob {name!r}: {_shown(entry)}")
        values = {}
        for key in ("low", "high", "max_step"):
            value = entry.get(key)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{where}: knobs[{index}].{key} is {_shown(value)}, not a number")
            if not math.isfinite(value):
                raise ValueError(f"{where}: knobs[{index}].{key} is {value}, not finite")
            values[key] = float(value)
        if not values["low"] < values["high"] or not values["max_step"] > 0:
            raise ValueError(
                f"{where}: knobs[{index}] ({name}) needs low < high and max_step > 0, got "
                f"[{values['low']:g}, {values['high']:g}] and {values['max_step']:g}"
            )
        checked.append({"name": name, **values})
    return checked


# --- provenance ---------------------------------------------------------------------------


GIT_TIMEOUT_S = 5.0


def git_commit(folder: Path | None = None) -> str | None:
    """The commit of the git checkout `folder` (default: alignrl's own) is in, `+dirty` with
    uncommitted changes; None where it is not one, or git is missing or slow."""
    import subprocess

    folder = folder or Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "-C", str(folder), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
        if head.returncode != 0:
            return None
        changes = subprocess.run(
            ["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = head.stdout.strip()
    return f"{commit}+dirty" if changes.stdout.strip() else commit


def run_provenance(overrides: list[str], argv: list[str] | None = None) -> dict[str, Any]:
    """How this process was started, for a run's config.yaml (alignrl.config.run.Provenance)."""
    import shlex
    import sys

    words = ["alignrl", *(sys.argv[1:] if argv is None else argv)]
    return {"command": shlex.join(words), "overrides": list(overrides), "git_commit": git_commit()}


def with_provenance(config: Any, overrides: list[str], argv: list[str] | None = None) -> Any:
    """`config` (a RunConfig) recording how its run was started."""
    from alignrl.config.run import Provenance

    provenance = Provenance(**run_provenance(overrides, argv))
    return config.model_copy(update={"provenance": provenance})

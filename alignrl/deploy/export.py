"""Policy export: a trained aligner as one self-contained file, ONNX, TorchScript or
safetensors (alignrl.deploy.formats), with its model card (alignrl.deploy.card).

`export_policy` writes a folder atomically (a staging folder beside it, then one rename), by
default (`default_out`) beside the run it came from, RUN/exports/<member>-<format>/, and a
policy outside any run (a member file on its own, an export, a shipped champion) under
runs/exports/<name>-<format>/: never into the working directory itself.

    policy.onnx | policy.pt   the graph (policy.pt: torch.jit.save of the traced module)
    policy.safetensors        or the acting network's tensors alone (Agent.policy_state),
                              no graph and no pickle: card.json's member rebuilds the network
    card.json                 the model card for machines (keys: docs/deploy.md)
    model_card.md             the same card for a person
    learner.safetensors       with learner_state (safetensors only): the member's whole
    learner.json              learner state, critics and optimizers included, as tensors
                              and strict JSON (format: alignrl.runs.learner_state;
                              written by alignrl.deploy.learner_state), what `alignrl adapt`
                              and a roster's `init_from` train on from

and refuses to write it unless the file it wrote, loaded back, gives the PyTorch policy's
actions on random histories within PARITY_TOLERANCE (alignrl.deploy.parity), and a learner
state unless, read back as `resolve_source` reads it, it is the source's to the last bit.
What the graph computes is in alignrl.deploy.graph; `alignrl.deploy.loading.load_exported`
runs the folder.

The knob intervals and steps (the action scale) are those the run recorded when it trained
(knobs.json, alignrl.runs.state), or an export's card, as the source read them: the instrument
is not opened. Only a run made before alignrl recorded them, or a member file outside any run,
has its training apparatus opened to read them, and the export says so in one line.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import shutil
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alignrl.checkpoints import atomic_write_text, publish_folder, staging_folder
from alignrl.deploy.formats import (
    EXPORT_FORMATS,
    import_onnxruntime,
    load_runner,
    sha256_of,
    write_policy,
)
from alignrl.deploy.graph import PolicyGraph, PolicyInterface, move_floors
from alignrl.deploy.learner_state import write_checked
from alignrl.deploy.parity import PARITY_HISTORIES, PARITY_TOLERANCE, Parity, check_parity
from alignrl.runs.sources import CHAMPION_PREFIX, ExportError, PolicySource
from alignrl.runs.state import KNOBS_FILE, recorded_knobs
from alignrl.runs.state import knob_limits as limits_on

__all__ = [
    "EXPORTS_FOLDER",
    "ExportResult",
    "check_out_folder",
    "check_within_recorded",
    "default_out",
    "export_command",
    "export_policy",
    "knob_limits",
]

EXPORTS_FOLDER = "exports"  # RUN/exports/, runs/exports/: where exports go without --out


def default_out(
    source: PolicySource, named: str, export_format: str, runs_dir: str | Path = "runs"
) -> Path:
    """Where `alignrl export` writes `source` (the spec `named`) without --out: beside its
    run, RUN/exports/<member>-<format>; a policy outside any run (a member file on its own, an
    export, a shipped champion) under `runs_dir`/exports/<name>-<format>, <name> the
    champion's or the member's."""
    if source.run_dir is not None:
        return source.run_dir / EXPORTS_FOLDER / f"{source.agent.id}-{export_format}"
    name = named.removeprefix(CHAMPION_PREFIX) if named.startswith(CHAMPION_PREFIX) else None
    return Path(runs_dir) / EXPORTS_FOLDER / f"{name or source.agent.id}-{export_format}"


def knob_limits(
    source: PolicySource, note: Callable[[str], None] | None = None
) -> list[dict[str, Any]]:
    """Per task knob of `source`: its interval on the training apparatus and the largest
    change one action makes, as its run recorded them or its card lists them
    (`PolicySource.knobs`). Where neither does, the training apparatus is opened to read
    them, and `note` is told so."""
    if source.knobs is not None:
        return source.knobs
    config = source.config
    if source.run_dir is not None:
        why = (
            f"{source.run_dir} records no knob intervals (no {KNOBS_FILE}: it was made before "
            "alignrl recorded them)"
        )
    else:
        why = f"{source.member_file} lies in no run, so no knob intervals are recorded"
    (note or _to_stderr)(f"{why}; reading them from the training apparatus {config.apparatus!r}")
    return _limits_of_apparatus(config, source.task)


def _to_stderr(line: str) -> None:
    print(f"note: {line}", file=sys.stderr)


def _limits_of_apparatus(config: Any, task: Any) -> list[dict[str, Any]]:
    from alignrl.apparatus.base import ApparatusError
    from alignrl.apparatus.registry import make_apparatus

    try:
        apparatus = make_apparatus(config.apparatus, config.apparatus_args)
        return limits_on(task, apparatus.knobs)
    except (ApparatusError, ImportError, OSError, ValueError) as error:
        raise ExportError(
            f"cannot read the knob intervals of the training apparatus {config.apparatus!r} "
            f"(they set the action scale): {error}"
        ) from None


def check_out_folder(out: Path, force: bool) -> None:
    """ExportError unless `out` can take an export: a name of a folder, not a file, empty
    unless `force`, in a folder this process may write (the nearest one that exists)."""
    if out.name in ("", ".", ".."):
        raise ExportError(f"--out {out}: name a new folder for the policy, e.g. exports/champion")
    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} is a file; give a folder to write the policy into")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ExportError(
            f"{out} is not empty: choose another --out, or add --force to replace what is there"
        )
    parent = out.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ExportError(f"--out {out}: {parent} is a file, not a folder to write into")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ExportError(f"--out {out}: cannot write in {parent} (permission denied)")


def check_within_recorded(
    source: PolicySource, knobs: list[dict[str, Any]], where: str = "the export"
) -> None:
    """ExportError where `knobs` (what an export is about to carry) has an interval or a
    max_step wider than the run `source` came from recorded in its knobs.json when it
    started: its own run's, or for an export or champion the run its card names, where that
    folder is here. A run that recorded none, or is not here, has nothing to hold them to."""
    run = source.run_dir
    if run is None and source.card is not None:
        named = (source.card.get("source") or {}).get("run")
        run = Path(named) if isinstance(named, str) and named else None
    path = run / KNOBS_FILE if run is not None else None
    if path is None or not path.is_file():
        return
    try:
        recorded = recorded_knobs(run, source.task) or []
    except ValueError as error:
        raise ExportError(str(error)) from None
    for index, (mine, theirs) in enumerate(zip(knobs, recorded, strict=False)):
        slack = 1e-9 * max(abs(theirs["low"]), abs(theirs["high"]), 1.0)
        wider = (
            ("low", mine["low"] < theirs["low"] - slack),
            ("high", mine["high"] > theirs["high"] + slack),
            ("max_step", mine["max_step"] > theirs["max_step"] * (1 + 1e-9) + slack),
        )
        for key, beyond in wider:
            if beyond:
                raise ExportError(
                    f"{where}: knobs[{index}].{key} ({mine['name']}) is {mine[key]:g}, wider "
                    f"than the {theirs[key]:g} its run recorded in {path} (interval "
                    f"[{theirs['low']:g}, {theirs['high']:g}], max_step "
                    f"{theirs['max_step']:g}): an export never carries an interval or a step "
                    "beyond what its policy trained on"
                )


@dataclass(frozen=True)
class ExportResult:
    out: Path
    policy_file: Path
    card: dict[str, Any]
    parity: Parity
    learner_file: Path | None = None  # learner.safetensors, where the learner state was written


def _check_learner_export(source: PolicySource, export_format: str, named: str) -> None:
    """Refuse, before any work, a learner state that cannot be written: beside a graph (it
    loads into the member a safetensors policy rebuilds), or of a source that has none."""
    if export_format != "safetensors":
        raise ExportError(
            f"--with-learner-state needs --format safetensors: the learner state loads into the "
            f"member that a safetensors policy rebuilds, and a {export_format} graph is none"
        )
    if not source.learner_state:
        what = "a shipped champion" if source.kind == "champion" else "an exported policy"
        origin = ((source.card or {}).get("source") or {}).get("member_file")
        raise ExportError(
            f"{named} is {what} without a learner state (its acting network alone): "
            "--with-learner-state exports critics, optimizers and entropy coefficient, so "
            "give the league run, training run or member .pt file it was exported from"
            + (f" (its card names {origin})" if origin else "")
        )


def export_policy(
    source: PolicySource,
    out: str | Path,
    export_format: str,
    force: bool = False,
    histories: int = PARITY_HISTORIES,
    seed: int = 0,
    tolerance: float = PARITY_TOLERANCE,
    command: str | None = None,
    note: Callable[[str], None] | None = None,
    learner_state: bool = False,
    named: str | None = None,
    extra_files: Mapping[str, str] | None = None,
) -> ExportResult:
    """Write `source`'s policy to the folder `out` as `export_format` (onnx, torchscript,
    safetensors) with its model card. The written file is loaded back and checked against
    the member on `histories` random histories; beyond `tolerance` nothing is written
    (ExportError). `note` receives a line where the knob intervals had to be read from the
    training apparatus (default: standard error). `learner_state` (safetensors only): the
    member's critics, optimizers and entropy coefficient too (learner.safetensors,
    learner.json), for a source that holds them; `named`: the source as the user gave it,
    for the messages; `extra_files`: more files (name: text) published in the same folder,
    all at once (alignrl calibrate's calibration.json). Knob intervals and steps wider
    than its run recorded (knobs.json) are refused (`check_within_recorded`)."""
    from alignrl.deploy.card import build_card, check_card, render_model_card

    if export_format not in EXPORT_FORMATS:
        raise ExportError(
            f"unknown export format {export_format!r}; formats: {', '.join(EXPORT_FORMATS)}"
        )
    if learner_state:
        _check_learner_export(source, export_format, named or str(source.member_file))
    if export_format == "onnx":
        import_onnxruntime()  # before any work: the parity check needs it
    out = Path(out)
    check_out_folder(out, force)
    knobs = knob_limits(source, note)
    check_within_recorded(source, knobs, str(source.config_file if source.card else out))
    power, floor = source.task.action_power, move_floors(source.task.move_floor, knobs)
    graph = PolicyGraph(source.agent, [knob["max_step"] for knob in knobs], power, floor)
    staging = staging_folder(out)
    try:
        policy_path = staging / EXPORT_FORMATS[export_format]
        write_policy(source.agent, graph, policy_path, export_format)
        interface = PolicyInterface(
            graph.input_names,
            graph.output_names,
            graph.max_step.tolist(),
            source.agent.spec,
            power,
            floor,
        )
        run, runtime = load_runner(policy_path, export_format, interface)
        parity = check_parity(source.agent, graph, run, runtime, histories, seed, tolerance)
        if not parity.passed:
            raise ExportError(
                f"the {export_format} policy of {source.agent.id!r} differs from the PyTorch "
                f"policy by {parity.max_abs_difference:.3g} (knob step "
                f"{parity.knob_step_max_abs_difference:.3g}) on {histories} histories, more "
                f"than {tolerance:g}: nothing was written to {out}"
            )
        card = build_card(
            source, graph, knobs, export_format, parity, command, sha256_of(policy_path)
        )
        try:  # a card that load_exported would refuse is never written
            check_card(card, out / "card.json")
        except ExportError as error:
            raise ExportError(f"{error}; nothing was written to {out}") from None
        atomic_write_text(staging / "card.json", json.dumps(card, indent=2) + "\n")
        atomic_write_text(staging / "model_card.md", render_model_card(card))
        learner_file = write_checked(source, staging, knobs, card) if learner_state else None
        for name, text in (extra_files or {}).items():
            if Path(name).name != name or (staging / name).exists():
                raise ExportError(f"{name!r} is no file an export may add beside its own")
            atomic_write_text(staging / name, text)
        publish_folder(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return ExportResult(
        out,
        out / EXPORT_FORMATS[export_format],
        card,
        parity,
        out / learner_file.name if learner_file else None,
    )


def with_acting_options(source: PolicySource, overrides: Sequence[str]) -> PolicySource:
    """`source` acting with the `--set task_options.NAME=VALUE` assignments, each NAME one of
    ACTING_OPTIONS (how its moves reach the column and how an alignment ends, never what it
    observes), checked by the same strict model as a run's config; anything else is an
    ExportError naming it."""
    from alignrl.config_reading import ConfigError, overridden, parse_config
    from alignrl.envs.option_table import ACTING_OPTIONS

    if not overrides:
        return source
    allowed = ", ".join(f"task_options.{name}" for name in ACTING_OPTIONS)
    for assignment in overrides:
        key = assignment.partition("=")[0].strip()
        if key.removeprefix("task_options.") not in ACTING_OPTIONS or "=" not in assignment:
            raise ExportError(
                f"export --set {assignment!r}: an export changes only how the trained policy "
                f"acts, KEY=VALUE with KEY one of {allowed}; the rest of its config is its "
                "training's"
            )
    data = source.config.model_dump(mode="json")
    try:
        data, where = overridden(data, f"the config of {source.member_file}", overrides)
        config = parse_config(type(source.config), data, where)
    except ConfigError as error:
        raise ExportError(str(error)) from None
    return dataclasses.replace(source, config=config)


def export_command(
    run: str | Path,
    member: str | None,
    export_format: str,
    out: str | Path,
    learner_state: bool = False,
    overrides: Sequence[str] = (),
) -> str:
    """The `alignrl export` command line that writes this export (for the model card)."""
    words = ["alignrl", "export", str(run)]
    if member is not None:
        words += ["--member", member]
    words += ["--format", export_format]
    if learner_state:
        words.append("--with-learner-state")
    for assignment in overrides:
        words += ["--set", assignment]
    words += ["--out", str(out)]
    return shlex.join(words)

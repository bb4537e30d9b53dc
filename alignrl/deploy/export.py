"""Policy export: a trained aligner as one self-contained file, ONNX, TorchScript or
safetensors (alignrl.deploy.formats), with its model card (alignrl.deploy.card).

`export_policy` writes a folder atomically (a staging folder beside it, then one rename):

    policy.onnx | policy.pt   the graph (policy.pt: torch.jit.save of the traced module)
    policy.safetensors        or the acting network's tensors alone (Agent.policy_state),
                              no graph and no pickle: card.json's member rebuilds the network
    card.json                 the model card for machines (keys: docs/deploy.md)
    model_card.md             the same card for a person

and refuses to write it unless the file it wrote, loaded back, gives the PyTorch policy's
actions on random histories within PARITY_TOLERANCE (alignrl.deploy.parity). What the graph
computes is in alignrl.deploy.graph; `alignrl.deploy.loading.load_exported` runs the folder.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alignrl.deploy.formats import (
    EXPORT_FORMATS,
    current_umask,
    import_onnxruntime,
    load_runner,
    sha256_of,
    write_policy,
)
from alignrl.deploy.graph import PolicyGraph, PolicyInterface
from alignrl.deploy.parity import PARITY_HISTORIES, PARITY_TOLERANCE, Parity, check_parity
from alignrl.runs.sources import ExportError, PolicySource

__all__ = ["ExportResult", "export_command", "export_policy", "knob_limits"]


def knob_limits(config: Any) -> list[dict[str, Any]]:
    """Per task knob of a run config: its interval on the training apparatus and the largest
    change one action makes (Task.step_sizes, as the env scales actions)."""
    from alignrl.apparatus.base import ApparatusError
    from alignrl.apparatus.registry import make_apparatus

    task = config.resolved_task()
    try:
        apparatus = make_apparatus(config.apparatus, config.apparatus_args)
        steps = task.step_sizes(apparatus.knobs)
    except (ApparatusError, ImportError, OSError, ValueError) as error:
        raise ExportError(
            f"cannot read the knob intervals of the training apparatus {config.apparatus!r} "
            f"(they set the action scale): {error}"
        ) from None
    return [
        {
            "name": knob,
            "low": float(apparatus.knobs[knob][0]),
            "high": float(apparatus.knobs[knob][1]),
            "max_step": float(step),
        }
        for knob, step in zip(task.knobs, steps, strict=True)
    ]


def _write_text(path: Path, text: str) -> None:
    with path.open("w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())


def _refuse_to_overwrite(out: Path, force: bool) -> None:
    if out.name in ("", ".", ".."):
        raise ExportError(f"--out {out}: name a new folder for the policy, e.g. exports/champion")
    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} is a file; give a folder to write the policy into")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ExportError(
            f"{out} is not empty: choose another --out, or add --force to replace what is there"
        )


def _publish(staging: Path, out: Path) -> None:
    """Put the staging folder in place of `out` with renames: a reader sees the old folder
    or the new one, never a half-written one."""
    # mkdtemp makes 0700; a policy folder is as mkdir makes it
    staging.chmod(0o777 & ~current_umask())
    if out.is_dir() and any(out.iterdir()):
        aside = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
        os.replace(out, aside / out.name)
        os.replace(staging, out)
        shutil.rmtree(aside)
    else:
        if out.is_dir():
            out.rmdir()
        os.replace(staging, out)
    descriptor = os.open(out.parent, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


@dataclass(frozen=True)
class ExportResult:
    out: Path
    policy_file: Path
    card: dict[str, Any]
    parity: Parity


def export_policy(
    source: PolicySource,
    out: str | Path,
    export_format: str,
    force: bool = False,
    histories: int = PARITY_HISTORIES,
    seed: int = 0,
    tolerance: float = PARITY_TOLERANCE,
    command: str | None = None,
) -> ExportResult:
    """Write `source`'s policy to the folder `out` as `export_format` (onnx, torchscript,
    safetensors) with its model card. The written file is loaded back and checked against
    the member on `histories` random histories; beyond `tolerance` nothing is written
    (ExportError)."""
    from alignrl.deploy.card import build_card, check_card, render_model_card

    if export_format not in EXPORT_FORMATS:
        raise ExportError(
            f"unknown export format {export_format!r}; formats: {', '.join(EXPORT_FORMATS)}"
        )
    if export_format == "onnx":
        import_onnxruntime()  # before any work: the parity check needs it
    out = Path(out)
    _refuse_to_overwrite(out, force)
    knobs = knob_limits(source.config)
    graph = PolicyGraph(source.agent, [knob["max_step"] for knob in knobs])
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    try:
        policy_path = staging / EXPORT_FORMATS[export_format]
        write_policy(source.agent, graph, policy_path, export_format)
        interface = PolicyInterface(
            graph.input_names, graph.output_names, graph.max_step.tolist(), source.agent.spec
        )
        run, runtime = load_runner(policy_path, export_format, interface)
        parity = check_parity(source.agent, graph, run, runtime, histories, seed, tolerance)
        if not parity.passed:
            memory = parity.memory_max_abs_difference
            raise ExportError(
                f"the {export_format} policy of {source.agent.id!r} differs from the PyTorch "
                f"policy by {parity.max_abs_difference:.3g} (knob step "
                f"{parity.knob_step_max_abs_difference:.3g}"
                + (f", memory {memory:.3g}" if memory is not None else "")
                + f") on {histories} histories, more than {tolerance:g}: nothing was written "
                f"to {out}"
            )
        card = build_card(
            source, graph, knobs, export_format, parity, command, sha256_of(policy_path)
        )
        try:  # a card that load_exported would refuse is never written
            check_card(card, out / "card.json")
        except ExportError as error:
            raise ExportError(f"{error}; nothing was written to {out}") from None
        _write_text(staging / "card.json", json.dumps(card, indent=2) + "\n")
        _write_text(staging / "model_card.md", render_model_card(card))
        _publish(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return ExportResult(out, out / EXPORT_FORMATS[export_format], card, parity)


def export_command(run: str | Path, member: str | None, export_format: str, out: str | Path) -> str:
    """The `alignrl export` command line that writes this export (for the model card)."""
    words = ["alignrl", "export", str(run)]
    if member is not None:
        words += ["--member", member]
    words += ["--format", export_format, "--out", str(out)]
    return shlex.join(words)

"""Running an exported policy without alignrl's learners: `load_exported` opens a folder that
`alignrl export` wrote (ONNX through onnxruntime, TorchScript through torch.jit.load,
safetensors in the acting network rebuilt from the card), checks the card and the policy file
against each other, and hands out an `ExportedPolicy`.

Nothing in the folder is believed unchecked: the card field by field, the policy file by its
tensors, by its outputs on a few histories and by its SHA-256 where the card has one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.agents.agent import MemberSpec
from alignrl.deploy.card_schema import read_card
from alignrl.deploy.formats import load_runner, sha256_of
from alignrl.deploy.graph import PolicyInterface, Runner, move_floors, random_histories
from alignrl.deploy.parity import PARITY_TOLERANCE
from alignrl.envs.task import Task, knob_change
from alignrl.runs.learner_state import LearnerStateError, has_learner_state, learner_record
from alignrl.runs.sources import ExportError

__all__ = ["ExportedPolicy", "load_exported"]

PROBE_HISTORIES = 8  # histories a loaded policy answers before it is handed out


@dataclass
class ExportedPolicy:
    """An exported policy, loaded: `act` for actions, `run` for every named output."""

    folder: Path
    card: dict[str, Any]
    task: Task
    history: int
    features: int
    max_step: np.ndarray  # per knob, instrument units per action
    runtime: str
    _run: Runner = field(repr=False)

    @property
    def input_names(self) -> list[str]:
        return [entry["name"] for entry in self.card["inputs"]]

    @property
    def output_names(self) -> list[str]:
        return [entry["name"] for entry in self.card["outputs"]]

    def run(self, history: np.ndarray) -> dict[str, np.ndarray]:
        """Every output (action, knob_step) for a batch (B, H, F) of histories. Float32,
        batch first."""
        history = np.asarray(history, np.float32)
        if history.ndim != 3 or history.shape[1:] != (self.history, self.features):
            raise ValueError(
                f"{self.folder}: the policy takes histories of shape (batch, {self.history}, "
                f"{self.features}), got {history.shape}"
            )
        return self._run({"history": history})

    def act(self, history: np.ndarray) -> np.ndarray:
        """Actions in [-1, 1] for one history (H, F) -> (k+1,) or a batch (B, H, F) ->
        (B, k+1), float64."""
        history = np.asarray(history, np.float32)
        single = history.ndim == 2
        action = self.run(history[None] if single else history)["action"].astype(np.float64)
        return action[0] if single else action


def _card_spec(member: dict[str, Any]) -> MemberSpec:
    """The member spec that card.json's `member` carries (MemberSpec.to_dict and more)."""
    return MemberSpec.from_dict({f.name: member[f.name] for f in dataclasses.fields(MemberSpec)})


def _probe(
    run: Runner,
    card: dict[str, Any],
    policy_path: Path,
    max_step: np.ndarray,
    power: float,
    floor: list[float],
) -> None:
    """Run a freshly loaded policy file on a zero history and a few random ones, as its card
    describes them: it must take the card's inputs, give the card's outputs in their shapes,
    every value finite, and knob_step = sign(a) (|a|^power x the card's max_step + floor)
    (the task's action_power and move_floor, alignrl.envs.task.knob_change). A file of another
    member, or a card whose steps were edited, is refused here, before any instrument."""
    knobs = len(max_step)
    history, features = int(card["history"]), int(card["features"])
    rng = np.random.default_rng(0)
    histories = random_histories(PROBE_HISTORIES, history, features, rng, knobs)
    histories[0] = 0.0  # the first call of an alignment sees a padded, empty history
    try:
        outputs = run({"history": histories})
    except Exception as error:  # any runtime's own error: the file does not fit the card
        raise ExportError(
            f"policy file {policy_path} does not run on the inputs its card.json names "
            f"({type(error).__name__}: {str(error).strip()[:300]}): the file and the card are "
            "of different members; export it again"
        ) from None
    for entry in card["outputs"]:
        name = entry["name"]
        shape = tuple(PROBE_HISTORIES if size == "batch" else int(size) for size in entry["shape"])
        value = outputs.get(name)
        if value is None or np.shape(value) != shape:
            found = "nothing" if value is None else f"shape {np.shape(value)}"
            raise ExportError(
                f"policy file {policy_path} answers {found} as {name!r}, where its card.json "
                f"says {shape}: the file and the card are of different members; export it again"
            )
        if not np.all(np.isfinite(value)):
            raise ExportError(
                f"policy file {policy_path} answers non-finite values as {name!r}: its weights "
                "hold NaN or infinity; export it again from a sound member"
            )
    action, knob_step = outputs["action"], outputs["knob_step"]
    expected = knob_change(action[:, :knobs], max_step, power, np.asarray(floor))
    allowed = PARITY_TOLERANCE * max(1.0, float(np.max(max_step)))
    if not np.allclose(knob_step, expected, rtol=1e-5, atol=allowed):
        scale = float(
            np.max(np.abs(knob_step)) / max(float(np.max(np.abs(action[:, :knobs]))), 1e-12)
        )
        raise ExportError(
            f"policy file {policy_path} scales its actions by about {scale:.4g}, where its "
            f"card.json's knobs[].max_step say {max_step.tolist()}: the card's steps were "
            "changed after the export; export it again"
        )


def load_exported(path: str | Path) -> ExportedPolicy:
    """An exported policy from its folder (or its policy file): ONNX through onnxruntime,
    TorchScript through torch.jit.load, safetensors weights in the member rebuilt from the
    card (Agent.act). The card is checked field by field (alignrl.deploy.card_schema),
    the policy file against it (its tensors, its outputs on a few histories, its SHA-256
    where the card has one), and learner.json, where the export ships one, against the
    card: a missing, corrupt or tampered card, policy file or learner record is an
    ExportError naming the file and what is wrong; ONNX without onnxruntime installed is an
    ImportError."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    card_path = folder / "card.json"
    if not card_path.is_file():
        raise ExportError(
            f"{card_path} is missing: {folder} is not an exported policy "
            "(`alignrl export` writes card.json beside the policy file)"
        )
    card, task = read_card(card_path)
    if has_learner_state(folder):  # its learner state tells the run its card does
        try:
            learner_record(folder, card, _card_spec(card["member"]).to_dict())
        except LearnerStateError as error:
            raise ExportError(str(error)) from None
    export_format = card["export_format"]
    policy_path = folder / card["policy_file"]
    max_step = np.array([knob["max_step"] for knob in card["knobs"]], np.float64)
    interface = PolicyInterface(
        input_names=[entry["name"] for entry in card["inputs"]],
        output_names=[entry["name"] for entry in card["outputs"]],
        max_step=max_step.tolist(),
        # Only weights need the member: a graph carries its own network.
        spec=_card_spec(card["member"]) if export_format == "safetensors" else None,
        action_power=task.action_power,
        move_floor=move_floors(task.move_floor, card["knobs"]),
    )
    run, runtime = load_runner(policy_path, export_format, interface)
    _probe(run, card, policy_path, max_step, task.action_power, interface.move_floor)
    recorded = card.get("policy_sha256")
    if recorded is not None and sha256_of(policy_path) != recorded:
        raise ExportError(
            f"{card_path}: policy_sha256 {recorded} is not the SHA-256 of {policy_path} "
            f"({sha256_of(policy_path)}): the card and the policy file are not of one export; "
            "export it again"
        )
    history, features = int(card["history"]), int(card["features"])
    return ExportedPolicy(folder, card, task, history, features, max_step, runtime, run)

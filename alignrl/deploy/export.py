"""Policy export: a trained aligner as one self-contained file, ONNX, TorchScript or
safetensors, with its model card; and `load_exported`, which runs such a file without
alignrl's learners (safetensors: the acting network alone, rebuilt from the card).

The exported graph is exactly the deterministic policy of `Agent.act(deterministic=True)`:

    history    float32 (batch, H, F)  the env's history (alignrl/envs/core.py), as it is
      -> history encoder -> mean of the policy head -> tanh -> clip to [-1, 1]
    action     float32 (batch, k + 1) k knob actions, then the stop component (stop if > 0)
    knob_step  float32 (batch, k)     action[:, :k] x max_step: the knob change asked for,
                                      in the apparatus's units (volts for a lens)

The learners apply no normalisation of their own: the env already scales every feature of
the history (knobs to [-1, 1], quality as log(width / reference)), so there is nothing to fold
in but the action's squashing, clipping and scaling. A GTrXL encoder with a Transformer-XL
memory (memory_length > 0) gets it as explicit tensors: inputs `memory_in_<i>` (one per block,
(batch, M, d_model)) and `memory_valid_in` (batch, M), float32 1/0, and the same as outputs
`memory_out_<i>`, `memory_valid_out`; any other member's whole memory is its history window.

`export_policy` writes a folder atomically (a staging folder beside it, then one rename):

    policy.onnx | policy.pt   the graph (policy.pt: torch.jit.save of the traced module)
    policy.safetensors        or the acting network's tensors alone (Agent.policy_state),
                              no graph and no pickle: card.json's member rebuilds the network
    card.json                 the model card for machines (keys: docs/deploy.md)
    model_card.md             the same card for a person

and refuses to write it unless the file it wrote, loaded back, gives the PyTorch policy's
actions on random histories within PARITY_TOLERANCE.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from alignrl.agents.agent import MEMBER_FORMAT, Agent, MemberSpec, finite_problem
from alignrl.agents.networks import GTrXLEncoder, Memory
from alignrl.agents.sac import SAC
from alignrl.envs.core import feature_layout, observation_bounds
from alignrl.envs.task import Task

__all__ = [
    "CARD_FORMAT",
    "EXPORT_FORMATS",
    "PARITY_HISTORIES",
    "PARITY_TOLERANCE",
    "ExportError",
    "ExportResult",
    "ExportedPolicy",
    "Parity",
    "PolicyGraph",
    "PolicySource",
    "check_parity",
    "export_command",
    "export_policy",
    "graph_signature",
    "knob_limits",
    "load_exported",
    "random_histories",
    "resolve_source",
    "sha256_of",
]

CARD_FORMAT = "alignrl-policy-card-1"
EXPORT_FORMATS = {  # format -> file name
    "onnx": "policy.onnx",
    "torchscript": "policy.pt",
    "safetensors": "policy.safetensors",
}
PARITY_HISTORIES = 1000  # random histories the written file is checked on
PARITY_TOLERANCE = 1e-5  # largest |exported - PyTorch| allowed, in action units
ONNX_OPSET = 17  # LayerNormalization is a single operator from 17 on
FULLY_PADDED_SHARE = 0.01  # share of parity histories with no valid row (a zero observation)
ONNX_MISSING = (
    "ONNX export and ONNX policies need onnx and onnxruntime: pip install 'alignrl[onnx]'"
)


class ExportError(ValueError):
    """An export that cannot be done, or an exported policy that cannot be used."""


# --- what is exported -------------------------------------------------------------------


@dataclass(frozen=True)
class PolicySource:
    """The aligner to export and where it came from.

    kind: "league" (a league run), "training" (an `alignrl train` run) or "member" (a
    checkpoint file outside any run); chosen_as: how RUN named it ("champion", "--member",
    "best checkpoint", "file"). `config` is the run's RunConfig (alignrl.config), or the
    defaults where no run config was found (config_file None).
    """

    agent: Agent
    member_file: Path
    kind: str
    chosen_as: str
    run_dir: Path | None
    config: Any
    config_file: Path | None
    env_steps: int | None = None  # training: env steps when the best checkpoint was saved
    best: dict[str, Any] | None = None  # league: the member's row of best/best.json

    @property
    def task(self) -> Task:
        return self.config.resolved_task()


def _member_ids(run_dir: Path) -> list[str]:
    """Members with a file in best/ or in the newest checkpoint."""
    ids = {path.stem for path in (run_dir / "best").glob("*.pt")}
    latest = run_dir / "checkpoints" / "LATEST"
    if latest.exists():
        folder = run_dir / "checkpoints" / latest.read_text().strip() / "members"
        ids |= {path.stem for path in folder.glob("*.pt")}
    return sorted(ids)


def _league_config(run_dir: Path) -> tuple[Any, Path]:
    from alignrl.league.config import parse_league
    from alignrl.yaml_io import read_yaml_file

    path = run_dir / "config.yaml"
    if not path.exists():
        raise ExportError(f"{run_dir} is not a league run: it has no config.yaml")
    return parse_league(read_yaml_file(path), str(path)), path


def _league_root(member_file: Path) -> Path | None:
    """The league run a member file lies in (best/, initial/, snapshots/ or a checkpoint)."""
    for folder in list(member_file.resolve().parents)[:4]:
        if (folder / "aligners.yaml").exists() and (folder / "config.yaml").exists():
            return folder
    return None


def _only_aligners(state: dict[str, Any], path: Path) -> None:
    spec = state.get("spec")
    if not isinstance(spec, dict):
        from alignrl.checkpoints import CheckpointError

        raise CheckpointError(
            f"{path}: not a usable member checkpoint: its spec is a {type(spec).__name__}, "
            "not a member record"
        )
    team = spec.get("team")
    if team != "aligner":
        raise ExportError(
            f"{path}: member {spec.get('id')!r} is a {team}; only aligners can be exported "
            "(a misaligner's actions mean nothing to an instrument)"
        )


def _member(state: dict[str, Any], path: Path) -> Agent:
    """The member a checkpoint holds, without its experience: a checkpoint's replay or
    rollout is shaped for the league's env slots, and a policy needs none of it."""
    from alignrl.checkpoints import CheckpointError

    _only_aligners(state, path)
    weights = {key: value for key, value in state.items() if key != "replay"}
    try:
        agent = Agent(MemberSpec.from_dict(weights["spec"]))
        agent.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: not a usable member checkpoint: {error}") from None
    return agent


def _league_source(run_dir: Path, member: str | None) -> PolicySource:
    from alignrl.checkpoints import load_checkpoint

    config, config_file = _league_config(run_dir)
    best_json = run_dir / "best" / "best.json"
    try:
        ranked = json.loads(best_json.read_text()) if best_json.exists() else []
    except json.JSONDecodeError as error:
        raise ExportError(f"{best_json} is not valid JSON ({error})") from None
    if member is None:
        if not ranked:
            raise ExportError(
                f"{run_dir} has no evaluated aligner yet ({best_json} is missing or empty): "
                f"name one with --member ID; members: {', '.join(_member_ids(run_dir)) or 'none'}"
            )
        member, chosen_as = str(ranked[0]["member"]), "champion"
        member_file = run_dir / "best" / f"{member}.pt"
    else:
        chosen_as = "--member"
        member_file = run_dir / "best" / f"{member}.pt"
        latest = run_dir / "checkpoints" / "LATEST"
        if not member_file.exists() and latest.exists():
            folder = run_dir / "checkpoints" / latest.read_text().strip()
            member_file = folder / "members" / f"{member}.pt"
        if not member_file.exists():
            raise ExportError(
                f"{run_dir} has no member {member!r}; its members: "
                f"{', '.join(_member_ids(run_dir)) or 'none'}"
            )
    agent = _member(load_checkpoint(member_file), member_file)
    best = next((row for row in ranked if row.get("member") == member), None)
    return PolicySource(
        agent, member_file, "league", chosen_as, run_dir, config, config_file, best=best
    )


def _training_source(run_dir: Path | None, checkpoint: Path, chosen_as: str) -> PolicySource:
    from alignrl.checkpoints import CheckpointError, load_checkpoint
    from alignrl.training import load_policy

    try:
        agent, config = load_policy(checkpoint)
    except CheckpointError:
        raise  # names the file already
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as error:
        # ValueError includes the config's own errors and a tensor that does not fit.
        reason = f"{error}" if not isinstance(error, KeyError) else f"it has no {error}"
        raise CheckpointError(f"{checkpoint}: not a usable training checkpoint: {reason}") from None
    state = load_checkpoint(checkpoint)
    env_steps = state.get("env_steps")
    if env_steps is not None and (isinstance(env_steps, bool) or not isinstance(env_steps, int)):
        raise CheckpointError(f"{checkpoint}: env_steps is {env_steps!r}, not a whole number")
    config_file = (
        run_dir / "config.yaml" if run_dir and (run_dir / "config.yaml").exists() else None
    )
    return PolicySource(
        agent,
        checkpoint,
        "training",
        chosen_as,
        run_dir,
        config,
        config_file,
        env_steps=int(env_steps) if env_steps is not None else None,
    )


def resolve_source(run: str | Path, member: str | None = None) -> PolicySource:
    """The aligner RUN names: a league run's champion (first of best/best.json) or its
    `member` (best/<id>.pt, else the newest checkpoint's file); a training run's
    checkpoints/best.pt; or a member/checkpoint .pt file."""
    from alignrl.checkpoints import load_checkpoint

    path = Path(run)
    if not path.exists():
        raise ExportError(
            f"{path} does not exist: give a league run directory, a training run directory "
            "or a member .pt file"
        )
    if path.is_dir():
        if (path / "aligners.yaml").exists():
            source = _league_source(path, member)
        elif member is not None:
            raise ExportError(
                f"--member picks a member of a league run; {path} is not one (no aligners.yaml)"
            )
        elif (path / "checkpoints" / "best.pt").exists():
            source = _training_source(path, path / "checkpoints" / "best.pt", "best checkpoint")
        else:
            raise ExportError(
                f"{path} is neither a league run (no aligners.yaml) nor a training run with "
                "an evaluated policy (no checkpoints/best.pt)"
            )
    else:
        if member is not None:
            raise ExportError(f"--member picks a member of a league run, not of the file {path}")
        state = load_checkpoint(path)
        if state.get("format") == MEMBER_FORMAT:
            agent = _member(state, path)
            root = _league_root(path)
            if root is None:  # a member file on its own: the run settings are the defaults
                from alignrl.config import parse_experiment

                history = agent.spec.observation_shape[0]
                config = parse_experiment({"name": agent.id, "history": history}, str(path))
                source = PolicySource(agent, path, "member", "file", None, config, None)
            else:
                config, config_file = _league_config(root)
                source = PolicySource(agent, path, "league", "file", root, config, config_file)
        else:
            run_dir = path.parent.parent if path.parent.name == "checkpoints" else None
            source = _training_source(run_dir, path, "file")
    _check_shapes(source)
    return source


def _check_shapes(source: PolicySource) -> None:
    spec, config = source.agent.spec, source.config
    knobs = len(source.task.knobs)
    if spec.observation_shape[0] != config.history or spec.action_dim != knobs + 1:
        where = source.config_file or "the default run settings"
        raise ExportError(
            f"{source.member_file}: member {spec.id!r} reads {spec.observation_shape[0]} "
            f"history rows and acts on {spec.action_dim - 1} knob(s), but {where} has "
            f"history {config.history} and task {source.task.name!r} with {knobs} knob(s)"
        )


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


# --- the graph --------------------------------------------------------------------------


class PolicyGraph(nn.Module):
    """The deployable policy of one aligner: history [+ memory] -> action, knob_step
    [+ memory]. A copy of the policy network alone (no critics, no optimizer); the member
    itself is left untouched."""

    def __init__(self, agent: Agent, max_step: Sequence[float]) -> None:
        super().__init__()
        learner = agent.learner
        policy = learner.actor if isinstance(learner, SAC) else learner.policy
        self.encoder = copy.deepcopy(policy.encoder)
        self.head = copy.deepcopy(policy.head)
        # SAC's head gives [mean, log_std]; PPO's gives the mean (its std is a parameter).
        self.action_dim = agent.spec.action_dim
        self.history, self.features = agent.spec.observation_shape
        self.knobs = len(max_step)
        if self.knobs != self.action_dim - 1:
            raise ExportError(
                f"member {agent.id!r} acts on {self.action_dim - 1} knob(s); "
                f"{self.knobs} max step(s) given"
            )
        self.register_buffer("max_step", torch.tensor(list(max_step), dtype=torch.float32))
        self.memory_length = getattr(self.encoder, "memory_length", 0)
        self.memory_layers = self.encoder.layers if isinstance(self.encoder, GTrXLEncoder) else 0
        # Parameters keep requires_grad, as the member's own: with it off, PyTorch's CPU
        # kernels take other paths whose float32 rounding differs (1e-6 on a trained GTrXL).
        self.eval()

    @property
    def input_names(self) -> list[str]:
        if not self.memory_length:
            return ["history"]
        layers = [f"memory_in_{i}" for i in range(self.memory_layers)]
        return ["history", *layers, "memory_valid_in"]

    @property
    def output_names(self) -> list[str]:
        if not self.memory_length:
            return ["action", "knob_step"]
        layers = [f"memory_out_{i}" for i in range(self.memory_layers)]
        return ["action", "knob_step", *layers, "memory_valid_out"]

    def signature(self) -> dict[str, list[dict[str, Any]]]:
        """Names, dtypes and shapes of the inputs and outputs ("batch": any size)."""
        width = getattr(self.encoder, "d_model", 0)
        return graph_signature(
            self.history, self.features, self.knobs, self.memory_length, self.memory_layers, width
        )

    def empty_memory(self, batch: int) -> dict[str, np.ndarray]:
        """Memory inputs of the first step of an alignment: every slot empty."""
        if not self.memory_length:
            return {}
        width = self.encoder.d_model
        memory = {
            f"memory_in_{i}": np.zeros((batch, self.memory_length, width), np.float32)
            for i in range(self.memory_layers)
        }
        memory["memory_valid_in"] = np.zeros((batch, self.memory_length), np.float32)
        return memory

    def forward(self, history: Tensor, *memory: Tensor) -> tuple[Tensor, ...]:
        past = None
        if self.memory_length:
            *layers, valid = memory
            past = Memory(list(layers), valid > 0.5)
        encoded, updated = self.encoder(history, past)  #                                 (B, D)
        mean = self.head(encoded)[:, : self.action_dim]  #                                  (B, k+1)
        # Agent.act(deterministic=True) is tanh(mean) for SAC and PPO alike; the clip only
        # pins the contract (float32 tanh can round to exactly 1, never beyond).
        action = torch.tanh(mean).clamp(-1.0, 1.0)  #                                   (B, k+1)
        knob_step = action[:, : self.knobs] * self.max_step  # as AlignmentEpisodes.step (B, k)
        if updated is None:
            return action, knob_step
        return (action, knob_step, *updated.layers, updated.valid.to(action.dtype))


def graph_signature(
    history: int, features: int, knobs: int, memory_length: int, memory_layers: int, d_model: int
) -> dict[str, list[dict[str, Any]]]:
    """The inputs and outputs of a policy graph: per tensor its name, dtype and shape
    ("batch": any size), as card.json lists them."""
    memory_shape: list[Any] = ["batch", memory_length]
    shapes = {
        "history": ["batch", history, features],
        "action": ["batch", knobs + 1],
        "knob_step": ["batch", knobs],
        "memory_valid_in": memory_shape,
        "memory_valid_out": memory_shape,
    }
    inputs, outputs = ["history"], ["action", "knob_step"]
    if memory_length:
        inputs += [*(f"memory_in_{i}" for i in range(memory_layers)), "memory_valid_in"]
        outputs += [*(f"memory_out_{i}" for i in range(memory_layers)), "memory_valid_out"]
    return {
        side: [
            {"name": name, "dtype": "float32", "shape": shapes.get(name, [*memory_shape, d_model])}
            for name in names
        ]
        for side, names in (("inputs", inputs), ("outputs", outputs))
    }


def random_histories(
    count: int, history: int, features: int, rng: np.random.Generator, knobs: int = 1
) -> np.ndarray:
    """Histories such as the env produces: (count, history, features) float32, each with 1 to
    `history` valid rows at the end and zero padding in front, feature values drawn within
    their bounds (alignrl/envs/core.py); features beyond a row of `knobs` knobs are the
    task's extras. About 1 in 100 is all padding."""
    extras = features - 5 - 2 * knobs
    if knobs < 1 or extras < 0:
        raise ValueError(f"a history row of {features} features does not fit {knobs} knob(s)")
    low, high = observation_bounds(knobs, extras)
    layout = feature_layout(knobs, extras)
    rows = rng.uniform(low, high, (count, history, features)).astype(np.float32)
    rows[..., layout["valid"]] = 1.0
    rows[..., layout["measured"]] = rng.integers(0, 2, (count, history, 1))
    valid = rng.integers(1, history + 1, count)
    valid[rng.random(count) < FULLY_PADDED_SHARE] = 0
    padding = np.arange(history)[None, :] < (history - valid)[:, None]  #         (count, history)
    rows[padding] = 0.0
    return rows


def _random_memory(graph: PolicyGraph, count: int, rng: np.random.Generator) -> dict[str, Any]:
    """Memory inputs as a run of steps leaves them: valid slots at the end, zeros before."""
    memory = graph.empty_memory(count)
    filled = rng.integers(0, graph.memory_length + 1, count)
    valid = np.arange(graph.memory_length)[None, :] >= (graph.memory_length - filled)[:, None]
    for name in memory:
        if name.startswith("memory_in_"):
            values = rng.normal(0.0, 1.0, memory[name].shape).astype(np.float32)
            memory[name] = np.where(valid[..., None], values, 0.0).astype(np.float32)
    memory["memory_valid_in"] = valid.astype(np.float32)
    return memory


# --- running an exported file ----------------------------------------------------------

Runner = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass(frozen=True)
class PolicyInterface:
    """What running a policy file takes besides the file: the names of its inputs and
    outputs, each knob's max_step, and the member's spec, which only a safetensors file
    needs (it holds weights, not a network). From the PolicyGraph when exporting, from
    card.json when loading."""

    input_names: list[str]
    output_names: list[str]
    max_step: list[float]
    spec: MemberSpec | None = None


def _onnxruntime() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise ImportError(ONNX_MISSING) from None
    return onnxruntime


def _onnx_runner(path: Path) -> tuple[Runner, str]:
    onnxruntime = _onnxruntime()
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1  # a policy this small runs fastest on one thread
    options.inter_op_num_threads = 1
    session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    _check_onnx_weights(path)
    names = [output.name for output in session.get_outputs()]

    def run(inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        feed = {name: np.asarray(value, np.float32) for name, value in inputs.items()}
        return dict(zip(names, session.run(names, feed), strict=True))

    return run, f"onnxruntime {onnxruntime.__version__}"


def _check_onnx_weights(path: Path) -> None:
    """Every weight (initializer) of an ONNX graph is finite. Needs the onnx package (the
    `onnx` extra installs it with onnxruntime); without it the probe of load_exported,
    which runs the graph, is the check."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        return
    for initializer in onnx.load(str(path)).graph.initializer:
        weights = torch.from_numpy(np.array(numpy_helper.to_array(initializer)))
        problem = finite_problem(f"weight {initializer.name!r}", weights)
        if problem:
            raise ExportError(f"policy file {path}: {problem}; export it again")


def _torchscript_runner(
    path: Path, input_names: Sequence[str], output_names: Sequence[str]
) -> tuple[Runner, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit: still the format
        module = torch.jit.load(str(path), map_location="cpu").eval()
    for name, tensor in module.state_dict().items():
        problem = finite_problem(f"tensor {name!r}", tensor)
        if problem:
            raise ExportError(f"policy file {path}: {problem}; export it again")

    @torch.no_grad()
    def run(inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        tensors = [torch.as_tensor(np.asarray(inputs[name], np.float32)) for name in input_names]
        outputs = module(*tensors)
        return {name: output.numpy() for name, output in zip(output_names, outputs, strict=True)}

    return run, f"torch.jit {torch.__version__}"


def _check_tensors(path: Path, found: dict[str, Tensor], expected: dict[str, Tensor]) -> None:
    """The file holds exactly the network's tensors: same names, shapes and dtypes; else an
    ExportError naming the file and the first tensor that differs."""
    network = "the network described by its card.json"

    def described(tensor: Tensor) -> str:
        return f"{tuple(tensor.shape)} {str(tensor.dtype).removeprefix('torch.')}"

    def problem(name: str) -> str | None:
        held, wanted = found.get(name), expected.get(name)
        if wanted is None:
            return f"holds tensor {name!r}, which {network} has not"
        if held is None:
            return f"has no tensor {name!r}, which {network} needs ({described(wanted)})"
        if (held.shape, held.dtype) != (wanted.shape, wanted.dtype):
            return f"holds {name!r} as {described(held)}; {network} needs {described(wanted)}"
        return finite_problem(f"holds {name!r}, which", held)

    names = [*expected, *sorted(set(found) - set(expected))]
    first = next((text for text in map(problem, names) if text), None)
    if first and "non-finite" in first:
        raise ExportError(f"policy file {path} {first}: export it again from a sound member")
    if first:
        raise ExportError(
            f"policy file {path} {first}: the file and the card are of different members; "
            "export it again"
        )


def _weights_runner(path: Path, interface: PolicyInterface) -> tuple[Runner, str]:
    """The member rebuilt from its spec with the file's weights, acting by Agent.act."""
    from safetensors.torch import load_file

    assert interface.spec is not None, "safetensors weights are loaded into the member's spec"
    agent = Agent(interface.spec)
    blank = agent.policy_state()
    weights = load_file(str(path), device="cpu")
    _check_tensors(path, weights, blank["policy"])
    agent.load_policy_state({**blank, "policy": weights})
    graph = PolicyGraph(agent, interface.max_step)
    max_step = graph.max_step.numpy()

    @torch.no_grad()
    def run(inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        arrays = [np.asarray(inputs[name], np.float32) for name in graph.input_names]
        if graph.memory_length:  # Agent.act takes no memory; the same network as a graph does
            outputs = graph(*(torch.from_numpy(array) for array in arrays))
            return {n: out.numpy() for n, out in zip(graph.output_names, outputs, strict=True)}
        action = agent.act(arrays[0], deterministic=True).astype(np.float32)  #   (batch, k+1)
        return {"action": action, "knob_step": action[:, : graph.knobs] * max_step}

    return run, f"torch {torch.__version__}: Agent.act on the safetensors weights"


def _load_runner(path: Path, export_format: str, interface: PolicyInterface) -> tuple[Runner, str]:
    """Open an exported policy file; a missing or unreadable file is an ExportError naming
    it."""
    if not path.is_file():
        raise ExportError(f"policy file {path} is missing")
    if export_format == "onnx":
        _onnxruntime()  # a missing runtime is an ImportError of its own, not a corrupt file
    try:
        if export_format == "onnx":
            return _onnx_runner(path)
        if export_format == "safetensors":
            return _weights_runner(path, interface)
        return _torchscript_runner(path, interface.input_names, interface.output_names)
    except ExportError:
        raise  # names the file and what is wrong with it already
    except Exception as error:  # any unreadable file: say which and why, never a traceback
        raise ExportError(
            f"policy file {path} cannot be loaded as {export_format} ({type(error).__name__}: "
            f"{str(error).strip()[:300]}); it may be truncated or corrupt: export it again"
        ) from None


# --- parity -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Parity:
    """How closely the written file reproduces the PyTorch policy on random histories.

    max_abs_difference: |exported action - Agent.act(deterministic=True)|, action units;
    knob_step_max_abs_difference: |exported knob_step - that action x max_step|, instrument
    units; memory_max_abs_difference: with random memory inputs, |exported - PyTorch graph|
    over the action and memory outputs (None for a policy without memory).
    """

    histories: int
    max_abs_difference: float
    knob_step_max_abs_difference: float
    memory_max_abs_difference: float | None
    tolerance: float
    knob_step_tolerance: float
    runtime: str
    reference: str = "Agent.act(deterministic=True)"

    @property
    def passed(self) -> bool:
        return (
            self.max_abs_difference <= self.tolerance
            and self.knob_step_max_abs_difference <= self.knob_step_tolerance
            and (self.memory_max_abs_difference or 0.0) <= self.tolerance
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "histories": self.histories,
            "max_abs_difference": self.max_abs_difference,
            "knob_step_max_abs_difference": self.knob_step_max_abs_difference,
            "memory_max_abs_difference": self.memory_max_abs_difference,
            "tolerance": self.tolerance,
            "knob_step_tolerance": self.knob_step_tolerance,
            "runtime": self.runtime,
            "reference": self.reference,
            "passed": self.passed,
        }


def _max_difference(left: np.ndarray, right: np.ndarray) -> float:
    if left.shape != right.shape:
        return float("inf")
    difference = np.abs(left.astype(np.float64) - right.astype(np.float64))
    return float(np.nanmax(difference)) if np.all(np.isfinite(difference)) else float("inf")


def check_parity(
    agent: Agent,
    graph: PolicyGraph,
    run: Runner,
    runtime: str,
    histories: int = PARITY_HISTORIES,
    seed: int = 0,
    tolerance: float = PARITY_TOLERANCE,
) -> Parity:
    """Compare an exported graph (`run`) with the member on `histories` random histories
    (random_histories), empty memory; with memory, also with random memory inputs."""
    rng = np.random.default_rng(seed)
    inputs = random_histories(histories, graph.history, graph.features, rng, graph.knobs)
    expected = agent.act(inputs, deterministic=True).astype(np.float64)  #   (histories, k+1)
    outputs = run({"history": inputs, **graph.empty_memory(histories)})
    max_step = graph.max_step.numpy().astype(np.float64)
    action_difference = _max_difference(outputs["action"], expected)
    knob_difference = _max_difference(outputs["knob_step"], expected[:, : graph.knobs] * max_step)
    memory_difference = None
    if graph.memory_length:
        memory = _random_memory(graph, histories, rng)
        exported = run({"history": inputs, **memory})
        with torch.no_grad():
            eager = graph(
                torch.from_numpy(inputs),
                *(torch.from_numpy(memory[n]) for n in graph.input_names[1:]),
            )
        memory_difference = max(
            _max_difference(exported[name], value.numpy())
            for name, value in zip(graph.output_names, eager, strict=True)
            if name != "knob_step"
        )
    return Parity(
        histories=histories,
        max_abs_difference=action_difference,
        knob_step_max_abs_difference=knob_difference,
        memory_max_abs_difference=memory_difference,
        tolerance=tolerance,
        knob_step_tolerance=tolerance * max(1.0, float(max_step.max())),
        runtime=runtime,
    )


# --- writing ----------------------------------------------------------------------------


def _tanh_from_exp(graph: Any, x: Any) -> Any:
    # tanh(x) = 1 - 2 / (exp(2x) + 1): exp overflows to inf for x > 44, giving exactly 1.
    one = graph.op("Constant", value_t=torch.tensor(1.0))
    two = graph.op("Constant", value_t=torch.tensor(2.0))
    exp = graph.op("Exp", graph.op("Mul", x, two))
    return graph.op("Sub", one, graph.op("Div", two, graph.op("Add", exp, one)))


def _sigmoid_from_exp(graph: Any, x: Any) -> Any:
    # sigmoid(x) = 1 / (1 + exp(-x)): exp(-x) = inf for very negative x, giving exactly 0.
    one = graph.op("Constant", value_t=torch.tensor(1.0))
    return graph.op("Div", one, graph.op("Add", one, graph.op("Exp", graph.op("Neg", x))))


@contextmanager
def _accurate_onnx_activations() -> Iterator[None]:
    """Export tanh and sigmoid through Exp. onnxruntime's own Tanh and Sigmoid kernels are
    fast approximations (3e-7 off in float32, where PyTorch is 3e-8); the GRU gates of a
    trained GTrXL amplify that to ~1e-5 at the action, the whole parity allowance. Through
    Exp the exported policy stays within PyTorch's own float32 rounding."""
    activations = {"aten::tanh": _tanh_from_exp, "aten::sigmoid": _sigmoid_from_exp}
    for name, symbolic in activations.items():
        torch.onnx.register_custom_op_symbolic(name, symbolic, ONNX_OPSET)
    try:
        yield
    finally:
        for name in activations:
            torch.onnx.unregister_custom_op_symbolic(name, ONNX_OPSET)


def _write_graph(graph: PolicyGraph, path: Path, export_format: str) -> None:
    # Traced at batch 2, so that the batch size stays a variable of the graph (parity then
    # runs it at 1000).
    rng = np.random.default_rng(0)
    example = (
        torch.from_numpy(random_histories(2, graph.history, graph.features, rng, graph.knobs)),
        *(torch.from_numpy(value) for value in graph.empty_memory(2).values()),
    )
    with warnings.catch_warnings(), torch.no_grad():
        # Tracing warns about the encoders' shape checks (constants of a fixed-shape graph,
        # as intended) and about the TorchScript-based ONNX exporter: no news to a user.
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        if export_format == "onnx":
            _onnxruntime()
            batch = {name: {0: "batch"} for name in graph.input_names + graph.output_names}
            # dynamo=False: the TorchScript-based exporter needs no onnxscript, and the
            # encoders' fixed-size loops trace to a plain graph.
            with _accurate_onnx_activations():
                torch.onnx.export(
                    graph,
                    example,
                    str(path),
                    input_names=graph.input_names,
                    output_names=graph.output_names,
                    dynamic_axes=batch,
                    opset_version=ONNX_OPSET,
                    dynamo=False,
                )
        else:
            torch.jit.save(torch.jit.trace(graph, example, check_trace=False), str(path))
    _fsync(path)


def _write_weights(agent: Agent, path: Path) -> None:
    """The acting network's tensors (Agent.policy_state) as safetensors: tensors and a few
    strings, nothing a loader would unpickle."""
    from safetensors.torch import save_file

    state = agent.policy_state()
    # save_file refuses non-contiguous tensors; a transposed parameter would be one.
    tensors = {name: tensor.contiguous() for name, tensor in state["policy"].items()}
    save_file(tensors, str(path), metadata={"format": state["format"], "member": agent.id})
    path.chmod(0o666 & ~_umask())  # save_file writes 0600 whatever the umask; card.json does not
    _fsync(path)


def _write_policy(agent: Agent, graph: PolicyGraph, path: Path, export_format: str) -> None:
    if export_format == "safetensors":
        _write_weights(agent, path)
    else:
        _write_graph(graph, path, export_format)


def _umask() -> int:
    mask = os.umask(0)  # reading the umask means setting it: put it straight back
    os.umask(mask)
    return mask


def _fsync(path: Path) -> None:
    with path.open("rb") as handle:
        os.fsync(handle.fileno())


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
    staging.chmod(0o777 & ~_umask())  # mkdtemp makes 0700; a policy folder is as mkdir makes it
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
        _onnxruntime()  # before any work: the parity check needs it
    out = Path(out)
    _refuse_to_overwrite(out, force)
    knobs = knob_limits(source.config)
    graph = PolicyGraph(source.agent, [knob["max_step"] for knob in knobs])
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    try:
        policy_path = staging / EXPORT_FORMATS[export_format]
        _write_policy(source.agent, graph, policy_path, export_format)
        interface = PolicyInterface(
            graph.input_names, graph.output_names, graph.max_step.tolist(), source.agent.spec
        )
        run, runtime = _load_runner(policy_path, export_format, interface)
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


# --- loading ----------------------------------------------------------------------------


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

    @property
    def memory_length(self) -> int:
        return int(self.card["memory"]["length"])

    def initial_memory(self, batch: int = 1) -> dict[str, np.ndarray]:
        """The memory inputs of an alignment's first step (empty for a window-only policy)."""
        memory = {}
        for entry in self.card["inputs"][1:]:
            shape = [batch if size == "batch" else int(size) for size in entry["shape"]]
            memory[entry["name"]] = np.zeros(shape, np.float32)
        return memory

    def run(
        self, history: np.ndarray, memory: dict[str, np.ndarray] | None = None
    ) -> dict[str, np.ndarray]:
        """Every output (action, knob_step, memory_out_*...) for a batch (B, H, F) of
        histories; `memory` defaults to empty. Float32, batch first."""
        history = np.asarray(history, np.float32)
        if history.ndim != 3 or history.shape[1:] != (self.history, self.features):
            raise ValueError(
                f"{self.folder}: the policy takes histories of shape (batch, {self.history}, "
                f"{self.features}), got {history.shape}"
            )
        inputs = {"history": history, **(memory or self.initial_memory(len(history)))}
        return self._run(inputs)

    def act(self, history: np.ndarray) -> np.ndarray:
        """Actions in [-1, 1] for one history (H, F) -> (k+1,) or a batch (B, H, F) ->
        (B, k+1), float64; a memory policy starts from empty memory, as Agent.act does."""
        history = np.asarray(history, np.float32)
        single = history.ndim == 2
        action = self.run(history[None] if single else history)["action"].astype(np.float64)
        return action[0] if single else action


def _card_spec(member: dict[str, Any]) -> MemberSpec:
    """The member spec that card.json's `member` carries (MemberSpec.to_dict and more)."""
    return MemberSpec.from_dict({f.name: member[f.name] for f in dataclasses.fields(MemberSpec)})


def sha256_of(path: Path) -> str:
    """The policy file's SHA-256, hex: card.json's `policy_sha256`."""
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


PROBE_HISTORIES = 8  # histories a loaded policy answers before it is handed out


def _probe(run: Runner, card: dict[str, Any], policy_path: Path, max_step: np.ndarray) -> None:
    """Run a freshly loaded policy file on a zero history and a few random ones, as its card
    describes them: it must take the card's inputs, give the card's outputs in their shapes,
    every value finite, and knob_step = action x the card's max_step. A file of another
    member, or a card whose steps were edited, is refused here, before any instrument."""
    knobs = len(max_step)
    history, features = int(card["history"]), int(card["features"])
    rng = np.random.default_rng(0)
    histories = random_histories(PROBE_HISTORIES, history, features, rng, knobs)
    histories[0] = 0.0  # the first call of an alignment sees a padded, empty history
    inputs: dict[str, np.ndarray] = {"history": histories}
    for entry in card["inputs"][1:]:
        shape = [PROBE_HISTORIES if size == "batch" else int(size) for size in entry["shape"]]
        inputs[entry["name"]] = np.zeros(shape, np.float32)
    try:
        outputs = run(inputs)
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
    expected = action[:, :knobs].astype(np.float64) * max_step
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
    card (Agent.act). The card is checked field by field (alignrl.deploy.card.check_card),
    the policy file against it (its tensors, its outputs on a few histories, its SHA-256
    where the card has one): a missing, corrupt or tampered card or policy file is an
    ExportError naming the file and what is wrong; ONNX without onnxruntime installed is an
    ImportError."""
    from alignrl.deploy.card import check_card

    path = Path(path)
    folder = path if path.is_dir() else path.parent
    card_path = folder / "card.json"
    if not card_path.is_file():
        raise ExportError(
            f"{card_path} is missing: {folder} is not an exported policy "
            "(`alignrl export` writes card.json beside the policy file)"
        )
    try:
        card = json.loads(card_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ExportError(f"{card_path} is not valid JSON ({error})") from None
    task = check_card(card, card_path)
    export_format = card["export_format"]
    policy_path = folder / card["policy_file"]
    max_step = np.array([knob["max_step"] for knob in card["knobs"]], np.float64)
    interface = PolicyInterface(
        input_names=[entry["name"] for entry in card["inputs"]],
        output_names=[entry["name"] for entry in card["outputs"]],
        max_step=max_step.tolist(),
        # Only weights need the member: a graph carries its own network.
        spec=_card_spec(card["member"]) if export_format == "safetensors" else None,
    )
    run, runtime = _load_runner(policy_path, export_format, interface)
    _probe(run, card, policy_path, max_step)
    recorded = card.get("policy_sha256")
    if recorded is not None and sha256_of(policy_path) != recorded:
        raise ExportError(
            f"{card_path}: policy_sha256 {recorded} is not the SHA-256 of {policy_path} "
            f"({sha256_of(policy_path)}): the card and the policy file are not of one export; "
            "export it again"
        )
    history, features = int(card["history"]), int(card["features"])
    return ExportedPolicy(folder, card, task, history, features, max_step, runtime, run)

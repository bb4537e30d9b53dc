"""The policy file of each export format: how a policy is written as one (`write_policy`)
and opened again as a `Runner` (`load_runner`), and its SHA-256.

    onnx          policy.onnx          the traced PolicyGraph, run by onnxruntime
    torchscript   policy.pt            the traced PolicyGraph (torch.jit.save), torch.jit.load
    safetensors   policy.safetensors   the acting network's tensors alone (Agent.policy_state):
                                       no graph and no pickle; the member rebuilt from its
                                       spec runs them by Agent.act

`save_tensors` writes any named tensors as safetensors (the learner state beside a policy,
alignrl.deploy.learner_state, too).

Every file is checked as it is opened: finite weights, and for safetensors exactly the
network's tensors. A missing or unreadable file is an ExportError naming it. Each file is
fsynced once written (alignrl.checkpoints): the export publishes the folder it lies in.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from alignrl.agents.agent import Agent, finite_problem
from alignrl.checkpoints import current_umask, fsync_file
from alignrl.deploy.graph import PolicyGraph, PolicyInterface, Runner, random_histories
from alignrl.envs.task import knob_change
from alignrl.runs.learner_state import file_sha256
from alignrl.runs.sources import ExportError

__all__ = [
    "EXPORT_FORMATS",
    "ONNX_MISSING",
    "ONNX_OPSET",
    "current_umask",  # from alignrl.checkpoints, named here for older importers
    "import_onnxruntime",
    "load_runner",
    "save_tensors",
    "sha256_of",
    "write_policy",
]

EXPORT_FORMATS = {  # format -> file name
    "onnx": "policy.onnx",
    "torchscript": "policy.pt",
    "safetensors": "policy.safetensors",
}
ONNX_OPSET = 17  # LayerNormalization is a single operator from 17 on
ONNX_MISSING = (
    "ONNX export and ONNX policies need onnx and onnxruntime: pip install 'alignrl[onnx]'"
)


# --- opening a policy file ------------------------------------------------------------


def import_onnxruntime() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise ImportError(ONNX_MISSING) from None
    return onnxruntime


def _onnx_runner(path: Path) -> tuple[Runner, str]:
    onnxruntime = import_onnxruntime()
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
    graph = PolicyGraph(agent, interface.max_step, interface.action_power, interface.move_floor)
    max_step, floor = graph.max_step.numpy(), graph.move_floor.numpy()

    @torch.no_grad()
    def run(inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        history = np.asarray(inputs["history"], np.float32)
        action = agent.act(history, deterministic=True).astype(np.float32)  #      (batch, k+1)
        knob_step = knob_change(action[:, : graph.knobs], max_step, graph.action_power, floor)
        return {"action": action, "knob_step": knob_step.astype(np.float32)}

    return run, f"torch {torch.__version__}: Agent.act on the safetensors weights"


def load_runner(path: Path, export_format: str, interface: PolicyInterface) -> tuple[Runner, str]:
    """Open an exported policy file; a missing or unreadable file is an ExportError naming
    it."""
    if not path.is_file():
        raise ExportError(f"policy file {path} is missing")
    if export_format == "onnx":
        import_onnxruntime()  # a missing runtime is an ImportError of its own, not a corrupt file
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


def sha256_of(path: Path) -> str:
    """The policy file's SHA-256, hex: card.json's `policy_sha256` (one reader of digests,
    alignrl.runs.learner_state's)."""
    return file_sha256(path)


# --- writing a policy file ------------------------------------------------------------


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
    )
    with warnings.catch_warnings(), torch.no_grad():
        # Tracing warns about the encoders' shape checks (constants of a fixed-shape graph,
        # as intended) and about the TorchScript-based ONNX exporter: no news to a user.
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        if export_format == "onnx":
            import_onnxruntime()
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
    fsync_file(path)


def save_tensors(path: Path, tensors: dict[str, Tensor], metadata: dict[str, str]) -> None:
    """`tensors` as one safetensors file at `path` (a new file in an export's staging
    folder): raw tensors and a header of strings, nothing a loader would unpickle. Made
    contiguous (save_file refuses a transposed parameter) and on the CPU; fsynced, with the
    permissions the umask gives (save_file writes 0600 whatever the umask; card.json does
    not)."""
    from safetensors.torch import save_file

    save_file(
        {name: tensor.detach().cpu().contiguous() for name, tensor in tensors.items()},
        str(path),
        metadata=metadata,
    )
    path.chmod(0o666 & ~current_umask())
    fsync_file(path)


def _write_weights(agent: Agent, path: Path) -> None:
    """The acting network's tensors (Agent.policy_state) as safetensors."""
    state = agent.policy_state()
    save_tensors(path, state["policy"], {"format": state["format"], "member": agent.id})


def write_policy(agent: Agent, graph: PolicyGraph, path: Path, export_format: str) -> None:
    if export_format == "safetensors":
        _write_weights(agent, path)
    else:
        _write_graph(graph, path, export_format)

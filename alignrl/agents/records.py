"""What a saved member may hold, checked before anything is loaded from it.

A member file comes from disk: a hand-edited, truncated or foreign one must be refused with
a message naming the first field or tensor that is wrong, never half-loaded and never run.
`check_record` checks a spec's fields by type, `check_tensors` a network's weights (names,
shapes, dtypes, finite values), `check_learner_state` a learner's whole state (its networks,
its optimizers' running statistics, its counters).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from alignrl.agents.learners import Learner

__all__ = [
    "MAX_SIZE",
    "check_learner_state",
    "check_optimizer",
    "check_record",
    "check_tensors",
    "finite_problem",
    "is_integer",
    "is_number",
    "tensor_problem",
]

MAX_SIZE = 1 << 16  # rows, features, actions or hidden units: beyond it a record is not ours


def is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_record(data: dict[str, Any]) -> None:
    """The types of a member record's fields (MemberSpec.from_dict); ValueError naming the
    first field that is wrong."""

    def size(value: Any, low: int) -> bool:
        return is_integer(value) and low <= value <= MAX_SIZE

    for name in ("id", "team", "algorithm"):
        if not isinstance(data[name], str):
            raise ValueError(f"member record field {name} is {data[name]!r}, not a string")
    shape = data["observation_shape"]
    if not (isinstance(shape, list | tuple) and len(shape) == 2 and all(size(n, 1) for n in shape)):
        raise ValueError(
            f"member record field observation_shape is {shape!r}: it must be [history rows, "
            f"features], two whole numbers from 1 to {MAX_SIZE}"
        )
    if not size(data["action_dim"], 1):
        raise ValueError(
            f"member record field action_dim is {data['action_dim']!r}: it must be a whole "
            f"number from 1 to {MAX_SIZE}"
        )
    if not size(data["secret_dim"], 0):
        raise ValueError(
            f"member record field secret_dim is {data['secret_dim']!r}, not a whole number >= 0"
        )
    hyperparameters = data.get("hyperparameters", {})
    if not isinstance(hyperparameters, dict) or not all(map(_is_name, hyperparameters)):
        raise ValueError("member record field hyperparameters is not a mapping of names")
    hidden = hyperparameters.get("hidden", [1])
    if not (isinstance(hidden, list | tuple) and all(size(n, 1) for n in hidden)):
        raise ValueError(
            f"member record field hyperparameters.hidden is {hidden!r}: it must be a list of "
            f"layer widths, whole numbers from 1 to {MAX_SIZE}"
        )
    for name, value in hyperparameters.items():
        if is_number(value) and not math.isfinite(value):
            raise ValueError(f"member record field hyperparameters.{name} is {value}")
    parent = data.get("parent")
    if parent is not None and not isinstance(parent, str):
        raise ValueError(f"member record field parent is {parent!r}, not a string or null")


def _is_name(key: Any) -> bool:
    return isinstance(key, str)


def _shape(shape: Sequence[int]) -> str:
    return "(" + ", ".join(str(n) for n in shape) + ("," if len(shape) == 1 else "") + ")"


def tensor_problem(name: str, held: Any, wanted: torch.Tensor) -> str | None:
    """What is wrong with the saved `held` where the network has `wanted`, in words naming
    the tensor; None where it fits (same shape and dtype, every value finite)."""
    if not isinstance(held, torch.Tensor):
        return (
            f"{name} is a {type(held).__name__}, where the spec needs a tensor of shape "
            f"{_shape(wanted.shape)}"
        )
    if held.shape != wanted.shape:
        return f"{name} has shape {_shape(held.shape)}, the spec needs {_shape(wanted.shape)}"
    if held.dtype != wanted.dtype:
        dtypes = (str(held.dtype), str(wanted.dtype))
        found, needed = (text.removeprefix("torch.") for text in dtypes)
        return f"{name} is {found}, the spec needs {needed}"
    return finite_problem(name, held)


def finite_problem(name: str, tensor: torch.Tensor) -> str | None:
    """A tensor holding NaN or infinity, in words; None where every value is finite. A
    network with such a weight answers NaN: it is refused when loaded, never run."""
    if not (tensor.is_floating_point() or tensor.is_complex()):
        return None
    bad = int((~torch.isfinite(tensor)).sum())
    if not bad:
        return None
    return f"{name} contains non-finite values ({bad} of {tensor.numel()} are NaN or infinite)"


def check_tensors(held: Any, wanted: Mapping[str, torch.Tensor], where: str) -> None:
    """The saved tensors `held` are exactly a network's `wanted` ones (names, shapes,
    dtypes, finite values); else ValueError naming the first that is not."""
    if not isinstance(held, dict):
        raise ValueError(f"{where} is a {type(held).__name__}, where the spec needs tensors")
    for name, tensor in wanted.items():
        if name not in held:
            raise ValueError(
                f"{where}.{name} is missing: the spec needs a tensor of shape "
                f"{_shape(tensor.shape)}"
            )
        problem = tensor_problem(f"{where}.{name}", held[name], tensor)
        if problem:
            raise ValueError(problem)
    unexpected = sorted(set(map(str, held)) - set(wanted))
    if unexpected:
        raise ValueError(f"{where}.{unexpected[0]} is not a tensor of the spec's network")


def check_optimizer(held: Any, optimizer: torch.optim.Optimizer, where: str) -> None:
    """A saved optimizer state fits `optimizer`: as many parameters per group, and each
    parameter's running statistics shaped as the parameter and finite."""
    if not isinstance(held, dict) or set(held) != {"state", "param_groups"}:
        raise ValueError(f"{where} is not an optimizer state (keys state and param_groups)")
    groups = held["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(optimizer.param_groups):
        count = len(groups) if isinstance(groups, list) else type(groups).__name__
        raise ValueError(
            f"{where}.param_groups holds {count} group(s), the spec's optimizer has "
            f"{len(optimizer.param_groups)}"
        )
    parameters: dict[Any, torch.Tensor] = {}
    for index, (saved, own) in enumerate(zip(groups, optimizer.param_groups, strict=True)):
        ids = saved.get("params") if isinstance(saved, dict) else None
        if not isinstance(ids, list) or len(ids) != len(own["params"]):
            count = len(ids) if isinstance(ids, list) else "no list of"
            raise ValueError(
                f"{where}.param_groups[{index}] holds {count} parameters, the spec's network "
                f"has {len(own['params'])}"
            )
        for name, value in saved.items():
            if is_number(value) and not math.isfinite(value):
                raise ValueError(f"{where}.param_groups[{index}].{name} is {value}")
        parameters.update(zip(ids, own["params"], strict=True))
    state = held["state"]
    if not isinstance(state, dict):
        raise ValueError(f"{where}.state is a {type(state).__name__}, not a mapping")
    for key, entry in state.items():
        if key not in parameters or not isinstance(entry, dict):
            raise ValueError(f"{where}.state[{key!r}] belongs to no parameter of the network")
        for name, value in entry.items():
            if not isinstance(value, torch.Tensor):
                continue
            label = f"{where}.state[{key}].{name}"
            if value.ndim and value.shape != parameters[key].shape:
                raise ValueError(
                    f"{label} has shape {_shape(value.shape)}, the spec needs "
                    f"{_shape(parameters[key].shape)}"
                )
            problem = finite_problem(label, value)
            if problem:
                raise ValueError(problem)


def check_learner_state(held: Any, learner: Learner) -> None:
    """A saved learner state (`Learner.state_dict`) fits `learner`: the same keys,
    each network's tensors shaped as this learner's, finite, and its optimizers' statistics
    shaped as their parameters; else ValueError naming the first key or tensor that does
    not ("learner.actor.head.0.weight has shape (64, 256), the spec needs (16, 256)")."""
    wanted = learner.state_dict()
    if not isinstance(held, dict):
        raise ValueError(f"learner is a {type(held).__name__}, not a learner's state")
    for key, value in wanted.items():
        where = f"learner.{key}"
        if key not in held:
            raise ValueError(f"{where} is missing from the saved state")
        own = getattr(learner, key, None)
        if isinstance(own, torch.nn.Module):
            check_tensors(held[key], value, where)
        elif isinstance(own, torch.optim.Optimizer):
            check_optimizer(held[key], own, where)
        elif isinstance(value, torch.Tensor):
            problem = tensor_problem(where, held[key], value)
            if problem:
                raise ValueError(problem)
        elif is_integer(value) and not (is_integer(held[key]) and held[key] >= 0):
            raise ValueError(f"{where} is {held[key]!r}, not a whole number >= 0")
        elif isinstance(value, dict) and not isinstance(held[key], dict):
            raise ValueError(f"{where} is a {type(held[key]).__name__}, not a mapping")
    unexpected = sorted(set(map(str, held)) - set(wanted))
    if unexpected:
        raise ValueError(f"learner.{unexpected[0]} is not part of a {learner.title} state")

"""The learner state of an exported aligner, read: what `alignrl adapt` and a roster's
`init_from` train on from, shipped beside the policy as safetensors and JSON, never pickled.
alignrl.deploy.learner_state writes it (`alignrl export --with-learner-state`);
alignrl.runs.sources reads it here when it resolves an export or a champion.

An export folder with a learner state holds, besides policy.safetensors and card.json:

    learner.safetensors  every tensor of the member's learner state (Agent.state_dict
                         without its experience): SAC's actor, critics q1 and q2, value v
                         and its target copy v_target, log_alpha (the entropy coefficient),
                         and each optimizer's running statistics (Adam's step, exp_avg and
                         exp_avg_sq of every parameter); PPO's policy, value and optimizer
                         in the same way
    learner.json         everything else, strict JSON: the member spec, the counters
                         (steps_seen, update_debt, updates), the optimizers' param-group
                         settings, the learner's settings, the run settings the source
                         trained with (task, task options, history, apparatus, learner), its
                         knob limits, and the SHA-256 of learner.safetensors and of the
                         policy file it belongs with

A learner state is a tree of mappings, lists and tuples whose leaves are tensors and plain
values. learner.json's `state` is that tree with each tensor replaced by {"$tensor": NAME},
NAME its path joined by "/" ("q1/head.0.weight", "critic_optimizer/state/3/exp_avg"), which
is its key in learner.safetensors. Two more markers keep what JSON cannot say:
{"$tuple": [...]} (Adam's betas) and {"$int_keys": {...}} (an optimizer's state, keyed by
parameter index). `split_state` and `join_state` turn one form into the other.

`load_learner_state` reads the pair strictly, and leaves the member untouched unless all of
it fits: card.json must describe the same member (spec, steps seen, updates, task, history,
knob limits); learner.json must name exactly the tensors learner.safetensors holds; every
tensor must be finite and shaped as the member's networks and optimizers need
(alignrl.agents.records); its acting network must be the policy file's; and both files must
have the SHA-256 that learner.json records. Anything else is a LearnerStateError (a
ValueError; sources turns it into its LearnerStateError) naming the file and the key.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from alignrl.agents.agent import MEMBER_FORMAT, Agent, check_learner_state, finite_problem
from alignrl.agents.records import is_integer, is_number

__all__ = [
    "LEARNER_FILE",
    "LEARNER_FORMAT",
    "LEARNER_KEYS",
    "LEARNER_RECORD",
    "POLICY_FILE",
    "RUN_KEYS",
    "LearnerStateError",
    "file_sha256",
    "has_learner_state",
    "join_state",
    "learner_record",
    "load_learner_state",
    "read_json_file",
    "split_state",
    "state_difference",
]

LEARNER_FORMAT = "alignrl-learner-state-1"
LEARNER_FILE = "learner.safetensors"
LEARNER_RECORD = "learner.json"
POLICY_FILE = "policy.safetensors"  # the only policy file a learner state goes with
TENSOR, TUPLE, INT_KEYS = "$tensor", "$tuple", "$int_keys"
MARKERS = (TENSOR, TUPLE, INT_KEYS)
HEX = set("0123456789abcdef")
# How deep a card.json or learner.json may nest (theirs: 4 and 7) and how large learner.json
# may be (an export's: 20 kB; its tensors are in learner.safetensors)
MAX_JSON_DEPTH = 64
MAX_LEARNER_RECORD_BYTES = 16 << 20
LEARNER_KEYS = (  # learner.json, in the order it is written
    "format",
    "learner_file",
    "learner_sha256",
    "policy_file",
    "policy_sha256",
    "member",
    "steps_seen",
    "update_debt",
    "updates",
    "tensors",
    "state",
    "run",
    "knobs",
    "source",
    "written_by",
)
# The run settings learner.json records (those of alignrl.config.run.RunConfig that say what the
# member was trained on and for), besides its learner.
RUN_KEYS = (
    "task",
    "task_options",
    "history",
    "apparatus",
    "apparatus_args",
    "eval_apparatus",
    "eval_apparatus_args",
    "complexity",
    "envs",
    "seed",
)


class LearnerStateError(ValueError):
    """A learner state that cannot be written or read: named by file and key."""


def file_sha256(path: Path) -> str:
    """A file's SHA-256, hex (learner.json records that of both safetensors files)."""
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def has_learner_state(folder: Path) -> bool:
    """Whether an export folder ships a learner state (either of its two files: one
    without the other is a damaged export, which load_learner_state names)."""
    return (folder / LEARNER_FILE).exists() or (folder / LEARNER_RECORD).exists()


# --- the tree and its tensors ---------------------------------------------------------------


def split_state(state: Any) -> tuple[Any, dict[str, Tensor]]:
    """A learner state as (plain JSON values with a {"$tensor": NAME} where each tensor was,
    the tensors by NAME). LearnerStateError naming the place of a value that JSON and safetensors
    cannot hold (a non-finite number, an object)."""
    tensors: dict[str, Tensor] = {}

    def walk(value: Any, path: tuple[str, ...]) -> Any:
        where = "/".join(path) or "(the whole state)"
        if isinstance(value, Tensor):
            if where in tensors:
                raise LearnerStateError(f"learner state: two tensors would both be named {where!r}")
            # A copy of its own: safetensors refuses tensors sharing memory, and a view
            # would write its whole storage.
            tensors[where] = value.detach().cpu().contiguous().clone()
            return {TENSOR: where}
        if isinstance(value, np.generic):
            value = value.item()
        if value is None or isinstance(value, str | bool | int):
            return value
        if isinstance(value, float):
            if not math.isfinite(value):
                raise LearnerStateError(f"learner state {where} is {value}: it cannot be exported")
            return value
        if isinstance(value, tuple):
            return {TUPLE: [walk(item, (*path, str(i))) for i, item in enumerate(value)]}
        if isinstance(value, list):
            return [walk(item, (*path, str(i))) for i, item in enumerate(value)]
        if isinstance(value, dict):
            if all(isinstance(key, str) and not key.startswith("$") for key in value):
                return {key: walk(item, (*path, key)) for key, item in value.items()}
            if all(is_integer(key) for key in value):
                inner = {str(key): walk(item, (*path, str(key))) for key, item in value.items()}
                return {INT_KEYS: inner}
            raise LearnerStateError(
                f"learner state {where}: keys {list(value)[:4]!r} are not names"
            )
        raise LearnerStateError(
            f"learner state {where} is a {type(value).__name__}, which safetensors and JSON "
            "cannot hold"
        )

    return walk(state, ()), tensors


def join_state(tree: Any, tensors: Mapping[str, Tensor], record: Path, weights: Path) -> Any:
    """The learner state that `split_state` split: `tree` (learner.json's `state`, read from
    `record`) with each marker replaced by what it stands for, tensors from `weights`.
    LearnerStateError naming the file and the key where a marker is malformed, a tensor named is
    missing or named twice, or a tensor is named nowhere."""
    used: set[str] = set()

    def bad(path: tuple[str, ...], problem: str) -> LearnerStateError:
        where = ".".join(("state", *path))
        return LearnerStateError(f"{record}: {where} {problem}; export it again")

    def walk(node: Any, path: tuple[str, ...]) -> Any:
        if isinstance(node, list):
            return [walk(item, (*path, str(i))) for i, item in enumerate(node)]
        if not isinstance(node, dict):
            return node
        marked = [key for key in node if key.startswith("$")]
        if not marked:
            return {key: walk(item, (*path, key)) for key, item in node.items()}
        if len(node) != 1 or marked[0] not in MARKERS:
            keys = ", ".join(map(repr, node))
            raise bad(path, f"holds {keys}; a marker stands alone, one of {', '.join(MARKERS)}")
        inner = node[marked[0]]
        if marked[0] == TENSOR:
            if not isinstance(inner, str):
                raise bad(path, f"names tensor {inner!r}, not a name")
            if inner not in tensors:
                raise LearnerStateError(
                    f"{weights} has no tensor {inner!r}, which {record} names at "
                    f"{'.'.join(('state', *path))}: the two files are not of one export; "
                    "export it again"
                )
            if inner in used:
                raise bad(path, f"names tensor {inner!r} a second time")
            used.add(inner)
            return tensors[inner]
        if marked[0] == TUPLE:
            if not isinstance(inner, list):
                raise bad(path, f"is a {TUPLE} of a {type(inner).__name__}, not a list")
            return tuple(walk(item, (*path, str(i))) for i, item in enumerate(inner))
        if not isinstance(inner, dict) or not all(_is_index(key) for key in inner):
            raise bad(path, f"is an {INT_KEYS} mapping whose keys are not whole numbers")
        return {int(key): walk(item, (*path, key)) for key, item in inner.items()}

    state = walk(tree, ())
    unnamed = sorted(set(tensors) - used)
    if unnamed:
        raise LearnerStateError(
            f"{weights} holds tensor {unnamed[0]!r}, which {record} names nowhere: the two "
            "files are not of one export; export it again"
        )
    return state


def _is_index(key: str) -> bool:
    return key.isascii() and key.isdigit()


def state_difference(held: Any, wanted: Any, where: str = "learner") -> str | None:
    """Where two learner states differ, in words (tensors compared value for value, dtype
    and shape included); None where they are equal."""
    if isinstance(wanted, Tensor) or isinstance(held, Tensor):
        same = (
            isinstance(held, Tensor)
            and isinstance(wanted, Tensor)
            and held.dtype == wanted.dtype
            and torch.equal(held.cpu(), wanted.cpu())
        )
        return None if same else f"{where} differs"
    if isinstance(wanted, dict):
        if not isinstance(held, dict) or set(held) != set(wanted):
            return f"{where} has other keys"
        for key in wanted:
            difference = state_difference(held[key], wanted[key], f"{where}.{key}")
            if difference:
                return difference
        return None
    if isinstance(wanted, list | tuple):
        if type(held) is not type(wanted) or len(held) != len(wanted):
            return f"{where} is not the same sequence"
        for index, (mine, theirs) in enumerate(zip(held, wanted, strict=True)):
            difference = state_difference(mine, theirs, f"{where}[{index}]")
            if difference:
                return difference
        return None
    if is_number(held) and is_number(wanted):  # 0 and 0.0 are one count
        return None if held == wanted else f"{where} differs"
    return None if held == wanted and type(held) is type(wanted) else f"{where} differs"


# --- reading --------------------------------------------------------------------------------


class _TwiceNamed(Exception):
    """A key named twice in one JSON object (read_json_file's hook)."""


def _once(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            raise _TwiceNamed(key)
        seen.add(key)
    return dict(pairs)


def _depth(value: Any) -> int:
    """How deep mappings and lists nest in `value` (0: a plain value), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict | list):
            deepest = max(deepest, depth + 1)
            stack.extend(
                (item, depth + 1) for item in (node.values() if isinstance(node, dict) else node)
            )
    return deepest


def read_json_file(
    path: Path,
    limit: int,
    error: type[ValueError],
    what: str,
    finite: bool = False,
) -> Any:
    """The JSON of an export's file (card.json, learner.json), read strictly: refused by its
    size before it is parsed (more than `limit` bytes), a key named twice in one object
    (named), nesting deeper than MAX_JSON_DEPTH (Python's own limit too: no RecursionError
    escapes), text that is not UTF-8 JSON, and with `finite`, NaN and Infinity. Each refusal
    is an `error` naming the file; `what` says what the file is ("a card")."""

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not a JSON number")

    try:
        with path.open("rb") as handle:  # a FIFO or /dev/zero named card.json: read no more
            size = os.fstat(handle.fileno()).st_size
            data = handle.read(limit + 1) if size <= limit else b""
    except OSError as problem:
        raise error(f"{path} cannot be read ({problem.strerror or problem})") from None
    if size > limit or len(data) > limit:
        shown = f"{size:,} bytes" if size > limit else f"more than {limit:,} bytes"
        raise error(
            f"{path} is {shown}, more than the {limit:,} bytes {what} may take: it is not "
            "one alignrl wrote; export it again"
        )
    try:
        value = json.loads(
            data.decode("utf-8"),
            object_pairs_hook=_once,
            **({"parse_constant": refuse} if finite else {}),
        )
    except _TwiceNamed as twice:
        key = str(twice.args[0])
        raise error(
            f"{path}: key {key[:80]!r} is named twice in one object (JSON readers differ on "
            "which one counts); export it again"
        ) from None
    except RecursionError:
        raise error(
            f"{path} nests too deeply to read (more than {MAX_JSON_DEPTH} levels): it is not "
            f"{what} alignrl wrote; export it again"
        ) from None
    except (UnicodeDecodeError, ValueError) as problem:  # JSONDecodeError, 5,000-digit ints
        raise error(f"{path} is not valid JSON ({str(problem)[:300]}); export it again") from None
    if _depth(value) > MAX_JSON_DEPTH:
        raise error(
            f"{path} nests more than {MAX_JSON_DEPTH} levels deep: it is not {what} alignrl "
            "wrote; export it again"
        )
    return value


def _strict_json(path: Path) -> Any:
    return read_json_file(
        path, MAX_LEARNER_RECORD_BYTES, LearnerStateError, "a learner record", finite=True
    )


def _read_record(record_path: Path) -> dict[str, Any]:
    record = _strict_json(record_path)
    if not isinstance(record, dict):
        raise LearnerStateError(
            f"{record_path} holds a {type(record).__name__}, not a learner record"
        )
    if record.get("format") != LEARNER_FORMAT:
        raise LearnerStateError(
            f"{record_path}: format {record.get('format')!r} is not {LEARNER_FORMAT}"
        )
    missing = [key for key in LEARNER_KEYS if key not in record]
    if missing:
        raise LearnerStateError(
            f"{record_path} has no {missing[0]}: it is incomplete; export it again"
        )
    unknown = sorted(set(record) - set(LEARNER_KEYS))
    if unknown:
        raise LearnerStateError(f"{record_path}: unknown key {unknown[0]!r}")
    for key, wanted in (("learner_file", LEARNER_FILE), ("policy_file", POLICY_FILE)):
        if record[key] != wanted:
            raise LearnerStateError(f"{record_path}: {key} is {record[key]!r}, not {wanted}")
    for key in ("learner_sha256", "policy_sha256"):
        digest = record[key]
        if not (isinstance(digest, str) and len(digest) == 64 and set(digest) <= HEX):
            raise LearnerStateError(f"{record_path}: {key} is {digest!r}, not a SHA-256 in hex")
    for key in ("steps_seen", "updates", "tensors"):
        if not (is_integer(record[key]) and record[key] >= 0):
            raise LearnerStateError(
                f"{record_path}: {key} is {record[key]!r}, not a whole number >= 0"
            )
    debt = record["update_debt"]
    if not (is_number(debt) and math.isfinite(debt) and debt >= 0):
        raise LearnerStateError(f"{record_path}: update_debt is {debt!r}, not a finite number >= 0")
    for key in ("member", "state", "run", "source", "written_by"):
        if not isinstance(record[key], dict):
            raise LearnerStateError(
                f"{record_path}: {key} is a {type(record[key]).__name__}, not a mapping"
            )
    return record


def _plain(value: Any) -> Any:
    """`value` as JSON reads it back (tuples as lists): a card built in memory and one read
    from its file compare alike."""
    return json.loads(json.dumps(value))


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _first_difference(mine: Any, theirs: Any, where: str) -> tuple[str, Any, Any] | None:
    """Where two JSON values first differ: (dotted path, value, value), the innermost
    mapping key or list index that does; None where they are equal."""
    if isinstance(mine, dict) and isinstance(theirs, dict):
        for key in sorted(set(map(str, mine)) | set(map(str, theirs))):
            if key not in mine or key not in theirs:
                return f"{where}.{key}", mine.get(key, "nothing"), theirs.get(key, "nothing")
            found = _first_difference(mine[key], theirs[key], f"{where}.{key}")
            if found:
                return found
        return None
    if isinstance(mine, list) and isinstance(theirs, list) and len(mine) == len(theirs):
        for index, (one, other) in enumerate(zip(mine, theirs, strict=True)):
            found = _first_difference(one, other, f"{where}[{index}]")
            if found:
                return found
        return None
    alike = type(mine) is type(theirs) or (is_number(mine) and is_number(theirs))
    same = alike and mine == theirs
    return None if same else (where, mine, theirs)


def _agrees_with_card(
    record: dict[str, Any], card: Mapping[str, Any], spec: dict[str, Any], record_path: Path
) -> None:
    """learner.json describes the member (`spec`, card.json's member spec as a record),
    the run (task, task options, history, training and evaluation apparatus), the knob
    intervals and steps, and the source that card.json does: a LearnerStateError naming both
    files and the first field where they differ."""
    run, task, training = record["run"], card["task"], card.get("training") or {}
    pairs = [
        *(
            (f"member.{name}", record["member"].get(name), spec.get(name), f"member.{name}")
            for name in sorted(set(spec) | set(record["member"]))
        ),
        *(
            (key, record[key], card["member"][key], f"member.{key}")
            for key in ("steps_seen", "updates")
        ),
        ("run.task", run.get("task"), task["name"], "task.name"),
        ("run.task_options", run.get("task_options"), task["options"], "task.options"),
        ("run.history", run.get("history"), card["history"], "history"),
        *(
            (f"run.{key}", run.get(key), training.get(key), f"training.{key}")
            for key in ("apparatus", "apparatus_args", "eval_apparatus", "eval_apparatus_args")
        ),
        ("knobs", record["knobs"], card["knobs"], "knobs"),
        ("source", record["source"], card["source"], "source"),
    ]
    for key, mine, theirs, field in pairs:
        found = _first_difference(_plain(mine), _plain(theirs), key)
        if found:
            where, one, other = found
            field += where[len(key) :]
            raise LearnerStateError(
                f"{record_path}: {where} is {_shown(one)}, but card.json's {field} is "
                f"{_shown(other)}: the learner state and the policy are not of one export; "
                "export it again"
            )


def _read_tensors(path: Path, what: str) -> dict[str, Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        tensors = load_file(str(path), device="cpu")
    except (OSError, ValueError, RuntimeError, SafetensorError) as error:
        raise LearnerStateError(
            f"{path} cannot be read as safetensors ({str(error).strip()[:200]}): {what} may be "
            "truncated or corrupt; export it again"
        ) from None
    for name, tensor in tensors.items():
        problem = finite_problem(f"tensor {name!r}", tensor)
        if problem:
            raise LearnerStateError(f"{path}: {problem}; export it again from a sound member")
    return tensors


def learner_record(folder: Path, card: Mapping[str, Any], spec: dict[str, Any]) -> dict[str, Any]:
    """learner.json of the export `folder`, read strictly and checked against its card.json
    (`card`, whose member spec is `spec`): the same member, run, knob intervals and source
    (what `alignrl align` and `evaluate` check too, where they run an export that ships a
    learner state). LearnerStateError naming both files and the first field that differs, or
    where one of the pair is missing."""
    record_path, weights = folder / LEARNER_RECORD, folder / LEARNER_FILE
    for present, absent in ((record_path, weights), (weights, record_path)):
        if present.exists() and not absent.exists():
            raise LearnerStateError(
                f"{folder} holds {present.name} but no {absent.name}: its learner state is "
                "incomplete; export it again with --with-learner-state"
            )
    record = _read_record(record_path)
    _agrees_with_card(record, card, spec, record_path)
    return record


def load_learner_state(folder: Path, agent: Agent, card: Mapping[str, Any]) -> dict[str, Any]:
    """Load the learner state of the export `folder` into `agent` (the member its card.json,
    `card`, describes): critics, target critics, entropy coefficient, optimizers, counters,
    and the acting network again (which must be the policy file's). The learner record read;
    LearnerStateError naming the file and the key where anything does not fit, the agent then
    left as it was."""
    record_path, weights = folder / LEARNER_RECORD, folder / LEARNER_FILE
    policy_path = folder / POLICY_FILE
    record = learner_record(folder, card, agent.spec.to_dict())
    tensors = _read_tensors(weights, "the learner state")
    learner = join_state(record["state"], tensors, record_path, weights)
    if len(tensors) != record["tensors"]:
        raise LearnerStateError(
            f"{weights} holds {len(tensors)} tensors, {record_path} says {record['tensors']}: "
            "the record was changed after the export; export it again"
        )
    own = agent.learner.state_dict()
    if not isinstance(learner, dict):
        raise LearnerStateError(f"{record_path}: state is not a learner's state; export it again")
    if "config" in own:
        difference = state_difference(learner.get("config"), own["config"], "state.config")
        if difference:
            raise LearnerStateError(
                f"{record_path}: {difference} from the learner settings of card.json's member "
                "(member.hyperparameters): the learner state is of another member; export it "
                "again"
            )
    try:  # every network tensor and optimizer statistic, named as in the member's learner
        check_learner_state(learner, agent.learner)
    except ValueError as error:
        raise LearnerStateError(
            f"{weights} does not fit the member its card.json describes: {error}; export it again"
        ) from None
    if learner.get("updates") != record["updates"]:
        raise LearnerStateError(
            f"{record_path}: updates is {record['updates']}, its state.updates "
            f"{learner.get('updates')!r}; export it again"
        )
    acting = agent.learner.acting_network  # its part of the state: SAC's actor, PPO's policy
    name = next((key for key in own if getattr(agent.learner, key, None) is acting), None)
    policy = _read_tensors(policy_path, "the policy")
    difference = state_difference(learner[name], policy, name) if name else None
    if difference:
        raise LearnerStateError(
            f"{weights}: its {difference} from the policy in {policy_path}: the two files "
            "are not of one export; export it again"
        )
    for key, path in (("learner_sha256", weights), ("policy_sha256", policy_path)):
        if file_sha256(path) != record[key]:
            raise LearnerStateError(
                f"{record_path}: {key} {record[key]} is not the SHA-256 of {path}: the file "
                "was changed after the export; export it again"
            )
    try:
        agent.load_state_dict(
            {
                "format": MEMBER_FORMAT,
                "spec": record["member"],
                "learner": learner,
                "steps_seen": record["steps_seen"],
                "update_debt": record["update_debt"],
            }
        )
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise LearnerStateError(
            f"{weights} does not fit the member its card.json describes ({error}); export it again"
        ) from None
    return record

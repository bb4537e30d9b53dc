"""Overlays: an experiment YAML that names another as its `base:` and changes a few keys.

    base: ../../experiments/focus-sac-mlp.yaml   # relative to this file's folder
    name: focus-sac-mlp-bonus
    task_options: {success_bonus: 5.0}

The base is read first (it may itself be an overlay: chains are allowed, a cycle is an error),
then each overlay's keys are laid over it: a mapping merges key by key, recursively; a list or
a scalar replaces the value below it. A key cannot be removed, only given another value. What
comes out is an ordinary experiment, checked by the same strict models as any file
(alignrl.config), so a typo in an overlay is refused as one in any experiment is.

This module only reads files and merges mappings: the caller passes the reader, and turns an
OverlayError into its own kind of error.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "BASE_KEY",
    "Layers",
    "OverlayError",
    "apply_overrides",
    "merge",
    "parse_override",
    "resolve",
]

BASE_KEY = "base"  # the top-level key that makes a file an overlay


class OverlayError(ValueError):
    """An overlay chain that cannot be resolved; the message names the files."""


def merge(below: Mapping[str, Any], above: Mapping[str, Any]) -> dict[str, Any]:
    """`above` laid over `below`: mappings merge key by key, recursively; anything else in
    `above` (a list, a scalar, null) replaces what `below` has. Neither input is changed."""
    merged = dict(below)
    for key, value in above.items():
        under = merged.get(key)
        if isinstance(value, Mapping) and isinstance(under, Mapping):
            merged[key] = merge(under, value)
        else:
            merged[key] = value
    return merged


@dataclass(frozen=True)
class Layers:
    """A resolved experiment: its settings with every base merged in, and where they came
    from."""

    data: Any  # the merged settings (a mapping, unless the file itself is not one)
    files: tuple[Path, ...]  # the file asked for first, then its base, that one's base, ...

    @property
    def root(self) -> Path:
        """The last file of the chain: the experiment that has no base."""
        return self.files[-1]

    @property
    def source(self) -> str:
        """How messages name these settings: the file, followed by its bases where it has
        some (`a.yaml (base b.yaml)`)."""
        if len(self.files) == 1:
            return str(self.files[0])
        return f"{self.files[0]} (base {', base '.join(_shown(f) for f in self.files[1:])})"


def _shown(path: Path) -> str:
    """A path as a message shows it: a/b/../../c/d.yaml as c/d.yaml."""
    return os.path.normpath(path)


def resolve(path: str | Path, read: Callable[[Path], Any]) -> Layers:
    """The experiment in `path` with its chain of bases merged, every file read by `read`
    (which refuses what it cannot use). A `base:` is read relative to the folder of the file
    that names it. OverlayError for a base that is not a path, is missing, or leads back to a
    file of the chain."""
    files: list[Path] = []
    layers: list[Any] = []
    seen: set[Path] = set()  # the chain's files so far, resolved
    current = Path(path)
    while True:
        identity = current.resolve()
        if identity in seen:
            loop = " -> ".join(_shown(file) for file in (*files, current))
            raise OverlayError(f"{files[-1]}: its base leads back to {_shown(current)}: {loop}")
        seen.add(identity)
        data = read(current)
        files.append(current)
        if not isinstance(data, dict) or BASE_KEY not in data:
            layers.append(data)
            break
        base = data[BASE_KEY]
        if not isinstance(base, str) or not base.strip():
            raise OverlayError(
                f"{current}: {BASE_KEY}: expected the path of the experiment this file changes, "
                f"relative to its folder, e.g. ../../experiments/focus-sac-mlp.yaml "
                f"(found {base!r:.100})"
            )
        layers.append({key: value for key, value in data.items() if key != BASE_KEY})
        target = current.parent / base
        if not target.is_file():
            raise OverlayError(
                f"{current}: {BASE_KEY} {base} does not exist (looked for {_shown(target)}); "
                "a base is read relative to the folder of the file that names it"
            )
        current = target
    merged = layers[-1]
    if len(layers) > 1 and not isinstance(merged, dict):
        raise OverlayError(f"{current}: expected a mapping of settings at the top level")
    for layer in reversed(layers[:-1]):
        merged = merge(merged, layer)
    return Layers(data=merged, files=tuple(files))


# --- command-line overrides: --set key.path=value -----------------------------------------


def parse_override(assignment: str) -> tuple[list[str], Any]:
    """`key.path=value` as (the key path, the value read as YAML: 3, 1e-4, true, null, [1, 2],
    {a: 1}; anything else a string). OverlayError for a malformed assignment."""
    import yaml

    key, equals, text = assignment.partition("=")
    path = key.strip().split(".")
    if not equals or not all(part.strip() for part in path):
        raise OverlayError(
            f"--set {assignment!r}: expected key.path=value, e.g. budget.env_steps=2000"
        )
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as error:
        raise OverlayError(f"--set {assignment!r}: the value is not YAML ({error})") from None
    return [part.strip() for part in path], value


def _index(node: list[Any], part: str) -> int | None:
    return int(part) if part.isdigit() and int(part) < len(node) else None


def apply_overrides(data: Mapping[str, Any], assignments: list[str]) -> dict[str, Any]:
    """`data` with each `key.path=value` of `assignments` set, in order (a later one wins):
    a mapping on the way is entered (made where missing), a list by its index. What comes out
    is checked by the same strict models as a file, so an unknown key or a value out of range
    is refused with its key path. OverlayError where the path runs through anything else.
    `data` is not changed (every container on the path is copied)."""
    result = merge({}, data)
    for assignment in assignments:
        path, value = parse_override(assignment)
        node: Any = result
        for depth, part in enumerate(path):
            where = ".".join(path[:depth]) or "the config"
            if isinstance(node, list):
                key: Any = _index(node, part)
                if key is None:
                    raise OverlayError(
                        f"--set {assignment!r}: {where} is a list of {len(node)}; {part} is "
                        "not one of its indices"
                    )
            elif isinstance(node, dict):
                key = part
            else:
                raise OverlayError(
                    f"--set {assignment!r}: {where} is {node!r}, not a mapping to set {part} in"
                )
            if depth == len(path) - 1:
                node[key] = value
                break
            child = node[key] if isinstance(node, list) else node.get(key)
            if child is None:
                child = {}
            elif isinstance(child, Mapping):
                child = dict(child)
            elif isinstance(child, list):
                child = list(child)
            node[key] = child
            node = child
    return result

"""The one way alignrl reads YAML: yaml.SafeLoader, made strict and bounded.

Every YAML file alignrl reads (experiments, leagues, rosters, synthetic-SEM presets, a run's
config.yaml) passes through `read_yaml_file` or `parse_yaml`. On top of the safe loader:

* a key given twice in one mapping is an error naming the key and both lines (plain
  yaml.safe_load keeps the last silently);
* aliases are bounded: the document, with every alias (`*name`, `<<: *name`) expanded to the
  nodes it stands for, may hold at most MAX_NODES nodes and nest MAX_DEPTH deep, and an alias
  may not refer to a node that contains it. A "billion laughs" document is refused while it is
  composed, before anything is built, in milliseconds and bounded memory;
* a file holds at most MAX_FILE_BYTES of UTF-8 text.

This module imports only yaml, so that alignrl.apparatus may read its presets with it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

__all__ = [
    "MAX_DEPTH",
    "MAX_FILE_BYTES",
    "MAX_NODES",
    "YAMLInputError",
    "parse_yaml",
    "read_yaml_file",
]

MAX_FILE_BYTES = 1024 * 1024  # a config is a few KB; nothing alignrl reads comes near
MAX_NODES = 10_000  # scalars, lists and mappings, each alias counted as all it stands for
MAX_DEPTH = 64  # nesting of lists and mappings, aliases expanded
MESSAGE_TEXT = 300  # characters of the parser's own message kept in ours

MERGE_TAG = "tag:yaml.org,2002:merge"


class YAMLInputError(ValueError):
    """A YAML file or text that alignrl refuses; the message names the source and where."""


def _shortened(text: str, limit: int = MESSAGE_TEXT) -> str:
    return (
        text if len(text) <= limit else f"{text[:limit]}... ({len(text) - limit} more characters)"
    )


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader that counts nodes while composing (an alias counts as the nodes it stands
    for), bounds the nesting, and refuses duplicate mapping keys while constructing."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._nodes = 0  # nodes of the document so far, aliases expanded
        self._depth = 0  # lists and mappings open around the node being composed
        self._open_anchors: list[str] = []  # anchors of lists and mappings still open
        self._measured: dict[int, tuple[int, int]] = {}  # id(node) -> (nodes, depth)

    def _measure(self, node: Node) -> tuple[int, int]:
        """(nodes, nesting depth) of a composed node with its aliases expanded. Memoized per
        node, so a tower of aliases costs one visit per distinct node."""
        known = self._measured.get(id(node))
        if known is not None:
            return known
        if isinstance(node, ScalarNode):
            children: list[Node] = []
        elif isinstance(node, SequenceNode):
            children = node.value
        else:
            children = [part for pair in node.value for part in pair]
        sizes = [self._measure(child) for child in children]
        nodes = 1 + sum(count for count, _ in sizes)
        depth = (0 if isinstance(node, ScalarNode) else 1) + max((d for _, d in sizes), default=0)
        self._measured[id(node)] = (nodes, depth)
        return nodes, depth

    def _grow(self, nodes: int, depth: int, mark: Any) -> None:
        self._nodes += nodes
        line = f"line {mark.line + 1}: " if mark is not None else ""
        if self._nodes > MAX_NODES:
            raise YAMLInputError(
                f"{line}the document expands to more than {MAX_NODES} values (aliases counted "
                "as all they stand for: an alias bomb?); write the values out"
            )
        if self._depth + depth > MAX_DEPTH:
            raise YAMLInputError(
                f"{line}lists and mappings nest more than {MAX_DEPTH} deep (aliases expanded)"
            )

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            if event.anchor in self._open_anchors:
                raise YAMLInputError(
                    f"line {event.start_mark.line + 1}: alias *{_shortened(event.anchor, 50)} "
                    "refers to a list or mapping that contains it"
                )
            target = self.anchors.get(event.anchor)
            if target is not None:  # an undefined alias: the composer says so
                self._grow(*self._measure(target), event.start_mark)
            return super().compose_node(parent, index)
        event = self.peek_event()
        is_collection = isinstance(event, yaml.SequenceStartEvent | yaml.MappingStartEvent)
        self._grow(1, 1 if is_collection else 0, event.start_mark)
        anchor = getattr(event, "anchor", None)
        if is_collection:
            self._depth += 1
            if anchor is not None:
                self._open_anchors.append(anchor)
        try:
            return super().compose_node(parent, index)
        finally:
            if is_collection:
                self._depth -= 1
                if anchor is not None:
                    self._open_anchors.remove(anchor)

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, MappingNode):
            first_line: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == MERGE_TAG or not isinstance(key_node, ScalarNode):
                    continue  # merged keys may be overridden; complex keys: the loader decides
                key = self.construct_object(key_node)
                line = key_node.start_mark.line + 1
                if key in first_line:
                    raise YAMLInputError(
                        f"line {line}: key {_shortened(repr(key), 80)} is given twice (first at "
                        f"line {first_line[key]}); a key may appear once in a mapping"
                    )
                first_line[key] = line
        return super().construct_mapping(node, deep=deep)


def _not_text(text: str, error: yaml.YAMLError) -> str:
    """The reader's refusal of a character (a NUL byte, another control character) as the
    line, the column and the character, not the reader's own words."""
    position, character = getattr(error, "position", None), getattr(error, "character", None)
    if isinstance(character, str) and len(character) == 1:
        character = ord(character)
    if not isinstance(position, int) or not isinstance(character, int):
        return f"not valid YAML: {_shortened(str(error))}"
    line = text.count("\n", 0, position) + 1
    column = position - (text.rfind("\n", 0, position) + 1) + 1
    what = "a NUL byte: a binary file?" if character == 0 else "a control character"
    return (
        f"line {line}, column {column}: character U+{character:04X} ({what}) is not allowed "
        "in a YAML file"
    )


def parse_yaml(text: str, source: str) -> Any:
    """One YAML document from `text`, read safely and strictly (see the module docstring);
    None for an empty document. Any problem is a YAMLInputError naming `source`."""
    if len(text) > MAX_FILE_BYTES:
        raise YAMLInputError(f"{source}: {len(text)} characters of YAML; at most {MAX_FILE_BYTES}")
    try:
        loader = _BoundedLoader(text)  # its reader refuses what is no YAML text (a NUL byte)
    except yaml.YAMLError as error:
        raise YAMLInputError(f"{source}: {_not_text(text, error)}") from None
    try:
        return loader.get_single_data()
    except YAMLInputError as error:
        raise YAMLInputError(f"{source}: {error}") from None
    except yaml.YAMLError as error:
        raise YAMLInputError(f"{source}: not valid YAML: {_shortened(str(error))}") from None
    finally:
        loader.dispose()


def read_yaml_file(path: str | Path) -> Any:
    """The YAML document of a file (see `parse_yaml`); None for an empty file. A missing file
    is FileNotFoundError; a file over MAX_FILE_BYTES or not UTF-8 is a YAMLInputError."""
    path = Path(path)
    with open(path, "rb") as handle:
        data = handle.read(MAX_FILE_BYTES + 1)
    if len(data) > MAX_FILE_BYTES:
        raise YAMLInputError(
            f"{path}: more than {MAX_FILE_BYTES // (1024 * 1024)} MB; a YAML config is a few KB"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise YAMLInputError(
            f"{path}: not UTF-8 text ({error.reason} at byte {error.start})"
        ) from None
    return parse_yaml(text, str(path))

"""Print every key of alignrl's config files as Markdown tables, read from the pydantic models.

One table per kind of file (training experiment, league experiment, team roster): the key path,
its default, the values it accepts (type, bounds, choices) and the field's description, nested
models walked. docs/configs.md carries this output below its marker line, and
tests/test_configs_doc.py fails when the two differ.

    .venv/bin/python docs/gen_configs.py            # print the tables
    .venv/bin/python docs/gen_configs.py --write    # replace them in docs/configs.md
"""

from __future__ import annotations

import argparse
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic.functional_validators import BeforeValidator
from pydantic.types import AllowInfNan

from alignrl.config.experiment import ExperimentConfig
from alignrl.league.config import LeagueConfig, Roster

DOC = Path(__file__).resolve().with_name("configs.md")
MARKER = (
    "<!-- Everything below is printed by docs/gen_configs.py from the config models: change a "
    "field's description there, then run `.venv/bin/python docs/gen_configs.py --write`. -->"
)

# (heading, which files and which command read them, model)
SECTIONS: tuple[tuple[str, str, type[BaseModel]], ...] = (
    (
        "Training experiment",
        "Read by `alignrl train FILE`: the files of experiments/ and benchmarks/configs/ "
        "that name no rosters (experiments/README.md says which is which).",
        ExperimentConfig,
    ),
    (
        "League experiment",
        "Read by `alignrl league run FILE`: the files of experiments/ and benchmarks/configs/ "
        "that name rosters (`aligners`, `misaligners`), themselves or in their base.",
        LeagueConfig,
    ),
    (
        "Team roster",
        "Named by a league experiment's `aligners` and `misaligners`: populations/\\*.yaml.",
        Roster,
    ),
)

Row = tuple[str, str, str, str]  # key path, default, allowed values, meaning


def _escape(text: str) -> str:
    """Plain text made safe for a Markdown table cell (`runs/<name>/` is not an HTML tag)."""
    for character in "\\|<>*":
        text = text.replace(character, "\\" + character)
    return text


def _yaml(value: Any) -> str:
    """A value as one would write it in the YAML file (flow style)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | str):
        return str(value)
    if isinstance(value, float):
        return repr(value)  # exact, unlike a rounded format
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_yaml(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key}: {_yaml(item)}" for key, item in value.items()) + "}"
    if isinstance(value, BaseModel):
        # A nested block's default is written as the keys that differ from their own defaults.
        return _yaml(value.model_dump(mode="json", exclude_defaults=True))
    raise ValueError(f"no YAML rendering for the default {value!r}: teach _yaml() its type")


def _default(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    value = field.default_factory() if field.default_factory is not None else field.default
    return f"`{_yaml(value)}`"


def _nested(annotation: Any) -> tuple[type[BaseModel], bool] | None:
    """The model inside a field (and whether it is a list of them), or None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    if typing.get_origin(annotation) is list:
        (item,) = typing.get_args(annotation)
        if isinstance(item, type) and issubclass(item, BaseModel):
            return item, True
    return None


BOUNDS = {
    annotated_types.Ge: "ge",
    annotated_types.Gt: "gt",
    annotated_types.Le: "le",
    annotated_types.Lt: "lt",
    annotated_types.MinLen: "min_length",
    annotated_types.MaxLen: "max_length",
}


def _bounds(key: str, field: FieldInfo) -> dict[str, Any]:
    """The field's constraints by name: ge, gt, le, lt, min_length, max_length."""
    return _constraints(key, field.metadata)


def _constraints(key: str, metadata: list[Any]) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for item in metadata:
        if isinstance(item, BeforeValidator | AllowInfNan):
            continue  # checks of the input's kind (a whole number, finite), not bounds
        if isinstance(item, FieldInfo):  # the Field(...) of an Annotated type
            found |= _constraints(key, item.metadata)
            continue
        name = BOUNDS.get(type(item))
        if name is None:
            raise ValueError(f"{key}: the constraint {item!r} is not shown; teach _bounds() it")
        found[name] = getattr(item, name)
    return found


def _range(noun: str, bounds: dict[str, Any]) -> str:
    """'0 < number ≤ 1', 'integer ≥ 1' or plain 'number', from ge/gt/le/lt."""
    below = [(sign, bounds[name]) for name, sign in (("gt", "<"), ("ge", "≤")) if name in bounds]
    above = [(sign, bounds[name]) for name, sign in (("lt", "<"), ("le", "≤")) if name in bounds]
    if below and above:
        (low_sign, low), (high_sign, high) = below[0], above[0]
        return f"{_yaml(low)} {low_sign} {noun} {high_sign} {_yaml(high)}"
    if below:
        sign, low = below[0]
        return f"{noun} {'>' if sign == '<' else '≥'} {_yaml(low)}"
    if above:
        sign, high = above[0]
        return f"{noun} {sign} {_yaml(high)}"
    return noun


def _unwrap(key: str, annotation: Any) -> tuple[Any, bool]:
    """`X | None` as (X, True); any other type as (it, False)."""
    if typing.get_origin(annotation) not in (typing.Union, types.UnionType):
        return annotation, False
    members = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
    if len(members) != 1:
        raise ValueError(f"{key}: a union of {members} is not shown; teach _unwrap() it")
    return members[0], len(members) < len(typing.get_args(annotation))


def _annotated(key: str, annotation: Any) -> tuple[Any, dict[str, Any]]:
    """`Annotated[X, ...]` as (X, its bounds); any other type as (it, {})."""
    if typing.get_origin(annotation) is not typing.Annotated:
        return annotation, {}
    base, *metadata = typing.get_args(annotation)
    return base, _constraints(key, metadata)


def _allowed(key: str, field: FieldInfo) -> str:
    annotation, optional = _unwrap(key, field.annotation)
    annotation, inner_bounds = _annotated(key, annotation)
    bounds = {**inner_bounds, **_bounds(key, field)}
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    nested = _nested(annotation)
    if nested is not None:
        _, is_list = nested
        if is_list:
            least = bounds.get("min_length", 0)
            text = f"list of {least} or more mappings of the `{key}[].*` keys below"
        else:
            text = f"mapping of the `{key}.*` keys below"
    elif origin is Literal:
        text = ", ".join(f"`{_yaml(choice)}`" for choice in args)
    elif annotation is bool:
        text = "`true`, `false`"
    elif annotation is int:
        text = _range("integer", bounds)
    elif annotation is float:
        text = _range("number", bounds)  # an integer is accepted too
    elif annotation is str:
        text = "non-empty text" if bounds.get("min_length", 0) >= 1 else "text"
    elif origin is dict:
        text = "mapping"
    elif (origin is tuple and args[-1] is Ellipsis) or origin is list:
        text = f"list of {_noun(key, args[0])}"
    elif origin is tuple:
        text = f"list of {len(args)} {_noun(key, args[0])}"
    else:
        raise ValueError(f"{key}: the type {annotation!r} is not shown; teach _allowed() it")
    return f"{text}, or `null`" if optional else text


def _noun(key: str, item: Any) -> str:
    """'integers', or with bounds on each item 'integers, each 1 ≤ integer ≤ 8192'."""
    item, bounds = _annotated(key, item)
    nouns = {int: ("integers", "integer"), float: ("numbers", "number"), str: ("texts", "text")}
    if item not in nouns:
        raise ValueError(f"{key}: a list of {item!r} is not shown; teach _noun() it")
    plural, singular = nouns[item]
    return f"{plural}, each {_range(singular, bounds)}" if bounds else plural


def rows(model: type[BaseModel], prefix: str = "") -> Iterator[Row]:
    """Every key of `model`, depth first, nested blocks right after the key that opens them."""
    for name, field in model.model_fields.items():
        key = prefix + name
        if not field.description:
            raise ValueError(
                f"{model.__name__}.{name} ({key}) has no description: give it "
                f"Field(..., description='one line a microscope engineer understands')"
            )
        yield key, _default(field), _allowed(key, field), _escape(field.description)
        nested = _nested(_unwrap(key, field.annotation)[0])
        if nested is not None:
            inner, is_list = nested
            yield from rows(inner, f"{key}[]." if is_list else f"{key}.")


def table(model: type[BaseModel]) -> str:
    lines = ["| key | default | allowed | meaning |", "| --- | --- | --- | --- |"]
    lines += [
        f"| `{key}` | {default} | {allowed} | {meaning} |"
        for key, default, allowed, meaning in rows(model)
    ]
    return "\n".join(lines) + "\n"


def markdown() -> str:
    """The generated part of docs/configs.md: one section and table per kind of file."""
    sections = [f"## {heading}\n\n{where}\n\n{table(model)}" for heading, where, model in SECTIONS]
    return "\n".join(sections)


def write(doc: Path = DOC) -> None:
    """Replace everything below the marker line of `doc` with fresh tables."""
    text = doc.read_text()
    head, marker, _ = text.partition(MARKER)
    if not marker:
        raise SystemExit(
            f"{doc} has no marker line; put this line where the tables begin:\n{MARKER}"
        )
    doc.write_text(f"{head}{MARKER}\n\n{markdown()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"replace the tables in {DOC.name}")
    if parser.parse_args().write:
        write()
        print(f"wrote {DOC}")
    else:
        print(markdown(), end="")


if __name__ == "__main__":
    main()

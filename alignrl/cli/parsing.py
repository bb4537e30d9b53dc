"""The parser of the `alignrl` command and of each of its verbs: options are never abbreviated
(`--scen` is refused, not read as `--scenarios`), and a mistyped option or verb is refused by
the parser it was given to, with that verb's usage and the closest names it knows ("did you
mean --scenarios?"), exit 2, as argparse refuses any other input."""

from __future__ import annotations

import argparse
import difflib
import sys
from collections.abc import Sequence
from typing import Any


def _closest(given: str, known: list[str]) -> str | None:
    """The names of `known` that `given` begins (what an abbreviation would have meant),
    else the closest by difflib; None where none is close."""
    begun = sorted(name for name in known if name.startswith(given) and len(given.lstrip("-")) > 1)
    if begun:
        return " or ".join(begun)
    found = difflib.get_close_matches(given, known, n=1)
    return found[0] if found else None


class CommandParser(argparse.ArgumentParser):
    """argparse's parser with `allow_abbrev=False` (also for every verb's parser, which
    add_subparsers makes of the same class) and unknown arguments refused by the parser of
    the verb they were given to, not by the top-level one after the verb has read its own."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def _verbs(self) -> bool:
        return any(isinstance(action, argparse._SubParsersAction) for action in self._actions)

    def _refuse(self, unknown: Sequence[str]) -> None:
        """Exit 2 with this parser's usage where `unknown` holds anything: each unknown
        option named with the closest option of this verb."""
        if not unknown:
            return
        options = list(self._option_string_actions)
        said = []
        for given in unknown:
            name = given.split("=", 1)[0]
            close = _closest(name, options) if name.startswith("-") else None
            said.append(f"{given} (did you mean {close}?)" if close else given)
        self.error(f"unrecognized arguments: {' '.join(said)}")

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """As argparse's, but a parser keeps nothing unknown for the one above it: it refuses
        an unknown long option of its own before it reads the rest (so that the option is
        named even where a required one is missing too; a parser with verbs looks at the
        words before its verb only), and what is left unread after it."""
        given = list(sys.argv[1:] if args is None else args)
        words = given[: given.index("--")] if "--" in given else given
        if self._verbs():  # its own options come before the verb (and take no value)
            words = words[: next((i for i, w in enumerate(words) if not w.startswith("-")), None)]
        known = set(self._option_string_actions)
        self._refuse(
            [
                word
                for word in words
                if word.startswith("--")
                and len(word) > 2
                and " " not in word
                and word.split("=", 1)[0] not in known
            ]
        )
        parsed, extras = super().parse_known_args(given, namespace)
        self._refuse(extras)
        return parsed, extras

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        """An invalid choice (a verb, a --format) also says the closest choice; a verb's
        message names no argument (argparse would name the verbs' dest, `league_verb`)."""
        try:
            super()._check_value(action, value)
        except argparse.ArgumentError as error:
            close = _closest(str(value), [str(choice) for choice in action.choices or ()])
            verb = isinstance(action, argparse._SubParsersAction)
            if close is None and not verb:
                raise
            message = error.message + (f"; did you mean {close!r}?" if close else "")
            raise argparse.ArgumentError(None if verb else action, message) from None

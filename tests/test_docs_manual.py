"""The manual is kept true by running it: every command that README.md and docs/*.md show
with its output runs here, and what it prints must be what the page shows.

What runs. A fenced block of `$ COMMAND` lines, each followed by the lines it prints, runs
command by command in bash, in a fresh working directory per page (a *session*; commands of a
page see the files its earlier commands made, as a reader following the page would). The
session holds links to the repository's read-only inputs (`alignrl/`, `docs/`, `experiments/`,
`populations/`, `benchmarks/`), so that paths resolve as from the repository root, while
`runs/` and `exports/` land in the session. `alignrl` and `python` are the virtual
environment's. A ```python block followed directly by a plain block (only a blank line
between) runs as a script in the page's session, with `docs/examples` on the path as the page
says, and prints that block. A block whose commands show no output is not run;
`test_every_shown_command_parses` checks each `alignrl` command in it against the parser
instead, and that every `experiments/`, `benchmarks/` or `populations/` path it names exists.

How output is compared. Standard output and standard error in one stream, in the order they
were written (the page shows what a terminal shows), except for the commands in STDOUT_ONLY.
Progress bars are dropped (the pages leave them out), as are trailing spaces and trailing blank
lines. Then every shown line must match its printed line exactly, except for these volatile
fields, and nothing else:

- a duration, a number followed by ` s` ("2.8 s"), matches any number;
- a `"seconds": N` JSON value matches any number;
- the cells of a table column headed `seconds` match any number;
- `...` in a shown line matches any text, and a shown line that is `...` alone matches any
  number of printed lines.

What does not run is listed in NOT_RUN with the reason (a run that takes hours, a Ctrl-C at a
moment the page names, a file the page does not make); a stale entry fails
`test_every_exclusion_names_a_shown_command`. A page's prerequisites from another page are in
SETUP. Commands that take more than about 15 s (or follow one in their session) are marked
`slow`; `make test` and `make docs-check` run them, `make test-fast` does not. Those of minutes
(`make run` and the commands that read its league) are marked `long` as well: `make
docs-check` runs them, `make test` does not. The README's
sessions (its tour, and `make run` with the commands that read its league) run from
tests/test_docs_readme.py, with the machinery of this file.
"""

from __future__ import annotations

import contextlib
import difflib
import io
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from alignrl.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(f"docs/{path.name}" for path in (ROOT / "docs").glob("*.md"))]
# What a session links to, so that paths resolve as from the repository root.
INPUTS = ("alignrl", "docs", "experiments", "populations", "benchmarks")
COMMAND_TIMEOUT_S = 600

# Why a command is not run, by (page, how the command starts).
_CTRL_C = "interrupted by hand at a moment the page names (tests/test_recorder.py does it)"
_TIGHT = "needs runs/focus-sac-gtrxl-tight, a training run of 14 minutes"
NOT_RUN: dict[tuple[str, str], str] = {
    ("README.md", "make test"): "the whole suite: its figures are pasted after a full run",
    ("docs/cli.md", "alignrl record --apparatus synthetic --scenarios 50 --out runs/tour/long"): (
        _CTRL_C
    ),
    ("docs/cli.md", "cd /tmp/doc/bad"): "text.csv, a damaged file, is not made on the page",
    ("docs/cli.md", "alignrl scenarios validate text.csv"): "reads text.csv (above)",
    ("docs/cli.md", "alignrl align --policy runs/focus-sac-gtrxl-tight"): _TIGHT,
    ("docs/cli.md", "alignrl report runs/focus-sac-mlp"): "needs a training run of minutes",
    ("docs/cli.md", "alignrl report runs/killed"): "needs a training run killed early",
    ("docs/deploy.md", "alignrl export runs/focus-sac-gtrxl-tight"): _TIGHT,
    ("docs/deploy.md", "alignrl align --policy runs/focus-sac-gtrxl-tight"): _TIGHT,
    ("docs/scenarios.md", "head -1 runs/tour/constant.csv"): "constant.csv is recorded below",
    ("docs/scenarios.md", "cat good.csv"): "good.csv: the page shows it but does not make it",
    ("docs/scenarios.md", "alignrl scenarios validate good.csv"): "reads good.csv (above)",
    ("docs/scenarios.md", "cmp runs/tour/grow.csv runs/tour/grow-before.csv"): (
        "grow-before.csv, the copy before the refused appends, is not made on the page"
    ),
    ("docs/scenarios.md", "alignrl record --apparatus synthetic --scenarios 50 --out runs/"): (
        _CTRL_C  # Ctrl-C into runs/tour/long.csv, kill -9 into runs/tour/killed.csv.gz
    ),
    ("docs/scenarios.md", "alignrl scenarios validate runs/tour/long.csv"): "reads one (above)",
    ("docs/scenarios.md", "alignrl scenarios validate runs/tour/killed"): "reads one (above)",
    ("docs/scenarios.md", "alignrl scenarios validate cut.csv"): "cut.csv is not made on the page",
}

# Pages that read what another page records, made before the page's first command.
_FIVE = "alignrl record --apparatus synthetic --scenarios 5 --out runs/tour/five.csv --quiet"
_B = "alignrl record --apparatus synthetic-b --scenarios 5 --out runs/tour/b.csv --quiet"
SETUP: dict[str, list[str]] = {"docs/apparatus.md": [_FIVE, _B], "docs/scenarios.md": [_B]}

# Commands that run in a session of their own, shared across pages, instead of their page's.
SESSION_OF: dict[tuple[str, str], str] = {
    ("README.md", "make run"): "make-run",
    ("docs/cli.md", "alignrl export runs/make-run/league-make-run"): "make-run",
    ("docs/cli.md", "alignrl leaderboard runs/make-run/league-make-run"): "make-run",
}

# The page shows standard output only (progress bars and log lines left out).
STDOUT_ONLY: set[tuple[str, str]] = {("README.md", "make run")}

# Minutes of one worker (`make run`: over 5 min on 2 busy cores), and so the commands after
# one in its session: `make docs-check` runs them, `make test` does not.
LONG: set[tuple[str, str]] = {
    ("README.md", "make run"),
    # 70 alignments of the champion, its posterior of 1,024 columns asked at every reading
    # from the second (over 3 min of one worker)
    ("README.md", "alignrl evaluate --policy champion:focus-v2 --set heldout --analytic"),
}
# Measured over ~15 s (on 2 busy cores), every long one among them; the commands after one in
# its session are slow too.
SLOW: set[tuple[str, str]] = set(LONG)


# --- reading the pages ----------------------------------------------------------------------


@dataclass(frozen=True)
class Shown:
    """One command (or Python example) of a page and the lines the page shows it print."""

    page: str
    line: int  # where the command starts on the page, counted from 1
    command: str  # the shell command, continuation lines joined; the script for Python
    output: str  # the shown lines; "" for a command shown without output
    python: bool = False
    in_block_with_output: bool = True

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"

    def key(self, table: dict | set) -> tuple[str, str] | None:
        """The entry of NOT_RUN, SESSION_OF, STDOUT_ONLY or SLOW that names this command."""
        for page, start in table:
            if page == self.page and self.command.startswith(start):
                return (page, start)
        return None


def _fenced_blocks(text: str) -> Iterator[tuple[int, str, str, int]]:
    """(first line of the body, language, body, end offset) of every fenced block."""
    for match in re.finditer(r"^```(\w*)\n(.*?)^```\n", text, re.MULTILINE | re.DOTALL):
        yield text.count("\n", 0, match.start()) + 2, match.group(1), match.group(2), match.end()


def _complete(command: str) -> bool:
    """Whether a command line is whole: no open quote (a `python -c '...'` over lines)."""
    try:
        shlex.split(command, comments=True)
    except ValueError:
        return False
    return True


def _commands(page: str, first_line: int, body: str) -> list[Shown]:
    lines = body.splitlines()
    found: list[tuple[int, str, list[str]]] = []
    index = 0
    while index < len(lines):
        if not lines[index].startswith("$ "):
            index += 1
            continue
        start, command = first_line + index, lines[index][2:]
        while command.endswith("\\") or not _complete(command):
            index += 1
            if command.endswith("\\"):  # a continued line
                command = command.removesuffix("\\").rstrip() + " " + lines[index].strip()
            else:  # inside a quote, as `python -c '...'` over lines: kept as written
                command += "\n" + lines[index]
        index += 1
        output: list[str] = []
        while index < len(lines) and not lines[index].startswith("$ "):
            if not re.match(r"\s+# ", lines[index]):  # the command's comment, carried on
                output.append(lines[index])
            index += 1
        found.append((start, command.strip(), output))
    with_output = any(output for _, _, output in found)
    return [
        Shown(page, start, command, "\n".join(output), in_block_with_output=with_output)
        for start, command, output in found
    ]


def read_page(page: str) -> list[Shown]:
    """Every `$ ` command of a page, and every Python example directly followed by output."""
    text = (ROOT / page).read_text()
    blocks = list(_fenced_blocks(text))
    shown: list[Shown] = []
    for number, (first_line, language, body, end) in enumerate(blocks):
        if language == "" and body.startswith("$ "):
            shown += _commands(page, first_line, body)
        elif language == "python" and number + 1 < len(blocks):
            _, following_language, following, _ = blocks[number + 1]
            directly = text[end:].startswith("\n```\n")  # only a blank line between
            if directly and following_language == "" and not following.startswith("$ "):
                shown.append(Shown(page, first_line - 1, body, following.rstrip("\n"), True))
    return shown


ALL_SHOWN = [shown for page in PAGES for shown in read_page(page)]
RUN = [s for s in ALL_SHOWN if s.in_block_with_output and s.key(NOT_RUN) is None]


# --- comparing ------------------------------------------------------------------------------

_BAR = re.compile(r"\d+%\|.*\|")  # a tqdm frame: "recording:  40%|████      | 2/5 [...]"
_LOOSE = re.compile(r"\.\.\.|\d+(?:\.\d+)?(?= s\b)|(?<=\"seconds\": )\d+(?:\.\d+)?")


def printed_lines(raw: bytes) -> list[str]:
    """What a terminal keeps of a command's output, without its progress bars."""
    lines = []
    for line in raw.decode().split("\n"):
        frames = [frame for frame in line.split("\r") if frame.strip()]
        if frames and _BAR.search(frames[-1]):
            continue
        lines.append((frames[-1] if frames else "").rstrip())
    while lines and not lines[-1]:
        lines.pop()
    return lines


def _pattern(shown_line: str, seconds_from: int | None) -> re.Pattern[str]:
    """A shown line as a regular expression, with its volatile fields loosened."""
    parts, position = [], 0
    for match in _LOOSE.finditer(shown_line):
        parts.append(re.escape(shown_line[position : match.start()]))
        parts.append(".*?" if match.group() == "..." else r"\d+(?:\.\d+)?")
        position = match.end()
    parts.append(re.escape(shown_line[position:]))
    pattern = "".join(parts)
    if seconds_from is not None:  # the last cell of a table row under a `seconds` heading
        head = re.escape(shown_line[:seconds_from].rstrip())
        if shown_line[seconds_from:].strip().replace(".", "").isdigit():
            pattern = head + r" +\d+(?:\.\d+)?"
    return re.compile(pattern)


def _shown_patterns(shown: str) -> list[re.Pattern[str] | None]:
    """One pattern per shown line; None for a line of `...` alone (any number of lines)."""
    patterns: list[re.Pattern[str] | None] = []
    seconds_from: int | None = None
    width = 0
    for line in shown.rstrip("\n").splitlines():
        line = line.rstrip()
        if re.search(r"\s{2}seconds$", line):  # a table header: its rows end where it does
            seconds_from, width = len(line) - len("seconds"), len(line)
        elif seconds_from is not None and len(line) != width:
            seconds_from = None  # past the table
        patterns.append(None if line == "..." else _pattern(line, seconds_from))
    return patterns


def matches(shown: str, printed: list[str]) -> bool:
    """Whether the printed lines are the shown ones, by the rules of the module docstring."""
    patterns = _shown_patterns(shown)

    def walk(p: int, q: int) -> bool:
        if p == len(patterns):
            return q == len(printed)
        pattern = patterns[p]
        if pattern is None:
            return any(walk(p + 1, skip) for skip in range(q, len(printed) + 1))
        return q < len(printed) and pattern.fullmatch(printed[q]) is not None and walk(p + 1, q + 1)

    return walk(0, 0)


# --- running --------------------------------------------------------------------------------


def make_run_recipe() -> str:
    """`make run`'s recipe, read from the Makefile, as a bash script in the session."""
    text = (ROOT / "Makefile").read_text().replace("\\\n", " ")
    recipe = re.search(r"^run: .*\n((?:\t.*\n)+)", text, re.MULTILINE)
    assert recipe, "Makefile: no `run:` target"
    run_dir = re.search(r"^RUN_DIR := (.*)$", text, re.MULTILINE)
    assert run_dir, "Makefile: no RUN_DIR"
    lines = [line.strip() for line in recipe.group(1).splitlines()]
    script = " && ".join(lines).replace("$(BIN)/", "").replace("$(RUN_DIR)", run_dir.group(1))
    assert "$(" not in script, f"Makefile: `make run` uses a variable the docs test lacks: {script}"
    return script


@dataclass
class Session:
    """A working directory in which one page's commands run in order, each once."""

    directory: Path
    setup: list[str]
    queue: list[Shown]
    printed: dict[str, tuple[int, bytes]] = field(default_factory=dict)
    started: bool = False

    def _run(
        self, command: str, python: bool = False, stdout_only: bool = False
    ) -> tuple[int, bytes]:
        environment = {
            key: value for key, value in os.environ.items() if not key.startswith("PYTHON")
        }
        bin_dir = str(Path(sys.executable).parent)
        environment |= {
            "PATH": f"{bin_dir}{os.pathsep}{environment.get('PATH', '')}",
            "PYTHONUNBUFFERED": "1",  # stdout and stderr interleave as on a terminal
            "COLUMNS": "80",
        }
        if python:
            environment["PYTHONPATH"] = "docs/examples"  # as the pages say to
            argv, stdin = [sys.executable, "-"], command.encode()
        else:
            argv, stdin = ["bash", "-c", command], None
        result = subprocess.run(
            argv,
            input=stdin,
            cwd=self.directory,
            env=environment,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL if stdout_only else subprocess.STDOUT,
            timeout=COMMAND_TIMEOUT_S,
            check=False,
        )
        return result.returncode, result.stdout

    def run_through(self, wanted: Shown) -> tuple[int, bytes]:
        """Run the session up to and including `wanted`; what it printed, and its exit code."""
        if not self.started:
            self.started = True
            self.directory.mkdir(parents=True, exist_ok=True)
            for name in INPUTS:
                (self.directory / name).symlink_to(ROOT / name)
            for command in self.setup:
                code, output = self._run(command)
                assert code == 0, f"setup `{command}` failed ({code}):\n{output.decode()}"
        for shown in self.queue:
            if shown.id not in self.printed:
                command = make_run_recipe() if shown.command == "make run" else shown.command
                stdout_only = shown.key(STDOUT_ONLY) is not None
                self.printed[shown.id] = self._run(command, shown.python, stdout_only)
            if shown.id == wanted.id:
                return self.printed[shown.id]
        raise AssertionError(f"{wanted.id} is not in its session")


def _session_name(shown: Shown) -> str:
    key = shown.key(SESSION_OF)
    return SESSION_OF[key] if key else shown.page


def _follows(shown: Shown, table: set[tuple[str, str]]) -> bool:
    """Whether `shown`, or a command before it in its session, is named in `table`."""
    name = _session_name(shown)
    before = RUN[: RUN.index(shown) + 1]
    return any(_session_name(s) == name and s.key(table) for s in before)


def _marks(shown: Shown) -> list[Any]:
    return [
        mark
        for mark, table in ((pytest.mark.slow, SLOW), (pytest.mark.long, LONG))
        if _follows(shown, table)
    ]


# The README's sessions run from tests/test_docs_readme.py, the pages' from here: two files,
# so that `pytest -n 2 --dist loadfile` runs them side by side.
README_SESSIONS = ("README.md", "make-run")


def make_sessions(root: Path, names: tuple[str, ...] | None = None) -> dict[str, Session]:
    """The sessions of RUN under `root`, those named in `names` or, without it, the others."""
    by_name: dict[str, Session] = {}
    for shown in RUN:
        name = _session_name(shown)
        if (name in names) if names is not None else (name not in README_SESSIONS):
            if name not in by_name:
                directory = root / re.sub(r"\W", "-", name)
                by_name[name] = Session(directory, SETUP.get(name, []), [])
            by_name[name].queue.append(shown)
    return by_name


def output_params(readme: bool) -> list[Any]:
    """One test parameter per command of the README's sessions, or of the others."""
    return [
        pytest.param(shown, marks=_marks(shown), id=shown.id)
        for shown in RUN
        if (_session_name(shown) in README_SESSIONS) == readme
    ]


def check_output(shown: Shown, sessions: dict[str, Session]) -> None:
    """Run `shown` in its session (after the session's earlier commands) and compare."""
    code, raw = sessions[_session_name(shown)].run_through(shown)
    printed = printed_lines(raw)
    if not matches(shown.output, printed):
        diff = "\n".join(
            difflib.unified_diff(
                shown.output.splitlines(), printed, "shown", "printed", lineterm=""
            )
        )
        what = "the Python example" if shown.python else f"`{shown.command}`"
        pytest.fail(f"{shown.id}: {what} (exit {code}) prints otherwise:\n{diff}")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Session]:
    return make_sessions(tmp_path_factory.mktemp("docs"))


@pytest.mark.parametrize("shown", output_params(readme=False))
def test_each_shown_output_is_what_the_command_prints(
    shown: Shown, sessions: dict[str, Session]
) -> None:
    check_output(shown, sessions)


# --- commands shown without output ----------------------------------------------------------

_PATH = re.compile(r"(experiments|benchmarks|populations)/")  # files the repository holds


def _alignrl_argvs(command: str) -> Iterator[list[str]]:
    """The argument lists of every `alignrl` call in a shell command line, variables set."""
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    variables: dict[str, str] = {}
    words: list[str] = []
    for token in [*lexer, ";"]:
        if token in (";", "&&", "||", "|"):
            while words and re.fullmatch(r"[A-Z_]+=.*", words[0]):  # A=runs/x, PYTHONPATH=
                name, value = words.pop(0).split("=", 1)
                variables[name] = value
            if words and words[0] == "alignrl":
                yield [
                    re.sub(r"\$(\w+)", lambda m: variables.get(m.group(1), m.group()), word)
                    for word in words[1:]
                ]
            words = []
        elif token in (">", ">>", "<"):  # a redirection: its target is not an argument
            if words and words[-1].isdigit():
                words.pop()  # the 2 of 2>/dev/null
            words.append("\0redirect")
        elif words and words[-1] == "\0redirect":
            words.pop()
        else:
            words.append(token)


@pytest.mark.parametrize("shown", [pytest.param(s, id=s.id) for s in ALL_SHOWN if not s.python])
def test_every_shown_command_parses(shown: Shown) -> None:
    """A renamed flag, verb or experiment file fails here, also where the page shows no output."""
    for argv in _alignrl_argvs(shown.command):
        errors = io.StringIO()
        try:
            with contextlib.redirect_stderr(errors):
                build_parser().parse_args(argv)
        except SystemExit as exit:  # argparse's way of refusing
            if exit.code:
                pytest.fail(f"{shown.id}: `alignrl {shlex.join(argv)}`: {errors.getvalue()}")
        for path in (word for word in argv if _PATH.match(word)):
            assert (ROOT / path).exists(), f"{shown.id}: `alignrl {shlex.join(argv)}`: no {path}"


def test_the_pages_show_commands_and_runnable_ones() -> None:
    # The parser finds what the pages hold (a failing regular expression would test nothing).
    assert len(RUN) > 40 and len(ALL_SHOWN) > len(RUN)
    tour = [s for s in RUN if s.page == "README.md"]
    assert any(s.python for s in tour) and any("scenarios validate" in s.command for s in tour)


def test_every_exclusion_names_a_shown_command() -> None:
    for table in (NOT_RUN, SESSION_OF, STDOUT_ONLY, SLOW):
        for page, start in table:
            assert any(s.page == page and s.command.startswith(start) for s in ALL_SHOWN), (
                f"{page} shows no command `{start}`: drop its entry"
            )


# --- the comparison rules, by hand ----------------------------------------------------------


def test_progress_bars_are_dropped_and_the_last_frame_kept() -> None:
    raw = (
        b"\rrecording:  0%|   | 0/2 [00:00<?]\rrecording: 100%|###| 2/2 [00:01<00:00]\nrecorded 2\n"
    )
    assert printed_lines(raw) == ["recorded 2"]
    assert printed_lines(b"\r        \rcheckpoint 40  \n\n") == ["checkpoint 40"]


def test_only_the_volatile_fields_are_loose() -> None:
    assert matches("recorded 5 (median 30 pairs, 2.8 s)", ["recorded 5 (median 30 pairs, 14.1 s)"])
    assert not matches(
        "recorded 5 (median 30 pairs, 2.8 s)", ["recorded 5 (median 31 pairs, 2.8 s)"]
    )
    assert matches('  "seconds": 2.83,', ['  "seconds": 4.126,'])
    assert not matches('  "median_pairs": 30.0,', ['  "median_pairs": 31.0,'])
    assert matches("aligned: ... final 2.85 px", ["aligned: stage 1 stopped; final 2.85 px"])
    assert not matches("aligned: ... final 2.85 px", ["aligned: stage 1 stopped; final 2.86 px"])
    assert matches("a\n...\nz", ["a", "b", "c", "z"]) and matches("a\n...\nz", ["a", "z"])
    assert not matches("a\nb", ["a", "b", "c"])
    table = "name  successes  seconds\n----  ---------  -------\nhb        20/20      0.0"
    assert matches(
        table, ["name  successes  seconds", "----  ---------  -------", "hb        20/20     12.4"]
    )
    assert not matches(
        table, ["name  successes  seconds", "----  ---------  -------", "hb        19/20      0.0"]
    )


def test_make_run_is_read_from_the_makefile() -> None:
    script = make_run_recipe()
    assert script.startswith("rm -rf runs/make-run && alignrl champions --scenarios 5")
    assert "alignrl league run experiments/league-make-run.yaml --runs-dir runs/make-run" in script


def test_the_alignrl_calls_of_a_shell_line_are_found() -> None:
    line = "A=runs/a; alignrl evaluate --policy $A --json 2>/dev/null && cmp x y  # why"
    assert list(_alignrl_argvs(line)) == [["evaluate", "--policy", "runs/a", "--json"]]
    assert list(_alignrl_argvs("PYTHONPATH=docs/examples alignrl record -h")) == [["record", "-h"]]

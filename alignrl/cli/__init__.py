"""The `alignrl` command. Verbs read like the work; every reporting verb has `--json`
(keys documented in docs/cli.md and kept stable).

    alignrl record --apparatus SPEC --scenarios N --out FILE.csv [--seed S] [--step adaptive]
    alignrl scenarios validate FILE [--plot PNG] [--json]
    alignrl evaluate --policy NAME --apparatus SPEC [--task T] --scenarios N [--seed S]
                     [--spec-px X]
    alignrl baselines --apparatus SPEC [--task T] --scenarios N [--seed S] [--spec-px X]
                      [--plot-dir DIR]
    alignrl report RUN [--out DIR] [--json]
    alignrl export RUN [--member ID] --format onnx|torchscript|safetensors --out DIR
                   [--force] [--json]

One module per verb group, each adding its verbs to the parser (main.py assembles them):
record.py (record, scenarios validate), sessions.py (evaluate, baselines), training.py (train,
adapt, report), league.py (league run|resume|status, leaderboard), deploy.py (align, export);
common.py holds what they share (exit codes, CommandError, option types and blocks), parsing.py
the parser class of every verb (no abbreviated options; a mistyped option or verb refused by
its verb with the closest name).
"""

from alignrl.cli.common import (
    EXIT_DRIVER_FAILURE,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_SHIELD_STOP,
    EXIT_USAGE,
    CommandError,
)
from alignrl.cli.main import build_parser, main

__all__ = [
    "EXIT_DRIVER_FAILURE",
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_SHIELD_STOP",
    "EXIT_USAGE",
    "CommandError",
    "build_parser",
    "main",
]

"""The `alignrl` command assembled: one parser whose verbs each group module adds, in the
order `alignrl --help` lists them, and `main()`, which turns every failure into one line and
an exit code (2 bad input, 3 stopped by the shield, 4 driver failure, 70 a bug in alignrl)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence

from alignrl import __version__
from alignrl.apparatus.base import ApparatusError
from alignrl.apparatus.shield import DriverFailure, ShieldStop
from alignrl.cli.calibrate import add_calibrate_parser
from alignrl.cli.champions import add_champions_parser
from alignrl.cli.common import (
    EXIT_DRIVER_FAILURE,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_SHIELD_STOP,
    EXIT_USAGE,
    CommandError,
    _message,
)
from alignrl.cli.deploy import add_deploy_parsers
from alignrl.cli.league import add_league_parsers
from alignrl.cli.parsing import CommandParser
from alignrl.cli.record import add_record_parsers
from alignrl.cli.sessions import add_session_parsers
from alignrl.cli.training import add_training_parsers


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(  # its verbs' parsers are CommandParsers too (no abbreviations)
        prog="alignrl",
        description="Train and run reinforcement-learning agents that align electron microscopes.",
        epilog="The method is that of the paper 'Method of aligning a charged particle beam "
        "apparatus' (docs/index.md, The method).",
    )
    parser.add_argument("--version", action="version", version=f"alignrl {__version__}")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    add_record_parsers(verbs)  # record, scenarios validate
    add_session_parsers(verbs)  # evaluate, baselines
    add_champions_parser(verbs)  # champions
    add_training_parsers(verbs)  # train, adapt, report
    add_league_parsers(verbs)  # league run|resume|status, leaderboard
    add_deploy_parsers(verbs)  # align, export
    add_calibrate_parser(verbs)  # calibrate
    return parser


def _terminated(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # recorded in a run's config
    # Ctrl-C must reach the recorder's handler as KeyboardInterrupt, also under `make`, and
    # SIGTERM (a `kill`, a service stop) ends every verb as Ctrl-C does, never a silent 143.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    terminate = signal.signal(signal.SIGTERM, _terminated)
    try:
        return int(args.handler(args))
    except KeyboardInterrupt:  # a verb that keeps nothing half-done says so itself first
        print("\nalignrl: interrupted (Ctrl-C or SIGTERM)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ShieldStop as error:  # the shield ended work on an instrument: nothing more sent
        failure = isinstance(error, DriverFailure)
        print(
            f"alignrl: {'driver failure' if failure else 'stopped by the shield'}: "
            f"{_message(error)}; nothing more was sent to the apparatus",
            file=sys.stderr,
        )
        return EXIT_DRIVER_FAILURE if failure else EXIT_SHIELD_STOP
    except ApparatusError as error:  # before ValueError: NoEdgesError is both
        print(f"alignrl: apparatus error: {_message(error)}", file=sys.stderr)
        return EXIT_USAGE
    except (CommandError, ValueError, OSError) as error:
        print(f"alignrl: error: {_message(error)}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as error:  # the last resort: a bug, said in one line, never a traceback
        if os.environ.get("ALIGNRL_DEBUG"):
            raise
        print(
            f"alignrl: internal error ({type(error).__name__}: {_message(error)}); this is a "
            "bug in alignrl: please report it with the command (ALIGNRL_DEBUG=1 shows the "
            "traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    finally:
        signal.signal(signal.SIGTERM, terminate)

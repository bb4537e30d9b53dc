"""What every verb of the `alignrl` command shares: the exit codes, the one-line CommandError,
the argparse types of its options, `--json` output, and the option blocks several verbs take
(the apparatus, the safety shield, an evaluation session, a policy), each written once."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.apparatus.shield import DEFAULT_CALL_TIMEOUT_S, ShieldStop

EXIT_USAGE = 2  # bad input: a clear message, nothing written
EXIT_SHIELD_STOP = 3  # the shield ended the work: watchdog, refused write, abort (as align)
EXIT_DRIVER_FAILURE = 4  # a driver call failed, hung or answered what cannot be (as align)
EXIT_INTERNAL = 70  # a bug in alignrl (EX_SOFTWARE): one line, never a refusal of input
EXIT_INTERRUPTED = 130


class CommandError(Exception):
    """A user-facing failure: printed as one line, exit code 2."""


JSON_LIMIT = 100_000  # characters of a JSON option: arguments, limits, steps are a few dozen


def _json_object(text: str, option: str) -> dict[str, Any]:
    if len(text) > JSON_LIMIT:
        raise CommandError(f"{option}: {len(text)} characters of JSON; at most {JSON_LIMIT}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise CommandError(f"{option}: not valid JSON ({error})") from None
    except RecursionError:
        raise CommandError(f"{option}: the JSON nests too deeply") from None
    except ValueError as error:  # e.g. an integer of more than 4300 digits
        raise CommandError(f"{option}: not usable JSON ({str(error)[:200]})") from None
    if not isinstance(value, dict):
        raise CommandError(f"{option}: expected a JSON object such as '{{\"noise\": 0.02}}'")
    return value


def _parsed(text: str, kind: type[int] | type[float]) -> Any:
    """An option's text as an int or a float; argparse's one-line error where it is not."""
    try:
        return kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"{text[:40]!r} is not {what}") from None


def _seed(text: str) -> int:
    """A --seed: an integer in [0, 2^63), as numpy and the scenario files store seeds."""
    value = _parsed(text, int)
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"{text[:40]} is outside [0, 2^63 - 1]")
    return value


def _at_least_one(text: str) -> int:
    """A count option (processes, ...): an integer of at least 1."""
    value = _parsed(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be at least 1")
    return value


def _scenarios(text: str) -> int:
    """--scenarios: an integer of at most MAX_SCENARIOS (a session of days, not of years);
    the verb says what the fewest are."""
    from alignrl.config_reading import MAX_SCENARIOS

    value = _parsed(text, int)
    if value > MAX_SCENARIOS:
        raise argparse.ArgumentTypeError(f"{text[:40]} scenarios: at most {MAX_SCENARIOS:,}")
    return value


def _at_least_zero(text: str) -> int:
    """A count that may be none: an integer of at least 0."""
    value = _parsed(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} must be at least 0")
    return value


def _share(text: str) -> float:
    """A share option: a finite number in [0, 1]."""
    value = _parsed(text, float)
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise argparse.ArgumentTypeError(f"{text[:40]} must be a share in [0, 1]")
    return value


def _updates_per_step(text: str) -> float:
    """--updates-per-step: gradient updates per acquisition, in (0, MAX_UPDATES_PER_STEP]."""
    from alignrl.config.learner import MAX_UPDATES_PER_STEP

    value = _parsed(text, float)
    if not 0 < value <= MAX_UPDATES_PER_STEP:
        raise argparse.ArgumentTypeError(
            f"{text[:40]} must be above 0 and at most {MAX_UPDATES_PER_STEP} updates per "
            "acquisition"
        )
    return value


def _new_run(config: Any, overrides: list[str], args: argparse.Namespace) -> tuple[Any, Path]:
    """A new run's config as `train` and `league run` start it: under the run name of --name
    (validated as a name in the file would be), with its provenance, its evaluation apparatus
    checked before the run directory exists (or --force takes it); and that directory."""
    from alignrl.config_reading import parse_config
    from alignrl.runs.state import with_provenance
    from alignrl.training import check_evaluation_apparatus

    if args.name is not None:
        config = parse_config(type(config), {**config.model_dump(), "name": args.name}, "--name")
    config = with_provenance(config, overrides, args.argv)
    check_evaluation_apparatus(config)
    return config, Path(args.runs_dir) / config.name


def _checkpoint_kept(error: ShieldStop, run_dir: Any, resume: str) -> ShieldStop:
    """A shield stop of a run (training, adaptation, league) as the same kind of stop, told
    what the run keeps and how to go on; main() says which kind it was."""
    return type(error)(
        f"{error}; the last checkpoint in {run_dir} is kept: continue with "
        f"`{resume} {run_dir}` once the instrument answers"
    )


def _emit(payload: dict[str, Any], as_json: bool, lines: Sequence[str]) -> None:
    if as_json:
        print(json.dumps(payload, indent=2, sort_keys=True))
    else:
        print("\n".join(lines))


MESSAGE_LIMIT = 2000  # characters of one error message: never an echo of an unbounded value


def _message(error: BaseException) -> str:
    text = str(error)
    if len(text) <= MESSAGE_LIMIT:
        return text
    return f"{text[:MESSAGE_LIMIT]}... ({len(text) - MESSAGE_LIMIT} more characters not shown)"


def _add_shield_options(
    parser: argparse.ArgumentParser, limits: bool = True, log: bool = True
) -> None:
    """The options of every verb that may touch an instrument: a driver's calls all pass the
    shield (alignrl/apparatus/shield.py); these set its site limits, largest step, call time
    limit and audit log."""
    if limits:
        parser.add_argument(
            "--limits",
            default="{}",
            metavar="JSON",
            help="site limits inside the knobs' intervals, e.g. '{\"defocus\": [40, 60]}'",
        )
        parser.add_argument(
            "--max-step",
            default="{}",
            metavar="JSON",
            help="largest change per write, e.g. '{\"defocus\": 2.0}' (instrument units)",
        )
    parser.add_argument(
        "--call-timeout",
        type=float,
        default=DEFAULT_CALL_TIMEOUT_S,
        metavar="S",
        help="longest one driver call may take before it is abandoned and the work ends "
        f"(default: {DEFAULT_CALL_TIMEOUT_S:g} s)",
    )
    if log:
        parser.add_argument("--log", metavar="FILE", help="audit log of driver calls, JSON lines")


def _shield_options(args: argparse.Namespace) -> Any:
    """The ShieldOptions of a verb with _add_shield_options; the audit log (a file with
    --log, else the newest records in memory) is closed by the caller."""
    from alignrl.apparatus.shield import JsonLinesAudit, ShieldOptions

    if not (args.call_timeout > 0 and np.isfinite(args.call_timeout)):
        raise CommandError(f"--call-timeout must be positive seconds, got {args.call_timeout}")
    return ShieldOptions(
        site_limits=_json_object(getattr(args, "limits", "{}"), "--limits"),
        max_step=_json_object(getattr(args, "max_step", "{}"), "--max-step"),
        call_timeout_s=args.call_timeout,
        audit=JsonLinesAudit(args.log) if args.log else None,
    )


def _add_apparatus_options(
    parser: argparse.ArgumentParser,
    required: bool = True,
    spec_help: str = "apparatus spec, e.g. synthetic",
    args_help: str = "JSON keyword arguments",
) -> None:
    """--apparatus SPEC and --apparatus-args JSON (read with _json_object)."""
    parser.add_argument("--apparatus", required=required, help=spec_help)
    parser.add_argument("--apparatus-args", default="{}", help=args_help)


def _add_policy_option(parser: argparse.ArgumentParser, help_text: str) -> None:
    """--policy, given once or several times (a sequence of stage aligners)."""
    parser.add_argument("--policy", required=True, action="append", help=help_text)


def _add_session_options(parser: argparse.ArgumentParser, apparatus_required: bool = True) -> None:
    """The options of an evaluation session (evaluate, baselines): where, which task, how many
    alignments against which spec. `apparatus_required=False`: the verb checks that it has
    --apparatus or its alternative (evaluate and baselines: --set)."""
    _add_apparatus_options(parser, required=apparatus_required)
    parser.add_argument(
        "--task",
        default=None,
        help="alignment task: focus, stigmation, aperture or column (default: focus; for a "
        "trained aligner, its own task)",
    )
    parser.add_argument(
        "--scenarios",
        type=_scenarios,
        default=100,
        help="alignments in the session (default: 100)",
    )
    parser.add_argument("--seed", type=_seed, default=0, help="seed of the scenarios and starts")
    parser.add_argument(
        "--spec-px",
        type=float,
        default=None,
        help="absolute success threshold, edge width in px (default: relative to the best "
        "the apparatus can reach; required where it cannot say)",
    )
    # The default is resolved by the handler: importing the session here would load the
    # RL environments (gymnasium) for every verb.
    parser.add_argument(
        "--budget",
        type=int,
        default=None,
        help="most acquisitions per alignment (default: 50; column: 63, the most a column "
        "episode takes)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="machine-readable summary")
    _add_shield_options(parser)


def _add_override_options(parser: argparse.ArgumentParser, seed: bool = True) -> None:
    """--set KEY.PATH=VALUE (repeatable) and, where `seed`, --seed N: the config changed from
    the command line, checked by the same strict models as a file."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="change one key of the config, e.g. budget.env_steps=2000 (repeatable; the value "
        "is read as YAML)",
    )
    if seed:
        parser.add_argument(
            "--seed", dest="override_seed", type=_seed, help="the run's seed (as --set seed=N)"
        )


def _overrides(args: argparse.Namespace) -> list[str]:
    """The --set assignments, then --seed as one more."""
    given = list(getattr(args, "overrides", []) or [])
    if getattr(args, "override_seed", None) is not None:
        given.append(f"seed={args.override_seed}")
    return given


def _replace_run(lock: Any, force: bool, resume: str) -> None:
    """With --force, remove the run already in the folder `lock` holds (only a run: a folder
    with a config.yaml or checkpoints), saying so, and hold the new folder; without it, leave
    it to the create step, which refuses it. A folder holding nothing but the lock holds no
    run."""
    import shutil

    run_dir = lock.run_dir
    if not force or lock.only_the_lock():
        return
    if not ((run_dir / "config.yaml").exists() or (run_dir / "checkpoints").is_dir()):
        raise CommandError(
            f"--force replaces a run, and {run_dir} is not one (no config.yaml, no "
            "checkpoints/): choose another --name or remove it yourself"
        )
    shutil.rmtree(run_dir)
    lock.renew()
    print(f"--force: removed the run in {run_dir} (not resumed with `{resume}`)", file=sys.stderr)

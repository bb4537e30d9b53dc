"""`--gif FILE` of `alignrl align` and `alignrl evaluate`: one alignment filmed as it runs
(alignrl/apparatus/filming.py) and written as an animated GIF (alignrl/animation.py), a frame
per acquisition and then the verification image. The path is checked before any work; a file
that cannot be written at the end is said on standard error, and the result still counts."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from alignrl.animation import Reading, Scene, alignment_gif, check_gif_path
from alignrl.apparatus.filming import Film
from alignrl.cli.common import CommandError

__all__ = [
    "add_gif_options",
    "check_gif",
    "session_film",
    "write_gif",
    "write_session_gif",
]


def add_gif_options(parser: argparse.ArgumentParser, session: bool) -> None:
    """--gif FILE, and for a session --gif-scenario N."""
    which = "one alignment of the session" if session else "the alignment"
    parser.add_argument(
        "--gif",
        metavar="FILE",
        default=None,
        help=f"write {which} as an animated GIF: each acquired image beside the walk on the "
        "focus curve (FILE ends in .gif; its folder must exist)"
        + ("; with --apparatus" if session else ""),
    )
    if session:
        parser.add_argument(
            "--gif-scenario",
            type=int,
            metavar="N",
            default=None,
            help="with --gif: film alignment N of the session (default 0, the first; with "
            "--seeds, of the first seed's session)",
        )


def check_gif(args: argparse.Namespace) -> None:
    """--gif (and a session's --gif-scenario), checked before any policy loads or anything
    is written."""
    session = hasattr(args, "gif_scenario")
    if args.gif is None:
        if session and args.gif_scenario is not None:
            raise CommandError("--gif-scenario chooses the alignment --gif shows: give --gif too")
        return
    if session:
        if args.set is not None:
            raise CommandError(
                "--gif films an alignment on one apparatus: give --apparatus, not --set"
            )
        scenario = args.gif_scenario or 0
        if not 0 <= scenario < args.scenarios:
            raise CommandError(
                f"--gif-scenario {scenario}: the session's alignments are 0 to {args.scenarios - 1}"
            )
    try:
        check_gif_path(args.gif)
    except ValueError as error:
        raise CommandError(str(error)) from None


def session_film(args: argparse.Namespace) -> Film | None:
    """The film of alignment --gif-scenario of the first session (whose seed is args.seed),
    or None without --gif."""
    if args.gif is None:
        return None
    from alignrl.apparatus.recorder import scenario_seed

    return Film(scenario_seed=scenario_seed(args.seed, args.gif_scenario or 0))


def write_gif(
    readings: list[Reading], scene: Scene, path: str, payload: dict[str, Any], what: str = ""
) -> str | None:
    """Write the GIF; payload["gif"] names it (None: nothing acquired, or not writable). The
    text line to print (`what`: the alignment it shows), or None."""
    payload["gif"] = None
    if not readings:
        return "animation: none, nothing was acquired"
    try:
        payload["gif"] = str(alignment_gif(readings, scene, path))
    except OSError as error:
        print(f"alignrl: the animation was not written: {error}", file=sys.stderr)
        return None
    frames = f"{len(readings)} frame{'' if len(readings) == 1 else 's'}"
    return f"animation: {path} ({what}{': ' if what else ''}{frames})"


def write_session_gif(
    args: argparse.Namespace, film: Film, result: Any, payload: dict[str, Any], lines: list[str]
) -> None:
    """The GIF of the filmed alignment of `result` (a SessionResult, the first seed's)."""
    index = args.gif_scenario or 0
    record = result.records[index]
    final = record.final_width_px
    width = "no edges" if final is None else f"final edge width {final:.2f} px"
    scene = Scene(
        knobs={knob: film.knobs[knob] for knob in result.knobs},
        title=f"{result.controller} on {args.apparatus}: alignment {index}, seed {result.seed}",
        threshold_px=record.threshold_px,
        acquisitions=record.acquisitions,
        ending=f"{'aligned' if record.success else 'not aligned'}: {width}, spec "
        f"{record.threshold_px:.2f} px",
    )
    what = f"alignment {index}, seed {result.seed}"
    line = write_gif(film.readings, scene, args.gif, payload, what)
    if line is not None:
        lines.append(line)

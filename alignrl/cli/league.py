"""`alignrl league run|resume|status` and `alignrl leaderboard`: the two-team league (aligners
against misaligners) run to its schedule, and its members ranked by rating (openskill mu ±
sigma, beside the anchors) with their best validation session, the champion reported on a
test session that chose nothing, and the league report. Every success figure says which
session it comes from and carries its 95 % Wilson interval."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.apparatus.shield import ShieldStop
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_override_options,
    _checkpoint_kept,
    _emit,
    _new_run,
    _overrides,
    _replace_run,
)

if TYPE_CHECKING:
    from alignrl.runs.lock import RunLock


@contextlib.contextmanager
def _working(what: str) -> Iterator[None]:
    """`what` on stderr while a step that shows nothing else works (only where stderr is a
    terminal: never in a log or a pipe), erased when it ends."""
    shown = sys.stderr.isatty()
    if shown:
        print(f"{what} ...", end="", file=sys.stderr, flush=True)
    try:
        yield
    finally:
        if shown:
            print("\r\033[K", end="", file=sys.stderr, flush=True)


def _leaderboard_lines(rows: list[dict[str, Any]]) -> list[str]:
    """The table: ratings as mu ± sigma, and each member's best validation session with its
    95 % interval."""
    from alignrl.intervals import success_text

    header = (
        f"{'member':28} {'team':10} {'architecture':36} {'learner':7}  {'rating μ ± σ':>12} "
        f"{'validation (95 %)':>18}  {'median acq':>10}  parent"
    )
    lines = [header, "-" * len(header)]
    for row in rows:
        known = row["successes"] is not None
        validation = success_text(row["successes"], row["scenarios"]) if known else "-"
        median = row["median_acquisitions"]
        rating = f"{row['rating']:.1f} ± {row['sigma']:.1f}"
        line = (
            f"{row['member']:28} {row['team']:10} {row['architecture'][:36]:36} "
            f"{row['learner']:7}  {rating:>12} {validation:>18}  "
            f"{'-' if median is None else f'{median:g}':>10}  {row['parent'] or ''}"
        )
        lines.append(line.rstrip())
    return lines


def _standing(league: Any) -> tuple[list[dict[str, Any]], dict[str, Any], list[str]]:
    """The leaderboard rows, the anchors' record and the lines that show both."""
    from alignrl.league.standings import anchor_lines, anchor_records, leaderboard

    rows = leaderboard(league)
    anchors = anchor_records(
        league.ratings, league.anchor_payoff, league.anchor_record, league.unanchored
    )
    return rows, anchors, [*_leaderboard_lines(rows), *anchor_lines(anchors)]


def _emit_with_league_report(
    payload: dict[str, Any],
    as_json: bool,
    lines: list[str],
    run_dir: Path,
    rows: list[dict[str, Any]],
) -> None:
    """The table first (drawing the report takes a while), then the report and where it went."""
    from alignrl.league.report import write_league_report

    if not as_json:
        print("\n".join(lines), flush=True)
    report = write_league_report(run_dir, rows)
    _emit(
        {**payload, "report": str(report)},
        as_json,
        [f"report: {report} and {report.with_suffix('.html')}"],
    )


def _run_league(
    start: Callable[[RunLock], Any], args: argparse.Namespace, run_dir: Path, new: bool
) -> int:
    """The one way of every league that plays (league run and resume): lock `run_dir` (a
    second process on the same run is refused at once, before either reads or writes a file
    of it), `start` the League under the lock, play it to its schedule and report it."""
    from alignrl.runs.lock import RunLock

    with RunLock(run_dir, create=new) as lock:
        return _played(start(lock), args)


def _played(league: Any, args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from alignrl.agents.sac import NonFiniteError
    from alignrl.deploy.align import operator_signals
    from alignrl.league.loop import WorkerFailedError
    from alignrl.league.sessions import lines_of_test

    log = None if args.quiet else (lambda line: tqdm.write(line, file=sys.stderr))
    started = time.perf_counter()
    try:
        with operator_signals():  # SIGTERM stops the league as Ctrl-C does
            league.run(progress=not args.quiet, log=log)
    except KeyboardInterrupt:
        print(
            f"\ninterrupted at iteration {league.iteration}; the last checkpoint is kept: "
            f"continue with `alignrl league resume {league.run_dir}`",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except (NonFiniteError, WorkerFailedError) as error:
        raise CommandError(
            f"league stopped: {error}; the last checkpoint in {league.run_dir} is intact"
        ) from None
    except ShieldStop as error:
        raise _checkpoint_kept(error, league.run_dir, "alignrl league resume") from None
    finally:
        league.close()  # a Ray backend's workers
    rows, anchors, lines = _standing(league)
    test = league.test()  # the champion on the test session, which chose nothing
    payload = {
        "run": str(league.run_dir),
        "iterations": league.iteration,
        "env_steps": league.env_steps,
        "seconds": round(time.perf_counter() - started, 1),
        "leaderboard": rows,
        "anchors": anchors,
        "test": test,
    }
    if test:
        lines += ["", *lines_of_test(test)]
    _emit_with_league_report(payload, args.json, lines, league.run_dir, rows)
    return 0


def cmd_league_run(args: argparse.Namespace) -> int:
    from alignrl.league.config import load_league
    from alignrl.league.loop import League

    overrides = _overrides(args)
    config, aligners, misaligners = load_league(args.config, overrides)
    config, run_dir = _new_run(config, overrides, args)

    def created(lock: RunLock) -> Any:
        _replace_run(lock, args.force, "alignrl league resume")
        return League.create(config, aligners, misaligners, args.runs_dir)

    return _run_league(created, args, run_dir, new=True)


def cmd_league_resume(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League

    return _run_league(lambda _: League.resume(args.run), args, Path(args.run), new=False)


def _status(run: str) -> Any:
    """What `league status` shows (alignrl.league.standings.LeagueStatus): read from the
    config and the last checkpoint's league state alone; a run without a checkpoint as
    League.resume starts it, from its rosters."""
    from alignrl.league.standings import LeagueStatus, read_status

    status = read_status(run)
    if status is not None:
        return status
    from alignrl.league.loop import League

    league = League.resume(run, read_only=True)
    return LeagueStatus(
        config=league.config,
        iteration=league.iteration,
        env_steps=league.env_steps,
        complexity=league.backend.complexity,
        members={team: league.pool.active(team) for team in ("aligner", "misaligner")},
        snapshots={
            team: [snapshot.id for snapshot in league.pool.snapshots(team)]
            for team in ("aligner", "misaligner")
        },
        best=league.best,
    )


def cmd_league_status(args: argparse.Namespace) -> int:
    from alignrl.intervals import success_text
    from alignrl.league.sessions import interval, lines_of_test

    with _working(f"reading {args.run}: its config and last checkpoint"):
        league = _status(args.run)
    sessions = league.config.sessions
    schedule = league.config.schedule
    payload = {
        "run": args.run,
        "iteration": league.iteration,
        "iterations": schedule.iterations,
        "env_steps": league.env_steps,
        "complexity": league.complexity,
        "members": league.members,
        "snapshots": league.snapshots,
        "best": [
            {
                **row,
                "session": "validation",
                "seed": sessions.validation_seed,
                "interval": interval(row["successes"], row["scenarios"]),
            }
            for row in league.best.values()
        ],
        "test": _read_test(Path(args.run)),
    }
    lines = [
        f"{args.run}: iteration {league.iteration} of {schedule.iterations}, "
        f"{league.env_steps} env steps, complexity {payload['complexity']:g}",
        *(f"  {team}s: {', '.join(ids)}" for team, ids in payload["members"].items()),
        *(
            f"  best (validation, seed {row['seed']}): {row['member']} "
            f"{success_text(row['successes'], row['scenarios'])} at iteration {row['iteration']}"
            for row in payload["best"]
        ),
    ]
    if payload["test"]:
        lines += [f"  {line}" for line in lines_of_test(payload["test"])]
    _emit(payload, args.json, lines)
    return 0


def cmd_leaderboard(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League
    from alignrl.league.sessions import lines_of_test

    with _working(f"reading {args.run}: its last checkpoint, every member and snapshot"):
        league = League.resume(args.run, read_only=True)
        rows, anchors, lines = _standing(league)
    test = _read_test(league.run_dir)
    payload = {"run": args.run, "leaderboard": rows, "anchors": anchors, "test": test}
    if test:
        lines += ["", *lines_of_test(test)]
    _emit_with_league_report(payload, args.json, lines, league.run_dir, rows)
    return 0


def _read_test(run_dir: Path) -> dict[str, Any] | None:
    """The run's test session (test.json), None before the league finished; a damaged file
    is a CommandError naming it."""
    from alignrl.league.sessions import read_test

    try:
        return read_test(run_dir)
    except ValueError as error:
        raise CommandError(str(error)) from None


def add_league_parsers(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    league = verbs.add_parser("league", help="the two-team league: run, resume, status")
    league_verbs = league.add_subparsers(dest="league_verb", required=True)
    league_run = league_verbs.add_parser("run", help="start a league from an experiment")
    league_run.add_argument("config", help="league experiment YAML, e.g. experiments/X.yaml")
    league_run.add_argument("--name", help="run name (default: the config's name)")
    league_run.add_argument("--runs-dir", default="runs", help="where run directories go")
    _add_override_options(league_run)
    league_run.add_argument(
        "--force", action="store_true", help="replace a run of the same name (it is removed)"
    )
    league_resume = league_verbs.add_parser("resume", help="continue a league from its checkpoint")
    league_resume.add_argument("run", metavar="RUN", help="a league run directory")
    for parser_ in (league_run, league_resume):
        parser_.add_argument("--quiet", action="store_true", help="no progress bar")
        parser_.add_argument("--json", action="store_true", help="machine-readable summary")
    league_run.set_defaults(handler=cmd_league_run)
    league_resume.set_defaults(handler=cmd_league_resume)
    league_status = league_verbs.add_parser("status", help="where a league run stands")
    league_status.add_argument("run", metavar="RUN", help="a league run directory")
    league_status.add_argument("--json", action="store_true", help="machine-readable summary")
    league_status.set_defaults(handler=cmd_league_status)

    board = verbs.add_parser("leaderboard", help="the members of a league run, best first")
    board.add_argument("run", metavar="RUN", help="a league run directory")
    board.add_argument("--json", action="store_true", help="machine-readable summary")
    board.set_defaults(handler=cmd_leaderboard)

"""`alignrl league run|resume|status` and `alignrl leaderboard`: the two-team league (aligners
against misaligners) run to its schedule, and its members ranked by rating and held-out
evaluation, with the league report."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from alignrl.apparatus.shield import ShieldStop
from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    CommandError,
    _add_override_options,
    _checkpoint_kept,
    _emit,
    _overrides,
    _renamed,
    _replace_run,
)


def _leaderboard_lines(rows: list[dict[str, Any]]) -> list[str]:
    header = (
        f"{'member':28} {'team':10} {'architecture':36} {'learner':7} {'rating':>7} "
        f"{'eval':>7} {'median acq':>10}  parent"
    )
    lines = [header, "-" * len(header)]
    for row in rows:
        evaluation = (
            f"{row['successes']}/{row['scenarios']}" if row["successes"] is not None else "-"
        )
        median = row["median_acquisitions"]
        lines.append(
            f"{row['member']:28} {row['team']:10} {row['architecture'][:36]:36} "
            f"{row['learner']:7} {row['rating']:7.1f} {evaluation:>7} "
            f"{'-' if median is None else f'{median:g}':>10}  {row['parent'] or ''}"
        )
    return lines


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


def _run_league(league: Any, args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from alignrl.agents.sac import NonFiniteError
    from alignrl.deploy.align import operator_signals
    from alignrl.league.loop import WorkerFailedError, leaderboard

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
    rows = leaderboard(league)
    champion = league.champion()
    payload = {
        "run": str(league.run_dir),
        "iterations": league.iteration,
        "env_steps": league.env_steps,
        "seconds": round(time.perf_counter() - started, 1),
        "leaderboard": rows,
        "champion": champion,
    }
    lines = _leaderboard_lines(rows)
    if champion:
        lines.append("")
        lines += [
            f"{label:9}: {row['member']} aligned {row['successes']}/{row['scenarios']} "
            f"held-out, median {row['median_acquisitions']:g} acquisitions"
            for label, row in champion.items()
        ]
    _emit_with_league_report(payload, args.json, lines, league.run_dir, rows)
    return 0


def cmd_league_run(args: argparse.Namespace) -> int:
    from alignrl.league.config import load_league
    from alignrl.league.loop import League

    overrides = _overrides(args)
    config, aligners, misaligners = load_league(args.config, overrides)
    if args.name is not None:
        config = _renamed(config, args.name)
    from alignrl.runs.state import with_provenance

    config = with_provenance(config, overrides, args.argv)
    _replace_run(Path(args.runs_dir) / config.name, args.force, "alignrl league resume")
    return _run_league(League.create(config, aligners, misaligners, args.runs_dir), args)


def cmd_league_resume(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League

    return _run_league(League.resume(args.run), args)


def cmd_league_status(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League

    league = League.resume(args.run, read_only=True)
    schedule = league.config.schedule
    payload = {
        "run": args.run,
        "iteration": league.iteration,
        "iterations": schedule.iterations,
        "env_steps": league.env_steps,
        "complexity": league.backend.complexity,
        "members": {team: league.pool.active(team) for team in ("aligner", "misaligner")},
        "snapshots": {
            team: [snapshot.id for snapshot in league.pool.snapshots(team)]
            for team in ("aligner", "misaligner")
        },
        "best": list(league.best.values()),
    }
    lines = [
        f"{args.run}: iteration {league.iteration} of {schedule.iterations}, "
        f"{league.env_steps} env steps, complexity {payload['complexity']:g}",
        *(f"  {team}s: {', '.join(ids)}" for team, ids in payload["members"].items()),
        *(
            f"  best: {row['member']} {row['successes']}/{row['scenarios']} at iteration "
            f"{row['iteration']}"
            for row in payload["best"]
        ),
    ]
    _emit(payload, args.json, lines)
    return 0


def cmd_leaderboard(args: argparse.Namespace) -> int:
    from alignrl.league.loop import League, leaderboard

    league = League.resume(args.run, read_only=True)
    rows = leaderboard(league)
    payload = {"run": args.run, "leaderboard": rows}
    _emit_with_league_report(payload, args.json, _leaderboard_lines(rows), league.run_dir, rows)
    return 0


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

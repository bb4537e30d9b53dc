"""Where a league stands, as rows: its leaderboard (every active member, kept snapshot and
anchor, each team best first by the rating's ordinal mu - 3 sigma) and its anchors' record.

A member's success figure is that of its best validation session (`"session": "validation"`)
with its 95 % Wilson interval; an anchor has none (it is judged on the test session with the
champion: alignrl.league.sessions), only its record in the league's rated matches: how many of
the starts the aligners were given it aligned within spec. These rows are what `alignrl
leaderboard` prints and gives as `--json`, and what the report's tables show.

`read_status` is what `alignrl league status` shows, read from the run directory's
config.yaml and last checkpoint's league state alone: no member is loaded, no backend built
(a few seconds fewer, and nothing started where the league plays on Ray).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.intervals import success_text
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.sessions import VALIDATION, interval

if TYPE_CHECKING:
    from alignrl.league.config import LeagueConfig

__all__ = [
    "ANCHOR_ARCHITECTURE",
    "LeagueStatus",
    "anchor_lines",
    "anchor_records",
    "leaderboard",
    "read_status",
]

ANCHOR_ARCHITECTURE = "classical controller (anchor)"


def _rating(league: Any, player: str) -> dict[str, float]:
    rating = league.ratings.rating(player)
    return {
        "rating": round(rating.mu, 2),
        "sigma": round(rating.sigma, 2),
        "ordinal": round(rating.ordinal, 2),
    }


def leaderboard(league: Any) -> list[dict[str, Any]]:
    """Every active member, kept snapshot and anchor of `league` (an
    alignrl.league.loop.League), per team, best first by ordinal."""
    rows = []
    for team in ("aligner", "misaligner"):
        for player in league.pool.candidates(team):
            spec = league.player(player).spec
            best = league.best.get(player)
            rows.append(
                {
                    "member": player,
                    "team": team,
                    "architecture": spec.architecture,
                    "learner": spec.algorithm,
                    **_rating(league, player),
                    "anchor": False,
                    "snapshot": league.pool.is_snapshot(player),
                    "session": VALIDATION if best else None,
                    "successes": best["successes"] if best else None,
                    "scenarios": best["scenarios"] if best else None,
                    "interval": interval(best["successes"], best["scenarios"]) if best else None,
                    "median_acquisitions": best["median_acquisitions"] if best else None,
                    "parent": spec.parent,
                }
            )
    for anchor in league.ratings.anchors:
        rows.append(
            {
                "member": anchor,
                "team": "aligner",
                "architecture": ANCHOR_ARCHITECTURE,
                "learner": "-",
                **_rating(league, anchor),
                "anchor": True,
                "snapshot": False,
                "session": None,
                "successes": None,
                "scenarios": None,
                "interval": None,
                "median_acquisitions": None,
                "parent": None,
            }
        )
    return sorted(rows, key=lambda row: (row["team"], -row["ordinal"]))


def anchor_records(
    ratings: Ratings, payoff: PayoffTable, record: dict[str, list[int]], unanchored: int
) -> dict[str, Any]:
    """Each anchor's record in the league's rated matches (the starts the misaligners gave
    the aligners): `record` maps it to [matches, those it aligned within spec], `payoff` holds
    each aligner's score against it. `unanchored`: rated matches no anchor played (an
    apparatus without twins: a real microscope)."""
    anchors = []
    for anchor in ratings.anchors:
        matches, successes = record.get(anchor, [0, 0])
        rating = ratings.rating(anchor)
        anchors.append(
            {
                "anchor": anchor,
                "rating": round(rating.mu, 2),
                "sigma": round(rating.sigma, 2),
                "session": "league matches",
                "matches": matches,
                "successes": successes,
                "interval": interval(successes, matches) if matches else None,
                "aligner_scores": {
                    aligner: round(payoff.win_rate(aligner, against) or 0.0, 4)
                    for aligner, against in payoff.pairs()
                    if against == anchor
                },
            }
        )
    return {"anchors": anchors, "unanchored_matches": int(unanchored)}


def anchor_lines(records: dict[str, Any]) -> list[str]:
    """The anchors' record as the terminal shows it; nothing for a league without anchors."""
    if not records["anchors"]:
        return []
    lines = [
        "anchors (fixed ratings; each aligned a twin of every rated match's column from its start):"
    ]
    for row in records["anchors"]:
        if row["matches"]:
            record = f"aligned {success_text(row['successes'], row['matches'])} within spec"
        else:
            record = "no rated match yet"
        lines.append(f"  {row['anchor']} {row['rating']:.1f} ± {row['sigma']:.1f}: {record}")
    if records["unanchored_matches"]:
        lines.append(
            f"  {records['unanchored_matches']} rated matches without anchors: their "
            "apparatus gives no twin of its column (a real microscope)"
        )
    return lines


@dataclass(frozen=True)
class LeagueStatus:
    """Where a league run stands as of its last checkpoint, as League.resume would give it:
    the iteration, the env steps, the curriculum's complexity, each team's active members and
    kept snapshots (ids, oldest snapshot first) and the best validation session per aligner."""

    config: LeagueConfig
    iteration: int
    env_steps: int
    complexity: float
    members: dict[str, list[str]]
    snapshots: dict[str, list[str]]
    best: dict[str, dict[str, Any]]


def read_status(run_dir: str | Path) -> LeagueStatus | None:
    """The status of the league in `run_dir` from config.yaml and the league state of its
    last checkpoint (checked as a resume checks it); None where it has no checkpoint (a run
    directory that lost its checkpoints: League.resume then starts from the rosters)."""
    from alignrl.checkpoints import load_checkpoint
    from alignrl.envs.curriculum import Curriculum
    from alignrl.league.checkpointing import check_state_format, latest_checkpoint
    from alignrl.league.config import parse_league
    from alignrl.league.matchmaking import TEAMS, OpponentPool
    from alignrl.runs.state import CONFIG_FILE, run_config_data

    run_dir = Path(run_dir)
    config = parse_league(run_config_data(run_dir, "league run"), str(run_dir / CONFIG_FILE))
    latest = latest_checkpoint(run_dir)
    if latest is None:
        return None
    path = run_dir / "checkpoints" / latest / "league.pt"
    state = load_checkpoint(path)
    check_state_format(state, path)
    pool = OpponentPool(config.matchmaking.max_snapshots)
    pool.load_state_dict(state["pool"])
    complexity = float(config.complexity)
    curriculum = Curriculum.from_config(config.curriculum)
    if curriculum:  # the level League.resume sets the backend to
        if state["curriculum"]:
            curriculum.load_state_dict(state["curriculum"])
        complexity = float(curriculum.level)
    return LeagueStatus(
        config=config,
        iteration=int(state["iteration"]),
        env_steps=int(state["env_steps"]),
        complexity=complexity,
        members={team: pool.active(team) for team in TEAMS},
        snapshots={team: [snapshot.id for snapshot in pool.snapshots(team)] for team in TEAMS},
        best=json.loads(state["best"]),
    )

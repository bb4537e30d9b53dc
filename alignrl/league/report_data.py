"""What a league report reads from a run directory (`read_league_run`): the last
checkpoint's ratings and payoff table, the metrics CSVs, the rosters, best/best.json and
config.yaml; it writes nothing. Read strictly (a CSV cell that is not a number names its
file, line and column), but a file the league has not written yet is no error: its table has
zero rows, and the report says why (`LeagueRun.why_empty`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.checkpoints import load_checkpoint
from alignrl.league.checkpointing import latest_checkpoint
from alignrl.league.matchmaking import TEAMS
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.report_figures import member_teams
from alignrl.metrics import LINEAGE_COLUMNS
from alignrl.plots import ReportError, read_metrics_csv, read_yaml_mapping

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["Checkpoint", "LeagueRun", "read_league_run"]

ITERATION_COLUMNS = ("iteration", "env_steps", "matches", "success_rate", "complexity", "seconds")
EVALUATION_COLUMNS = ("iteration", "member", "successes", "scenarios", "median_acquisitions")


@dataclass(frozen=True)
class Checkpoint:
    """What the report takes from the league's last checkpoint."""

    iteration: int
    ratings: Ratings
    payoff: PayoffTable


@dataclass(frozen=True)
class LeagueRun:
    """Everything the report reads from a league's run directory."""

    run_dir: Path
    config: dict[str, Any]  # config.yaml as plain data: only shown
    iterations: pd.DataFrame  # metrics/iterations.csv
    evaluations: pd.DataFrame  # metrics/evaluations.csv
    lineage: pd.DataFrame  # metrics/lineage.csv
    best: list[dict[str, Any]] | None  # best/best.json; None before the first evaluation
    teams: dict[str, str]  # every member ever -> its team
    replaced: dict[str, int]  # replaced member -> the iteration it was replaced at
    checkpoint: Checkpoint | None  # None before the first checkpoint
    warm_starts: dict[str, str] = field(default_factory=dict)  # aligner -> init_from
    designs: pd.DataFrame | None = None  # metrics/designs.csv, where misaligners design

    def why_empty(self, relative: str) -> str:
        """Why the CSV at `relative` has no rows, for the reader."""
        state = "has no rows yet" if (self.run_dir / relative).exists() else "is missing"
        return f"{relative} {state}"


def _last_checkpoint(run_dir: Path) -> Checkpoint | None:
    latest = latest_checkpoint(run_dir)
    if latest is None:
        return None
    state = load_checkpoint(run_dir / "checkpoints" / latest / "league.pt")
    if int(state["iteration"]) == 0:
        return None  # the start League.create checkpoints: nothing rated or played yet
    ratings, payoff = Ratings(), PayoffTable()
    ratings.load_state_dict(state["ratings"])
    payoff.load_state_dict(state["payoff"])
    return Checkpoint(int(state["iteration"]), ratings, payoff)


def _best_rows(path: Path) -> list[dict[str, Any]] | None:
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ReportError(f"{path}: not valid JSON ({error})") from None


def read_league_run(run_dir: Path) -> LeagueRun:
    """Everything the report shows of the league in `run_dir` (see the module docstring)."""
    if not (run_dir / "config.yaml").exists():
        raise ReportError(
            f"{run_dir} is not a league run (no config.yaml): give runs/<name> as written by "
            "`alignrl league run`"
        )
    metrics = run_dir / "metrics"
    lineage = read_metrics_csv(
        metrics / "lineage.csv", LINEAGE_COLUMNS, text_columns=("member", "parent", "replaced")
    )
    roster_files = {team: read_yaml_mapping(run_dir / f"{team}s.yaml")["members"] for team in TEAMS}
    rosters = {team: [member["id"] for member in members] for team, members in roster_files.items()}
    warm_starts = {
        member["id"]: str(member["init_from"])
        for member in roster_files["aligner"]
        if member.get("init_from")
    }
    return LeagueRun(
        run_dir=run_dir,
        config=read_yaml_mapping(run_dir / "config.yaml"),
        iterations=read_metrics_csv(
            metrics / "iterations.csv",
            ITERATION_COLUMNS,
            text_columns=("aligner", "misaligner", "learner"),
        ),
        evaluations=read_metrics_csv(
            metrics / "evaluations.csv", EVALUATION_COLUMNS, text_columns=("member",)
        ),
        lineage=lineage,
        best=_best_rows(run_dir / "best" / "best.json"),
        teams=member_teams(rosters, lineage),
        replaced={
            member: int(iteration)
            for member, iteration in zip(lineage["replaced"], lineage["iteration"], strict=True)
        },
        checkpoint=_last_checkpoint(run_dir),
        warm_starts=warm_starts,
        designs=_designs(metrics / "designs.csv"),
    )


def _designs(path: Path) -> pd.DataFrame | None:
    """metrics/designs.csv (its parameter columns are the family's), None where absent."""
    import pandas as pd

    if not path.exists():
        return None
    frame = pd.read_csv(path)
    return frame if len(frame) else None

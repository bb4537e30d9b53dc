"""What a league report reads from a run directory (`read_league_run`): the last
checkpoint's ratings, payoff table and anchors' record, the metrics CSVs, the rosters,
best/best.json (the validation sessions' choice), test.json (the champion's test session)
and config.yaml; it writes nothing. Read strictly (a CSV cell that is not a number names its
file, line and column), but a file the league has not written yet is no error: its table has
zero rows, and the report says why (`LeagueRun.why_empty`). `member_teams` and `team_of`
give each player's team, `rating_histories` each player's ratings as arrays.

A member's CSVs (metrics/members/<id>/) count env steps as the league does, all matches
together. `member_env_steps` turns them into the member's own: the transitions it learned
from, worked out from metrics/iterations.csv (`on_own_env_steps` moves a member's tables
onto them).
"""

from __future__ import annotations

import json
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from alignrl.checkpoints import CheckpointError, load_checkpoint
from alignrl.league.checkpointing import check_state_format, latest_checkpoint
from alignrl.league.matchmaking import SNAPSHOT_MARK, TEAMS
from alignrl.league.ratings import PayoffTable, Ratings
from alignrl.league.sessions import read_test
from alignrl.league.standings import anchor_records
from alignrl.metrics import LEAGUE_EVALUATION_COLUMNS, LEAGUE_ITERATION_COLUMNS, LINEAGE_COLUMNS
from alignrl.plots import Reference
from alignrl.run_tables import ReportError, RunMetrics, read_metrics_csv, read_yaml_mapping

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "Checkpoint",
    "LeagueRun",
    "classical_references",
    "member_env_steps",
    "member_sessions",
    "member_teams",
    "on_own_env_steps",
    "rated_matches",
    "rating_histories",
    "read_league_run",
    "team_of",
]

# Read as the league writes them (alignrl.league.logs); the member ids as text.
ITERATION_COLUMNS = LEAGUE_ITERATION_COLUMNS
EVALUATION_COLUMNS = LEAGUE_EVALUATION_COLUMNS


@dataclass(frozen=True)
class Checkpoint:
    """What the report takes from the league's last checkpoint."""

    iteration: int
    ratings: Ratings
    payoff: PayoffTable
    anchors: dict[str, Any]  # alignrl.league.standings.anchor_records


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
    test: dict[str, Any] | None = None  # test.json: the champion's test session, once finished

    def why_empty(self, relative: str) -> str:
        """Why the CSV at `relative` has no rows, for the reader."""
        state = "has no rows yet" if (self.run_dir / relative).exists() else "is missing"
        return f"{relative} {state}"

    @property
    def uniform_starts(self) -> float:
        """schedule.uniform_starts of config.yaml (0 where a config predates it)."""
        return float((self.config.get("schedule") or {}).get("uniform_starts") or 0.0)


def _last_checkpoint(run_dir: Path) -> Checkpoint | None:
    latest = latest_checkpoint(run_dir)
    if latest is None:
        return None
    path = run_dir / "checkpoints" / latest / "league.pt"
    try:
        state = load_checkpoint(path)
        check_state_format(state, path)
    except CheckpointError as error:
        raise ReportError(str(error)) from None
    if int(state["iteration"]) == 0:
        return None  # the start League.create checkpoints: nothing rated or played yet
    ratings, payoff, anchor_payoff = Ratings(), PayoffTable(), PayoffTable()
    ratings.load_state_dict(json.loads(state["ratings"]))
    payoff.load_state_dict(state["payoff"])
    anchors = json.loads(state["anchors"])
    anchor_payoff.load_state_dict(anchors["payoff"])
    record = anchor_records(ratings, anchor_payoff, anchors["record"], anchors["unanchored"])
    return Checkpoint(int(state["iteration"]), ratings, payoff, record)


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
        test=_test(run_dir),
    )


def _test(run_dir: Path) -> dict[str, Any] | None:
    try:
        return read_test(run_dir)
    except ValueError as error:
        raise ReportError(str(error)) from None


def _designs(path: Path) -> pd.DataFrame | None:
    """metrics/designs.csv (its parameter columns are the family's), None where absent."""
    import pandas as pd

    if not path.exists():
        return None
    frame = pd.read_csv(path)
    return frame if len(frame) else None


# --- the players: their teams and ratings --------------------------------------------------


def member_teams(rosters: Mapping[str, Sequence[str]], lineage: pd.DataFrame) -> dict[str, str]:
    """The team of every member the league ever had: the rosters' members (team -> ids), and
    each copy made by population-based training (lineage.csv), which joins its parent's."""
    teams = {member: team for team, members in rosters.items() for member in members}
    for member, parent in zip(lineage["member"], lineage["parent"], strict=True):
        if parent not in teams:
            raise ReportError(
                f"metrics/lineage.csv: {member!r} copies {parent!r}, a member of neither "
                "roster nor an earlier copy; is the run directory complete?"
            )
        teams[member] = teams[parent]
    return teams


def team_of(player: str, teams: Mapping[str, str]) -> str:
    """The team of a player: its member's (a snapshot `x@N` is member x's)."""
    member = player.split(SNAPSHOT_MARK)[0]
    if member not in teams:
        raise ReportError(
            f"{player!r} was rated but is in neither roster (aligners.yaml, misaligners.yaml) "
            "nor metrics/lineage.csv; is the run directory complete?"
        )
    return teams[member]


def rating_histories(ratings: Ratings) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per player, anchors included, in order of first appearance: the iterations its rating
    was recorded at, and its mu and sigma there."""
    rows: dict[str, list[tuple[int, float, float]]] = {}
    for iteration, player, mu, sigma in ratings.history:
        rows.setdefault(player, []).append((iteration, mu, sigma))
    return {
        player: (
            np.array([i for i, _, _ in points]),
            np.array([mu for _, mu, _ in points]),
            np.array([sigma for _, _, sigma in points]),
        )
        for player, points in rows.items()
    }


# --- a member's own env steps -------------------------------------------------------------


def rated_matches(iterations: pd.DataFrame, uniform_starts: float = 0.0) -> np.ndarray:
    """Each iteration's rated matches, those whose start its misaligner chose: all of them
    on a misaligner's turn; on an aligner's, all but the share `uniform_starts` started
    uniformly, as League.step splits them (at least one is the misaligner's)."""
    matches = iterations["matches"].to_numpy().astype(int)
    aligners_turn = (iterations["learner"] == iterations["aligner"]).to_numpy()
    uniform = [min(round(n * uniform_starts), n - 1) for n in matches.tolist()]
    return matches - np.where(aligners_turn, uniform, 0)


def member_env_steps(
    iterations: pd.DataFrame,
    lineage: pd.DataFrame,
    rosters: Collection[str] = (),
    uniform_starts: float = 0.0,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per member (never a snapshot): the league's env steps at the end of each iteration
    from the one it joined in (the rosters' members, `rosters`, the first), and the member's
    own env steps there, the transitions it has learned from in this league. An aligner
    learns from every image of its matches (the iteration's env steps); a misaligner from
    one step per match whose start it chose (not the uniform starts of an aligner's turn,
    `uniform_starts`); a copy made by population-based training starts with its parent's
    count, as it starts with its parent's replay. Snapshots learn nothing."""
    copies: dict[int, list[tuple[str, str]]] = {}
    for iteration, member, parent in zip(
        lineage["iteration"], lineage["member"], lineage["parent"], strict=True
    ):
        copies.setdefault(int(iteration), []).append((member, parent))
    own = dict.fromkeys(rosters, 0)
    points: dict[str, list[tuple[int, int]]] = {}
    previous = 0
    for row, rated in zip(
        iterations.itertuples(), rated_matches(iterations, uniform_starts).tolist(), strict=True
    ):
        league_steps = int(row.env_steps)
        for player, gained in ((row.aligner, league_steps - previous), (row.misaligner, rated)):
            if SNAPSHOT_MARK not in player:
                own[player] = own.get(player, 0) + gained
        previous = league_steps
        for member, parent in copies.get(int(row.iteration), []):
            own[member] = own.get(parent, 0)
        for member, steps in own.items():
            points.setdefault(member, []).append((league_steps, steps))
    return {
        member: (np.array([a for a, _ in rows]), np.array([b for _, b in rows]))
        for member, rows in points.items()
    }


def _at_own_steps(
    table: pd.DataFrame, steps: tuple[np.ndarray, np.ndarray], where: str
) -> pd.DataFrame:
    """`table` (an env_steps column of the league's) with the member's own env steps; rows
    of an iteration that metrics/iterations.csv does not hold yet (a league killed between
    the two writes) are left out."""
    league_steps, own_steps = steps
    kept = table[table["env_steps"] <= (league_steps[-1] if len(league_steps) else -1)]
    index = np.searchsorted(league_steps, kept["env_steps"].to_numpy())
    if not np.array_equal(league_steps[index], kept["env_steps"].to_numpy()):
        raise ReportError(
            f"{where}: a row at an env step no iteration of metrics/iterations.csv ended at; "
            "is the run directory complete?"
        )
    return kept.assign(env_steps=own_steps[index].astype(float))


def member_sessions(run: LeagueRun, member: str) -> pd.DataFrame:
    """The validation sessions of `member` (metrics/evaluations.csv) as a training run's
    evaluations table, at the league's env steps of the iteration each was held at."""
    rows = run.evaluations[run.evaluations["member"] == member]
    ends = dict(zip(run.iterations["iteration"], run.iterations["env_steps"], strict=True))
    held = rows[rows["iteration"].isin(ends)]
    return held.assign(env_steps=held["iteration"].map(ends))[
        ["env_steps", "successes", "scenarios", "median_acquisitions", "p90_acquisitions"]
    ]


def on_own_env_steps(
    metrics: RunMetrics,
    sessions: pd.DataFrame,
    steps: tuple[np.ndarray, np.ndarray] | None,
) -> RunMetrics:
    """A member's tables (metrics/members/<id>/) and its validation `sessions` (as
    `member_sessions` gives them) at the member's own env steps (`steps`, of
    member_env_steps; None: the member has not played, nor have its tables rows)."""
    if steps is None:
        steps = (np.zeros(0, int), np.zeros(0, int))
    return replace(
        metrics,
        updates=_at_own_steps(metrics.updates, steps, f"{metrics.folder}/updates.csv"),
        episodes=_at_own_steps(metrics.episodes, steps, f"{metrics.folder}/episodes.csv"),
        evaluations=_at_own_steps(sessions, steps, "metrics/evaluations.csv"),
    )


def classical_references(test: Mapping[str, Any] | None) -> list[Reference]:
    """The classical controllers of the test session (test.json), as reference lines."""
    if test is None:
        return []
    return [
        Reference(
            row["label"],
            "test session",
            int(row["successes"]),
            int(row["scenarios"]),
            float(row["median_acquisitions"]),
        )
        for row in test["rows"]
        if row["member"] is None
    ]

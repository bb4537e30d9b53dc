"""What a league writes as it plays, besides checkpoints: runs/<name>/metrics/ and tensorboard/.

    metrics/iterations.csv                  one row per iteration (LEAGUE_ITERATION_COLUMNS)
    metrics/evaluations.csv                 one row per evaluation session of an aligner
    metrics/lineage.csv                     one row per copy population-based training made
    metrics/members/<id>/updates.csv        a member's learner figures, a few rows per iteration
    metrics/members/<id>/episodes.csv       an aligner's matches as training episodes
    metrics/designs.csv                     where designing misaligners put each column
                                            (fractions of the family's box), per match
    tensorboard/                            the league's and the ratings' curves

A resumed league cuts every file back to its checkpoint (`cut_back`) and writes the rows after
it again; the CSVs are append-only (alignrl.metrics) and the events go through one
`TensorBoardLog` (alignrl.runs.state).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from alignrl.agents.agent import Agent
from alignrl.league.matches import MatchResult
from alignrl.metrics import (
    EPISODE_COLUMNS,
    LEAGUE_EVALUATION_COLUMNS,
    LEAGUE_ITERATION_COLUMNS,
    LINEAGE_COLUMNS,
    CsvLog,
    truncate_csv,
)
from alignrl.runs.state import TensorBoardLog

__all__ = ["LeagueLogs"]

MEMBER_ROWS_PER_ITERATION = 10  # about this many updates.csv rows per member and iteration


class LeagueLogs:
    """The metrics CSVs and TensorBoard events of the league in `run_dir`; making one writes
    the headers of the league's own CSVs where they are missing."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        metrics = run_dir / "metrics"
        self.iterations = CsvLog(
            metrics / "iterations.csv", list(LEAGUE_ITERATION_COLUMNS), key="iteration"
        )
        self.evaluations = CsvLog(
            metrics / "evaluations.csv", list(LEAGUE_EVALUATION_COLUMNS), key="iteration"
        )
        self.lineage = CsvLog(metrics / "lineage.csv", list(LINEAGE_COLUMNS), key="iteration")
        self.tensorboard = TensorBoardLog(run_dir / "tensorboard")
        self._members: dict[str, tuple[CsvLog, CsvLog]] = {}
        self.designs: CsvLog | None = None

    def write_designs(
        self,
        iteration: int,
        aligner: str,
        misaligner: str,
        result: MatchResult,
        names: tuple[str, ...],
    ) -> None:
        """Where the misaligner of `iteration` designed each column, one row per match, with
        the aligner's payoff and success there; a TensorBoard histogram per parameter."""
        if not names or not result.designs:
            return
        if self.designs is None:
            fields = ["iteration", "aligner", "misaligner", "match", "aligner_payoff",
                      "success", *names]  # fmt: skip
            self.designs = CsvLog(self.run_dir / "metrics" / "designs.csv", fields, "iteration")
        rows = []
        for match, (design, payoff, success) in enumerate(
            zip(result.designs, result.payoffs, result.successes, strict=True)
        ):
            row = {
                "iteration": iteration,
                "aligner": aligner,
                "misaligner": misaligner,
                "match": match,
                "aligner_payoff": round(payoff, 5),
                "success": int(success),
            }
            row.update({name: round(float(v), 5) for name, v in zip(names, design, strict=True)})
            rows.append(row)
        self.designs.write(rows)
        stacked = np.stack(result.designs)
        for column, name in enumerate(names):
            self.tensorboard.add_histogram(f"design/{name}", stacked[:, column], iteration)

    def member(self, member: str, metric_names: list[str]) -> tuple[CsvLog, CsvLog]:
        """The updates and episodes logs of `member` (made on first use)."""
        if member not in self._members:
            folder = self.run_dir / "metrics" / "members" / member
            self._members[member] = (
                CsvLog(folder / "updates.csv", ["env_steps", "updates", *metric_names]),
                CsvLog(folder / "episodes.csv", list(EPISODE_COLUMNS)),
            )
        return self._members[member]

    def write_members(
        self,
        result: MatchResult,
        members: Mapping[str, Agent],
        aligner: str,
        env_steps: int,
        first_episode: int,
        complexity: float,
    ) -> None:
        """One iteration's learner figures of each active member (of `members`) that learned,
        and the matches of `aligner`, where it is active, as its episodes, numbered from
        `first_episode`."""
        for member, rows in result.updates.items():
            if member not in members or not rows:
                continue
            agent = members[member]
            updates_log, _ = self.member(member, agent.metric_names)
            stride = max(1, len(rows) // MEMBER_ROWS_PER_ITERATION)  # not every step's
            first = agent.updates - len(rows) + 1
            updates_log.write(
                [
                    {
                        "env_steps": env_steps,
                        "updates": first + i,
                        **{key: round(value, 6) for key, value in rows[i].items()},
                    }
                    for i in range(0, len(rows), stride)
                ]
            )
        if aligner in members:
            _, episodes_log = self.member(aligner, members[aligner].metric_names)
            episodes_log.write(
                [
                    {
                        "env_steps": env_steps,
                        "episode": first_episode + i,
                        "return": round(ret, 5),
                        "success": int(ok),
                        "acquisitions": acq,
                        "complexity": complexity,
                    }
                    for i, (ret, ok, acq) in enumerate(
                        zip(result.returns, result.successes, result.acquisitions, strict=True)
                    )
                ]
            )

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.tensorboard.add_scalar(tag, value, step)

    def cut_back(self, iteration: int, env_steps: int) -> None:
        """Drop what was written after the checkpoint of `iteration` (at `env_steps`): rows of
        the league's CSVs and of every member's (also of a member that a PBT copy after the
        checkpoint made: it comes back), and TensorBoard events."""
        for log in (self.iterations, self.evaluations, self.lineage):
            log.truncate_after(iteration)
        designs = self.run_dir / "metrics" / "designs.csv"
        if designs.exists():
            truncate_csv(designs, "iteration", iteration)
        for path in sorted((self.run_dir / "metrics" / "members").glob("*/*.csv")):
            truncate_csv(path, "env_steps", env_steps)
        self.tensorboard.resume_after(iteration)

    def flush(self) -> None:
        self.tensorboard.flush()

"""What a league writes as it plays, besides checkpoints: runs/<name>/metrics/ and tensorboard/.

    metrics/iterations.csv                  one row per iteration (LEAGUE_ITERATION_COLUMNS)
    metrics/evaluations.csv                 one row per evaluation session of an aligner
    metrics/lineage.csv                     one row per copy population-based training made
    metrics/members/<id>/updates.csv        a member's learner figures, a few rows per iteration
    metrics/members/<id>/episodes.csv       an aligner's matches as training episodes
    metrics/designs.csv                     where designing misaligners put each column
                                            (fractions of the family's box), per match
    tensorboard/                            the league's and the ratings' curves, per
                                            iteration, and its settings for the HParams
                                            dashboard
    tensorboard/members/<id>/               a TensorBoard run per member, at the league's env
                                            steps (as its CSVs): learner/<name> (the mean of
                                            an iteration's updates), episode/<column> (the
                                            mean of an aligner's matches), validation/<figure>
                                            (its evaluation sessions, with the 95 % interval),
                                            and its hyperparameters for the HParams dashboard

A resumed league cuts every file back to its checkpoint (`cut_back`) and writes the rows after
it again; the CSVs are append-only (alignrl.metrics) and the events go through
`TensorBoardLog`s (alignrl.runs.state), cut back as the CSVs are.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.agents.learners import learner_defaults
from alignrl.league.matches import MatchResult
from alignrl.metrics import (
    EPISODE_COLUMNS,
    LEAGUE_EVALUATION_COLUMNS,
    LEAGUE_ITERATION_COLUMNS,
    LINEAGE_COLUMNS,
    CsvLog,
    session_figures,
    truncate_csv,
)
from alignrl.runs.state import (
    CONFIG_FILE,
    EVENT_FILES,
    TensorBoardLog,
    flat_hparams,
    run_config_data,
    run_hparams,
)

__all__ = ["DESIGN_COLUMNS", "LeagueLogs", "member_hparams"]

# The columns of metrics/designs.csv before the design parameters, one row per match.
DESIGN_COLUMNS = ("iteration", "aligner", "misaligner", "match", "aligner_payoff", "success")
MEMBER_ROWS_PER_ITERATION = 10  # about this many updates.csv rows per member and iteration


def member_hparams(spec: MemberSpec) -> dict[str, float | str]:
    """A member's settings as TensorBoard hyperparameters: team, learner, architecture, the
    member it was copied from, and every learner setting (its own, else the default)."""
    settings = {**learner_defaults(spec.algorithm), **spec.hyperparameters}
    return flat_hparams(
        {
            "team": spec.team,
            "algorithm": spec.algorithm,
            "architecture": spec.architecture,
            "parent": spec.parent or "",
            **{key: list(v) if isinstance(v, tuple) else v for key, v in settings.items()},
        }
    )


class _EvaluationLog(CsvLog):
    """metrics/evaluations.csv, each row also its member's TensorBoard figures."""

    def __init__(self, path: Path, logs: LeagueLogs) -> None:
        super().__init__(path, list(LEAGUE_EVALUATION_COLUMNS), key="iteration")
        self.logs = logs

    def write(self, rows: list[dict[str, Any]]) -> None:
        super().write(rows)
        for row in rows:
            session = str(row.get("session", "validation"))
            board = self.logs.board(str(row["member"]))
            board.add_scalars(session, session_figures(row), self.logs.env_steps)


class _LineageLog(CsvLog):
    """metrics/lineage.csv; a copy's spec (its parent's, with the new learning rate as the row
    records it, to 3 significant digits) is known from its row, for its hyperparameters
    where it is evaluated before it first plays."""

    def __init__(self, path: Path, logs: LeagueLogs) -> None:
        super().__init__(path, list(LINEAGE_COLUMNS), key="iteration")
        self.logs = logs

    def write(self, rows: list[dict[str, Any]]) -> None:
        super().write(rows)
        for row in rows:
            parent = self.logs.specs.get(str(row["parent"]))
            if parent is not None:
                rate = float(row["learning_rate"])
                self.logs.specs[str(row["member"])] = dataclasses.replace(
                    parent,
                    id=str(row["member"]),
                    parent=parent.id,
                    hyperparameters={**parent.hyperparameters, "learning_rate": rate},
                )


class LeagueLogs:
    """The metrics CSVs and TensorBoard events of the league in `run_dir`; making one writes
    the headers of the league's own CSVs where they are missing."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        metrics = run_dir / "metrics"
        self.iterations = CsvLog(
            metrics / "iterations.csv", list(LEAGUE_ITERATION_COLUMNS), key="iteration"
        )
        self.evaluations: CsvLog = _EvaluationLog(metrics / "evaluations.csv", self)
        self.lineage: CsvLog = _LineageLog(metrics / "lineage.csv", self)
        self.tensorboard = TensorBoardLog(run_dir / "tensorboard")
        self._members: dict[str, tuple[CsvLog, CsvLog]] = {}
        self._boards: dict[str, TensorBoardLog] = {}
        self.designs: CsvLog | None = None
        self.env_steps = 0  # the league's, as last written or cut back to (member events' step)
        self.specs: dict[str, MemberSpec] = {}  # the members seen, for their hyperparameters

    def _board(self, member: str) -> TensorBoardLog:
        if member not in self._boards:
            folder = self.run_dir / "tensorboard" / "members" / member
            self._boards[member] = TensorBoardLog(folder)
        return self._boards[member]

    def board(self, member: str) -> TensorBoardLog:
        """The TensorBoard run of `member`, tensorboard/members/<id>/ (made on first use), its
        hyperparameters written first where its spec is known."""
        board = self._board(member)
        if not board.has_hparams and member in self.specs:
            board.add_hparams(member_hparams(self.specs[member]), self.env_steps)
        return board

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
            fields = [*DESIGN_COLUMNS, *names]
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
        `first_episode`. In TensorBoard, the iteration's means at `env_steps`, and the
        league's settings and each active member's hyperparameters once."""
        self.env_steps = env_steps
        if not self.tensorboard.has_hparams and (self.run_dir / CONFIG_FILE).exists():
            settings = run_config_data(self.run_dir, "league run")
            self.tensorboard.add_hparams(run_hparams(settings), step=0)
        for member, agent in members.items():
            self.specs[member] = agent.spec
            self.board(member)
        for member, rows in result.updates.items():
            if member not in members or not rows:
                continue
            agent = members[member]
            means = {name: float(np.mean([row[name] for row in rows])) for name in rows[0]}
            self.board(member).add_scalars("learner", means, env_steps)
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
            figures = {
                "return": result.returns,
                "success": result.successes,
                "acquisitions": result.acquisitions,
            }
            means = {name: float(np.mean(values)) for name, values in figures.items()}
            self.board(aligner).add_scalars("episode", means, env_steps)

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.tensorboard.add_scalar(tag, value, step)

    def cut_back(self, iteration: int, env_steps: int) -> None:
        """Drop what was written after the checkpoint of `iteration` (at `env_steps`): rows of
        the league's CSVs and of every member's (also of a member that a PBT copy after the
        checkpoint made: it comes back), and TensorBoard events, the league's to `iteration`
        and the members' to `env_steps` (a member's folder left empty goes)."""
        for log in (self.iterations, self.evaluations, self.lineage):
            log.truncate_after(iteration)
        designs = self.run_dir / "metrics" / "designs.csv"
        if designs.exists():
            truncate_csv(designs, "iteration", iteration)
        for path in sorted((self.run_dir / "metrics" / "members").glob("*/*.csv")):
            truncate_csv(path, "env_steps", env_steps)
        self.tensorboard.resume_after(iteration)
        self.env_steps = env_steps
        for folder in sorted((self.run_dir / "tensorboard" / "members").glob("*/")):
            self._board(folder.name).resume_after(env_steps)
            if not any(folder.glob(EVENT_FILES)):
                folder.rmdir()

    def flush(self) -> None:
        for board in (self.tensorboard, *self._boards.values()):
            board.flush()

"""What a training run (`alignrl train`, `alignrl adapt`) writes as it trains, besides its
checkpoints: runs/<name>/metrics/ and tensorboard/, the same figures in both.

    metrics/updates.csv       the learner's losses, entropy, alpha (a row per 50 SAC updates,
                              per PPO rollout)         TensorBoard learner/<name>
    metrics/episodes.csv      each training episode's return, success, acquisitions (its
                              length in images) and complexity   episode/<column>, the mean
                              of the episodes that ended at that env step
    metrics/evaluations.csv   the validation sessions, which choose checkpoints/best.pt
                                                       validation/<figure>
    metrics/test.csv          the test session of best.pt at the end, at another seed and
                              never used for a choice  test/<figure>
    tensorboard/              the events above, and the run's settings for the HParams
                              dashboard (written once)

Every TensorBoard tag has one point per env step. A resumed run cuts every file back to its
checkpoint (`cut_back`) and writes the rows and events after it again.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from alignrl.config.experiment import ExperimentConfig
from alignrl.metrics import (
    EPISODE_COLUMNS,
    EVALUATION_COLUMNS,
    TEST_COLUMNS,
    CsvLog,
    session_figures,
)
from alignrl.runs.state import TensorBoardLog, run_hparams

__all__ = ["TrainingLogs"]


class TrainingLogs:
    """The metrics CSVs and TensorBoard events of the training run in `run_dir`; making one
    writes the CSV headers where they are missing."""

    def __init__(self, run_dir: Path, metric_names: Sequence[str]) -> None:
        metrics = run_dir / "metrics"
        self.metric_names = list(metric_names)
        self.updates = CsvLog(metrics / "updates.csv", ["env_steps", "updates", *metric_names])
        self.episodes = CsvLog(metrics / "episodes.csv", list(EPISODE_COLUMNS))
        self.validation = CsvLog(metrics / "evaluations.csv", list(EVALUATION_COLUMNS))
        self.test = CsvLog(metrics / "test.csv", list(TEST_COLUMNS))
        self.tensorboard = TensorBoardLog(run_dir / "tensorboard")

    def write_hparams(self, config: ExperimentConfig) -> None:
        """The run's settings, once per run (a resumed run that has them writes nothing)."""
        self.tensorboard.add_hparams(run_hparams(config.model_dump(mode="json")))

    def write_episodes(self, rows: list[dict[str, Any]], curriculum: bool) -> None:
        """The episodes that ended at one env step; TensorBoard gets their mean (the
        complexity only where a curriculum moves it)."""
        if not rows:
            return
        self.episodes.write(rows)
        columns = ["return", "success", "acquisitions", *(["complexity"] if curriculum else [])]
        means = {name: float(np.mean([row[name] for row in rows])) for name in columns}
        self.tensorboard.add_scalars("episode", means, int(rows[0]["env_steps"]))

    def write_updates(self, rows: list[dict[str, Any]]) -> None:
        """The learner's rows of one env step; TensorBoard gets their mean."""
        if not rows:
            return
        self.updates.write(rows)
        means = {name: float(np.mean([row[name] for row in rows])) for name in self.metric_names}
        self.tensorboard.add_scalars("learner", means, int(rows[0]["env_steps"]))

    def write_validation(self, row: dict[str, Any]) -> None:
        self.validation.write([row])
        self.tensorboard.add_scalars("validation", session_figures(row), int(row["env_steps"]))

    def write_test(self, row: dict[str, Any]) -> None:
        self.test.write([row])
        self.tensorboard.add_scalars("test", session_figures(row), int(row["env_steps"]))

    def cut_back(self, env_steps: int) -> None:
        """Drop the rows and events written after the checkpoint at `env_steps`."""
        for log in (self.updates, self.episodes, self.validation, self.test):
            log.truncate_after(env_steps)
        self.tensorboard.resume_after(env_steps)

    def flush(self) -> None:
        self.tensorboard.flush()

    def close(self) -> None:
        self.tensorboard.close()

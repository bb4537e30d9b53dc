"""The metrics CSVs of a run directory: their columns, and an append-only writer that a
resumed run can cut back to its last checkpoint. Torch-free, so reports read it cheaply."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

__all__ = [
    "EPISODE_COLUMNS",
    "EVALUATION_COLUMNS",
    "LEAGUE_EVALUATION_COLUMNS",
    "LEAGUE_ITERATION_COLUMNS",
    "LINEAGE_COLUMNS",
    "CsvLog",
]

# metrics/episodes.csv: one row per finished training episode (alignrl train, league members)
EPISODE_COLUMNS = ("env_steps", "episode", "return", "success", "acquisitions", "complexity")
# metrics/evaluations.csv of `alignrl train`: one row per held-out evaluation session
EVALUATION_COLUMNS = (
    "env_steps",
    "successes",
    "scenarios",
    "median_acquisitions",
    "p90_acquisitions",
    "median_final_px",
    "seconds",
)
# A league's metrics/: one row per iteration, per evaluation session, per PBT copy.
LEAGUE_ITERATION_COLUMNS = (
    "iteration",
    "env_steps",
    "aligner",
    "misaligner",
    "learner",
    "matches",
    "success_rate",
    "mean_acquisitions",
    "aligner_payoff",
    "aligner_rating",
    "misaligner_rating",
    "complexity",
    "seconds",
)
LEAGUE_EVALUATION_COLUMNS = (
    "iteration",
    "member",
    "successes",
    "scenarios",
    "median_acquisitions",
    "p90_acquisitions",
    "rating",
)
LINEAGE_COLUMNS = ("iteration", "member", "parent", "replaced", "learning_rate")


class CsvLog:
    """Append-only CSV with a fixed header; rows past a checkpoint's count of `key` (env
    steps, league iterations) are dropped on resume."""

    def __init__(self, path: Path, fields: list[str], key: str = "env_steps") -> None:
        self.path, self.fields, self.key = path, fields, key
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            with path.open("w", newline="") as handle:
                csv.writer(handle).writerow(fields)

    def truncate_after(self, count: int) -> None:
        with self.path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        kept = [row for row in rows if int(row[self.key]) <= count]
        text = (
            ",".join(self.fields)
            + "\n"
            + "".join(",".join(row[field] for field in self.fields) + "\n" for row in kept)
        )
        from alignrl.checkpoints import atomic_write_text  # (torch loads only when needed)

        atomic_write_text(self.path, text)

    def write(self, rows: list[dict[str, Any]]) -> None:
        if not rows:
            return
        with self.path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, self.fields)
            writer.writerows(rows)

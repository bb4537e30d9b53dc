"""The metrics CSVs of a run directory: their columns, and an append-only writer that a
resumed run can cut back to its last checkpoint. Torch-free, so reports read it cheaply."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

from alignrl.checkpoints import atomic_write_text
from alignrl.intervals import wilson

__all__ = [
    "EPISODE_COLUMNS",
    "EVALUATION_COLUMNS",
    "LEAGUE_EVALUATION_COLUMNS",
    "LEAGUE_ITERATION_COLUMNS",
    "LINEAGE_COLUMNS",
    "TEST_COLUMNS",
    "CsvLog",
    "session_figures",
    "truncate_csv",
]

# metrics/episodes.csv: one row per finished training episode (alignrl train, league members)
EPISODE_COLUMNS = ("env_steps", "episode", "return", "success", "acquisitions", "complexity")
# metrics/evaluations.csv of `alignrl train`: one row per validation session (the sessions
# that choose checkpoints/best.pt), at the env steps it was held
EVALUATION_COLUMNS = (
    "env_steps",
    "successes",
    "scenarios",
    "median_acquisitions",
    "p90_acquisitions",
    "median_final_px",
    "seconds",
)
# metrics/test.csv of `alignrl train`: the test session of best.pt at the end of the run (at
# env_steps), another seed than the validation sessions', never used for a choice; the
# successes' 95 % Wilson interval as rates
TEST_COLUMNS = (
    "env_steps",
    "checkpoint_env_steps",
    "seed",
    "successes",
    "scenarios",
    "success_rate_low",
    "success_rate_high",
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


def _rows_of(text: str) -> list[list[str]]:
    """The complete rows of a CSV's text: a last line without its line break is the row a
    kill cut short, and is left out."""
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    return list(csv.reader(io.StringIO(text, newline="")))


def _csv_text(rows: list[list[str]]) -> str:
    buffer = io.StringIO(newline="")
    csv.writer(buffer).writerows(rows)
    return buffer.getvalue()


def _named(error: OSError, path: Path) -> OSError:
    if error.filename is not None:
        return error
    return OSError(error.errno, error.strerror or str(error), str(path))


def truncate_csv(path: Path, key: str, count: int) -> None:
    """Keep the rows of the CSV at `path` whose `key` is at most `count`, and its header; a row
    cut short by a kill goes too. The file is left as it is where nothing changes (a resumed
    run that is already finished writes nothing)."""
    with path.open(newline="") as handle:
        text = handle.read()
    header, *rows = _rows_of(text) or [[]]
    if not header:
        return  # made and killed before its header: CsvLog writes one
    if key not in header:
        raise ValueError(f"{path}: no column {key!r} (the header is {','.join(header)})")
    column = header.index(key)
    kept = [row for row in rows if len(row) == len(header) and int(row[column]) <= count]
    if len(kept) == len(rows) and text.endswith("\n"):
        return
    atomic_write_text(path, _csv_text([header, *kept]))


class CsvLog:
    """Append-only CSV with a fixed header; rows past a checkpoint's count of `key` (env
    steps, league iterations) are dropped on resume."""

    def __init__(self, path: Path, fields: list[str], key: str = "env_steps") -> None:
        self.path, self.fields, self.key = path, fields, key
        if not path.exists() or path.stat().st_size == 0:  # (empty: killed as it was made)
            atomic_write_text(path, _csv_text([fields]))

    def truncate_after(self, count: int) -> None:
        truncate_csv(self.path, self.key, count)

    def write(self, rows: list[dict[str, Any]]) -> None:
        if not rows:
            return
        try:
            with self.path.open("a", newline="") as handle:
                csv.DictWriter(handle, self.fields).writerows(rows)
        except OSError as error:  # a full disk: say which file
            raise _named(error, self.path) from None


def session_figures(row: dict[str, Any]) -> dict[str, float | None]:
    """The figures of an evaluation session's row (of a training run's evaluations.csv or
    test.csv, or a league's evaluations.csv) as TensorBoard shows them: its successes, their
    rate with its 95 % Wilson interval, its acquisitions and, where the row has it, the median
    final edge width (None: not measured)."""
    successes, scenarios = int(row["successes"]), int(row["scenarios"])
    low, high = wilson(successes, scenarios)
    final = row.get("median_final_px")
    return {
        "successes": successes,
        "success_rate": successes / scenarios,
        "success_rate_low": low,
        "success_rate_high": high,
        "median_acquisitions": float(row["median_acquisitions"]),
        "p90_acquisitions": float(row["p90_acquisitions"]),
        "median_final_px": None if final in (None, "") else float(final),
    }

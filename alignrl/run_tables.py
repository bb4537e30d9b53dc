"""The metrics tables of a run directory, read strictly for a report: a training run's
metrics/*.csv (updates, episodes, validation sessions in evaluations.csv, the test session in
test.csv), a league's and its members', and its YAML files as plain data. A cell that is not a
number names its file, line and column (`ReportError`); a file not written yet is zero rows,
not an error. Writes nothing.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from alignrl.metrics import EPISODE_COLUMNS, EVALUATION_COLUMNS, TEST_COLUMNS

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "UPDATE_COUNTERS",
    "ReportError",
    "RunMetrics",
    "read_metrics_csv",
    "read_metrics_folder",
    "read_run_metrics",
    "read_yaml_mapping",
    "update_metric_columns",
]

UPDATE_COUNTERS = ("env_steps", "updates")  # the columns of updates.csv that are not plotted


class ReportError(ValueError):
    """A run directory or metrics file that cannot be reported on; the message names it."""


def _number(cell: str, blank_allowed: bool) -> float:
    if cell == "" and blank_allowed:
        return math.nan  # e.g. median_final_px of a session whose images all lacked edges
    try:
        value = float(cell)
    except ValueError:
        raise ValueError(f"{cell!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{cell!r} is not a finite number")
    return value


def read_metrics_csv(
    path: Path,
    required: Sequence[str],
    blank_allowed: Collection[str] = (),
    text_columns: Collection[str] = (),
) -> pd.DataFrame:
    """A metrics CSV as float64 columns, read strictly: every column must hold numbers (blank
    cells only in `blank_allowed`, as NaN), except `text_columns`, kept as strings (the
    member ids of a league's CSVs). A missing or empty file gives zero rows, because a run
    killed before its first update or evaluation is a run, not an error; so is a last line
    without its line break, the row a kill cut short (left out: the resumed run rewrites it)."""
    import pandas as pd

    try:
        text = path.read_text(encoding="utf-8") if path.exists() else ""
        text = text[: text.rfind("\n") + 1]
        header, *rows = csv.reader(io.StringIO(text, newline="")) if text else [[]]
    except (UnicodeDecodeError, csv.Error) as error:
        raise ReportError(f"{path}: not a CSV text file ({error})") from None
    if not header:
        return pd.DataFrame(
            {name: np.empty(0, object if name in text_columns else float) for name in required}
        )
    missing = [name for name in required if name not in header]
    if missing:
        raise ReportError(f"{path}: no column {missing[0]!r} (the header is {','.join(header)})")
    if len(set(header)) < len(header):
        raise ReportError(f"{path}: a column name appears twice in the header")
    values = np.full((len(rows), len(header)), np.nan)
    blank = [name in blank_allowed for name in header]
    numeric = [name not in text_columns for name in header]
    for index, row in enumerate(rows):
        line = index + 2  # the trainer never quotes a line break, so rows and lines agree
        if len(row) != len(header):
            raise ReportError(
                f"{path}, line {line}: {len(row)} fields, the header has {len(header)}"
            )
        for column, cell in enumerate(row):
            if not numeric[column]:
                continue
            try:
                values[index, column] = _number(cell, blank[column])
            except ValueError as problem:
                raise ReportError(
                    f"{path}, line {line}, column {header[column]}: {problem}"
                ) from None
    frame = pd.DataFrame(values, columns=header)
    for column, name in enumerate(header):
        if not numeric[column]:
            frame[name] = [row[column] for row in rows]
    return frame


@dataclass(frozen=True)
class RunMetrics:
    """The metrics tables of a run, or of a league member; a table whose file is missing has
    zero rows."""

    run_dir: Path
    updates: pd.DataFrame
    episodes: pd.DataFrame
    evaluations: pd.DataFrame  # the validation sessions
    folder: str = "metrics"  # where the CSVs are, relative to run_dir
    test: pd.DataFrame | None = None  # test.csv: a finished training run's test session

    def why_empty(self, table: str) -> str:
        """Why `table` ('updates', 'episodes', 'evaluations' or 'test') has no rows, for the
        reader."""
        path = self.run_dir / self.folder / f"{table}.csv"
        state = "is missing" if not path.exists() else "has no rows yet"
        return f"{self.folder}/{table}.csv {state}"


def _check_run_dir(run_dir: Path) -> None:
    if not run_dir.is_dir():
        raise ReportError(f"run directory {run_dir} does not exist")
    for needed in ("config.yaml", "metrics"):
        if not (run_dir / needed).exists():
            raise ReportError(
                f"{run_dir} is not a run directory (no {needed}): give runs/<name> as "
                "written by `alignrl train`"
            )


def read_metrics_folder(run_dir: Path, folder: str = "metrics") -> RunMetrics:
    """The updates, episodes, evaluations and test CSVs in run_dir/folder. A training run
    keeps them in metrics/; a league keeps each member's first two in
    metrics/members/<id>/ (its sessions are the league's)."""
    metrics = run_dir / folder
    sessions = {"blank_allowed": {"median_final_px"}}
    return RunMetrics(
        run_dir=run_dir,
        updates=read_metrics_csv(metrics / "updates.csv", UPDATE_COUNTERS),
        episodes=read_metrics_csv(metrics / "episodes.csv", EPISODE_COLUMNS),
        evaluations=read_metrics_csv(metrics / "evaluations.csv", EVALUATION_COLUMNS, **sessions),
        folder=folder,
        test=read_metrics_csv(metrics / "test.csv", TEST_COLUMNS, **sessions),
    )


def read_run_metrics(run_dir: Path) -> RunMetrics:
    """The metrics of a run directory, after checking that it is one."""
    _check_run_dir(run_dir)
    return read_metrics_folder(run_dir)


def update_metric_columns(updates: pd.DataFrame) -> list[str]:
    """The columns of updates.csv to plot: all but the step counters, in file order."""
    return [name for name in updates.columns if name not in UPDATE_COUNTERS]


def read_yaml_mapping(path: Path) -> dict[str, Any]:
    """A run's YAML file (config.yaml, a league's rosters) as plain data, for a report: only
    shown, so an older or newer config still reports. Not a mapping is a ReportError."""
    from alignrl.yaml_io import YAMLInputError, read_yaml_file

    try:
        data = read_yaml_file(path)
    except YAMLInputError as error:  # names the file and what is wrong
        raise ReportError(str(error)) from None
    if not isinstance(data, dict):
        raise ReportError(f"{path}: expected a mapping at the top level")
    return data

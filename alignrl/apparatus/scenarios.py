"""The scenario CSV: recorded focus sweeps, one alignment scenario per row (seed section 4.3).

A recording sets a lens voltage, measures the image's edge width, stores the pair and raises
the voltage, until the knob's interval is swept. The file (docs/scenarios.md) is::

    scenario,seed,knob,low,high,n_pairs,n_failed,voltage_1,edge_width_1,...,voltage_K,edge_width_K

* `scenario`   integer id of the scenario (unique in the file)
* `seed`       integer passed to `Apparatus.reset` before the sweep
* `knob`       the swept knob, e.g. `defocus`
* `low`,`high` the knob's allowed interval during the recording, volts
* `n_pairs`    how many (voltage, edge width) pairs follow; at least 5
* `n_failed`   acquisitions of the sweep that gave no value (no edges, driver fault)
* `voltage_i`  lens voltage of the i-th measurement, volts, strictly increasing along the row
* `edge_width_i` measured average edge width there, pixels (> 0)

Rows differ in length: a row ends after its `n_pairs` pairs (trailing cells absent or empty);
the header carries as many pair columns as the longest possible sweep. Files may be gzipped
(`.csv.gz`). Reading is strict: a bad cell is an error naming file, row, line and column;
nothing is dropped or repaired. Reading is bounded: a file (a gzipped one once decompressed)
holds at most MAX_TEXT_BYTES; knob values and edge widths must be physical (MAX_KNOB_VALUE,
MAX_EDGE_WIDTH_PX) and a sweep must span at least MIN_SPAN of its knob.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import io
import math
import os
import threading
import zlib
from collections.abc import Iterator, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO

import numpy as np

__all__ = [
    "META_COLUMNS",
    "MIN_PAIRS",
    "ScenarioFormatError",
    "ScenarioRecord",
    "ScenarioSet",
    "ScenarioWriter",
    "header",
    "read_scenarios",
]

META_COLUMNS = ("scenario", "seed", "knob", "low", "high", "n_pairs", "n_failed")
MIN_PAIRS = 5  # fewer points cannot locate a focus minimum
MAX_TEXT_BYTES = 200 * 1024 * 1024  # the shipped 2000 scenarios take 0.8 MB
READ_CHUNK = 1024 * 1024
INT64_LIMIT = 2**63  # ids, seeds and counts are stored as int64
MAX_KNOB_VALUE = 1e6  # |volts| (or the knob's unit) beyond any lens or stigmator setting
MAX_EDGE_WIDTH_PX = 1e6  # an edge wider than any frame
MIN_SPAN = 1e-6  # knob units a sweep must cover: less cannot locate a focus (the fit is singular)
SHOWN_CELL = 40  # characters of a bad cell echoed in a message


class ScenarioFormatError(ValueError):
    """A scenario file that breaks the format; the message names where."""


@dataclass(frozen=True)
class ScenarioRecord:
    """One recorded sweep: voltages (V) and the edge widths (px) measured at them."""

    scenario: int
    seed: int
    knob: str
    low: float
    high: float
    voltages: np.ndarray
    edge_widths: np.ndarray
    n_failed: int = 0

    @property
    def usable(self) -> bool:
        """Enough points to locate a focus minimum (and to be written)."""
        return len(self.voltages) >= MIN_PAIRS

    def to_cells(self) -> list[str]:
        cells = [
            str(self.scenario),
            str(self.seed),
            self.knob,
            repr(float(self.low)),
            repr(float(self.high)),
            str(len(self.voltages)),
            str(self.n_failed),
        ]
        for voltage, width in zip(self.voltages, self.edge_widths, strict=True):
            # repr: the shortest text that reads back as the same float, so rows round-trip.
            cells += [repr(float(voltage)), repr(float(width))]
        return cells


def header(max_pairs: int) -> list[str]:
    """The header row for files whose sweeps have at most `max_pairs` points."""
    if max_pairs < MIN_PAIRS:
        raise ValueError(f"a scenario file needs room for at least {MIN_PAIRS} pairs")
    pairs = [name for i in range(1, max_pairs + 1) for name in (f"voltage_{i}", f"edge_width_{i}")]
    return [*META_COLUMNS, *pairs]


@dataclass(frozen=True)
class ScenarioSet:
    """All scenarios of a file as padded arrays, ready for batched interpolation.

    Row s has `n_pairs[s]` valid points; beyond them `voltages` repeats its last value and
    `edge_widths` its last width, so each row stays non-decreasing.
    """

    path: str
    knob: str
    scenario_ids: np.ndarray  # (S,) int
    seeds: np.ndarray  # (S,) int
    lows: np.ndarray  # (S,) V
    highs: np.ndarray  # (S,) V
    n_pairs: np.ndarray  # (S,) int
    n_failed: np.ndarray  # (S,) int
    voltages: np.ndarray  # (S, K) V
    edge_widths: np.ndarray  # (S, K) px
    max_pairs: int  # pair columns in the header

    def __len__(self) -> int:
        return int(self.scenario_ids.size)

    def record(self, index: int) -> ScenarioRecord:
        count = int(self.n_pairs[index])
        return ScenarioRecord(
            scenario=int(self.scenario_ids[index]),
            seed=int(self.seeds[index]),
            knob=self.knob,
            low=float(self.lows[index]),
            high=float(self.highs[index]),
            voltages=self.voltages[index, :count].copy(),
            edge_widths=self.edge_widths[index, :count].copy(),
            n_failed=int(self.n_failed[index]),
        )


def _open_for_reading(path: Path) -> IO[str]:
    if _is_gzip(path):
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", newline="")
    return open(path, encoding="utf-8", newline="")


def _is_gzip(path: Path) -> bool:
    return path.suffix == ".gz"


def _read_bounded(path: Path, stored: bytes | None = None) -> bytes:
    """The file's bytes (decompressed for .gz), read in chunks and refused past
    MAX_TEXT_BYTES: a small gzip file may decompress to gigabytes. `stored`: its bytes as
    already read from the disk."""
    raw = open(path, "rb") if stored is None else io.BytesIO(stored)
    unpacked = gzip.GzipFile(fileobj=raw, mode="rb") if _is_gzip(path) else nullcontext(raw)
    chunks, size = [], 0
    with raw, unpacked as handle:
        while chunk := handle.read(READ_CHUNK):
            size += len(chunk)
            if size > MAX_TEXT_BYTES:
                what = "decompresses to" if _is_gzip(path) else "holds"
                raise ScenarioFormatError(
                    f"{path}: {what} more than {MAX_TEXT_BYTES // (1024 * 1024)} MB; a scenario "
                    "file of 100,000 scenarios takes about 40 MB"
                )
            chunks.append(chunk)
    return b"".join(chunks)


def _read_text(path: Path, stored: bytes | None = None) -> str:
    try:
        return _read_bounded(path, stored).decode("utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"scenario file {path} does not exist") from None
    except (EOFError, gzip.BadGzipFile, zlib.error, UnicodeDecodeError) as error:
        hint = ""
        if isinstance(error, EOFError):
            hint = (
                "; the last row was cut while being written (a killed recorder): decompress "
                "what is readable (zcat FILE > FILE.csv, ignoring the error), delete the last, "
                "incomplete line, and continue with --append"
            )
        raise ScenarioFormatError(
            f"{path}: cannot be read as a (gzipped) CSV: {error}{hint}"
        ) from None


class _Where:
    """Formats error locations: file, data row, line and column."""

    def __init__(self, path: Path, names: Sequence[str]) -> None:
        self.path, self.names = path, names

    def __call__(self, row: int, column: int | None, message: str) -> ScenarioFormatError:
        place = f"{self.path}, row {row} (line {row + 1})"
        if column is not None:
            name = self.names[column] if column < len(self.names) else f"#{column + 1}"
            place += f", column {name}"
        return ScenarioFormatError(f"{place}: {message}")


def _shown(text: str) -> str:
    """A cell as echoed in a message: its repr, cut short."""
    return repr(text) if len(text) <= SHOWN_CELL else f"{text[:SHOWN_CELL]!r}..."


def _number(text: str, where: _Where, row: int, column: int) -> float:
    try:
        value = float(text)
    except ValueError:
        raise where(row, column, f"{_shown(text)} is not a number") from None
    if not math.isfinite(value):
        raise where(row, column, f"{_shown(text)} is not a finite number")
    return value


def _integer(text: str, where: _Where, row: int, column: int, low: int = -INT64_LIMIT) -> int:
    """An integer cell in [low, 2^63): ids, seeds and counts are stored as int64."""
    try:
        value = int(text)
    except ValueError:  # also a number of more than 4300 digits
        raise where(row, column, f"{_shown(text)} is not an integer") from None
    if not low <= value < INT64_LIMIT:
        allowed = "[0, 2^63 - 1]" if low == 0 else "[-2^63, 2^63 - 1] (a 64-bit integer)"
        raise where(row, column, f"{_shown(text)} is outside {allowed}")
    return value


def _knob_value(text: str, where: _Where, row: int, column: int) -> float:
    value = _number(text, where, row, column)
    if abs(value) > MAX_KNOB_VALUE:
        raise where(row, column, f"{value:g} lies beyond +-{MAX_KNOB_VALUE:g}, no lens setting")
    return value


def _check_header(names: list[str], path: Path) -> int:
    """Validate the header; return the number of pair columns it declares."""
    for position, expected in enumerate(META_COLUMNS):
        found = names[position] if position < len(names) else None
        if found != expected:
            raise ScenarioFormatError(
                f"{path}, line 1 (header), column {position + 1}: expected {expected!r}, found "
                f"{found if found is None else _shown(found)}. The header must start with "
                f"{','.join(META_COLUMNS)}"
            )
    pair_names = names[len(META_COLUMNS) :]
    if len(pair_names) % 2:
        raise ScenarioFormatError(
            f"{path}, line 1 (header): the pair columns must come in (voltage_i, edge_width_i) "
            f"pairs, found an odd number ({len(pair_names)})"
        )
    max_pairs = len(pair_names) // 2
    for i in range(1, max_pairs + 1):
        got = pair_names[2 * i - 2 : 2 * i]
        want = [f"voltage_{i}", f"edge_width_{i}"]
        if got != want:
            column = len(META_COLUMNS) + 2 * i - 1
            raise ScenarioFormatError(
                f"{path}, line 1 (header), column {column}: expected {','.join(want)}, "
                f"found {_shown(','.join(got))}"
            )
    if max_pairs < MIN_PAIRS:
        raise ScenarioFormatError(
            f"{path}, line 1 (header): {max_pairs} pair columns; a scenario needs at least "
            f"{MIN_PAIRS} (voltage, edge_width) pairs"
        )
    return max_pairs


def _parse_row(cells: list[str], row: int, where: _Where, max_pairs: int) -> ScenarioRecord:
    n_meta = len(META_COLUMNS)
    if len(cells) > n_meta + 2 * max_pairs:
        raise where(row, None, f"{len(cells)} cells, but the header has {n_meta + 2 * max_pairs}")
    for column in range(n_meta):
        if column >= len(cells) or cells[column].strip() == "":
            raise where(row, column, "empty cell: every metadata column needs a value")
    scenario = _integer(cells[0], where, row, 0)
    seed = _integer(cells[1], where, row, 1, low=0)  # numpy seeds are non-negative
    knob = cells[2].strip()
    if not knob.isidentifier():
        raise where(row, 2, f"{_shown(knob)} is not a knob name")
    low = _knob_value(cells[3], where, row, 3)
    high = _knob_value(cells[4], where, row, 4)
    if not low < high:
        raise where(row, 4, f"high {high:g} must be above low {low:g}")
    if high - low < MIN_SPAN:
        raise where(
            row,
            4,
            f"the interval [{low:g}, {high:g}] spans only {high - low:.3g}; a sweep "
            f"needs at least {MIN_SPAN:g}",
        )
    n_pairs = _integer(cells[5], where, row, 5)
    n_failed = _integer(cells[6], where, row, 6)
    if n_failed < 0:
        raise where(row, 6, f"{n_failed} is negative")
    if n_pairs < MIN_PAIRS:
        raise where(
            row, 5, f"only {n_pairs} (voltage, edge_width) pairs; a scenario needs {MIN_PAIRS}"
        )
    if n_pairs > max_pairs:
        raise where(row, 5, f"{n_pairs} pairs, but the header has room for {max_pairs}")
    pair_cells = cells[n_meta:]
    for offset in range(2 * n_pairs):
        if offset >= len(pair_cells) or pair_cells[offset].strip() == "":
            raise where(
                row,
                n_meta + offset,
                f"missing cell inside the row (n_pairs says {n_pairs} pairs)",
            )
    for offset in range(2 * n_pairs, len(pair_cells)):
        if pair_cells[offset].strip() != "":
            raise where(row, n_meta + offset, f"data beyond the row's n_pairs = {n_pairs}")
    values = [_number(pair_cells[k], where, row, n_meta + k) for k in range(2 * n_pairs)]
    voltages = np.asarray(values[0::2], dtype=np.float64)
    widths = np.asarray(values[1::2], dtype=np.float64)
    for i in range(n_pairs):
        column = n_meta + 2 * i
        if not low <= voltages[i] <= high:
            raise where(
                row,
                column,
                f"{voltages[i]:g} V lies outside the row's interval [{low:g}, {high:g}]",
            )
        if i and voltages[i] <= voltages[i - 1]:
            raise where(
                row,
                column,
                f"{voltages[i]:g} V is not above the previous voltage {voltages[i - 1]:g} V; "
                "voltages must increase along a row",
            )
        if not 0 < widths[i] <= MAX_EDGE_WIDTH_PX:
            raise where(
                row,
                column + 1,
                f"edge width {widths[i]:g} px must be positive and at most "
                f"{MAX_EDGE_WIDTH_PX:g} px",
            )
    span = voltages[-1] - voltages[0]
    if span < MIN_SPAN:
        raise where(
            row,
            n_meta + 2 * (n_pairs - 1),
            f"the voltages span only {span:.3g} V; a focus curve needs at least {MIN_SPAN:g} V "
            "between its first and last point",
        )
    return ScenarioRecord(scenario, seed, knob, low, high, voltages, widths, n_failed)


def iter_records(path: str | Path, stored: bytes | None = None) -> Iterator[ScenarioRecord]:
    """Parse and validate a scenario file row by row (`stored`: its bytes as already read)."""
    path = Path(path)
    text = _read_text(path, stored)
    if text.strip() == "":
        raise ScenarioFormatError(f"{path} is empty: expected a header line, then one row each")
    if not text.endswith("\n"):
        last_line = text.count("\n") + 1
        raise ScenarioFormatError(
            f"{path}, line {last_line}: the last line is incomplete (no line end); the recorder "
            "was probably interrupted while writing it. Delete that line, then record again "
            "with --append"
        )
    reader = csv.reader(io.StringIO(text))
    try:
        names = next(reader)
    except csv.Error as error:
        raise ScenarioFormatError(f"{path}, line 1 (header): not CSV: {error}") from None
    max_pairs = _check_header(names, path)
    where = _Where(path, names)
    knob: str | None = None
    first_row_of: dict[int, int] = {}
    for row, cells in enumerate(_rows(reader, where), start=1):
        if not cells:
            raise where(row, None, "blank line inside the file")
        record = _parse_row(cells, row, where, max_pairs)
        if knob is None:
            knob = record.knob
        elif record.knob != knob:
            raise where(row, 2, f"knob {record.knob!r} differs from the file's {knob!r}")
        if record.scenario in first_row_of:
            raise where(
                row,
                0,
                f"scenario {record.scenario} already appears in row "
                f"{first_row_of[record.scenario]}",
            )
        first_row_of[record.scenario] = row
        yield record


def _rows(reader: Iterator[list[str]], where: _Where) -> Iterator[list[str]]:
    """The reader's rows; a line the csv module cannot split (a cell over its 128 KB field
    limit, a stray quote) is an error naming the row."""
    row = 0
    while True:
        row += 1
        try:
            cells = next(reader)
        except StopIteration:
            return
        except csv.Error as error:
            raise where(row, None, f"not CSV: {error}") from None
        yield cells


def read_header_pairs(path: str | Path) -> int:
    """Number of pair columns declared by an existing file's header."""
    path = Path(path)
    with _open_for_reading(path) as handle:
        try:
            names = next(csv.reader(handle), [])
        except csv.Error as error:
            raise ScenarioFormatError(f"{path}, line 1 (header): not CSV: {error}") from None
    return _check_header(names, path)


# Files parsed, by their bytes: a league or a training run builds an apparatus per environment
# and per session from the same recording (csv:default: 2000 scenarios, 0.3 s to parse and
# validate, under 1 ms to read and digest), so a process parses a file's contents once.
_READ: dict[tuple[str, bytes], ScenarioSet] = {}
_READ_KEPT = 4  # files kept (the shipped recording takes about 2 MB as arrays)
_READ_LOCK = threading.Lock()


def _stored(path: Path) -> bytes | None:
    """The file's bytes as stored; None for one that cannot be read or is too large (parsing
    it then names the error)."""
    try:
        return None if path.stat().st_size > MAX_TEXT_BYTES else path.read_bytes()
    except OSError:
        return None


def _copied(data: ScenarioSet, path: Path) -> ScenarioSet:
    """`data` as read from `path`, with arrays of its own: a caller may change them."""
    arrays = {
        name: value.copy() for name, value in vars(data).items() if isinstance(value, np.ndarray)
    }
    return replace(data, path=str(path), **arrays)


def read_scenarios(path: str | Path) -> ScenarioSet:
    """Read and validate a whole scenario file into padded arrays. Contents this process has
    read before from the same file are not parsed again; each call gets arrays of its own."""
    path = Path(path)
    stored = _stored(path)  # read once: digested, and parsed where not parsed before
    key = None
    if stored is not None:
        key = (str(path.resolve()), hashlib.blake2b(stored, digest_size=16).digest())
    with _READ_LOCK:  # (a driver's calls may run on a thread of their own)
        data = _READ.pop(key, None) if key is not None else None
        if data is not None:
            _READ[key] = data  # the most recently read is kept longest
    if data is not None:
        return _copied(data, path)
    data = _parse_scenarios(path, stored)
    if key is not None:
        with _READ_LOCK:
            _READ[key] = data
            while len(_READ) > _READ_KEPT:
                del _READ[next(iter(_READ))]
    return _copied(data, path)


def _parse_scenarios(path: Path, stored: bytes | None) -> ScenarioSet:
    records = list(iter_records(path, stored))
    if not records:
        raise ScenarioFormatError(f"{path}: a header but no scenarios")
    max_pairs = read_header_pairs(path)
    width = max(len(record.voltages) for record in records)
    voltages = np.empty((len(records), width))
    widths = np.empty((len(records), width))
    for index, record in enumerate(records):
        count = len(record.voltages)
        voltages[index, :count] = record.voltages
        voltages[index, count:] = record.voltages[-1]
        widths[index, :count] = record.edge_widths
        widths[index, count:] = record.edge_widths[-1]
    return ScenarioSet(
        path=str(path),
        knob=records[0].knob,
        scenario_ids=np.array([r.scenario for r in records], dtype=np.int64),
        seeds=np.array([r.seed for r in records], dtype=np.int64),
        lows=np.array([r.low for r in records]),
        highs=np.array([r.high for r in records]),
        n_pairs=np.array([len(r.voltages) for r in records], dtype=np.int64),
        n_failed=np.array([r.n_failed for r in records], dtype=np.int64),
        voltages=voltages,
        edge_widths=widths,
        max_pairs=max_pairs,
    )


class ScenarioWriter:
    """Writes scenario rows as they finish: each row is one write, flushed and synced, so an
    interrupted recording keeps every finished row. In a `.gz` file every row is a gzip member
    of its own (a multi-member gzip file is standard), so the file is complete after each row.

    mode "new" refuses an existing file, "force" replaces it, "append" continues it (its header
    must declare the same number of pair columns). A new file is written under a temporary
    name and takes its real name with its first row: a recording that fails or is stopped
    before any row leaves no header-only file, and `force` replaces the old file only once
    there is something to replace it with.
    """

    def __init__(self, path: str | Path, max_pairs: int, mode: str = "new") -> None:
        self.path = Path(path)
        self.max_pairs = max_pairs
        if mode not in ("new", "force", "append"):
            raise ValueError(f"mode must be new, force or append, not {mode!r}")
        exists = self.path.exists()
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path} is a folder: give a file name such as x.csv")
        if mode == "new" and exists:
            raise FileExistsError(
                f"{self.path} already exists: pass --force to replace it or --append to continue it"
            )
        if mode == "append" and exists:
            declared = read_header_pairs(self.path)
            if declared != max_pairs:
                raise ScenarioFormatError(
                    f"{self.path}: its header has {declared} pair columns, this recording needs "
                    f"{max_pairs}; append only with the same sweep settings"
                )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rows = 0
        if mode == "append" and exists:
            self._pending: Path | None = None
            self._handle = open(self.path, "ab")
        else:
            self._pending = self.path.with_name(f".{self.path.name}.recording")
            self._handle = open(self._pending, "wb")
            self._write_line(header(max_pairs))

    def _write_line(self, cells: list[str]) -> None:
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\n").writerow(cells)
        data = buffer.getvalue().encode("utf-8")
        if _is_gzip(self.path):
            data = gzip.compress(data, mtime=0)  # mtime 0: the same rows give the same bytes
        self._handle.write(data)
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def write(self, record: ScenarioRecord) -> None:
        if len(record.voltages) > self.max_pairs:
            raise ValueError(
                f"scenario {record.scenario}: {len(record.voltages)} pairs exceed the header's "
                f"{self.max_pairs}"
            )
        cells = record.to_cells()
        # The row as `alignrl scenarios validate` will read it: a recording never writes a
        # file its own validation rejects (a driver's interval beyond any lens, say).
        _parse_row(cells, self.rows + 1, _Where(self.path, header(self.max_pairs)), self.max_pairs)
        self._write_line(cells)
        self.rows += 1
        if self._pending is not None:
            # The open handle follows the file across the rename: later rows land in place.
            os.replace(self._pending, self.path)
            self._pending = None

    def close(self) -> None:
        self._handle.close()
        if self._pending is not None:
            self._pending.unlink(missing_ok=True)  # no row: nothing to show, nothing replaced
            self._pending = None

    def __enter__(self) -> ScenarioWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

"""The scenario CSV: what the writer produces the reader returns unchanged, and every way a
file can be broken is refused with a message that says where (file, row, column)."""

from __future__ import annotations

import gzip
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from alignrl.apparatus import scenarios
from alignrl.apparatus.scenarios import (
    META_COLUMNS,
    ScenarioFormatError,
    ScenarioRecord,
    ScenarioWriter,
    header,
    read_scenarios,
)
from alignrl.cli import main

MAX_PAIRS = 6  # pair columns of the hand-written files: rows of 5 pairs leave one spare
GOOD_PAIRS = (("10", "8"), ("20", "5"), ("30", "3"), ("40", "5"), ("50", "8"))


# --- helpers ----------------------------------------------------------------------------


def cells(
    scenario: int | str = 0,
    *,
    seed: int | str = 7,
    knob: str = "defocus",
    low: str = "0",
    high: str = "100",
    n_pairs: int | str | None = None,
    n_failed: int | str = 0,
    pairs: Sequence[Sequence[str]] = GOOD_PAIRS,
    trailing: Sequence[str] = (),
) -> list[str]:
    """One data row as cells; `n_pairs` defaults to the number of `pairs` given."""
    count = len(pairs) if n_pairs is None else n_pairs
    flat = [cell for pair in pairs for cell in pair]
    return [str(scenario), str(seed), knob, low, high, str(count), str(n_failed), *flat, *trailing]


def csv_text(*rows: Sequence[str], names: Sequence[str] | None = None) -> str:
    """A whole file: the header (default: MAX_PAIRS pair columns), then the rows."""
    names = header(MAX_PAIRS) if names is None else names
    return "".join(",".join(line) + "\n" for line in (names, *rows))


def write(path: Path, text: str) -> Path:
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(text.encode("utf-8")))
    else:
        path.write_bytes(text.encode("utf-8"))
    return path


def record(
    scenario: int,
    voltages: Sequence[float],
    widths: Sequence[float],
    *,
    seed: int = 0,
    knob: str = "defocus",
    low: float = 0.0,
    high: float = 100.0,
    n_failed: int = 0,
) -> ScenarioRecord:
    return ScenarioRecord(
        scenario=scenario,
        seed=seed,
        knob=knob,
        low=low,
        high=high,
        voltages=np.asarray(voltages, dtype=np.float64),
        edge_widths=np.asarray(widths, dtype=np.float64),
        n_failed=n_failed,
    )


def write_records(path: Path, records: Sequence[ScenarioRecord], max_pairs: int = 8) -> Path:
    with ScenarioWriter(path, max_pairs) as writer:
        for item in records:
            writer.write(item)
    return path


# Values with at most 6 significant digits: the writer stores them exactly.
RECORDS = (
    record(0, [0, 12.5, 25, 37.5, 50], [9.75, 6.5, 2.5625, 6.25, 9.5], seed=11, n_failed=2),
    record(
        1,
        [-4.5, 3, 10.25, 20, 30, 55.5, 70],
        [12, 8.125, 4, 2.75, 3.5, 7, 11.0625],
        seed=12,
        low=-5.0,
        high=80.0,
    ),
    record(7, [10, 20, 30, 40, 50, 60], [7, 5, 3, 2.5, 4, 6], seed=987654321, low=10, high=60),
)


def assert_where(error: pytest.ExceptionInfo, path: Path, row: int, column: str | None) -> None:
    message = str(error.value)
    assert str(path) in message
    assert f"row {row} (line {row + 1})" in message
    if column is not None:
        assert f"column {column}" in message


# --- valid files ------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_writer_then_reader_round_trips(tmp_path: Path, suffix: str) -> None:
    path = write_records(tmp_path / f"set{suffix}", RECORDS)
    if suffix == ".csv.gz":
        assert path.read_bytes()[:2] == b"\x1f\x8b"  # really gzipped
    else:
        assert path.read_text().splitlines()[0] == ",".join(header(8))
    data = read_scenarios(path)
    assert len(data) == 3
    assert data.path == str(path)
    assert data.knob == "defocus"
    assert data.max_pairs == 8
    np.testing.assert_array_equal(data.scenario_ids, [0, 1, 7])
    np.testing.assert_array_equal(data.seeds, [11, 12, 987654321])
    np.testing.assert_array_equal(data.lows, [0.0, -5.0, 10.0])
    np.testing.assert_array_equal(data.highs, [100.0, 80.0, 60.0])
    np.testing.assert_array_equal(data.n_pairs, [5, 7, 6])
    np.testing.assert_array_equal(data.n_failed, [2, 0, 0])
    assert data.voltages.shape == data.edge_widths.shape == (3, 7)
    for index, original in enumerate(RECORDS):
        count = len(original.voltages)
        np.testing.assert_array_equal(data.voltages[index, :count], original.voltages)
        np.testing.assert_array_equal(data.edge_widths[index, :count], original.edge_widths)
        # Padding repeats the last point, so each row stays non-decreasing.
        assert np.all(data.voltages[index, count:] == original.voltages[-1])
        assert np.all(data.edge_widths[index, count:] == original.edge_widths[-1])
        assert np.all(np.diff(data.voltages[index]) >= 0)
        again = data.record(index)
        assert (again.scenario, again.seed, again.knob) == (
            original.scenario,
            original.seed,
            original.knob,
        )
        assert (again.low, again.high, again.n_failed) == (
            original.low,
            original.high,
            original.n_failed,
        )
        np.testing.assert_array_equal(again.voltages, original.voltages)
        np.testing.assert_array_equal(again.edge_widths, original.edge_widths)


def test_contents_read_before_are_not_parsed_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A process parses a file's contents once (a league builds an apparatus per environment
    from one recording): each read gets arrays of its own, and a file that changed, even to
    as many bytes within the same clock tick, is parsed again."""
    parsed: list[Path] = []
    parse = scenarios._parse_scenarios
    monkeypatch.setattr(
        scenarios,
        "_parse_scenarios",
        lambda path, *stored: parsed.append(path) or parse(path, *stored),
    )
    path = write_records(tmp_path / "set.csv", RECORDS[:2])
    first = read_scenarios(path)
    first.voltages[:] = 0.0  # the caller's own
    again = read_scenarios(tmp_path / "." / "set.csv")
    assert len(parsed) == 1 and again.path == str(tmp_path / "." / "set.csv")
    np.testing.assert_array_equal(again.voltages[0, :5], RECORDS[0].voltages)
    # rewritten with one digit changed: as many bytes, and read anew
    text = path.read_text()
    path.write_text(text.replace("12.5,6.5", "12.5,6.6"))
    assert path.stat().st_size == len(text)
    assert read_scenarios(path).edge_widths[0, 1] == 6.6 and len(parsed) == 2
    with ScenarioWriter(path, 8, mode="append") as writer:  # a recorder continuing it
        writer.write(RECORDS[2])
    assert len(read_scenarios(path)) == 3 and len(parsed) == 3
    path.write_text(text.replace("12.5,6.5", "12.5,x.5"))  # and a broken one is refused
    with pytest.raises(ScenarioFormatError, match="column edge_width_2"):
        read_scenarios(path)


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_ragged_rows_with_absent_or_empty_trailing_cells_are_accepted(
    tmp_path: Path, suffix: str
) -> None:
    six = (*GOOD_PAIRS, ("60", "9"))
    text = csv_text(
        cells(0),  # trailing cells absent
        cells(1, trailing=("", "")),  # trailing cells present but empty
        cells(2, trailing=(" ", "  ")),  # blank counts as empty
        cells(3, pairs=(*GOOD_PAIRS[:4], ("45", "6")), trailing=("",)),  # one of two
        cells(4, pairs=six),  # a full row
    )
    data = read_scenarios(write(tmp_path / f"ragged{suffix}", text))
    assert len(data) == 5
    np.testing.assert_array_equal(data.n_pairs, [5, 5, 5, 5, 6])
    np.testing.assert_array_equal(data.voltages[0], [10, 20, 30, 40, 50, 50])
    np.testing.assert_array_equal(data.edge_widths[0], [8, 5, 3, 5, 8, 8])
    np.testing.assert_array_equal(data.voltages[3], [10, 20, 30, 40, 45, 45])
    np.testing.assert_array_equal(data.voltages[4], [10, 20, 30, 40, 50, 60])
    np.testing.assert_array_equal(data.edge_widths[4], [8, 5, 3, 5, 8, 9])


def test_row_with_crlf_line_ends_is_read(tmp_path: Path) -> None:
    text = csv_text(cells(0), cells(1)).replace("\n", "\r\n")
    data = read_scenarios(write(tmp_path / "crlf.csv", text))
    np.testing.assert_array_equal(data.scenario_ids, [0, 1])


# --- malformed files: the whole file ----------------------------------------------------


@pytest.mark.parametrize("content", [b"", b"\n", b"  \n\n"], ids=["zero-bytes", "newline", "blank"])
def test_empty_file_is_rejected(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "empty.csv"
    path.write_bytes(content)
    with pytest.raises(ScenarioFormatError, match="empty") as error:
        read_scenarios(path)
    assert str(path) in str(error.value)


def test_empty_gz_file_is_rejected(tmp_path: Path) -> None:
    path = write(tmp_path / "empty.csv.gz", "")
    with pytest.raises(ScenarioFormatError, match="empty") as error:
        read_scenarios(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_header_only_is_rejected(tmp_path: Path, suffix: str) -> None:
    path = write(tmp_path / f"header{suffix}", csv_text())
    with pytest.raises(ScenarioFormatError, match="no scenarios") as error:
        read_scenarios(path)
    assert str(path) in str(error.value)


def test_last_line_without_newline_is_an_incomplete_write(tmp_path: Path) -> None:
    complete = csv_text(cells(0), cells(1))
    # The recorder died in the middle of row 3 (line 4).
    partial = complete + ",".join(cells(2))[:-3]
    path = write(tmp_path / "interrupted.csv", partial)
    with pytest.raises(ScenarioFormatError, match="incomplete") as error:
        read_scenarios(path)
    assert str(path) in str(error.value)
    assert "line 4" in str(error.value)


def test_complete_row_without_final_newline_is_still_rejected(tmp_path: Path) -> None:
    path = write(tmp_path / "nonewline.csv", csv_text(cells(0)).rstrip("\n"))
    with pytest.raises(ScenarioFormatError, match="incomplete") as error:
        read_scenarios(path)
    assert "line 2" in str(error.value)


def test_truncated_gz_file_is_rejected(tmp_path: Path) -> None:
    whole = gzip.compress(csv_text(*(cells(i) for i in range(50))).encode())
    path = tmp_path / "truncated.csv.gz"
    path.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ScenarioFormatError) as error:
        read_scenarios(path)
    assert str(path) in str(error.value)


def test_gz_suffix_on_plain_text_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "plain.csv.gz"
    path.write_text(csv_text(cells(0)))
    with pytest.raises(ScenarioFormatError) as error:
        read_scenarios(path)
    assert str(path) in str(error.value)


def test_missing_file_is_file_not_found(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.csv"
    with pytest.raises(FileNotFoundError, match=r"nowhere\.csv"):
        read_scenarios(path)


# --- malformed files: the header --------------------------------------------------------


def pair_names(count: int) -> list[str]:
    return [name for i in range(1, count + 1) for name in (f"voltage_{i}", f"edge_width_{i}")]


BAD_HEADERS = {
    "wrong-metadata-name": (
        ["scenario", "seed", "knobs", "low", "high", "n_pairs", "n_failed", *pair_names(6)],
        ["'knob'", "'knobs'", "column 3"],
    ),
    "metadata-out-of-order": (
        ["seed", "scenario", "knob", "low", "high", "n_pairs", "n_failed", *pair_names(6)],
        ["'scenario'", "'seed'", "column 1"],
    ),
    "missing-metadata-column": (
        ["scenario", "seed", "knob", "low", "high", "n_pairs", *pair_names(6)],
        ["'n_failed'", "column 7"],
    ),
    "wrong-pair-names": (
        [*META_COLUMNS, "voltage_1", "width_1", *pair_names(6)[2:]],
        ["voltage_1,edge_width_1", "width_1", "column 8"],
    ),
    "pairs-swapped": (
        [*META_COLUMNS, *pair_names(2), "edge_width_3", "voltage_3", *pair_names(6)[6:]],
        ["voltage_3,edge_width_3", "column 12"],
    ),
    "pairs-misnumbered": (
        [*META_COLUMNS, *pair_names(2), "voltage_4", "edge_width_4", *pair_names(6)[6:]],
        ["voltage_3,edge_width_3", "voltage_4"],
    ),
    "odd-number-of-pair-columns": (
        [*META_COLUMNS, *pair_names(6), "voltage_7"],
        ["odd", "13"],
    ),
    "fewer-than-5-pairs": (
        [*META_COLUMNS, *pair_names(4)],
        ["4 pair columns", "at least 5"],
    ),
    "no-pair-columns": (list(META_COLUMNS), ["0 pair columns"]),
}


@pytest.mark.parametrize("names, fragments", BAD_HEADERS.values(), ids=BAD_HEADERS.keys())
def test_bad_header_is_rejected(tmp_path: Path, names: list[str], fragments: list[str]) -> None:
    # Rows that fit the good header; the reader must stop at the header already.
    path = write(tmp_path / "header.csv", csv_text(cells(0), names=names))
    with pytest.raises(ScenarioFormatError) as error:
        read_scenarios(path)
    message = str(error.value)
    assert str(path) in message
    assert "line 1 (header)" in message
    for fragment in fragments:
        assert fragment in message


def test_header_helper_refuses_fewer_than_5_pairs() -> None:
    with pytest.raises(ValueError, match="at least 5"):
        header(4)
    assert header(5)[-2:] == ["voltage_5", "edge_width_5"]


# --- malformed files: one bad row -------------------------------------------------------

P = GOOD_PAIRS
BAD_ROWS = {
    # name: (the bad row, column named in the message or None, message fragment)
    "empty-voltage-cell-inside": (
        cells(1, pairs=(P[0], P[1], ("", "3"), P[3], P[4])),
        "voltage_3",
        "missing cell",
    ),
    "empty-width-cell-inside": (
        cells(1, pairs=(P[0], P[1], ("30", ""), P[3], P[4])),
        "edge_width_3",
        "missing cell",
    ),
    "blank-width-cell-inside": (
        cells(1, pairs=(P[0], P[1], P[2], ("40", "  "), P[4])),
        "edge_width_4",
        "missing cell",
    ),
    "row-ends-before-n_pairs": (cells(1, n_pairs=5, pairs=P[:4]), "voltage_5", "missing cell"),
    "row-ends-mid-pair": (
        cells(1, n_pairs=5, pairs=P[:4], trailing=("50",)),
        "edge_width_5",
        "missing cell",
    ),
    "missing-seed": (cells(1, seed=""), "seed", "empty cell"),
    "missing-scenario": (cells(""), "scenario", "empty cell"),
    "missing-knob": (cells(1, knob=" "), "knob", "empty cell"),
    "missing-low": (cells(1, low=""), "low", "empty cell"),
    "missing-n_pairs": (cells(1, n_pairs=""), "n_pairs", "empty cell"),
    "missing-n_failed": (cells(1, n_failed=""), "n_failed", "empty cell"),
    "row-shorter-than-metadata": (["1", "7", "defocus", "0"], "high", "empty cell"),
    "non-numeric-voltage": (
        cells(1, pairs=(P[0], ("abc", "5"), *P[2:])),
        "voltage_2",
        "'abc' is not a number",
    ),
    "non-numeric-edge-width": (
        cells(1, pairs=(*P[:3], ("40", "5px"), P[4])),
        "edge_width_4",
        "'5px' is not a number",
    ),
    "non-numeric-low": (cells(1, low="zero"), "low", "'zero' is not a number"),
    "nan-voltage": (cells(1, pairs=(("nan", "8"), *P[1:])), "voltage_1", "not a finite"),
    "NaN-edge-width": (cells(1, pairs=(*P[:4], ("50", "NaN"))), "edge_width_5", "not a finite"),
    "inf-voltage": (cells(1, pairs=(*P[:4], ("inf", "8"))), "voltage_5", "not a finite"),
    "minus-inf-voltage": (cells(1, pairs=(("-inf", "8"), *P[1:])), "voltage_1", "not a finite"),
    "inf-edge-width": (
        cells(1, pairs=(P[0], ("20", "Infinity"), *P[2:])),
        "edge_width_2",
        "finite",
    ),
    "nan-high": (cells(1, high="nan"), "high", "not a finite"),
    "inf-high": (cells(1, high="inf"), "high", "not a finite"),
    "equal-voltages": (
        cells(1, pairs=(P[0], P[1], ("20", "3"), P[3], P[4])),
        "voltage_3",
        "not above the previous",
    ),
    "decreasing-voltages": (
        cells(1, pairs=(P[0], P[1], P[2], ("25", "5"), P[4])),
        "voltage_4",
        "not above the previous",
    ),
    "voltage-above-high": (
        cells(1, high="45"),
        "voltage_5",
        "outside the row's interval",
    ),
    "voltage-below-low": (cells(1, low="15"), "voltage_1", "outside the row's interval"),
    "voltage-beyond-global-high": (
        cells(1, pairs=(*P[:4], ("100.5", "8"))),
        "voltage_5",
        "outside the row's interval",
    ),
    "low-equals-high": (cells(1, low="100", high="100"), "high", "must be above low"),
    "low-above-high": (cells(1, low="100", high="5"), "high", "must be above low"),
    "fewer-than-5-points": (cells(1, pairs=P[:3]), "n_pairs", "only 3"),
    "zero-points": (cells(1, n_pairs=0, pairs=()), "n_pairs", "only 0"),
    "negative-n_pairs": (cells(1, n_pairs=-5, pairs=()), "n_pairs", "only -5"),
    "n_pairs-beyond-header": (
        cells(1, n_pairs=7, pairs=(*P, ("60", "9"))),
        "n_pairs",
        "room for 6",
    ),
    "data-beyond-n_pairs": (cells(1, n_pairs=5, pairs=(*P, ("60", "9"))), "voltage_6", "beyond"),
    "width-beyond-n_pairs": (
        cells(1, n_pairs=5, pairs=P, trailing=("", "9")),
        "edge_width_6",
        "beyond",
    ),
    "too-many-cells": (cells(1, pairs=(*P, ("60", "9")), trailing=("",)), None, "20 cells"),
    "zero-edge-width": (cells(1, pairs=(P[0], ("20", "0"), *P[2:])), "edge_width_2", "positive"),
    "negative-edge-width": (cells(1, pairs=(*P[:4], ("50", "-1.5"))), "edge_width_5", "positive"),
    "duplicated-scenario-id": (cells(0), "scenario", "scenario 0 already appears in row 1"),
    "different-knob": (cells(1, knob="stigmator_x"), "knob", "'stigmator_x' differs"),
    "bad-knob-name": (cells(1, knob="de focus"), "knob", "not a knob name"),
    "non-integer-seed": (cells(1, seed="1.5"), "seed", "'1.5' is not an integer"),
    "non-numeric-seed": (cells(1, seed="s1"), "seed", "'s1' is not an integer"),
    "non-integer-scenario": (cells("1.0"), "scenario", "not an integer"),
    "non-integer-n_pairs": (cells(1, n_pairs="5.0"), "n_pairs", "not an integer"),
    "non-integer-n_failed": (cells(1, n_failed="two"), "n_failed", "not an integer"),
    "negative-n_failed": (cells(1, n_failed=-1), "n_failed", "negative"),
    "blank-line": ([], None, "blank line"),
}


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
@pytest.mark.parametrize("bad, column, fragment", BAD_ROWS.values(), ids=BAD_ROWS.keys())
def test_bad_row_is_rejected_with_file_row_and_column(
    tmp_path: Path, suffix: str, bad: list[str], column: str | None, fragment: str
) -> None:
    # A good row 1 (scenario 0), the bad row 2, a good row 3: the error must name row 2.
    path = write(tmp_path / f"bad{suffix}", csv_text(cells(0), bad, cells(2)))
    with pytest.raises(ScenarioFormatError) as error:
        read_scenarios(path)
    assert_where(error, path, 2, column)
    assert fragment in str(error.value)


def test_error_names_the_first_bad_row_not_a_later_one(tmp_path: Path) -> None:
    rows = [cells(i) for i in range(6)]
    rows[4] = cells(4, seed="x")
    rows[5] = cells(5, low="y")
    path = write(tmp_path / "late.csv", csv_text(*rows))
    with pytest.raises(ScenarioFormatError) as error:
        read_scenarios(path)
    assert_where(error, path, 5, "seed")


def test_format_error_is_a_value_error() -> None:
    assert issubclass(ScenarioFormatError, ValueError)


# --- the writer's modes -----------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_mode_new_refuses_an_existing_file_and_leaves_it_alone(tmp_path: Path, suffix: str) -> None:
    path = write_records(tmp_path / f"set{suffix}", RECORDS[:1])
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="already exists"):
        ScenarioWriter(path, 8)
    with pytest.raises(FileExistsError):
        ScenarioWriter(path, 8, mode="new")
    assert path.read_bytes() == before


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_mode_append_with_other_pair_count_raises_and_leaves_file_alone(
    tmp_path: Path, suffix: str
) -> None:
    path = write_records(tmp_path / f"set{suffix}", RECORDS[:1], max_pairs=8)
    before = path.read_bytes()
    with pytest.raises(ScenarioFormatError, match="8 pair columns"):
        ScenarioWriter(path, 9, mode="append")
    with pytest.raises(ValueError):
        ScenarioWriter(path, 5, mode="append")
    assert path.read_bytes() == before


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_mode_append_continues_the_file(tmp_path: Path, suffix: str) -> None:
    path = write_records(tmp_path / f"set{suffix}", RECORDS[:1])
    with ScenarioWriter(path, 8, mode="append") as writer:
        writer.write(RECORDS[1])
        writer.write(RECORDS[2])
    data = read_scenarios(path)
    np.testing.assert_array_equal(data.scenario_ids, [0, 1, 7])
    if suffix == ".csv":
        assert path.read_text().count("scenario,seed") == 1  # a single header


def test_mode_append_creates_a_missing_file_with_header(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "fresh.csv"
    with ScenarioWriter(path, 8, mode="append") as writer:
        writer.write(RECORDS[0])
    assert read_scenarios(path).max_pairs == 8


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_mode_force_replaces_the_file(tmp_path: Path, suffix: str) -> None:
    path = write_records(tmp_path / f"set{suffix}", RECORDS, max_pairs=8)
    with ScenarioWriter(path, 6, mode="force") as writer:
        writer.write(RECORDS[2])
    data = read_scenarios(path)
    np.testing.assert_array_equal(data.scenario_ids, [7])
    assert data.max_pairs == 6


def test_mode_force_replaces_even_a_broken_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.csv"
    path.write_text("garbage without newline")
    with ScenarioWriter(path, 8, mode="force") as writer:
        writer.write(RECORDS[0])
    np.testing.assert_array_equal(read_scenarios(path).scenario_ids, [0])


def test_writer_refuses_unknown_mode_and_too_long_records(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"):
        ScenarioWriter(tmp_path / "x.csv", 8, mode="overwrite")
    assert not (tmp_path / "x.csv").exists()
    path = tmp_path / "short.csv"
    with ScenarioWriter(path, 6) as writer:
        with pytest.raises(ValueError, match="exceed"):
            writer.write(RECORDS[1])  # 7 pairs
        writer.write(RECORDS[0])
    np.testing.assert_array_equal(read_scenarios(path).scenario_ids, [0])


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
def test_finished_rows_are_readable_before_close(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"live{suffix}"
    writer = ScenarioWriter(path, 8)
    try:
        writer.write(RECORDS[0])
        writer.write(RECORDS[1])
        # What a killed recorder leaves behind: the bytes on disk before close().
        snapshot = tmp_path / f"killed{suffix}"
        snapshot.write_bytes(path.read_bytes())
    finally:
        writer.close()
    np.testing.assert_array_equal(read_scenarios(path).scenario_ids, [0, 1])
    np.testing.assert_array_equal(read_scenarios(snapshot).scenario_ids, [0, 1])


# --- precision of the writer ------------------------------------------------------------


def test_writer_round_trips_full_precision_floats(tmp_path: Path) -> None:
    voltages = np.array([0.0, 13.0 / 3.0, 17.123456789, 42.987654321, 77.7777777, 100.0])
    widths = np.array([9.87654321, 5.5555555, 2.5631234567, 3.14159265, 6.0, 11.0 / 7.0])
    path = write_records(tmp_path / "precise.csv", [record(0, voltages, widths)])
    data = read_scenarios(path)
    np.testing.assert_array_equal(data.voltages[0], voltages)
    np.testing.assert_array_equal(data.edge_widths[0], widths)


@pytest.mark.parametrize(
    "low, high, voltages",
    [
        (-12.3456789, 87.6543211, [-12.3456789, 10.0, 30.0, 50.0, 87.6543211]),
        (0.0, 100.0, [0.0, 25.0, 50.0, 99.99996, 100.0]),
    ],
    ids=["bounds-with-many-digits", "voltages-collapse"],
)
def test_writer_output_is_always_readable(
    tmp_path: Path, low: float, high: float, voltages: list[float]
) -> None:
    item = record(0, voltages, [9.0, 5.0, 3.0, 5.0, 9.0], low=low, high=high)
    path = write_records(tmp_path / "edge.csv", [item])
    data = read_scenarios(path)
    assert data.n_pairs[0] == 5


# --- the CLI ----------------------------------------------------------------------------


def test_cli_validate_accepts_a_good_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = write_records(tmp_path / "good.csv.gz", RECORDS)
    assert main(["scenarios", "validate", str(path)]) == 0
    out, err = capsys.readouterr()
    assert "valid" in out
    assert "3 scenarios" in out
    assert "'defocus'" in out
    assert err == ""


def test_cli_validate_rejects_a_bad_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = cells(1, pairs=(P[0], P[1], ("20", "3"), P[3], P[4]))
    path = write(tmp_path / "bad.csv", csv_text(cells(0), bad))
    assert main(["scenarios", "validate", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert str(path) in err
    assert "row 2 (line 3)" in err
    assert "column voltage_3" in err


def test_cli_validate_json_bad_file_also_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    path = write(tmp_path / "bad.csv", csv_text(cells(0, seed="x")))
    assert main(["scenarios", "validate", "--json", str(path)]) == 2
    _, err = capsys.readouterr()
    assert str(path) in err and "row 1 (line 2)" in err and "column seed" in err


def test_cli_validate_missing_file_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "absent.csv"
    assert main(["scenarios", "validate", str(path)]) == 2
    assert str(path) in capsys.readouterr().err


def test_cli_validate_json(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = write_records(tmp_path / "good.csv", RECORDS)
    assert main(["scenarios", "validate", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    payload = json.loads(out)
    expected_keys = {
        "valid",
        "scenarios",
        "knob",
        "interval",
        "pairs",
        "optimum_v",
        "best_edge_width_px",
    }
    assert expected_keys <= set(payload)
    assert payload["valid"] is True
    assert payload["scenarios"] == 3
    assert payload["knob"] == "defocus"
    assert payload["interval"] == [-5.0, 100.0]
    assert payload["pairs"] == {"min": 5, "median": 6.0, "max": 7}
    assert payload["best_edge_width_px"] == {"min": 2.5, "median": 2.5625, "max": 2.75}
    optimum = payload["optimum_v"]
    assert optimum["min"] <= optimum["median"] <= optimum["max"]
    # Each optimum lies between the neighbours of its recorded minimum.
    assert 10.25 <= optimum["min"]
    assert optimum["max"] <= 50.0

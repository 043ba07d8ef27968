"""Rows of a track file: reading them in blocks, parsing them, and counting what happened to each.

A track file has one row per measurement: a track id, a time and the position components
(``track_id, time, x, y[, z]`` by default; :class:`Columns` renames them). Every row ends in
exactly one of three fates, counted by :class:`RowReport`:

* **measurement**: placed at a step of its track with at least one observed component;
* **prediction**: placed at a step with no observed component (all positions missing); the
  estimate written for it is the estimator's prediction at that time;
* **set aside** (with a reason): not placed at any step; its output row carries the id and time
  read and NaN estimates.

Fix-ups applied to placed rows are counted too (``RowReport.notes``): non-numeric values read
as missing, rows sorted into time order, rows sharing a time merged into one measurement.
Nothing is dropped silently.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: Reasons a row is set aside (not placed at any step).
SET_ASIDE = {
    "no_track_id": "the track id is empty",
    "no_time": "the time is empty, not a number and not a date",
    "track_without_position": "its track has no observed position at all (nothing to start from)",
    "on_ground": "ADS-B: the aircraft reports being on the ground (taxiing or parked, not flying)",
}

#: Fix-ups applied to placed rows, and other things worth counting.
NOTES = {
    "non_numeric_value": "a position value that is not a finite number, read as missing",
    "partial_position": "some position components missing; the others are used",
    "out_of_order": "time earlier than the track's row before it in the file; sorted into place",
    "duplicate_time": "same track and time as an earlier row; merged into one measurement (the "
    "mean of the observed values)",
    "repeated_position": "position identical to the previous report (not a new measurement: "
    "ADS-B repeats the last position between position messages), read as missing",
    "implausible_jump": "ADS-B: a position further from the previous one than 600 m/s allows "
    "(spoofing, a time-stamp jump); kept, the estimators see a maneuver",
    "tracks_single_point_axis": "tracks (not rows) observing an axis once: its velocity prior "
    "is 0 with a wide variance (torchsvs.datasets.priors)",
    "tracks_axis_never_observed": "tracks (not rows) never observing an axis: their estimates "
    "there are NaN",
}


@dataclass
class RowReport:
    """What happened to every row read (see the module docstring)."""

    total: int = 0
    measurement: int = 0
    prediction: int = 0
    set_aside: Counter[str] = field(default_factory=Counter)
    notes: Counter[str] = field(default_factory=Counter)
    tracks: int = 0

    def add(self, other: RowReport) -> None:
        """Accumulates another block's counts into this one."""
        self.total += other.total
        self.measurement += other.measurement
        self.prediction += other.prediction
        self.set_aside.update(other.set_aside)
        self.notes.update(other.notes)
        self.tracks += other.tracks

    @property
    def placed(self) -> int:
        return self.measurement + self.prediction

    def check(self) -> None:
        """Every row has exactly one fate."""
        aside = sum(self.set_aside.values())
        if self.measurement + self.prediction + aside != self.total:
            raise AssertionError(
                f"row accounting: {self.measurement} + {self.prediction} + {aside} != {self.total}"
            )

    def summary(self) -> str:
        """A few lines a person can read."""
        lines = [
            f"{self.total} rows in {self.tracks} tracks: {self.measurement} measurements, "
            f"{self.prediction} prediction-only (no position), "
            f"{sum(self.set_aside.values())} set aside"
        ]
        for reason, count in sorted(self.set_aside.items()):
            lines.append(f"  set aside, {reason}: {count} ({SET_ASIDE.get(reason, '')})")
        for reason, count in sorted(self.notes.items()):
            lines.append(f"  note, {reason}: {count} ({NOTES.get(reason, '')})")
        return "\n".join(lines)


@dataclass(frozen=True)
class Columns:
    """Column names of a track file.

    Args:
        track_id: the track identifier (any text; kept as written).
        time: the time of each row: a number (in ``time_unit``) or a date-time text
            (ISO 8601 or anything pandas parses), or a timestamp column of a Parquet file.
        position: the position components, two or three; ``None`` takes ``x, y`` and ``z`` when
            the file has a ``z`` column.
        extra: further numeric columns carried per step (e.g. a reported speed).
        time_unit: seconds per unit of a numeric time (``1.0`` for seconds, ``1e-3`` for
            milliseconds).
    """

    track_id: str = "track_id"
    time: str = "time"
    position: tuple[str, ...] | None = None
    extra: tuple[str, ...] = ()
    time_unit: float = 1.0

    def resolve(self, available: Sequence[str]) -> Columns:
        """These columns with ``position`` filled in, checked against the file's columns."""
        position = self.position
        if position is None:
            position = ("x", "y", "z") if "z" in available else ("x", "y")
        if len(position) not in (1, 2, 3):
            raise ValueError(f"position: expected 1 to 3 columns, got {list(position)}")
        missing = [
            c for c in (self.track_id, self.time, *position, *self.extra) if c not in available
        ]
        if missing:
            raise ValueError(
                f"columns: {missing} not in the file (its columns: {list(available)}); "
                "name yours with --id-col/--time-col/--pos-cols (torchsvs track) or Columns(...)"
            )
        if not (self.time_unit > 0 and math.isfinite(self.time_unit)):
            raise ValueError(f"time_unit: expected seconds per unit > 0, got {self.time_unit!r}")
        return Columns(self.track_id, self.time, tuple(position), tuple(self.extra), self.time_unit)


def file_format(path: str | Path) -> str:
    """``"csv"`` or ``"parquet"`` from the file name (``.csv[.gz]``, ``.parquet``, ``.pq``)."""
    name = str(path).lower()
    if name.endswith((".parquet", ".pq")):
        return "parquet"
    if name.endswith((".csv", ".csv.gz", ".csv.bz2", ".txt", ".tsv")):
        return "csv"
    raise ValueError(f"path: expected a .csv or .parquet file, got {str(path)!r}")


def file_columns(path: str | Path) -> list[str]:
    """The column names of a CSV or Parquet file (reads only the header or schema)."""
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    if file_format(path) == "parquet":
        return list(pq.ParquetFile(path).schema_arrow.names)
    with pcsv.open_csv(path, parse_options=_parse_options(path)) as reader:
        return list(reader.schema.names)


def _parse_options(path: str | Path) -> Any:
    import pyarrow.csv as pcsv

    return pcsv.ParseOptions(delimiter="\t" if str(path).lower().endswith(".tsv") else ",")


def read_blocks(path: str | Path, columns: Columns, block_rows: int = 1 << 20) -> Iterator[Any]:
    """The file's rows as ``pyarrow.Table`` blocks of about ``block_rows`` rows, in file order.

    Only the needed columns are read. CSV columns are read as text (so ids and times are written
    back exactly as they were, and a stray non-numeric value is counted, not fatal); Parquet
    columns keep their stored types.
    """
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    names = [columns.track_id, columns.time, *(columns.position or ()), *columns.extra]
    if file_format(path) == "parquet":
        parquet = pq.ParquetFile(path)
        for batch in parquet.iter_batches(batch_size=block_rows, columns=names):
            yield pa.Table.from_batches([batch])
        return
    # Average row of a track file is 20-60 bytes; the reader's block is in bytes.
    read = pcsv.ReadOptions(block_size=max(1 << 16, min(block_rows * 48, 1 << 30)))
    convert = pcsv.ConvertOptions(
        column_types={name: pa.string() for name in names},
        include_columns=names,
        strings_can_be_null=True,
    )
    with pcsv.open_csv(
        path, read_options=read, parse_options=_parse_options(path), convert_options=convert
    ) as reader:
        for batch in reader:
            for start in range(0, batch.num_rows, block_rows):
                yield pa.Table.from_batches([batch.slice(start, block_rows)])


@dataclass
class ParsedRows:
    """One block of rows as numbers (``R`` rows, ``m`` position components)."""

    track_code: np.ndarray  #: [R] int64, -1 where the id is empty
    track_ids: list[str]  #: id text of each code
    time: np.ndarray  #: [R] float64 seconds, NaN where unusable
    position: np.ndarray  #: [R, m] float64, NaN where missing
    extra: dict[str, np.ndarray]  #: [R] float64 each
    non_numeric: np.ndarray  #: [R] bool: some position value was text or not finite


def to_float(column: Any) -> tuple[np.ndarray, np.ndarray]:
    """A pyarrow column as float64 (NaN where empty) and where a value was not a finite number."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
        try:
            numbers = pc.cast(column, pa.float64())
        except pa.ArrowInvalid:
            import pandas as pd

            numbers = pa.array(
                pd.to_numeric(column.to_pandas(), errors="coerce"), type=pa.float64()
            )
    elif pa.types.is_integer(column.type) or pa.types.is_floating(column.type):
        numbers = pc.cast(column, pa.float64())
    elif pa.types.is_null(column.type):
        numbers = pa.nulls(len(column), pa.float64())
    else:
        raise TypeError(f"column of type {column.type}: expected numbers or text")
    values = np.asarray(numbers.to_numpy(zero_copy_only=False), dtype=np.float64)
    written = np.asarray(pc.is_valid(column).to_numpy(zero_copy_only=False), dtype=bool)
    bad = written & ~np.isfinite(values)
    values = np.where(np.isfinite(values), values, np.nan)
    return values, bad


def to_seconds(column: Any, unit: float) -> np.ndarray:
    """A time column as float64 seconds (NaN where unusable): numbers times ``unit``, date-time
    texts and timestamps as seconds since 1970-01-01 UTC."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_timestamp(column.type) or pa.types.is_date(column.type):
        ns = pc.cast(pc.cast(column, pa.timestamp("ns")), pa.int64())
        return np.asarray(ns.to_numpy(zero_copy_only=False), dtype=np.float64) * 1e-9
    values, bad = to_float(column)
    values = values * unit
    if bad.any():  # texts that are not numbers may be dates
        import pandas as pd

        texts = column.filter(pa.array(bad)).to_pandas()
        with warnings.catch_warnings():  # a best-effort parse of every date-time format is meant
            warnings.simplefilter("ignore", UserWarning)
            parsed = pd.to_datetime(texts, errors="coerce", utc=True, format="mixed")
        ns = parsed.to_numpy(dtype="datetime64[ns]").astype(np.int64).astype(np.float64)
        ns[parsed.isna().to_numpy()] = np.nan
        values[bad] = ns * 1e-9
    return values


def parse_block(table: Any, columns: Columns) -> ParsedRows:
    """Parses a block read by :func:`read_blocks` (columns already resolved)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    ids = table.column(columns.track_id)
    if not (pa.types.is_string(ids.type) or pa.types.is_large_string(ids.type)):
        ids = pc.cast(ids, pa.string())
    ids = pc.if_else(pc.equal(pc.utf8_trim_whitespace(ids), ""), pa.scalar(None, pa.string()), ids)
    encoded = pc.dictionary_encode(ids).combine_chunks()
    codes = pc.fill_null(encoded.indices, -1).to_numpy(zero_copy_only=False).astype(np.int64)
    track_ids = [str(v) for v in encoded.dictionary.to_pylist()]
    time = to_seconds(table.column(columns.time), columns.time_unit)
    assert columns.position is not None
    parts = [to_float(table.column(name)) for name in columns.position]
    position = np.stack([p[0] for p in parts], axis=1)
    non_numeric = np.any(np.stack([p[1] for p in parts], axis=1), axis=1)
    extra = {name: to_float(table.column(name))[0] for name in columns.extra}
    return ParsedRows(codes, track_ids, time, position, extra, non_numeric)


def slice_rows(rows: ParsedRows, start: int, stop: int) -> ParsedRows:
    """Rows ``start:stop`` of a parsed block (track codes keep their meaning)."""
    part = slice(start, stop)
    return ParsedRows(
        rows.track_code[part],
        rows.track_ids,
        rows.time[part],
        rows.position[part],
        {k: v[part] for k, v in rows.extra.items()},
        rows.non_numeric[part],
    )

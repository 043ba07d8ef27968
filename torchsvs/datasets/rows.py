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

Positions are metres as read, or WGS 84 latitude and longitude (degrees; columns named
``latitude``/``lat`` and ``longitude``/``lon``/``lng``, any case, or ``Columns(frame="wgs84")``)
with an optional altitude (metres), estimated in a local metric frame per track (see
:class:`Columns`). Numeric times are seconds, or milliseconds, microseconds or nanoseconds since
1970 when their size says so (:mod:`torchsvs.datasets.times`); texts are date-times.
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from torchsvs.datasets.arrow_numpy import repeated_text, texts, to_float
from torchsvs.datasets.ids import track_codes
from torchsvs.datasets.times import TIME_UNITS, detect_time_unit, to_seconds, unlike_their_track

#: Reasons a row is set aside (not placed at any step).
SET_ASIDE = {
    "no_track_id": "the track id is empty",
    "no_time": "the time is empty, not a number and not a date",
    "time_unlike_its_track": "a date-time text among its track's numbers (or a number among its "
    "date-times) that lies a year or more from the track's other times: it cannot be placed "
    "among them (torchsvs.datasets.times.unlike_their_track)",
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
    "outliers": "a position far off the path its neighbours agree on (a chance below one in a "
    "million for the noise), set aside as missing: estimated from the rest, flagged in the "
    "output's outlier column (torchsvs.fitting.outliers; --keep-outliers to use them)",
    "smoother_fallback": "tracks (not rows) the IMM's smoother estimated worse than its filter "
    "(Stein's unbiased risk estimate): those tracks are the filter's "
    "(torchsvs.smoother_guard.smoothed_or_filtered)",
    "tracks_not_finite": "tracks (not rows) whose estimates came out NaN or infinite at a "
    "measurement (a numerical breakdown of the estimator on them): written without estimates",
    "particle_steps": "steps a particle filter weighed a measurement at",
    "particle_steps_degenerate": "of those, steps whose effective sample size fell below a tenth "
    "of the particles (torchsvs.filters.particle.degenerate_share)",
    "track_breaks": "jumps of a track to another path between two reports (two tracks' ids "
    "swapped): the track is estimated as two, the part after the break named 'ID (part 2)' in "
    "the summary (torchsvs.datasets.breaks)",
    "tracks_still": "tracks (not rows) that repeat one position throughout (a parked beacon, a "
    "receiver holding its fix): estimated as that position; their error cannot be read off "
    "them, and they are left out of the error estimate and of reading the settings",
    "tracks_axis_never_observed": "tracks (not rows) never observing an axis: their estimates "
    "there are NaN",
    "invalid_coordinate": "a latitude outside ±90° or a longitude outside -180° to 360°, or a "
    "lone report more than 80° of arc from its track's first position among nearer ones (a "
    "stray: the track's local frame cannot hold it), read as missing",
}

#: Column names (compared in lower case) read as WGS 84 latitude, longitude, altitude.
LATITUDE_NAMES = ("latitude", "lat")
LONGITUDE_NAMES = ("longitude", "lon", "lng", "long")
ALTITUDE_NAMES = ("altitude", "alt", "height", "elevation")
#: ``Columns.frame``: what the position columns hold.
FRAMES = {
    "auto": "WGS 84 when the columns are named as latitude and longitude, else metric",
    "metric": "metres (any Cartesian frame), estimated as read",
    "wgs84": "WGS 84 latitude, longitude (degrees) [, altitude (m)], estimated in a local "
    "east-north[-up] frame in metres at each track's first position",
}


class InputWarning(UserWarning):
    """Input that is read, but may not be what the user meant (degrees taken for metres, times
    in milliseconds taken for seconds)."""


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
        time_unit: of a numeric time: ``"auto"`` (seconds, or milliseconds, microseconds,
            nanoseconds since 1970 when the values are that large: :func:`~torchsvs.datasets.
            times.detect_time_unit`),
            a name of :data:`~torchsvs.datasets.times.TIME_UNITS` (``"s"``, ``"ms"``, ``"us"``,
            ``"ns"``) or seconds per unit (``1e-3`` for milliseconds).
        frame: what the positions are (:data:`FRAMES`). ``"wgs84"``: latitude and longitude in
            degrees and an optional altitude in metres (the third column). Each track is
            estimated in the tangent plane of the WGS 84 ellipsoid at its first position in
            time (:func:`~torchsvs.datasets.geodesy.to_local`: east, north in metres) with its
            altitude as the third axis; estimates are written back as latitude, longitude
            (degrees) and altitude, velocities as ``v_east, v_north[, v_up]`` (m/s, in the
            east and north at the estimate) and covariances in metres, named by ``east,
            north, up``. ``"auto"`` takes ``"wgs84"`` when two position columns are named as
            :data:`LATITUDE_NAMES` and :data:`LONGITUDE_NAMES` (any case), and when
            ``position`` is not given and the file has no ``x, y`` but such columns (with an
            :data:`ALTITUDE_NAMES` column if there is one).
    """

    track_id: str = "track_id"
    time: str = "time"
    position: tuple[str, ...] | None = None
    extra: tuple[str, ...] = ()
    time_unit: float | str = "auto"
    frame: str = "auto"

    def resolve(self, available: Sequence[str], source: str = "the file") -> Columns:
        """These columns with ``position`` and ``frame`` filled in (a WGS 84 frame's positions
        in the order latitude, longitude[, altitude]), checked against the columns of
        ``source`` (named in an error);
        ``time_unit`` stays ``"auto"`` (it needs the values: :func:`~torchsvs.datasets.times.
        detect_time_unit`)."""
        if self.frame not in FRAMES:
            raise ValueError(f"frame: expected one of {sorted(FRAMES)}, got {self.frame!r}")
        unit = self.time_unit
        if isinstance(unit, str):
            if unit != "auto" and unit not in TIME_UNITS:
                raise ValueError(
                    f"time_unit: expected 'auto', one of {sorted(TIME_UNITS)} or seconds per "
                    f"unit > 0, got {unit!r}"
                )
        elif isinstance(unit, bool) or not (
            isinstance(unit, (int, float)) and unit > 0 and math.isfinite(unit)
        ):
            raise ValueError(f"time_unit: expected seconds per unit > 0, got {unit!r}")
        position, frame = self.position, self.frame
        if position is None:
            position, frame = _default_position(available, frame)
        track_id, time = _named(self.track_id, available), _named(self.time, available)
        position = tuple(_named(p, available) for p in position)
        if len(position) not in (1, 2, 3):
            raise ValueError(f"position: expected 1 to 3 columns, got {list(position)}")
        if len(set(position)) != len(position):
            raise ValueError(f"position: a column named twice, got {list(position)}")
        roles = [track_id, time, *position]
        if len(set(roles)) != len(roles):
            raise ValueError(
                f"columns: each column serves one role, got the id {track_id!r}, the time "
                f"{time!r} and the position {list(position)}; name them apart with --id-col, "
                "--time-col, --pos-cols (torchsvs track) or Columns(...)"
            )
        if frame != "metric":
            geodetic = _geodetic_order(position)
            if geodetic is not None:
                position, frame = geodetic, "wgs84"
            elif frame == "wgs84":
                if len(position) not in (2, 3):
                    raise ValueError(
                        "position: expected latitude, longitude[, altitude] columns with "
                        f"frame 'wgs84', got {list(position)}"
                    )
            else:
                frame = "metric"
        flags = {track_id: "--id-col", time: "--time-col", **dict.fromkeys(position, "--pos-cols")}
        missing = [c for c in (track_id, time, *position, *self.extra) if c not in available]
        if missing:
            hint = ", ".join(sorted({flags.get(c, "--noise-col") for c in missing}))  # (extra)
            raise ValueError(
                f"columns: {missing} not in {source} (its columns: {list(available)}); "
                f"name yours with {hint} (torchsvs track) or Columns(...)"
            )
        return replace(
            self,
            track_id=track_id,
            time=time,
            position=position,
            extra=tuple(self.extra),
            frame=frame,
        )

    @property
    def seconds_per_unit(self) -> float:
        """``time_unit`` in seconds (``"auto"`` not yet resolved: an error)."""
        unit = self.time_unit
        if unit == "auto":
            raise ValueError("time_unit: 'auto' is resolved on the data first (detect_time_unit)")
        return TIME_UNITS[unit] if isinstance(unit, str) else float(unit)

    @property
    def geodetic(self) -> bool:
        """Whether the positions are WGS 84 latitude, longitude[, altitude]."""
        return self.frame == "wgs84"


def _named(name: str, available: Sequence[str]) -> str:
    """``name``, or the one column of ``available`` that differs from it only in case."""
    if name in available:
        return name
    same = [c for c in available if c.lower() == name.lower()]
    return same[0] if len(same) == 1 else name


def _default_position(available: Sequence[str], frame: str) -> tuple[tuple[str, ...], str]:
    """The position columns of a file whose positions were not named: ``x, y[, z]`` or, without
    them, latitude, longitude[, altitude] (WGS 84 unless the frame is metric)."""
    if frame != "wgs84" and "x" in available and "y" in available:
        return (("x", "y", "z") if "z" in available else ("x", "y")), "metric"
    lower = {name.lower(): name for name in reversed(list(available))}
    lat = next((lower[n] for n in LATITUDE_NAMES if n in lower), None)
    lon = next((lower[n] for n in LONGITUDE_NAMES if n in lower), None)
    if lat is not None and lon is not None:
        alt = next((lower[n] for n in ALTITUDE_NAMES if n in lower), None)
        found = (lat, lon) if alt is None else (lat, lon, alt)
        return found, "metric" if frame == "metric" else "wgs84"
    if frame == "wgs84":  # (x, y would be metres: WGS 84 reads latitude and longitude)
        raise ValueError(
            f"position: the frame is WGS 84 (--frame wgs84), which reads latitude and longitude "
            f"columns (named {'/'.join(LATITUDE_NAMES)} and {'/'.join(LONGITUDE_NAMES)}), and "
            f"the file has none (its columns: {list(available)}); name them with --pos-cols "
            "LAT,LON, or drop --frame wgs84 for metres"
        )
    lacking = [c for c in ("x", "y") if c not in available]
    which = "x, y columns" if len(lacking) == 2 else f"column {lacking[0]!r} beside the other"
    raise ValueError(
        f"position: the file has no {which} and no latitude, longitude columns (its columns: "
        f"{list(available)}); name the position columns with --pos-cols (torchsvs track) or "
        "Columns(position=...)"
    )


def _geodetic_order(position: Sequence[str]) -> tuple[str, ...] | None:
    """``position`` as latitude, longitude[, the other] when two of its names are a latitude's
    and a longitude's (:data:`LATITUDE_NAMES`, :data:`LONGITUDE_NAMES`), else ``None``."""
    lower = [name.lower() for name in position]
    lat = [i for i, n in enumerate(lower) if n in LATITUDE_NAMES]
    lon = [i for i, n in enumerate(lower) if n in LONGITUDE_NAMES]
    if len(lat) != 1 or len(lon) != 1:
        return None
    rest = [p for i, p in enumerate(position) if i not in (lat[0], lon[0])]
    return (position[lat[0]], position[lon[0]], *rest)


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
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    if file_format(path) == "parquet":
        return list(pq.ParquetFile(path).schema_arrow.names)
    try:
        with pcsv.open_csv(path, parse_options=_parse_options(path)) as reader:
            return list(reader.schema.names)
    except pa.ArrowInvalid as err:
        if "Empty CSV file" in str(err):
            raise ValueError(f"path: {str(path)!r} is empty (no header, no rows)") from err
        raise ValueError(f"path: {str(path)!r}: {err}") from err


def _parse_options(path: str | Path) -> Any:
    import pyarrow.csv as pcsv

    return pcsv.ParseOptions(delimiter=csv_delimiter(path))


#: Separators a CSV file's header is checked for (the most frequent one is taken).
DELIMITERS = (",", ";", "\t", "|")


def csv_delimiter(path: str | Path) -> str:
    """The separator of a CSV file: the one of :data:`DELIMITERS` found most often in its
    header (``,`` when none is, or on a tie; a ``.tsv`` file's is a tab unless its header
    says otherwise)."""
    import pyarrow as pa

    with pa.input_stream(str(path), compression="detect") as stream:
        head = stream.read(1 << 16)
    line = head.split(b"\n", 1)[0].decode("utf-8", errors="replace")
    counts = {d: line.count(d) for d in DELIMITERS}
    default = "\t" if str(path).lower().endswith(".tsv") else ","
    best = max(DELIMITERS, key=lambda d: (counts[d], d == default))
    return best if counts[best] > counts[default] else default


def read_blocks(
    path: str | Path,
    columns: Columns,
    block_rows: int = 1 << 20,
    dictionary_ids: bool = False,
    partition: dict[str, str] | None = None,
) -> Iterator[Any]:
    """The file's rows as ``pyarrow.Table`` blocks of about ``block_rows`` rows, in file order.

    Only the needed columns are read. CSV columns are read as text (so ids and times are written
    back exactly as they were, and a stray non-numeric value is counted, not fatal); Parquet
    columns keep their stored types, but with ``dictionary_ids`` a text id column comes
    dictionary-encoded (as Parquet stores it: :func:`~torchsvs.datasets.ids.track_codes` then
    reads each distinct id once; :func:`parquet_id_type` is its type to write back). A needed
    column the Parquet file lacks is taken from ``partition`` (a dataset's hive partition
    values: text, one value for the whole file).
    """
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    names = [columns.track_id, columns.time, *(columns.position or ()), *columns.extra]
    if file_format(path) == "parquet":
        read = [columns.track_id] if dictionary_ids and parquet_id_type(path, columns) else None
        parquet = pq.ParquetFile(path, read_dictionary=read)
        stored = set(parquet.schema_arrow.names)
        constant = {k: v for k, v in (partition or {}).items() if k in names and k not in stored}
        for batch in parquet.iter_batches(
            batch_size=block_rows, columns=[n for n in names if n not in constant]
        ):
            table = pa.Table.from_batches([batch])
            for key, value in constant.items():
                table = table.append_column(key, repeated_text(value, len(table)))
            yield table
        return
    # Average row of a track file is 20-60 bytes; the reader's block is in bytes.
    read = pcsv.ReadOptions(block_size=max(1 << 16, min(block_rows * 48, 1 << 30)))
    # Only an empty field is null as read: an id "NA" or "null" is an id (Arrow's default null
    # texts made those rows lose their id); in the other columns those texts are missing values.
    convert = pcsv.ConvertOptions(
        column_types={name: pa.string() for name in names},
        include_columns=names,
        strings_can_be_null=True,
        null_values=[""],
    )
    values = [i for i, name in enumerate(names) if name != columns.track_id]
    try:
        with pcsv.open_csv(
            path, read_options=read, parse_options=_parse_options(path), convert_options=convert
        ) as reader:
            for batch in reader:
                batch = _null_texts(batch, values)
                for start in range(0, batch.num_rows, block_rows):
                    yield pa.Table.from_batches([batch.slice(start, block_rows)])
    except pa.ArrowInvalid as err:  # a row of more fields than the header, a bad quote, ...
        raise ValueError(f"path: {str(path)!r}: {err}") from err


#: Texts a CSV value column holds for a missing value (Arrow's, but the empty field: read as
#: null already), read as null: "NA" in a position is missing, not a text to count.
NULL_TEXTS = (
    "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
    "N/A", "NA", "NULL", "NaN", "n/a", "nan", "null",
)  # fmt: skip


def _null_texts(batch: Any, columns: list[int]) -> Any:
    """``batch`` with :data:`NULL_TEXTS` set to null in the ``columns`` (indices)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    missing = texts(NULL_TEXTS)
    arrays = list(batch.columns)
    for i in columns:
        found = pc.is_in(arrays[i], value_set=missing)
        if pc.any(found).as_py():  # (nulls, not a null scalar: pa.scalar imports pandas)
            arrays[i] = pc.if_else(found, pa.nulls(len(found), pa.string()), arrays[i])
    return pa.RecordBatch.from_arrays(arrays, schema=batch.schema)


def parquet_id_type(path: str | Path, columns: Columns) -> Any:
    """The type of a Parquet file's id column where it is text (read dictionary-encoded with
    ``read_blocks(..., dictionary_ids=True)``), else ``None``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if file_format(path) != "parquet":
        return None
    schema = pq.read_schema(path)
    if columns.track_id not in schema.names:  # a dataset's partition value
        return None
    kind = schema.field(columns.track_id).type
    return kind if pa.types.is_string(kind) or pa.types.is_large_string(kind) else None


@dataclass
class ParsedRows:
    """One block of rows as numbers (``R`` rows, ``m`` position components)."""

    track_code: np.ndarray  #: [R] int64, -1 where the id is empty
    track_ids: list[str]  #: id text of each code
    time: np.ndarray  #: [R] float64 seconds, NaN where unusable
    position: np.ndarray  #: [R, m] float64, NaN where missing (metres: WGS 84 rows projected)
    extra: dict[str, np.ndarray]  #: [R] float64 each
    non_numeric: np.ndarray  #: [R] bool: some position value was text or not finite
    #: [codes, 2] latitude, longitude (degrees) of each track's local frame (``Columns(frame=
    #: "wgs84")``; NaN for a track without a position), or None for metric positions
    reference: np.ndarray | None = None
    invalid: np.ndarray | None = None  #: [R] bool: a coordinate out of range (WGS 84)
    #: [R] bool: a time written unlike its track's others, set to NaN (:func:`~torchsvs.
    #: datasets.times.unlike_their_track`), or None
    time_unlike: np.ndarray | None = None


def parse_block(table: Any, columns: Columns) -> ParsedRows:
    """Parses a block read by :func:`read_blocks` (columns already resolved; a time unit still
    ``"auto"`` is detected on this block). WGS 84 positions are projected to each track's local
    frame (:func:`~torchsvs.datasets.local_frame.project_rows`)."""
    codes, track_ids = track_codes(table.column(columns.track_id))
    column = table.column(columns.time)
    unit = detect_time_unit(column)[0] if columns.time_unit == "auto" else columns.seconds_per_unit
    time, dated = to_seconds(column, unit)
    unlike = unlike_their_track(time, dated, codes)
    if unlike is not None:
        time[unlike] = np.nan
    assert columns.position is not None
    parts = [to_float(table.column(name)) for name in columns.position]
    position = np.stack([p[0] for p in parts], axis=1)
    non_numeric = functools.reduce(np.logical_or, [p[1] for p in parts])
    extra = {name: to_float(table.column(name))[0] for name in columns.extra}
    rows = ParsedRows(codes, track_ids, time, position, extra, non_numeric, time_unlike=unlike)
    if not columns.geodetic:
        return rows
    from torchsvs.datasets.local_frame import project_rows

    local, reference, invalid = project_rows(position, codes, time, track_ids)
    return replace(rows, position=local, reference=reference, invalid=invalid)


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
        rows.reference,
        None if rows.invalid is None else rows.invalid[part],
        None if rows.time_unlike is None else rows.time_unlike[part],
    )

"""What a track file holds, settled on its first block before anything runs
(:func:`describe_input`): the position columns and their frame, the time unit, and what may not
be what was meant (degrees read as metres, milliseconds read as seconds)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from torchsvs.datasets.arrow_numpy import to_float
from torchsvs.datasets.paths import check_input, dataset_files
from torchsvs.datasets.rows import (
    Columns,
    csv_delimiter,
    file_columns,
    file_format,
    parse_block,
    read_blocks,
)
from torchsvs.datasets.steps import TrackSteps, group_rows
from torchsvs.datasets.times import detect_time_unit


@dataclass
class InputDescription:
    """What a track file holds, settled on its first block (:func:`describe_input`)."""

    columns: Columns  #: resolved: positions and frame named, the time unit in seconds
    lines: list[str] = field(default_factory=list)  #: what was found, for a person
    warnings: list[str] = field(default_factory=list)  #: what may not be what was meant
    #: position columns constant within every track of the first block (no noise to read off)
    constant: list[str] = field(default_factory=list)
    rows: int = 0  #: rows of the first block (what was looked at)
    source: Path | None = None  #: the file described (a dataset's first file with rows)


#: Typical interval (in the detected unit, read as seconds) above which the unit is questioned.
LONG_INTERVAL = 1000.0


def describe_input(
    path: str | Path, columns: Columns | None = None, block_rows: int = 1 << 18, name: str = "path"
) -> InputDescription:
    """Settles what ``columns`` leaves open on the file's first ``block_rows`` rows and checks
    them: the position columns (``x, y[, z]``, or latitude, longitude[, altitude]: the frame),
    the time unit (:func:`~torchsvs.datasets.times.detect_time_unit`), a position column without
    numbers, a file without rows or without a row to place. Raises ``ValueError`` naming the
    column or the file; returns the resolved columns, a description and warnings."""
    described, blocks = open_blocks(path, columns, block_rows, name, thorough=True)
    close = getattr(blocks, "close", None)
    if close is not None:
        close()
    return described


def open_blocks(
    path: str | Path,
    columns: Columns | None,
    block_rows: int,
    name: str = "path",
    thorough: bool = False,
    dictionary_ids: bool = False,
) -> tuple[InputDescription, Iterator[Any]]:
    """The file's description (:func:`describe_input`) and all its blocks (the first read
    once; ``dictionary_ids`` as for :func:`~torchsvs.datasets.rows.read_blocks`). Unless
    ``thorough``, the checks that group the first block's rows into tracks run only where
    ``columns`` leaves the frame or the time unit open (``torchsvs track`` settles them first,
    with ``thorough``)."""
    check_input(path, name)
    partition: dict[str, str] = {}
    if Path(path).is_dir():  # a Parquet dataset: described on its first file with rows
        import pyarrow.parquet as pq

        files = dataset_files(path, name)
        path, partition = next(
            ((f, p) for f, p in files if pq.ParquetFile(f).metadata.num_rows > 0), files[0]
        )
    if Path(path).stat().st_size == 0:
        raise ValueError(f"{name}: {str(path)!r} is empty (no header, no rows)")
    available = file_columns(path)
    cols = (columns or Columns()).resolve(
        [*available, *(k for k in partition if k not in available)]
    )
    blocks = read_blocks(path, cols, block_rows, dictionary_ids, partition)
    first = next(blocks, None)
    if first is None or len(first) == 0:
        raise ValueError(f"{name}: {str(path)!r} has a header but no rows")
    described = _describe(path, first, cols, columns or Columns(), name, thorough)
    described.source = Path(path)
    return described, itertools.chain([first], blocks)


def describe_table(
    table: Any, columns: Columns | None = None, name: str = "table"
) -> InputDescription:
    """:func:`describe_input` of a ``pyarrow.Table`` of track rows (all of it is looked at)."""
    if len(table) == 0:
        raise ValueError(f"{name}: expected rows of tracks, got an empty table")
    cols = (columns or Columns()).resolve(table.column_names, source=f"the {name}")
    return _describe(None, table, cols, columns or Columns(), name, thorough=True)


def _describe(
    path: str | Path | None,
    table: Any,
    cols: Columns,
    asked: Columns,
    name: str,
    thorough: bool,
) -> InputDescription:
    import pyarrow.compute as pc

    rows = len(table)
    lines: list[str] = []
    notes: list[str] = []
    if path is not None and file_format(path) == "csv" and csv_delimiter(path) != ",":
        lines.append(f"separator {csv_delimiter(path)!r} (read from the header)")
    assert cols.position is not None
    for label in cols.position:
        column = table.column(label)
        values, text = to_float(column)
        if np.isfinite(values).any():
            continue
        if text.any():
            shown = [str(v) for v in pc.drop_null(column).to_pylist()[:3]]
            comma = any("," in v and v.replace(",", "").lstrip("-").isdigit() for v in shown)
            raise ValueError(
                f"position: column {label!r} holds no numbers in the first {rows} rows (e.g. "
                f"{shown}){'; decimal commas are not read, write decimal points' if comma else ''}"
                "; name the position columns with --pos-cols (torchsvs track) or Columns(...)"
            )
        raise ValueError(
            f"position: column {label!r} holds no numbers in the first {rows} rows (each empty "
            "or a text read as missing: NA, n/a, null, NaN, ...); name the position columns that "
            "hold positions with --pos-cols (torchsvs track) or Columns(...)"
        )
    if cols.geodetic:
        for label, limit in zip(cols.position[:2], (90.0, 360.0), strict=True):
            values = to_float(table.column(label))[0]
            values = values[np.isfinite(values)]
            if np.mean(np.abs(values) > limit) > 0.5:  # mostly not degrees
                big = values[np.abs(values) > limit][:3].tolist()
                kind = "latitude" if limit == 90 else "longitude"
                raise ValueError(
                    f"position: column {label!r} holds mostly no {kind} in degrees in the first "
                    f"{rows} rows (e.g. {big}); if the positions are metres, pass --frame metric "
                    "(torchsvs track) or Columns(frame='metric')"
                )
    if cols.time_unit == "auto":
        unit, found = detect_time_unit(table.column(cols.time))
        cols = replace(cols, time_unit=unit)
    else:
        found = f"numbers in units of {cols.seconds_per_unit:g} s (as given)"
    lines.append(f"time {cols.time!r}: {found}")
    assert cols.position is not None
    if not (thorough or asked.frame == "auto" or asked.time_unit == "auto"):
        return InputDescription(cols, lines, notes, [], rows)
    feet = _altitude_in_feet(table, cols)
    if feet is not None:
        notes.append(feet)
    steps = group_rows(parse_block(table, cols))
    if steps.num_tracks == 0:
        raise ValueError(
            f"{name}: no row of the first {rows} rows can be placed at a step of a track:\n"
            + steps.report.summary()
        )
    positions = ", ".join(repr(p) for p in cols.position)
    if cols.geodetic:
        m = len(cols.position)
        lines.append(
            f"position {positions}: WGS 84 latitude, longitude (degrees)"
            + (", altitude (m)" if m == 3 else "")
            + ", estimated in metres east, north"
            + (", up" if m == 3 else "")
            + " of each track's first position; written back as degrees"
            + (" and metres" if m == 3 else "")
            + ", velocities as v_east, v_north"
            + (", v_up" if m == 3 else "")
            + " (m/s), covariances in metres (--frame metric: estimate them as they are)"
        )
    else:
        lines.append(f"position {positions}: metres, estimated as read")
        if asked.frame == "auto" and _look_like_degrees(steps):
            notes.append(
                f"position: the columns {positions} hold values within ±90 and ±180 that move "
                "by less than 0.01 per step: if they are latitude and longitude in degrees, "
                "name them latitude/longitude (or lat/lon) or pass --frame wgs84; they are "
                "read as metres"
            )
    interval = typical_interval(steps)
    if asked.time_unit == "auto" and cols.time_unit == 1.0 and interval >= LONG_INTERVAL:
        if "date-time" not in found and "timestamps" not in found:
            notes.append(
                f"time: the typical interval between a track's rows is {interval:.4g} s; if the "
                "times are milliseconds, pass --time-unit ms"
            )
    coarse = _coarse_times(table.column(cols.time), cols, interval, steps)
    if coarse is not None:
        notes.append(coarse)
    constant = [
        label
        for j, label in enumerate(cols.position)
        if not np.any(np.abs(np.diff(steps.position[:, j])[_within_track(steps)]) > 0)
    ]
    return InputDescription(cols, lines, notes, constant, rows)


def _within_track(steps: TrackSteps) -> np.ndarray:
    """``[S - 1]`` True where steps ``s`` and ``s + 1`` belong to one track."""
    track = steps.track_of_step
    return track[1:] == track[:-1]


def typical_interval(steps: TrackSteps, most: int | None = None) -> float:
    """The median interval between successive steps of a track (NaN without any); of the
    first ``most`` steps' alone where given (a block's check: a few ms, not 25)."""
    time, track = steps.time, steps.track_of_step
    if most is not None:
        time, track = time[: most + 1], track[: most + 1]
    dt = np.diff(time)[track[1:] == track[:-1]]
    return float(np.median(dt)) if len(dt) else float("nan")


#: A time column of short floats is named where its resolution at its largest value is this
#: share of the typical interval or more.
COARSE_TIME_SHARE = 0.1


def _coarse_times(column: Any, cols: Columns, interval: float, steps: TrackSteps) -> str | None:
    """A note where the times are 16- or 32-bit floats too coarse for the intervals between
    rows: 1.7e9 s since 1970 as float32 are 128 s apart, so rows a second apart shared times
    and were merged, and the estimates came out 200 times the measurements' error."""
    import pyarrow as pa

    if not (pa.types.is_float32(column.type) or pa.types.is_float16(column.type)):
        return None
    values = to_float(column)[0]
    values = np.abs(values[np.isfinite(values)])
    if not len(values):
        return None
    bits, dtype = (32, np.float32) if pa.types.is_float32(column.type) else (16, np.float16)
    spacing = float(np.spacing(dtype(values.max()))) * cols.seconds_per_unit
    step = interval if np.isfinite(interval) and interval > 0 else math.inf
    if spacing < COARSE_TIME_SHARE * step:
        return None
    return (
        f"time: column {cols.time!r} holds {bits}-bit floats: near {values.max():.4g} "
        f"they are {spacing:.3g} s apart, against a typical interval of {interval:.3g} s "
        f"between a track's rows ({steps.report.notes['duplicate_time']} rows shared a time "
        "and were merged): the times cannot place the rows; store them as 64-bit floats or "
        "integers, or as times from a nearer start"
    )


#: An altitude above this is above any aircraft's in metres (airliners cruise below 13,100 m,
#: business jets below 15,600 m): a column reaching it holds feet (ADS-B's altitude does)
FEET_ABOVE = 16_000.0
#: ... as does one whose values nearly all are whole multiples of ADS-B's 25 ft steps
FEET_STEP = 25.0
FEET_STEP_SHARE = 0.95


def _altitude_in_feet(table: Any, cols: Columns) -> str | None:
    """A warning where the altitude of latitude, longitude, altitude looks like feet: above
    :data:`FEET_ABOVE`, or (above 1,000) all but a few values multiples of :data:`FEET_STEP`.
    Read as metres, its noise, estimates and ``v_up`` come out in feet and the 3-D error
    estimate mixes the two."""
    if not cols.geodetic or cols.position is None or len(cols.position) != 3:
        return None
    label = cols.position[2]
    values, _ = to_float(table.column(label))
    values = values[np.isfinite(values) & (values != 0)]
    if len(values) < 20:
        return None
    top = float(np.abs(values).max())
    steps = float(np.mean(np.remainder(values, FEET_STEP) == 0))
    if top <= FEET_ABOVE and not (top > 1000 and steps >= FEET_STEP_SHARE):
        return None
    why = (
        f"reaches {top:,.0f}, above any aircraft in metres"
        if top > FEET_ABOVE
        else f"holds {steps:.0%} whole multiples of {FEET_STEP:g} (ADS-B's steps in feet)"
    )
    return (
        f"altitude: column {label!r} {why}: if it is feet, convert it to metres (x 0.3048) or "
        "leave it out (--pos-cols of the latitude and longitude): read as metres, its noise, "
        "estimates and v_up are in feet and the 3-D error estimate mixes the two (the "
        "horizontal one, given apart, does not)"
    )


def _look_like_degrees(steps: TrackSteps) -> bool:
    """Whether metric positions look like latitude, longitude: the first two axes within ±90
    and ±180 (either way round), not all near 0, moving by less than 0.01 per step (1 km in
    degrees; a metre-sized step per scan is rare in a track file in metres)."""
    if steps.position.shape[1] < 2:
        return False
    xy = steps.position[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy) < 2:
        return False
    a, b = np.abs(xy).max(axis=0)
    if not ((a <= 90 and b <= 180) or (a <= 180 and b <= 90)) or max(a, b) < 1.0:
        return False
    moves = np.abs(np.diff(steps.position[:, :2], axis=0))[_within_track(steps)]
    moves = moves[np.isfinite(moves).all(axis=1)].max(axis=1, initial=0.0) if len(moves) else moves
    return len(moves) > 0 and float(np.median(moves)) < 0.01

"""Track files in and estimates out: whole files or streams of complete tracks, and writers.

* :func:`read_tracks`: a whole CSV/Parquet file as one padded batch with priors
  (:class:`~torchsvs.datasets.RecordedTracks`), for Python use and training.
* :func:`track_blocks`: the file as a stream of blocks of *complete* tracks, in bounded memory:
  a track's rows must then be contiguous in the file (any order within the track).
* :func:`estimate_table`: the output rows of a block: one per input row, with the id and time as
  read and the estimates of the step the row was placed at.
* :class:`EstimateWriter`: appends output blocks to a CSV or Parquet file, written next to it
  under a temporary name and renamed over it only once complete.
* :func:`describe_input`, :func:`check_input`, :func:`check_output`: what a file holds (time
  unit, frame) and whether a path may be read or written, before anything runs.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets.priors import two_point_prior
from torchsvs.datasets.rows import (
    Columns,
    InputWarning,
    RowReport,
    csv_delimiter,
    detect_time_unit,
    file_columns,
    file_format,
    parse_block,
    read_blocks,
    slice_rows,
    to_float,
)
from torchsvs.datasets.tracks import RecordedTracks, TrackSteps, check_contiguous, group_rows


@dataclass
class TrackBlock:
    """Complete tracks read from a file: the raw rows (for writing back) and their steps."""

    table: Any  #: pyarrow.Table of the block's rows as read
    steps: TrackSteps
    columns: Columns
    path: Path | None = None  #: the file read (an output must not replace it)


def track_blocks(
    path: str | Path,
    columns: Columns | None = None,
    block_rows: int = 1 << 20,
    whole: bool = False,
) -> Iterator[TrackBlock]:
    """Reads a track file as blocks of complete tracks, in file order.

    Streaming (``whole=False``) holds about ``block_rows`` rows at a time, plus the rows of the
    track that a block boundary cut (carried into the next block). It needs every track's rows
    to be contiguous in the file; a track whose rows reappear after other tracks raises
    ``ValueError`` naming it and ``--in-memory`` (sort the file by track id, or read it whole).
    ``whole=True`` reads the file at once and accepts any row order.

    What ``columns`` leaves open (``time_unit="auto"``, ``frame="auto"``) is settled on the
    first block (:func:`describe_input`), with an :class:`~torchsvs.datasets.rows.InputWarning`
    where the data look unlike what was settled (degrees read as metres, a typical interval of
    over 1,000 s read as seconds).
    """
    import pyarrow as pa

    described, blocks = _open_blocks(path, columns, block_rows)
    for text in described.warnings:
        warnings.warn(text, InputWarning, stacklevel=2)
    cols, source = described.columns, Path(path)
    if whole:
        table = pa.concat_tables(list(blocks))
        yield TrackBlock(table, group_rows(parse_block(table, cols)), cols, source)
        return
    done: set[str] = set()
    carry = None
    for block in blocks:
        table = block if carry is None else pa.concat_tables([carry, block])
        parsed = parse_block(table, cols)
        codes = parsed.track_code
        with_id = np.flatnonzero(codes >= 0)
        if len(with_id) == 0:
            cut = len(table)
        else:
            # The last track may go on in the next block: carry its run (and what follows).
            last = codes[with_id[-1]]
            others = with_id[codes[with_id] != last]
            cut = int(others[-1]) + 1 if len(others) else 0
        if cut == 0:
            carry = table
            continue
        carry = table.slice(cut)
        head = slice_rows(parsed, 0, cut)
        yield TrackBlock(table.slice(0, cut), _complete(head, done), cols, source)
    if carry is not None and len(carry):
        parsed = parse_block(carry, cols)
        yield TrackBlock(carry, _complete(parsed, done), cols, source)


@dataclass
class InputDescription:
    """What a track file holds, settled on its first block (:func:`describe_input`)."""

    columns: Columns  #: resolved: positions and frame named, the time unit in seconds
    lines: list[str] = field(default_factory=list)  #: what was found, for a person
    warnings: list[str] = field(default_factory=list)  #: what may not be what was meant
    #: position columns constant within every track of the first block (no noise to read off)
    constant: list[str] = field(default_factory=list)
    rows: int = 0  #: rows of the first block (what was looked at)


#: Typical interval (in the detected unit, read as seconds) above which the unit is questioned.
LONG_INTERVAL = 1000.0


def describe_input(
    path: str | Path, columns: Columns | None = None, block_rows: int = 1 << 18, name: str = "path"
) -> InputDescription:
    """Settles what ``columns`` leaves open on the file's first ``block_rows`` rows and checks
    them: the position columns (``x, y[, z]``, or latitude, longitude[, altitude]: the frame),
    the time unit (:func:`~torchsvs.datasets.rows.detect_time_unit`), a position column without
    numbers, a file without rows or without a row to place. Raises ``ValueError`` naming the
    column or the file; returns the resolved columns, a description and warnings."""
    described, blocks = _open_blocks(path, columns, block_rows, name, thorough=True)
    close = getattr(blocks, "close", None)
    if close is not None:
        close()
    return described


def check_input(path: str | Path, name: str = "path") -> None:
    """Raises ``ValueError``/``FileNotFoundError`` (starting with ``name``) unless ``path`` is
    an existing ``.csv``/``.parquet`` file."""
    source = Path(path)
    if source.is_dir():
        raise ValueError(f"{name}: {str(path)!r} is a directory; expected a .csv or .parquet file")
    try:
        file_format(source)
    except ValueError as err:
        raise ValueError(
            f"{name}: expected a .csv or .parquet file (.csv, .csv.gz, .csv.bz2, .tsv, .txt, "
            f".parquet, .pq), got {str(path)!r}"
        ) from err
    if not source.exists():
        raise FileNotFoundError(f"{name}: {str(path)!r}: no such file")


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one file (symbolic links, ``./`` and hard links seen through)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return Path(a).resolve() == Path(b).resolve()


def check_output(
    path: str | Path,
    name: str = "output",
    inputs: Sequence[str | Path | None] = (),
    force: bool = False,
) -> None:
    """Raises ``ValueError`` (starting with ``name``) unless ``path`` may be written: never one
    of ``inputs`` (an input is never replaced, not even with ``force``), an existing file only
    with ``force``, and only in a directory that exists and can be written."""
    target = Path(path)
    for source in inputs:
        if source is not None and same_file(target, source):
            raise ValueError(
                f"{name}: {str(path)!r} is the input file {str(source)!r}; the output never "
                "replaces an input: name another file"
            )
    if target.is_dir():
        raise ValueError(f"{name}: {str(path)!r} is a directory; expected a file name")
    if target.exists() and not force:
        raise ValueError(
            f"{name}: {str(path)!r} exists; pass --force to replace it (torchsvs track), or "
            "name another file"
        )
    folder = target.resolve().parent
    if not folder.is_dir():
        raise ValueError(f"{name}: the directory {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{name}: the directory {str(folder)!r} cannot be written")


def _open_blocks(
    path: str | Path,
    columns: Columns | None,
    block_rows: int,
    name: str = "path",
    thorough: bool = False,
) -> tuple[InputDescription, Iterator[Any]]:
    """The file's description (:func:`describe_input`) and all its blocks (the first read
    once). Unless ``thorough``, the checks that group the first block's rows into tracks run
    only where ``columns`` leaves the frame or the time unit open (``torchsvs track`` settles
    them first, with ``thorough``)."""
    check_input(path, name)
    if Path(path).stat().st_size == 0:
        raise ValueError(f"{name}: {str(path)!r} is empty (no header, no rows)")
    cols = (columns or Columns()).resolve(file_columns(path))
    blocks = read_blocks(path, cols, block_rows)
    first = next(blocks, None)
    if first is None or len(first) == 0:
        raise ValueError(f"{name}: {str(path)!r} has a header but no rows")
    described = _describe(path, first, cols, columns or Columns(), name, thorough)
    return described, itertools.chain([first], blocks)


def _describe(
    path: str | Path, table: Any, cols: Columns, asked: Columns, name: str, thorough: bool
) -> InputDescription:
    import pyarrow.compute as pc

    rows = len(table)
    lines: list[str] = []
    notes: list[str] = []
    if file_format(path) == "csv" and csv_delimiter(path) != ",":
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
            f"position: column {label!r} is empty in the first {rows} rows; name the position "
            "columns that hold positions with --pos-cols (torchsvs track) or Columns(...)"
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
    interval = _typical_interval(steps)
    if asked.time_unit == "auto" and cols.time_unit == 1.0 and interval >= LONG_INTERVAL:
        if "date-time" not in found and "timestamps" not in found:
            notes.append(
                f"time: the typical interval between a track's rows is {interval:.4g} s; if the "
                "times are milliseconds, pass --time-unit ms"
            )
    constant = [
        label
        for j, label in enumerate(cols.position)
        if not np.any(np.abs(np.diff(steps.position[:, j])[_within_track(steps)]) > 0)
    ]
    return InputDescription(cols, lines, notes, constant, rows)


def _within_track(steps: TrackSteps) -> np.ndarray:
    """``[S - 1]`` True where steps ``s`` and ``s + 1`` belong to one track."""
    track = np.repeat(np.arange(steps.num_tracks), steps.length)
    return track[1:] == track[:-1]


def _typical_interval(steps: TrackSteps) -> float:
    """The median interval between successive steps of a track (NaN without any)."""
    dt = np.diff(steps.time)[_within_track(steps)]
    return float(np.median(dt)) if len(dt) else float("nan")


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


def _complete(rows: Any, done: set[str]) -> TrackSteps:
    check_contiguous(rows.track_code, rows.track_ids)
    present = {rows.track_ids[c] for c in np.unique(rows.track_code[rows.track_code >= 0])}
    again = present & done
    if again:
        raise ValueError(
            f"track {sorted(again)[0]!r}: its rows are not contiguous (it reappears after "
            "other tracks); streaming reads a file track by track, so sort it by track id, "
            "or read it whole (torchsvs track --in-memory)"
        )
    done |= present
    return group_rows(rows)


@dataclass
class TrackSource:
    """Where a padded batch came from, to write estimates back row by row."""

    block: TrackBlock
    tracks: np.ndarray  #: [B] the batch's tracks among the block's


def read_tracks(
    path: str | Path,
    columns: Columns | None = None,
    meas_std: float | Sequence[float] | None = None,
    dtype: torch.dtype = torch.float64,
) -> tuple[RecordedTracks, RowReport]:
    """A whole track file as one padded batch with priors from its first measurements.

    Args:
        path: a ``.csv`` or ``.parquet`` file.
        columns: its column names (default ``track_id, time, x, y[, z]``).
        meas_std: measurement noise standard deviation (one number or one per axis) for the
            priors; ``None`` estimates it from the data (:func:`estimate_noise`).
        dtype: of the measurement tensors.

    Returns:
        The tracks (``source`` set, for :func:`write_estimates`) and the row report.
    """
    block = next(track_blocks(path, columns, whole=True))
    everything = np.arange(block.steps.num_tracks)
    tracks = with_prior(block.steps.pad(everything, dtype), meas_std)
    tracks.source = TrackSource(block, everything)
    report = block.steps.report
    report.notes.update(short_track_notes(tracks))
    report.notes = +report.notes
    return tracks, report


def short_track_notes(tracks: RecordedTracks) -> dict[str, int]:
    """How many tracks observe an axis only once, or never (the prior's fix-ups)."""
    seen = (~torch.isnan(tracks.z)).sum(dim=1)  # [B, m] observations per axis
    return {
        "tracks_single_point_axis": int((seen == 1).any(dim=-1).sum()),
        "tracks_axis_never_observed": int((seen == 0).any(dim=-1).sum()),
    }


def meas_variance(tracks: RecordedTracks, meas_std: float | Sequence[float] | None) -> Tensor:
    """Measurement variance per axis ``[m]``: from ``meas_std``, or estimated from the data."""
    m = tracks.z.shape[-1]
    if meas_std is None:
        from torchsvs.datasets.priors import estimate_noise

        return estimate_noise(tracks.z, tracks.dt).meas_var
    std = torch.as_tensor(meas_std, dtype=tracks.z.dtype).reshape(-1)
    if (
        std.numel() not in (1, m)
        or not bool((std > 0).all())
        or not bool(torch.isfinite(std).all())
    ):
        raise ValueError(
            f"meas_std: expected one standard deviation > 0 or one per axis ({m}), "
            f"got {std.tolist()}"
        )
    return std.expand(m).square()


def with_prior(
    tracks: RecordedTracks,
    meas_std: float | Sequence[float] | Tensor | None = None,
    inflation: float | None = None,
) -> RecordedTracks:
    """The tracks with ``x0, P0`` from two-point differencing (:func:`two_point_prior`);
    ``meas_std`` as for :func:`read_tracks`, or a tensor of standard deviations per axis."""
    var = meas_std.square() if isinstance(meas_std, Tensor) else meas_variance(tracks, meas_std)
    kwargs = {} if inflation is None else {"inflation": inflation}
    prior = two_point_prior(tracks.z, tracks.dt, var, **kwargs)
    return replace(tracks, x0=prior.x0, P0=prior.P0, never_observed=prior.never_observed)


def state_names(position: Sequence[str]) -> list[str]:
    """Names of the state components in the layout of ConstantVelocity: ``x, vx, y, vy, ...``."""
    return [name for p in position for name in (p, f"v{p}")]


#: Names of a WGS 84 file's local axes (east, north, up: the altitude).
LOCAL_AXES = ("east", "north", "up")


def output_names(columns: Columns) -> tuple[list[str], list[str]]:
    """The output's names of the state components in state order (positions under the
    input's names, velocities: ``x, vx, y, vy, ...``; WGS 84: ``lat, v_east, lon, v_north[,
    alt, v_up]``, written positions first)
    and the names the covariance columns use (``cov_<a>_<b>``: ``x, vx, ...`` or ``east,
    v_east, ...``, in metres)."""
    assert columns.position is not None
    if not columns.geodetic:
        names = state_names(columns.position)
        return names, names
    axes = LOCAL_AXES[: len(columns.position)]
    state = [n for p, a in zip(columns.position, axes, strict=True) for n in (p, f"v_{a}")]
    return state, [n for a in axes for n in (a, f"v_{a}")]


def to_geodetic(
    steps: TrackSteps, mean: np.ndarray, cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Estimates in the tracks' local frames (``[S, 2m]``: east, v_east, north, v_north[, up,
    v_up]) back to latitude, longitude (degrees)[, altitude]; velocities and covariances into
    metres along the east and north at each estimate (:func:`~torchsvs.datasets.geodesy.
    local_axes`; the frame's own axes turn against them away from its reference)."""
    from torchsvs.datasets import geodesy

    assert steps.reference is not None
    S, n = mean.shape
    m = n // 2
    track = np.repeat(np.arange(steps.num_tracks), steps.length)
    ref = steps.reference[track]
    east_north = mean[:, [0, 2]]
    lat, lon = geodesy.from_local(east_north, ref[:, 0], ref[:, 1])
    known = np.isfinite(lat + lon + ref.sum(axis=1))
    axes = np.broadcast_to(np.eye(2), (S, 2, 2)).copy()
    axes[known] = geodesy.local_axes(lat[known], lon[known], ref[known, 0], ref[known, 1])
    back = np.broadcast_to(np.eye(m), (S, m, m)).copy()
    back[:, :2, :2] = np.linalg.inv(axes)  # frame's axes -> east, north at the estimate
    transform = np.zeros((S, n, n))
    transform[:, 0::2, 0::2] = back  # positions (for the covariances)
    transform[:, 1::2, 1::2] = back  # velocities
    out = np.einsum("sij,sj->si", transform, mean)
    out[:, 0], out[:, 2] = lat, lon
    if cov is None:
        return out, None
    return out, transform @ cov @ np.swapaxes(transform, -1, -2)


def estimate_table(
    block: TrackBlock,
    mean: np.ndarray,
    cov: np.ndarray | None = None,
    never_observed: np.ndarray | None = None,
    outlier: np.ndarray | None = None,
) -> Any:
    """The output rows of a block: ``track_id, time`` as read, then the estimates.

    Args:
        block: the block the estimates belong to.
        mean: ``[S, 2m]`` estimate at each of the block's steps (NaN where not estimated).
        cov: ``[S, 2m, 2m]`` covariances, or ``None``.
        never_observed: ``[K, m]`` axes a track never observes (their estimates become NaN).
        outlier: ``[S]`` bool steps whose position was set aside as an outlier, written as a
            last column ``outlier`` (rows not placed: false); None: no such column.

    Returns:
        A ``pyarrow.Table`` with one row per input row: the id and time columns as read,
        positions under the input's names, velocities as ``v<name>`` (``x, vx, y, vy, ...``;
        WGS 84: ``lat, lon[, alt], v_east, v_north[, v_up]``), and with ``cov`` the
        upper triangle as ``cov_<a>_<b>``. WGS 84 positions (:class:`~torchsvs.datasets.rows.
        Columns`) come back as degrees (:func:`to_geodetic`), velocities as ``v_east,
        v_north[, v_up]`` and covariances named by ``east, north, up`` in metres.
    """
    import pyarrow as pa

    steps, cols = block.steps, block.columns
    assert cols.position is not None
    names, cov_names = output_names(cols)
    m = len(cols.position)
    if never_observed is not None and never_observed.any():
        track_of_step = np.repeat(np.arange(steps.num_tracks), steps.length)
        hidden = np.repeat(never_observed[track_of_step], 2, axis=1)  # [S, 2m]
        mean = np.where(hidden, np.nan, mean)
        if cov is not None:
            cov = np.where(hidden[:, :, None] | hidden[:, None, :], np.nan, cov)
    if cols.geodetic and len(mean):
        mean, cov = to_geodetic(steps, mean, cov)
    row_step = steps.row_step
    placed = row_step >= 0
    index = np.where(placed, row_step, 0)

    def per_row(values: np.ndarray) -> Any:
        # NaN (not estimated) becomes an empty field
        return pa.array(
            np.where(placed, values[index], np.nan), type=pa.float64(), from_pandas=True
        )

    out = {
        cols.track_id: block.table.column(cols.track_id),
        cols.time: block.table.column(cols.time),
    }
    # metric: x, vx, y, vy, ...; WGS 84: the positions, then the velocities
    order = range(2 * m) if not cols.geodetic else [*range(0, 2 * m, 2), *range(1, 2 * m, 2)]
    for j in order:
        out[names[j]] = per_row(mean[:, j]) if len(mean) else pa.nulls(len(row_step), pa.float64())
    if cov is not None:
        for a in range(2 * m):
            for b in range(a, 2 * m):
                out[f"cov_{cov_names[a]}_{cov_names[b]}"] = per_row(cov[:, a, b])
    if outlier is not None:
        flags = outlier[index] if len(outlier) else np.zeros(len(row_step), dtype=bool)
        out["outlier"] = pa.array(placed & flags, type=pa.bool_())
    return pa.table(out)


class EstimateWriter:
    """Appends output tables to a CSV (``.csv``) or Parquet (``.parquet``) file.

    The rows go to a temporary file beside ``path`` (``.<name>.<random>.part``), renamed over
    ``path`` when the writer is closed without an error: a run that fails midway leaves any
    earlier file at ``path`` as it was, and no half-written one."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.format = file_format(path)
        self._writer: Any = None
        self._temporary: Path | None = None

    def write(self, table: Any) -> None:
        import pyarrow.csv as pcsv
        import pyarrow.parquet as pq

        if self._writer is None:
            self._schema = table.schema
            handle, name = tempfile.mkstemp(
                prefix=f".{self.path.name}.", suffix=".part", dir=self.path.parent
            )
            os.close(handle)
            self._temporary = Path(name)
            _set_mode(self._temporary, self.path)
            if self.format == "parquet":
                self._writer = pq.ParquetWriter(self._temporary, table.schema)
            else:
                options = pcsv.WriteOptions(quoting_style="needed")
                self._writer = pcsv.CSVWriter(self._temporary, table.schema, write_options=options)
        self._writer.write_table(table.cast(self._schema))

    def close(self) -> None:
        """Finishes the file and puts it in place."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
            assert self._temporary is not None
            os.replace(self._temporary, self.path)
            self._temporary = None

    def discard(self) -> None:
        """Drops what was written; ``path`` stays as it was."""
        if self._writer is not None:
            try:
                self._writer.close()
            finally:
                self._writer = None
        if self._temporary is not None:
            self._temporary.unlink(missing_ok=True)
            self._temporary = None

    def __enter__(self) -> EstimateWriter:
        return self

    def __exit__(self, kind: object, *exc: object) -> None:
        if kind is None:
            self.close()
        else:
            self.discard()


def _set_mode(temporary: Path, target: Path) -> None:
    """Gives a temporary file the mode the target has, or a new file would get (``mkstemp``
    makes it private)."""
    try:
        mode = target.stat().st_mode & 0o777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    os.chmod(temporary, mode)


def write_estimates(
    tracks: RecordedTracks, mean: Tensor, path: str | Path, cov: Tensor | None = None
) -> None:
    """Writes an estimator's result on tracks from :func:`read_tracks`, one row per input row
    (never over the file they were read from: ``ValueError``)."""
    if tracks.source is None or tracks.steps is None:
        raise ValueError("tracks: expected tracks read by read_tracks (they know their rows)")
    block = tracks.source.block
    check_output(path, "path", inputs=(block.path,), force=True)
    flat_mean, flat_cov = scatter_steps(block.steps, tracks, mean, cov)
    never = None if tracks.never_observed is None else tracks.never_observed.numpy()
    never_all = None
    if never is not None:
        never_all = np.zeros((block.steps.num_tracks, never.shape[1]), dtype=bool)
        never_all[tracks.source.tracks] = never
    with EstimateWriter(path) as writer:
        writer.write(estimate_table(block, flat_mean, flat_cov, never_all))


def scatter_steps(
    steps: TrackSteps, tracks: RecordedTracks, mean: Tensor, cov: Tensor | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Padded results ``[B, T, ...]`` back to the flat steps of the block (``[S, ...]``, NaN at
    the steps of other tracks)."""
    n = mean.shape[-1]
    S = len(steps.time)
    flat_mean = np.full((S, n), np.nan)
    flat_cov = None if cov is None else np.full((S, n, n), np.nan)
    target, values, covs = flat_steps(tracks, mean, cov)
    flat_mean[target] = values
    if covs is not None and flat_cov is not None:
        flat_cov[target] = covs
    return flat_mean, flat_cov


def flat_steps(
    tracks: RecordedTracks, mean: Tensor, cov: Tensor | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Padded results at the real steps only: the block's flat step of each (``[s]`` int64) and
    the float64 values there (``mean [s, n]``, ``cov [s, n, n]`` or ``None``)."""
    assert tracks.steps is not None
    where = tracks.steps >= 0
    target = tracks.steps[where].numpy()
    covs = None if cov is None else cov.detach()[where].double().numpy()
    return target, mean.detach()[where].double().numpy(), covs

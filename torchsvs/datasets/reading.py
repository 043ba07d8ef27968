"""Track files in: whole, as one padded batch with priors (:func:`read_tracks`, for Python
use and training), or as a stream of blocks of *complete* tracks in bounded memory
(:func:`track_blocks`: a track's rows must then be contiguous in the file, any order within the
track)."""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets.describe import open_blocks
from torchsvs.datasets.paths import dataset_files
from torchsvs.datasets.priors import two_point_prior
from torchsvs.datasets.rows import (
    Columns,
    InputWarning,
    RowReport,
    file_columns,
    file_format,
    parquet_id_type,
    parse_block,
    read_blocks,
    slice_rows,
)
from torchsvs.datasets.tracks import (
    RecordedTracks,
    TrackSteps,
    check_contiguous,
    group_rows,
    track_runs,
)


@dataclass
class TrackBlock:
    """Complete tracks read from a file: the raw rows (for writing back) and their steps."""

    table: Any  #: pyarrow.Table of the block's rows as read
    steps: TrackSteps
    columns: Columns
    path: Path | None = None  #: the file read (an output must not replace it)
    #: the id column's type in the file where ``table`` holds it dictionary-encoded (it is
    #: written back in this type), else None
    id_type: Any = None


#: Rows up to which a file is read whole by default (:func:`reads_whole`): 1-2 GB in memory.
WHOLE_ROWS = 1 << 22
#: Bytes a CSV row takes, to estimate a file's rows from its size (ids, times and positions
#: written with 6-10 digits each), and a compressed one's (``.gz``, ``.bz2``: about 5 times less).
CSV_ROW_BYTES = 40
CSV_ROW_BYTES_COMPRESSED = 8


def reads_whole(path: str | Path) -> bool:
    """Whether ``torchsvs track`` reads ``path`` whole (any row order) rather than streaming it
    (:func:`track_blocks`): when it holds at most :data:`WHOLE_ROWS` rows (a Parquet file's
    count from its metadata, a CSV file's estimated from its size); a dataset when its largest
    file does."""
    import pyarrow.parquet as pq

    files = [f for f, _ in dataset_files(path)] if Path(path).is_dir() else [Path(path)]
    for file in files:
        if file_format(file) == "parquet":
            rows = pq.ParquetFile(file).metadata.num_rows
        else:
            packed = file.name.lower().endswith((".gz", ".bz2"))
            rows = file.stat().st_size // (CSV_ROW_BYTES_COMPRESSED if packed else CSV_ROW_BYTES)
        if rows > WHOLE_ROWS:
            return False
    return True


def track_blocks(
    path: str | Path,
    columns: Columns | None = None,
    block_rows: int = 1 << 20,
    whole: bool = False,
) -> Iterator[TrackBlock]:
    """Reads a track file, or a directory of Parquet files (a dataset:
    :func:`~torchsvs.datasets.paths.dataset_files`, file by file), as blocks of complete
    tracks, in file order.

    Streaming (``whole=False``) holds about ``block_rows`` rows at a time, plus the rows of the
    track that a block boundary cut (carried into the next block). It needs every track's rows
    to be contiguous in the file; a track whose rows reappear after other tracks raises
    ``ValueError`` naming it and ``--in-memory`` (sort the file by track id, or read it whole).
    ``whole=True`` reads the file (each file of a dataset) at once and accepts any row order
    within it. A track's rows must lie in one file of a dataset (``ValueError`` naming it).

    What ``columns`` leaves open (``time_unit="auto"``, ``frame="auto"``) is settled on the
    first block (:func:`~torchsvs.datasets.describe.describe_input`), with an
    :class:`~torchsvs.datasets.rows.InputWarning` where the data look unlike what was settled
    (degrees read as metres, a typical interval of over 1,000 s read as seconds).
    """
    described, blocks = open_blocks(path, columns, block_rows, dictionary_ids=True)
    for text in described.warnings:
        warnings.warn(text, InputWarning, stacklevel=2)
    cols = described.columns
    files = dataset_files(path) if Path(path).is_dir() else [(Path(path), {})]
    done: dict[str, Path] = {}  # each track read: the file it was in
    for file, partition in files:
        if file == described.source:
            rows = blocks
        else:
            _check_columns(file, cols, partition)
            rows = read_blocks(file, cols, block_rows, True, partition)
        yield from _file_blocks(file, rows, cols, whole, done, len(files) > 1)


def _check_columns(file: Path, columns: Columns, partition: dict[str, str]) -> None:
    """Raises ``ValueError`` naming a dataset's file that lacks a column the first one has."""
    available = {*file_columns(file), *partition}
    needed = (columns.track_id, columns.time, *(columns.position or ()), *columns.extra)
    missing = [c for c in needed if c not in available]
    if missing:
        raise ValueError(
            f"path: {str(file)!r} has no column {missing} (the dataset's first file has them); "
            "every file of a dataset needs the same columns"
        )


def _file_blocks(
    file: Path,
    blocks: Iterator[Any],
    cols: Columns,
    whole: bool,
    done: dict[str, Path],
    dataset: bool,
) -> Iterator[TrackBlock]:
    """One file's blocks of complete tracks (:func:`track_blocks`); ``done``: the tracks read
    before (a dataset's track in two files raises ``ValueError``)."""
    import pyarrow as pa

    id_type = parquet_id_type(file, cols)
    if whole:
        tables = list(blocks)
        if not tables:  # a dataset's file without rows
            return
        table = pa.concat_tables(tables)
        parsed = parse_block(table, cols)
        if dataset:
            _record(parsed, done, file)
        yield TrackBlock(table, group_rows(parsed), cols, file, id_type)
        return
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
        yield TrackBlock(table.slice(0, cut), _complete(head, done, file), cols, file, id_type)
    if carry is not None and len(carry):
        parsed = parse_block(carry, cols)
        yield TrackBlock(carry, _complete(parsed, done, file), cols, file, id_type)


def _complete(rows: Any, done: dict[str, Path], file: Path) -> TrackSteps:
    check_contiguous(rows.track_code, rows.track_ids)
    _record(rows, done, file)
    return group_rows(rows)


def _record(rows: Any, done: dict[str, Path], file: Path) -> None:
    """Adds the tracks of ``rows`` (read from ``file``) to ``done``; raises ``ValueError``
    naming a track read before (streaming needs a track's rows together, in one file)."""
    present = {rows.track_ids[c] for c in track_runs(rows.track_code)[1]}
    again = present & done.keys()
    if again:
        track = sorted(again)[0]
        if done[track] == file:
            raise ValueError(
                f"track {track!r}: its rows are not contiguous (it reappears after "
                "other tracks); streaming reads a file track by track, so sort it by track id, "
                "or read it whole (torchsvs track --in-memory)"
            )
        raise ValueError(
            f"track {track!r}: its rows are in two files of the dataset "
            f"({str(done[track])!r} and {str(file)!r}); a track's rows must lie in one file "
            "(write the dataset partitioned or bucketed by track id)"
        )
    done.update(dict.fromkeys(present, file))


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
            priors; ``None`` estimates it from the data (:func:`~torchsvs.datasets.estimate_noise`).
        dtype: of the measurement tensors.

    Returns:
        The tracks (``source`` set, for :func:`~torchsvs.datasets.write_estimates`) and the row
        report.
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
        from torchsvs.datasets.noise_estimate import estimate_noise

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

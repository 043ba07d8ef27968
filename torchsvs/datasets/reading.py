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
from torchsvs.datasets.priors import two_point_prior
from torchsvs.datasets.rows import (
    Columns,
    InputWarning,
    RowReport,
    parquet_id_type,
    parse_block,
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
    first block (:func:`~torchsvs.datasets.describe.describe_input`), with an
    :class:`~torchsvs.datasets.rows.InputWarning` where the data look unlike what was settled
    (degrees read as metres, a typical interval of over 1,000 s read as seconds).
    """
    import pyarrow as pa

    described, blocks = open_blocks(path, columns, block_rows, dictionary_ids=True)
    for text in described.warnings:
        warnings.warn(text, InputWarning, stacklevel=2)
    cols, source = described.columns, Path(path)
    id_type = parquet_id_type(path, cols)
    if whole:
        table = pa.concat_tables(list(blocks))
        yield TrackBlock(table, group_rows(parse_block(table, cols)), cols, source, id_type)
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
        yield TrackBlock(table.slice(0, cut), _complete(head, done), cols, source, id_type)
    if carry is not None and len(carry):
        parsed = parse_block(carry, cols)
        yield TrackBlock(carry, _complete(parsed, done), cols, source, id_type)


def _complete(rows: Any, done: set[str]) -> TrackSteps:
    check_contiguous(rows.track_code, rows.track_ids)
    present = {rows.track_ids[c] for c in track_runs(rows.track_code)[1]}
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

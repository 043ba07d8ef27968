"""Track files in and estimates out: whole files or streams of complete tracks, and writers.

* :func:`read_tracks`: a whole CSV/Parquet file as one padded batch with priors
  (:class:`~torchsvs.datasets.RecordedTracks`), for Python use and training.
* :func:`track_blocks`: the file as a stream of blocks of *complete* tracks, in bounded memory:
  a track's rows must then be contiguous in the file (any order within the track).
* :func:`estimate_table`: the output rows of a block: one per input row, with the id and time as
  read and the estimates of the step the row was placed at.
* :class:`EstimateWriter`: appends output blocks to a CSV or Parquet file.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets.priors import two_point_prior
from torchsvs.datasets.rows import (
    Columns,
    RowReport,
    file_columns,
    file_format,
    parse_block,
    read_blocks,
    slice_rows,
)
from torchsvs.datasets.tracks import RecordedTracks, TrackSteps, check_contiguous, group_rows


@dataclass
class TrackBlock:
    """Complete tracks read from a file: the raw rows (for writing back) and their steps."""

    table: Any  #: pyarrow.Table of the block's rows as read
    steps: TrackSteps
    columns: Columns


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
    ``ValueError`` (sort the file by track id, or read it whole). ``whole=True`` reads the file
    at once and accepts any row order.
    """
    import pyarrow as pa

    cols = (columns or Columns()).resolve(file_columns(path))
    if whole:
        table = pa.concat_tables(list(read_blocks(path, cols, block_rows)))
        yield TrackBlock(table, group_rows(parse_block(table, cols)), cols)
        return
    done: set[str] = set()
    carry = None
    for block in read_blocks(path, cols, block_rows):
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
        yield TrackBlock(table.slice(0, cut), _complete(head, done), cols)
    if carry is not None and len(carry):
        parsed = parse_block(carry, cols)
        yield TrackBlock(carry, _complete(parsed, done), cols)


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


def estimate_table(
    block: TrackBlock,
    mean: np.ndarray,
    cov: np.ndarray | None = None,
    never_observed: np.ndarray | None = None,
) -> Any:
    """The output rows of a block: ``track_id, time`` as read, then the estimates.

    Args:
        block: the block the estimates belong to.
        mean: ``[S, 2m]`` estimate at each of the block's steps (NaN where not estimated).
        cov: ``[S, 2m, 2m]`` covariances, or ``None``.
        never_observed: ``[K, m]`` axes a track never observes (their estimates become NaN).

    Returns:
        A ``pyarrow.Table`` with one row per input row: the id and time columns as read,
        positions under the input's names, velocities as ``v<name>``, and with ``cov`` the
        upper triangle as ``cov_<a>_<b>``.
    """
    import pyarrow as pa

    steps, cols = block.steps, block.columns
    assert cols.position is not None
    names = state_names(cols.position)
    m = len(cols.position)
    if never_observed is not None and never_observed.any():
        track_of_step = np.repeat(np.arange(steps.num_tracks), steps.length)
        hidden = np.repeat(never_observed[track_of_step], 2, axis=1)  # [S, 2m]
        mean = np.where(hidden, np.nan, mean)
        if cov is not None:
            cov = np.where(hidden[:, :, None] | hidden[:, None, :], np.nan, cov)
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
    for j, name in enumerate(names):
        out[name] = per_row(mean[:, j]) if len(mean) else pa.nulls(len(row_step), pa.float64())
    if cov is not None:
        for a in range(2 * m):
            for b in range(a, 2 * m):
                out[f"cov_{names[a]}_{names[b]}"] = per_row(cov[:, a, b])
    return pa.table(out)


class EstimateWriter:
    """Appends output tables to a CSV (``.csv``) or Parquet (``.parquet``) file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.format = file_format(path)
        self._writer: Any = None

    def write(self, table: Any) -> None:
        import pyarrow.csv as pcsv
        import pyarrow.parquet as pq

        if self._writer is None:
            self._schema = table.schema
            if self.format == "parquet":
                self._writer = pq.ParquetWriter(self.path, table.schema)
            else:
                options = pcsv.WriteOptions(quoting_style="needed")
                self._writer = pcsv.CSVWriter(self.path, table.schema, write_options=options)
        self._writer.write_table(table.cast(self._schema))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

    def __enter__(self) -> EstimateWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_estimates(
    tracks: RecordedTracks, mean: Tensor, path: str | Path, cov: Tensor | None = None
) -> None:
    """Writes an estimator's result on tracks from :func:`read_tracks`, one row per input row."""
    if tracks.source is None or tracks.steps is None:
        raise ValueError("tracks: expected tracks read by read_tracks (they know their rows)")
    block = tracks.source.block
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

"""Estimates out: :func:`estimate_table` gives a block's output rows (one per input row, with
the id and time as read and the estimates of the step the row was placed at), and
:class:`EstimateWriter` appends them to a CSV or Parquet file, written beside it under a
temporary name and renamed over it only once complete."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from torchsvs.datasets.arrow_numpy import from_numpy, to_float
from torchsvs.datasets.paths import check_output, dataset_files
from torchsvs.datasets.reading import TrackBlock
from torchsvs.datasets.rows import Columns, file_format
from torchsvs.datasets.steps import TrackSteps, as_rows
from torchsvs.datasets.tracks import RecordedTracks


def state_names(position: Sequence[str]) -> list[str]:
    """Names of the state components in the layout of ConstantVelocity: ``x, vx, y, vy, ...``."""
    return [name for p in position for name in (p, f"v{p}")]


#: numpy type of the estimates written at each ``precision``.
OUTPUT_TYPES = {"float64": np.float64, "float32": np.float32}
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
    track = steps.track_of_step
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
    precision: str = "float64",
) -> Any:
    """The output rows of a block: ``track_id, time`` as read, then the estimates.

    Args:
        block: the block the estimates belong to.
        mean: ``[S, 2m]`` estimate at each of the block's steps (NaN where not estimated).
        cov: ``[S, 2m, 2m]`` covariances, or ``None``.
        never_observed: ``[K, m]`` axes a track never observes (their estimates become NaN).
        outlier: ``[S]`` bool steps whose position was set aside as an outlier, written as a
            last column ``outlier`` (rows not placed: false); None: no such column.
        precision: of the estimates, ``"float64"`` or ``"float32"`` (computed in float64,
            rounded once as they are written).

    Returns:
        A ``pyarrow.Table`` with one row per input row: the id and time columns as read,
        positions under the input's names, velocities as ``v<name>`` (``x, vx, y, vy, ...``;
        WGS 84: ``lat, lon[, alt], v_east, v_north[, v_up]``), and with ``cov`` the
        upper triangle as ``cov_<a>_<b>``. WGS 84 positions (:class:`~torchsvs.datasets.rows.
        Columns`) come back as degrees (:func:`to_geodetic`), velocities as ``v_east,
        v_north[, v_up]`` and covariances named by ``east, north, up`` in metres.
    """
    import pyarrow as pa

    if precision not in OUTPUT_TYPES:
        raise ValueError(f"precision: expected one of {list(OUTPUT_TYPES)}, got {precision!r}")
    kind = OUTPUT_TYPES[precision]
    steps, cols = block.steps, block.columns
    assert cols.position is not None
    names, cov_names = output_names(cols)
    m = len(cols.position)
    if never_observed is not None and never_observed.any():
        track_of_step = steps.track_of_step
        hidden = np.repeat(never_observed[track_of_step], 2, axis=1)  # [S, 2m]
        mean = np.where(hidden, np.nan, mean)
        if cov is not None:
            cov = np.where(hidden[:, :, None] | hidden[:, None, :], np.nan, cov)
    if cols.geodetic and len(mean):
        mean, cov = to_geodetic(steps, mean, cov)
    row_step = steps.row_step
    placed = row_step >= 0
    everywhere = bool(placed.all())
    # each row's step's estimates, the rows taken once as items (as_rows: not column by
    # column); rows that are their steps in order (a sorted file's usual case) need none taken
    if everywhere and len(row_step) == len(mean) and _counts_up(row_step):
        index, rows, row_cov = row_step, mean, cov
    else:
        index = np.where(placed, row_step, 0)

        def take(values: np.ndarray) -> np.ndarray:
            picked = as_rows(np.ascontiguousarray(values))[index]
            picked = picked.view(values.dtype).reshape(len(index), *values.shape[1:])
            if not everywhere:
                picked[~placed] = np.nan
            return picked

        rows = take(mean) if len(mean) else mean
        row_cov = cov if cov is None or not len(cov) else take(cov)

    if cols.geodetic and len(rows):
        rows = _longitudes_as_read(rows, block.table.column(cols.position[1]))

    def per_row(values: np.ndarray) -> Any:
        # NaN (not estimated) becomes an empty field; no step at all: every field
        if not len(values):
            return pa.nulls(len(row_step), pa.from_numpy_dtype(kind))
        return nan_as_null(values.astype(kind, copy=False))

    ids = block.table.column(cols.track_id)
    out = {
        cols.track_id: ids if block.id_type is None else ids.cast(block.id_type),
        cols.time: block.table.column(cols.time),
    }
    # metric: x, vx, y, vy, ...; WGS 84: the positions, then the velocities
    order = range(2 * m) if not cols.geodetic else [*range(0, 2 * m, 2), *range(1, 2 * m, 2)]
    for j in order:
        out[names[j]] = per_row(rows[:, j])
    if row_cov is not None:
        for a in range(2 * m):
            for b in range(a, 2 * m):
                out[f"cov_{cov_names[a]}_{cov_names[b]}"] = per_row(row_cov[:, a, b])
    if outlier is not None:
        flags = outlier[index] if len(outlier) else np.zeros(len(row_step), dtype=bool)
        out["outlier"] = from_numpy(placed & flags, pa.bool_())
    return pa.table(out)


def _longitudes_as_read(rows: np.ndarray, column: Any) -> np.ndarray:
    """``rows [R, 2m]`` (WGS 84 estimates, the longitude at index 2) with each longitude in the
    convention its row was read in: a row read in 0-360° (above 180°) gets its estimate there,
    where it came back in -180..180° (180.5° was written as -179.5°)."""
    read = to_float(column)[0]
    wrapped = (read > 180.0) & (rows[:, 2] < 0.0)  # (NaN: False)
    if not wrapped.any():
        return rows
    rows = rows.copy()
    rows[wrapped, 2] += 360.0
    return rows


def _counts_up(values: np.ndarray) -> bool:
    """Whether ``values`` is ``0, 1, 2, ...``."""
    return len(values) == 0 or (values[0] == 0 and bool((np.diff(values) == 1).all()))


def nan_as_null(values: np.ndarray) -> Any:
    """A float array as a ``pyarrow`` array with NaN as empty (null) values: the numbers'
    buffer as it is and a validity bitmap only where a value is NaN (as ``pyarrow.array(...,
    from_pandas=True)`` gives, at a fraction of its cost)."""
    return from_numpy(values, valid=~np.isnan(values))


class EstimateWriter:
    """Appends output tables to a CSV (``.csv``) or Parquet (``.parquet``) file, or, where
    ``source`` is a directory (a Parquet dataset:
    :func:`~torchsvs.datasets.paths.dataset_files`), to one Parquet file per input file in the
    directory ``path``, under the input file's name and relative path (``part=3/a.parquet``
    gives ``path/part=3/a.parquet``; an input file without rows gives one without rows).

    The rows go to a temporary file (a dataset's to a temporary directory) beside ``path``
    (``.<name>.<random>.part``), renamed over ``path`` when the writer is closed without an
    error: a run that fails midway leaves any earlier file or directory at ``path`` as it
    was, and no half-written one. A directory at ``path`` is replaced as a whole."""

    def __init__(self, path: str | Path, source: str | Path | None = None) -> None:
        self.path = Path(path)
        self.source = Path(source) if source is not None and Path(source).is_dir() else None
        self.format = "parquet" if self.source is not None else file_format(path)
        self._writer: Any = None
        self._schema: Any = None
        self._temporary: Path | None = None  #: the file (a dataset: the directory) written
        self._current: Path | None = None  #: a dataset's input file being written
        self._written: set[Path] = set()  #: a dataset's input files written

    def write(self, table: Any, read_from: str | Path | None = None) -> None:
        """Appends ``table``; a dataset's rows go to the output file of their input file
        ``read_from`` (:attr:`TrackBlock.path <torchsvs.datasets.reading.TrackBlock.path>`;
        files one after the other)."""
        if self._schema is None:
            self._schema = table.schema
        elif not table.schema.equals(self._schema):
            table = table.cast(self._schema)
        if self.source is None:
            if self._writer is None:
                self._temporary = _temporary_file(self.path)
                self._writer = _open_file(self._temporary, self.format, self._schema)
        else:
            if read_from is None:
                raise ValueError(
                    "read_from: expected the input file of the rows (a dataset's output has "
                    "one file per input file)"
                )
            if self._temporary is None:
                self._temporary = _temporary_directory(self.path)
            if Path(read_from) != self._current:
                self._next_file(Path(read_from))
        self._writer.write_table(table)

    def _close_file(self) -> None:
        """Finishes the file being written (a dataset's next rows open the next one)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _next_file(self, read_from: Path) -> None:
        """Finishes a dataset's output file and opens that of ``read_from``."""
        assert self._temporary is not None and self.source is not None
        self._close_file()
        if read_from in self._written:
            raise ValueError(
                f"read_from: {str(read_from)!r} was written before; a dataset's files are "
                "written one after the other"
            )
        target = self._temporary / read_from.relative_to(self.source)
        target.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _open_file(target, "parquet", self._schema)
        self._current = read_from
        self._written.add(read_from)

    def close(self) -> None:
        """Finishes the file (a dataset's files) and puts it in place."""
        self._close_file()
        if self._temporary is None:
            return
        if self.source is None:
            os.replace(self._temporary, self.path)
        else:
            for file, _ in dataset_files(self.source):  # input files without rows
                if file not in self._written:
                    self._next_file(file)
                    self._close_file()
            _replace_directory(self._temporary, self.path)
        self._temporary = None

    def discard(self) -> None:
        """Drops what was written; ``path`` stays as it was."""
        if self._writer is not None:
            try:
                self._writer.close()
            finally:
                self._writer = None
        if self._temporary is not None:
            if self._temporary.is_dir():
                shutil.rmtree(self._temporary, ignore_errors=True)
            else:
                self._temporary.unlink(missing_ok=True)
            self._temporary = None

    def __enter__(self) -> EstimateWriter:
        return self

    def __exit__(self, kind: object, *exc: object) -> None:
        if kind is None:
            self.close()
        else:
            self.discard()


def _open_file(path: Path, kind: str, schema: Any) -> Any:
    """A ``pyarrow`` writer of a CSV or Parquet file."""
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    if kind == "parquet":
        return pq.ParquetWriter(path, schema, use_dictionary=_dictionary_columns(schema))
    options = pcsv.WriteOptions(quoting_style="needed")
    return pcsv.CSVWriter(path, schema, write_options=options)


def _temporary_file(target: Path) -> Path:
    """A new empty file beside ``target``, with the mode ``target`` has or would get."""
    handle, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    os.close(handle)
    _set_mode(Path(name), target)
    return Path(name)


def _temporary_directory(target: Path) -> Path:
    """A new empty directory beside ``target``, with the mode a new directory would get."""
    folder = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(folder, 0o777 & ~umask)
    return folder


def _replace_directory(finished: Path, target: Path) -> None:
    """Puts the directory ``finished`` at ``target``; a directory there before is moved
    aside first and removed only once the new one is in place."""
    if not target.exists():
        os.replace(finished, target)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
    os.replace(target, old / target.name)
    os.replace(finished, target)
    shutil.rmtree(old, ignore_errors=True)


def _dictionary_columns(schema: Any) -> list[str]:
    """The columns a Parquet output stores dictionary-encoded: the id and the time as read
    (:func:`estimate_table`'s first two columns, few distinct values) and any column not of
    floats. Estimates are distinct floats: a dictionary would be built and dropped at every row
    group (that doubled the writing time)."""
    import pyarrow as pa

    return [
        field.name
        for j, field in enumerate(schema)
        if j < 2 or not pa.types.is_floating(field.type)
    ]


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
    """Writes an estimator's result on tracks from :func:`~torchsvs.datasets.read_tracks`, one
    row per input row (never over the file they were read from: ``ValueError``)."""
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
    if bool(where.all()):  # no padding (tracks of one length): views, not a masked copy
        n = mean.shape[-1]
        target = tracks.steps.reshape(-1).numpy()
        covs = None if cov is None else cov.detach().reshape(-1, n, n).double().numpy()
        return target, mean.detach().reshape(-1, n).double().numpy(), covs
    target = tracks.steps[where].numpy()
    covs = None if cov is None else cov.detach()[where].double().numpy()
    return target, mean.detach()[where].double().numpy(), covs

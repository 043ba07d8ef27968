"""Track files in as blocks of *complete* tracks (:func:`track_blocks`: a file whole, or
streamed in bounded memory, a track's rows then contiguous in the file, any order within the
track), read in a thread of their own ahead of the caller (:class:`ReadAhead`). A whole file as
one padded batch with priors, for Python use and training, is
:func:`~torchsvs.datasets.tracks.read_tracks`.

Reading needs numpy and Arrow alone, not torch: ``torchsvs track`` reads its input while torch
is imported."""

from __future__ import annotations

import threading
import time
import warnings
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchsvs.datasets.describe import InputDescription, describe_input, open_blocks
from torchsvs.datasets.paths import dataset_files
from torchsvs.datasets.rows import (
    Columns,
    InputWarning,
    file_columns,
    file_format,
    parquet_id_type,
    parse_block,
    read_blocks,
    slice_rows,
)
from torchsvs.datasets.steps import TrackSteps, check_contiguous, group_rows, track_runs


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


class ReadAhead:
    """A track file's blocks of complete tracks (:func:`track_blocks`), read in a thread of its
    own from the moment this is made (``whole=None``: whole where :func:`reads_whole` says),
    one block ahead of the caller (memory for two blocks: reading more ahead gained nothing and
    cost 240 MB on 10 M rows): what the caller does meanwhile (importing torch, settling the
    plan, estimating the block before) runs beside the reading. With ``describe``, the thread
    first describes the file
    (:func:`~torchsvs.datasets.describe.describe_input`, with ``name``): :meth:`description`
    waits for it, and the blocks are read with its resolved columns.

    Iterate once; :meth:`close` (or ``with``) stops the thread after the block it is reading.
    An error of the reading is raised where its block (or the description) is asked for.
    :attr:`reading` adds the seconds spent reading blocks, :attr:`waiting` the seconds the
    caller waited for one."""

    def __init__(
        self,
        path: str | Path,
        columns: Columns | None = None,
        *,
        block_rows: int = 1 << 20,
        whole: bool | None = False,
        describe: bool = False,
        name: str = "path",
    ) -> None:
        self.path = Path(path)  #: the file read
        self.describes = describe  #: :meth:`description` is made
        self.reading = self.waiting = 0.0
        self._ready = threading.Condition()
        self._blocks: deque[TrackBlock] = deque()
        self._described: InputDescription | None = None
        self._error: BaseException | None = None
        self._done = self._closed = False
        self._thread = threading.Thread(
            target=self._read,
            args=(path, columns, block_rows, whole, describe, name),
            name="read-ahead",
            daemon=True,  # (a caller that fails leaves it at its next block)
        )
        self._thread.start()

    def _read(
        self,
        path: str | Path,
        columns: Columns | None,
        block_rows: int,
        whole: bool | None,
        describe: bool,
        name: str,
    ) -> None:
        try:
            if describe:
                described = describe_input(path, columns, block_rows=block_rows, name=name)
                with self._ready:
                    self._described = described
                    self._ready.notify_all()
                columns = described.columns
            if whole is None:
                whole = reads_whole(path)
            blocks = track_blocks(path, columns, block_rows=block_rows, whole=whole)
            while True:
                with self._ready:  # the caller has taken the block before
                    self._ready.wait_for(lambda: self._closed or not self._blocks)
                    if self._closed:
                        return
                tick = time.perf_counter()
                block = next(blocks, None)
                self.reading += time.perf_counter() - tick
                with self._ready:
                    if block is None or self._closed:  # (closed meanwhile: dropped)
                        break
                    self._blocks.append(block)
                    self._ready.notify_all()
        except BaseException as error:  # (handed to the caller: raised where it asks)
            with self._ready:
                self._error = error
        finally:
            with self._ready:
                self._done = True
                self._ready.notify_all()

    def description(self) -> InputDescription:
        """The file's description (``describe=True``), once read; raises the reading's
        error."""
        if not self.describes:
            raise ValueError("describe: this ReadAhead was made without describe=True")
        with self._ready:
            self._ready.wait_for(lambda: self._described is not None or self._done)
            if self._described is None:
                self._raise()
            assert self._described is not None, "a description, or the reading's error"
            return self._described

    def __iter__(self) -> Iterator[TrackBlock]:
        while True:
            tick = time.perf_counter()
            with self._ready:
                self._ready.wait_for(lambda: bool(self._blocks) or self._done)
                self.waiting += time.perf_counter() - tick
                if not self._blocks:
                    self._raise()
                    return
                block = self._blocks.popleft()
                self._ready.notify_all()
            yield block

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        """Stops reading (after the block being read) and drops the blocks read."""
        with self._ready:
            self._closed = True
            self._blocks.clear()
            self._ready.notify_all()

    def __enter__(self) -> ReadAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Track rows given as a table (a ``pandas.DataFrame`` or ``pyarrow.Table``) or a file's first
rows, as a block of complete tracks (:func:`block_of`): what a sample is planned on and what
:func:`~torchsvs.track_table.track_table` estimates."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torchsvs.datasets.describe import describe_table
from torchsvs.datasets.reading import TrackBlock, reads_whole, track_blocks
from torchsvs.datasets.rows import Columns, parse_block
from torchsvs.datasets.steps import group_rows


def block_of(data: Any, columns: Columns | None = None, block_rows: int = 1 << 18) -> TrackBlock:
    """Track rows as a block (a block as it is): a table's (``pandas.DataFrame`` or
    ``pyarrow.Table``; columns still open are settled on it,
    :func:`~torchsvs.datasets.describe.describe_table`) or the first block of a
    ``.csv``/``.parquet`` file or Parquet dataset (a path): all of it where ``torchsvs track``
    reads it whole (:func:`~torchsvs.datasets.reading.reads_whole`), else its first
    ``block_rows`` rows' complete tracks."""
    import pyarrow as pa

    if isinstance(data, TrackBlock):
        return data
    if isinstance(data, (str, Path)):
        return next(track_blocks(data, columns, block_rows=block_rows, whole=reads_whole(data)))
    if is_pandas(data):
        data = pa.Table.from_pandas(data, preserve_index=False)
    elif not isinstance(data, pa.Table):
        raise TypeError(
            "data: expected a pandas DataFrame, a pyarrow Table or a file path, got "
            f"{type(data).__name__}"
        )
    if columns is None or not _settled(columns):
        columns = describe_table(data, columns, name="data").columns
    steps = group_rows(parse_block(data, columns))
    return TrackBlock(data, steps, columns)


def _settled(columns: Columns) -> bool:
    """Whether nothing of ``columns`` is left to settle on the data."""
    return columns.position is not None and columns.frame != "auto" and columns.time_unit != "auto"


def is_pandas(data: Any) -> bool:
    """Whether ``data`` is a pandas DataFrame (without importing pandas)."""
    return type(data).__module__.startswith("pandas") and hasattr(data, "columns")

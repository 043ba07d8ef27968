"""Track rows given as a table (a ``pandas.DataFrame`` or ``pyarrow.Table``) or a file's first
rows, as a block of complete tracks (:func:`block_of`): what a sample is planned on and what
:func:`~torchsvs.track_table.track_table` estimates."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torchsvs.datasets.describe import describe_table
from torchsvs.datasets.reading import TrackBlock, reads_whole, track_blocks
from torchsvs.datasets.rows import Columns, parse_block
from torchsvs.datasets.steps import group_rows, join_steps

#: Tracks a sample's settings are read off (``torchsvs track --fit-tracks``' default): a
#: file's first block holds them, or a dataset's first files (:func:`sample_taken`).
SAMPLE_TRACKS = 2000
#: ... or at most this many steps of them (tracks of 500 steps and more: fewer tracks).
SAMPLE_STEPS = 1 << 20


def block_of(
    data: Any,
    columns: Columns | None = None,
    block_rows: int = 1 << 18,
    tracks: int = SAMPLE_TRACKS,
) -> TrackBlock:
    """Track rows as a block (a block as it is): a table's (``pandas.DataFrame`` or
    ``pyarrow.Table``; columns still open are settled on it,
    :func:`~torchsvs.datasets.describe.describe_table`) or the sample ``torchsvs track`` plans
    on of a ``.csv``/``.parquet`` file or Parquet dataset (a path): its first blocks as
    :func:`sample_taken` takes them (a block is all of a file where ``torchsvs track`` reads it
    whole, :func:`~torchsvs.datasets.reading.reads_whole`, else ``block_rows`` rows' complete
    tracks), joined."""
    import pyarrow as pa

    if isinstance(data, TrackBlock):
        return data
    if isinstance(data, (str, Path)):
        taken: list[TrackBlock] = []
        for block in track_blocks(data, columns, block_rows=block_rows, whole=reads_whole(data)):
            taken.append(block)
            if sample_taken(taken, tracks):
                break
        return joined(taken)
    if is_pandas(data):
        data = pa.Table.from_pandas(data, preserve_index=False)
    elif not isinstance(data, pa.Table):
        raise TypeError(
            "data: expected a pandas DataFrame, a pyarrow Table or a file path, got "
            f"{type(data).__name__}"
        )
    if columns is None or not _settled(columns):
        columns = describe_table(data, columns, name="data").columns
    _check_float_ids(data, columns.track_id)
    steps = group_rows(parse_block(data, columns))
    return TrackBlock(data, steps, columns)


def _check_float_ids(table: Any, name: str) -> None:
    """A ValueError where the track ids are floats beyond 2^53, where distinct integers become
    one number: Dask reads an int64 column with an empty value as float64, and 60 tracks of
    ids near 2^60 were estimated as one (26 km off; an outside probe)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if name not in table.column_names or not pa.types.is_floating(table.schema.field(name).type):
        return
    largest = pc.max(pc.abs(table.column(name))).as_py()
    if largest is not None and largest >= 2.0**53:
        raise ValueError(
            f"data: the track ids {name!r} are floats reaching {largest:.6g}, beyond 2^53, where "
            "distinct integer ids become one number (an int64 column with an empty value read "
            "as float64, as pandas and Dask do); read the ids as integers (Int64, "
            "dtype_backend='pyarrow') or as text"
        )


def _settled(columns: Columns) -> bool:
    """Whether nothing of ``columns`` is left to settle on the data."""
    return columns.position is not None and columns.frame != "auto" and columns.time_unit != "auto"


def is_pandas(data: Any) -> bool:
    """Whether ``data`` is a pandas DataFrame (without importing pandas)."""
    return type(data).__module__.startswith("pandas") and hasattr(data, "columns")


def to_pandas_like(table: Any, like: Any) -> Any:
    """An Arrow ``table`` as a pandas DataFrame whose columns from the DataFrame ``like`` keep
    its dtypes where they are pandas' own (nullable ``Int64``, ``string``, ...): Arrow's default
    turns an integer column with an empty value into float64, which alters ids above 2^53."""
    frame = table.to_pandas()
    for name in frame.columns:
        if name not in like.columns:
            continue
        dtype = like[name].dtype
        if frame[name].dtype != dtype and hasattr(dtype, "__from_arrow__"):
            frame[name] = dtype.__from_arrow__(table.column(name))
    return frame


def sample_taken(blocks: list[TrackBlock], tracks: int = SAMPLE_TRACKS) -> bool:
    """Whether a file's or a dataset's first ``blocks`` (in reading order) hold the sample its
    settings are read off: ``tracks`` tracks or :data:`SAMPLE_STEPS` steps. One block of a
    file read whole holds all of it; a dataset of small files takes files until the sample is
    full, so that its settings are read off as many tracks as the same rows in one file."""
    held = sum(b.steps.num_tracks for b in blocks)
    return held >= tracks or sum(len(b.steps.time) for b in blocks) >= SAMPLE_STEPS


def joined(blocks: list[TrackBlock]) -> TrackBlock:
    """Blocks of distinct tracks (a dataset's files) as one, to plan on: the steps joined
    (:func:`~torchsvs.datasets.steps.join_steps`), the rows' tables concatenated (text ids
    decoded where a file holds them dictionary-encoded, types unified where files differ), no
    path."""
    import pyarrow as pa

    if len(blocks) == 1:
        return blocks[0]
    tables = [_decoded(b.table) for b in blocks]
    table = pa.concat_tables(tables, promote_options="permissive")
    steps = join_steps([b.steps for b in blocks])
    return TrackBlock(table, steps, blocks[0].columns)


def _decoded(table: Any) -> Any:
    """``table`` with its dictionary-encoded columns as their values."""
    import pyarrow as pa

    for i, field in enumerate(table.schema):
        if pa.types.is_dictionary(field.type):
            table = table.set_column(i, field.name, table.column(i).cast(field.type.value_type))
    return table

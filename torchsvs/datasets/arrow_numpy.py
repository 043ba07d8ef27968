"""Numbers between Arrow and numpy through their buffers, without pandas.

``pyarrow``'s own conversions (``Array.to_numpy``, ``pyarrow.array``, a scalar made from a
Python value) first load its pandas support, which imports pandas: 0.35-0.4 s of a process's
start. ``torchsvs track`` reads its input beside torch's import, and the two imports then took
turns on one interpreter lock (torch's import: 0.91 s alone, 1.27 s beside pandas'). The
pipeline's own conversions are of fixed-width numbers and booleans, which these functions read
and write as the buffers are: the values' buffer (bit-packed for booleans) and a validity
bitmap where there are empty values.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def numpy_dtype(kind: Any) -> np.dtype:
    """The numpy dtype of an Arrow type of fixed-width numbers or booleans; ``TypeError``
    naming the type otherwise."""
    import pyarrow as pa

    if pa.types.is_boolean(kind):
        return np.dtype(bool)
    if pa.types.is_floating(kind):
        return np.dtype(f"f{kind.bit_width // 8}")
    if pa.types.is_signed_integer(kind):
        return np.dtype(f"i{kind.bit_width // 8}")
    if pa.types.is_unsigned_integer(kind):
        return np.dtype(f"u{kind.bit_width // 8}")
    raise TypeError(f"column: expected numbers or booleans, got Arrow type {kind}")


def _bits(buffer: Any, offset: int, count: int) -> np.ndarray:
    """``count`` bits of a bit-packed Arrow buffer (least significant bit first) from bit
    ``offset``, as booleans."""
    start = offset // 8
    packed = np.frombuffer(buffer, dtype=np.uint8, count=(offset % 8 + count + 7) // 8,
                           offset=start)  # fmt: skip
    return np.unpackbits(packed, bitorder="little", count=offset % 8 + count)[offset % 8 :].astype(
        bool
    )


def to_numpy(column: Any, fill: Any = None) -> np.ndarray:
    """A ``pyarrow`` array or chunked array of fixed-width numbers or booleans as a 1-D numpy
    array of its type (:func:`numpy_dtype`): zero-copy (read-only) for one chunk of numbers
    without empty values, as ``to_numpy`` gives. Empty values become ``fill`` (the result's
    type then as numpy promotes it); ``ValueError`` if there are some and no ``fill``."""
    chunks = column.chunks if hasattr(column, "chunks") else [column]
    dtype = numpy_dtype(column.type)
    parts = []
    for chunk in chunks:
        n, offset = len(chunk), chunk.offset
        if n == 0:
            continue
        validity, data = chunk.buffers()[:2]
        if dtype.kind == "b":
            values = _bits(data, offset, n)
        else:
            values = np.frombuffer(data, dtype=dtype, count=n, offset=offset * dtype.itemsize)
        if chunk.null_count:
            if fill is None:
                raise ValueError(
                    f"column: {chunk.null_count} empty values and no fill value for them"
                )
            values = np.where(_bits(validity, offset, n), values, fill)
        parts.append(values)
    if not parts:
        return np.zeros(0, dtype=dtype if fill is None else np.result_type(dtype, fill))
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def from_numpy(values: np.ndarray, kind: Any = None, valid: np.ndarray | None = None) -> Any:
    """A 1-D numpy array of numbers or booleans as a ``pyarrow`` array of ``kind`` (an Arrow
    type; the values' own by default, else they are cast to it first), empty where ``valid``
    (booleans) is False, without empty values where it is not given (NaN stays a number, as
    ``pyarrow.array`` keeps it)."""
    import pyarrow as pa

    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"values: expected a 1-D array, got shape {values.shape}")
    if kind is None:
        kind = pa.bool_() if values.dtype == bool else pa.from_numpy_dtype(values.dtype)
    dtype = numpy_dtype(kind)
    values = np.ascontiguousarray(values, dtype=dtype)
    data = np.packbits(values, bitorder="little") if dtype.kind == "b" else values
    if valid is None or bool(valid.all()):
        return pa.Array.from_buffers(kind, len(values), [None, pa.py_buffer(data)], null_count=0)
    bitmap = pa.py_buffer(np.packbits(valid, bitorder="little"))
    empty = len(valid) - int(np.count_nonzero(valid))
    return pa.Array.from_buffers(kind, len(values), [bitmap, pa.py_buffer(data)], empty)


def repeated_text(value: str, count: int) -> Any:
    """``count`` copies of one text as a ``pyarrow`` string array (a hive partition's value as
    a column of every row), built from its buffers: offsets and the text repeated."""
    import pyarrow as pa

    data = value.encode()
    total = count * len(data)
    wide = total >= 2**31  # (a string array's offsets are 32-bit)
    offsets = np.arange(count + 1, dtype=np.int64 if wide else np.int32) * len(data)
    kind = pa.large_string() if wide else pa.string()
    buffers = [None, pa.py_buffer(offsets), pa.py_buffer(data * count)]
    return pa.Array.from_buffers(kind, count, buffers, null_count=0)


def texts(values: Sequence[str]) -> Any:
    """Texts as a ``pyarrow`` string array, built from its buffers (``pa.array`` of a list
    imports pandas)."""
    import pyarrow as pa

    data = [v.encode() for v in values]
    offsets = np.cumsum([0] + [len(d) for d in data], dtype=np.int32)
    buffers = [None, pa.py_buffer(offsets), pa.py_buffer(b"".join(data))]
    return pa.Array.from_buffers(pa.string(), len(values), buffers, null_count=0)


def to_float(column: Any) -> tuple[np.ndarray, np.ndarray]:
    """A pyarrow column as float64 (NaN where empty) and where a value was not a finite number."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if column.null_count == 0 and (
        pa.types.is_floating(column.type) or pa.types.is_integer(column.type)
    ):
        # Numbers without empty values: nothing to mark as missing but what is not finite.
        values = np.asarray(to_numpy(column), dtype=np.float64)
        finite = np.isfinite(values)
        if finite.all():
            return values, np.zeros(len(values), dtype=bool)
        return np.where(finite, values, np.nan), ~finite
    if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
        try:
            numbers = pc.cast(column, pa.float64())
        except pa.ArrowInvalid:
            import pandas as pd

            numbers = pa.array(
                pd.to_numeric(column.to_pandas(), errors="coerce"), type=pa.float64()
            )
    elif pa.types.is_integer(column.type) or pa.types.is_floating(column.type):
        numbers = pc.cast(column, pa.float64())
    elif pa.types.is_null(column.type):
        numbers = pa.nulls(len(column), pa.float64())
    else:
        raise TypeError(f"column of type {column.type}: expected numbers or text")
    values = np.asarray(to_numpy(numbers, np.nan), dtype=np.float64)
    written = to_numpy(pc.is_valid(column))
    bad = written & ~np.isfinite(values)
    values = np.where(np.isfinite(values), values, np.nan)
    return values, bad

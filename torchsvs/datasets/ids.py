"""Track ids as codes: :func:`track_codes` numbers a block's ids in order of first appearance,
reading each distinct id's text once (a Parquet file's text ids come dictionary-encoded)."""

from __future__ import annotations

from typing import Any

import numpy as np

from torchsvs.datasets.arrow_numpy import from_numpy, to_numpy


def track_codes(ids: Any) -> tuple[np.ndarray, list[str]]:
    """A track id column as codes (``[R]`` int64 numbering the ids in order of first
    appearance, -1 where the id is empty or blank) and the id text of each code.

    Each distinct id's text is looked at once (dictionary-encoded, as a Parquet file's text
    columns may be read): the rows cost only their dictionary indices."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if isinstance(ids, pa.Array):
        ids = pa.chunked_array([ids])
    if not pa.types.is_dictionary(ids.type):
        if not (pa.types.is_string(ids.type) or pa.types.is_large_string(ids.type)):
            ids = pc.cast(ids, pa.string())
        ids = pc.dictionary_encode(ids)
    known: dict[str, int] = {}
    parts = []
    for chunk in ids.chunks:
        size = len(chunk.dictionary)
        index = to_numpy(chunk.indices, size)
        # The entries in use, in order of first appearance (found among the runs of equal
        # indices: a sorted file has one per track).
        first = np.flatnonzero(index[1:] != index[:-1]) + 1
        runs = index[np.concatenate([[0], first])] if len(index) else index
        used, at = np.unique(runs, return_index=True)
        used = used[np.argsort(at, kind="stable")]
        used = used[used < size]
        entries = chunk.dictionary.take(from_numpy(used, pa.int64()))
        if not (pa.types.is_string(entries.type) or pa.types.is_large_string(entries.type)):
            entries = pc.cast(entries, pa.string())
        # (empty, or of white space alone; a length, not a comparison with "": a text made
        # from Python's would load pyarrow's pandas support, arrow_numpy)
        blank = to_numpy(pc.utf8_length(pc.utf8_trim_whitespace(entries)), 0) == 0
        lookup = np.full(size + 1, -1, dtype=np.int64)
        texts = entries.filter(from_numpy(~blank)).to_pylist()
        lookup[used[~blank]] = [known.setdefault(str(text), len(known)) for text in texts]
        parts.append(lookup[index])
    codes = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
    return codes, list(known)

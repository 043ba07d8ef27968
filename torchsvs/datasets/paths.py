"""Whether a path may be read or written, before anything runs: :func:`check_input` (an
existing ``.csv``/``.parquet`` file) and :func:`check_output` (never an input, an existing file
only with ``force``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from torchsvs.datasets.rows import file_format


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

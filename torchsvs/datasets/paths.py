"""Whether a path may be read or written, before anything runs: :func:`check_input` (an
existing ``.csv``/``.parquet`` file, or a directory of Parquet files: :func:`dataset_files`)
and :func:`check_output` (never an input, an existing file only with ``force``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from torchsvs.datasets.rows import file_format


def check_input(path: str | Path, name: str = "path") -> None:
    """Raises ``ValueError``/``FileNotFoundError`` (starting with ``name``) unless ``path`` is
    an existing ``.csv``/``.parquet`` file or a directory holding Parquet files (a dataset:
    :func:`dataset_files`)."""
    source = Path(path)
    if source.is_dir():
        dataset_files(source, name)
        return
    try:
        file_format(source)
    except ValueError as err:
        raise ValueError(
            f"{name}: expected a .csv or .parquet file (.csv, .csv.gz, .csv.bz2, .tsv, .txt, "
            f".parquet, .pq) or a directory of Parquet files, got {str(path)!r}"
        ) from err
    if not source.exists():
        raise FileNotFoundError(f"{name}: {str(path)!r}: no such file")


def dataset_files(path: str | Path, name: str = "path") -> list[tuple[Path, dict[str, str]]]:
    """The Parquet files (``.parquet``, ``.pq``) of a dataset directory, with the hive partition
    values of each (``part=3/...``: ``{"part": "3"}``), in order of their paths below it.

    Files and directories whose names start with ``.`` or ``_`` are skipped, as Spark and
    ``pyarrow.dataset`` skip them (``_SUCCESS``, ``_common_metadata``, temporary files).
    Raises ``ValueError`` (starting with ``name``) where there is no Parquet file, or where
    the directory also holds CSV files (a dataset is read as Parquet only)."""
    root = Path(path)
    found: list[tuple[Path, dict[str, str]]] = []
    other: list[str] = []
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if not d.startswith((".", "_")))
        for file in sorted(files):
            if file.startswith((".", "_")):
                continue
            relative = Path(folder, file).relative_to(root)
            try:
                kind = file_format(file)
            except ValueError:
                continue
            if kind != "parquet":
                other.append(str(relative))
                continue
            parts = [p.split("=", 1) for p in relative.parts[:-1] if "=" in p]
            found.append((Path(folder, file), {key: value for key, value in parts}))
    if other:
        raise ValueError(
            f"{name}: {str(path)!r} holds CSV files ({other[:3]}); a directory is read as a "
            "Parquet dataset: convert them, or track each CSV file on its own"
        )
    if not found:
        raise ValueError(
            f"{name}: the directory {str(path)!r} holds no Parquet file (.parquet, .pq); "
            "expected a file or a directory of Parquet files"
        )
    found.sort(key=lambda item: item[0].relative_to(root).parts)
    return found


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
    with ``force``, and only in a directory that exists and can be written.

    Where an input is a directory (a Parquet dataset), ``path`` names the output directory:
    neither inside an input directory nor holding one, and an existing one only with
    ``force`` (it is then replaced as a whole)."""
    target = Path(path)
    for source in inputs:
        if source is not None and same_file(target, source):
            raise ValueError(
                f"{name}: {str(path)!r} is the input file {str(source)!r}; the output never "
                "replaces an input: name another file"
            )
    folders = [Path(s) for s in inputs if s is not None and Path(s).is_dir()]
    if folders:
        where = target.resolve()
        for folder in folders:
            inside = folder.resolve()
            if inside in where.parents or where in inside.parents:
                raise ValueError(
                    f"{name}: {str(path)!r} and the input directory {str(folder)!r} lie one "
                    "inside the other; name an output directory apart from the input"
                )
        if target.exists() and not target.is_dir():
            raise ValueError(
                f"{name}: {str(path)!r} is a file; a directory input writes a directory of "
                "Parquet files: name a directory"
            )
        if target.exists() and not force:
            raise ValueError(
                f"{name}: {str(path)!r} exists; pass --force to replace it (torchsvs track), or "
                "name another directory"
            )
    else:
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

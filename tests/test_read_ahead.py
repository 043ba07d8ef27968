"""A track file read in a thread of its own while the caller works (:class:`~torchsvs.datasets.
reading.ReadAhead`), and the modules that read it without torch, so that ``torchsvs track``
reads its input while torch is imported and answers ``--help`` or a bad path at once."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pyarrow.parquet as pq
import pytest

import torchsvs
import torchsvs.datasets
import torchsvs.training
from tests.test_datasets_io import _table
from torchsvs.datasets import Columns, describe_input, track_blocks
from torchsvs.datasets import reading as reading_module
from torchsvs.datasets.reading import ReadAhead

COLUMNS = Columns(time_unit="s")


@pytest.fixture
def dataset(tmp_path):
    source = tmp_path / "in"
    source.mkdir()
    pq.write_table(_table(5), source / "a.parquet", row_group_size=40)
    pq.write_table(_table(4, first=5), source / "b.parquet", row_group_size=40)
    return source


def _same_blocks(got, expected) -> None:
    assert len(got) == len(expected) > 2
    for a, b in zip(got, expected, strict=True):
        assert a.path == b.path and a.table.equals(b.table)
        assert a.steps.ids == b.steps.ids
        np.testing.assert_array_equal(a.steps.position, b.steps.position)
        np.testing.assert_array_equal(a.steps.row_step, b.steps.row_step)


def test_read_ahead_gives_the_blocks_of_track_blocks(dataset):
    expected = list(track_blocks(dataset, COLUMNS, block_rows=64))
    with ReadAhead(dataset, COLUMNS, block_rows=64) as reader:
        got = list(reader)
    _same_blocks(got, expected)
    assert reader.reading > 0.0 and reader.waiting >= 0.0
    with pytest.raises(ValueError, match="describe: .*describe=True"):  # (not a wait forever)
        reader.description()


def test_read_ahead_describes_first_and_reads_with_the_resolved_columns(dataset):
    """The columns left open (the time unit) are settled by the description, as the command
    settles them before reading."""
    open_columns = Columns()
    expected = describe_input(dataset, open_columns, block_rows=64, name="input")
    with ReadAhead(dataset, open_columns, block_rows=64, describe=True, name="input") as reader:
        described = reader.description()
        got = list(reader)
    assert described.columns == expected.columns and described.lines == expected.lines
    _same_blocks(got, list(track_blocks(dataset, expected.columns, block_rows=64)))


def test_read_ahead_reads_no_more_than_asked_ahead(dataset, monkeypatch):
    """Memory stays bounded: with room for one block, the thread reads the next only once the
    caller has taken the one before (one read, one waiting at most)."""
    made = []
    blocks = track_blocks

    def counted(*args, **kwargs):
        for block in blocks(*args, **kwargs):
            made.append(block)
            yield block

    monkeypatch.setattr(reading_module, "track_blocks", counted)
    taken = 0
    with ReadAhead(dataset, COLUMNS, block_rows=64) as reader:
        for _ in reader:
            taken += 1
            time.sleep(0.05)  # (the thread would read everything meanwhile, unbounded)
            assert len(made) <= taken + 1
    assert taken == len(made) > 2


def test_read_ahead_hands_its_errors_to_the_caller(tmp_path, dataset, monkeypatch):
    """A file that cannot be described raises where the description is asked for; an error
    midway comes after the blocks read before it."""
    missing = tmp_path / "nothing.parquet"
    reader = ReadAhead(missing, COLUMNS, describe=True, name="input")
    with pytest.raises(FileNotFoundError, match="input: .*nothing.parquet"):
        reader.description()
    with pytest.raises(FileNotFoundError, match="input: .*nothing.parquet"):
        list(reader)

    blocks = track_blocks

    def failing(*args, **kwargs):
        for k, block in enumerate(blocks(*args, **kwargs)):
            if k == 2:
                raise OSError("disk gone")
            yield block

    monkeypatch.setattr(reading_module, "track_blocks", failing)
    got = []
    with pytest.raises(OSError, match="disk gone"), ReadAhead(dataset, COLUMNS, block_rows=64) as r:
        got.extend(r)
    assert len(got) == 2


def test_closing_stops_the_thread(dataset):
    reader = ReadAhead(dataset, COLUMNS, block_rows=64)
    next(iter(reader))
    reader.close()
    reader._thread.join(timeout=10)
    assert not reader._thread.is_alive()
    assert list(reader) == []  # (the blocks read, and one in reading as it closed, dropped)
    assert not any(t.name == "read-ahead" and t is reader._thread for t in threading.enumerate())


def test_reading_and_the_command_line_import_no_torch():
    """What runs before torch is imported: the command's parser, its path checks and the
    reading modules (the estimators come with torch)."""
    code = (
        "import sys\n"
        "import torchsvs, torchsvs.datasets\n"
        "import torchsvs.datasets.reading, torchsvs.datasets.describe, torchsvs.track_command\n"
        "from torchsvs.track_options import track_parser\n"
        "track_parser()\n"
        "from torchsvs.cli import main\n"
        "try:\n"
        "    main(['track', 'no-such-file.csv', '-o', 'out.csv'])\n"
        "except SystemExit as stop:\n"
        "    assert 'no-such-file' in str(stop.code), stop.code\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
        "print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


@pytest.mark.parametrize("package", [torchsvs, torchsvs.datasets, torchsvs.training])
def test_every_public_name_of_a_lazy_package_resolves(package):
    """Each name of ``__all__`` resolves, and the three lists of a lazy package agree: its
    homes, its ``__all__`` and the names it imports for the type checker (``TYPE_CHECKING``),
    so a name added to one and not the others fails here."""
    import ast
    import inspect

    checked: set[str] = set()
    for node in ast.walk(ast.parse(inspect.getsource(package))):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for statement in ast.walk(node):
                if isinstance(statement, ast.ImportFrom):
                    checked |= {alias.asname or alias.name for alias in statement.names}
    assert checked == set(package._HOMES) == set(package.__all__)
    for name in package.__all__:
        assert getattr(package, name) is not None, name
    assert set(package.__all__) <= set(dir(package))
    with pytest.raises(AttributeError, match="no_such_name"):
        package.no_such_name  # noqa: B018
    assert torchsvs.SVSF is torchsvs.filters.SVSF
    assert torchsvs.datasets.read_tracks is torchsvs.datasets.tracks.read_tracks


def test_track_file_refuses_the_reading_of_another_file(dataset, tmp_path):
    """A run handed blocks already being read (``torchsvs track``) checks they are its
    source's: estimates of one file written as another's rows would be silently wrong."""
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    other = tmp_path / "other.parquet"
    other.write_bytes(next(dataset.iterdir()).read_bytes())
    with (
        ReadAhead(dataset) as reader,
        pytest.raises(ValueError, match="blocks: expected the reading of .*other.parquet"),
    ):
        track_file(other, tmp_path / "out.csv", Settings("ks"), blocks=reader)

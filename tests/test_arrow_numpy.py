"""Numbers between Arrow and numpy through their buffers (:mod:`torchsvs.datasets.arrow_numpy`),
held to pyarrow's own conversions, and a whole ``torchsvs track`` run of a Parquet dataset
without pandas (whose import, beside torch's, held up the command's start)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

from tests.test_datasets_io import _table
from torchsvs.datasets.arrow_numpy import (
    from_numpy,
    numpy_dtype,
    repeated_text,
    texts,
    to_numpy,
)

KINDS = [pa.float64(), pa.float32(), pa.int8(), pa.int32(), pa.int64(), pa.uint16(), pa.bool_()]


def _values(kind, n, seed=0):
    rng = np.random.default_rng(seed)
    if kind == pa.bool_():
        return rng.random(n) < 0.5
    return (rng.normal(size=n) * 50).astype(numpy_dtype(kind))


@pytest.mark.parametrize("kind", KINDS, ids=str)
@pytest.mark.parametrize("start", [0, 3, 8, 13])
def test_to_numpy_reads_each_chunk_and_offset_as_pyarrow_does(kind, start):
    # chunks of odd lengths, sliced at bit and byte offsets: the bitmaps' edges
    data = [_values(kind, n, seed=n) for n in (37, 1, 0, 20)]
    column = pa.chunked_array([pa.array(d, type=kind) for d in data], type=kind).slice(start)
    got = to_numpy(column)
    assert got.dtype == numpy_dtype(kind)
    np.testing.assert_array_equal(got, column.to_numpy())


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_to_numpy_fills_the_empty_values(kind):
    values = _values(kind, 29)
    empty = np.zeros(29, dtype=bool)
    empty[[0, 7, 8, 9, 28]] = True
    array = pa.array(values, type=kind, mask=empty).slice(5)
    fill = False if kind == pa.bool_() else 99
    expected = np.where(empty[5:], fill, values[5:])
    np.testing.assert_array_equal(to_numpy(array, fill), expected)
    with pytest.raises(ValueError, match="empty values"):
        to_numpy(array)
    floats = pa.array(np.arange(6.0), mask=np.array([0, 1, 0, 0, 1, 0], dtype=bool))
    np.testing.assert_array_equal(to_numpy(floats, np.nan), floats.to_numpy(zero_copy_only=False))


def test_to_numpy_refuses_other_types_and_reads_nothing_as_empty():
    with pytest.raises(TypeError, match="expected numbers or booleans, got Arrow type string"):
        to_numpy(pa.array(["a"]))
    empty = to_numpy(pa.chunked_array([], type=pa.float32()))
    assert empty.shape == (0,) and empty.dtype == np.float32


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_from_numpy_gives_pyarrows_array(kind):
    values = _values(kind, 45)
    if kind == pa.float64():
        values[3] = np.nan  # a number, as pyarrow.array keeps it
    got = from_numpy(values, kind)
    assert got.equals(pa.array(values, type=kind)) or (
        kind == pa.float64() and np.array_equal(got.to_numpy(), values, equal_nan=True)
    )
    assert got.null_count == 0
    assert from_numpy(values).type == kind
    with pytest.raises(ValueError, match="1-D"):
        from_numpy(values.reshape(5, 9))


def test_texts_are_pyarrows_string_array():
    for values in (["NA", "", "null", "é-2"], [], [""]):
        got = texts(values)
        assert got.equals(pa.array(values, pa.string())), values
        got.validate(full=True)


def test_repeated_text_is_pyarrows_column_of_one_value():
    for value, count in (("t7", 5), ("", 3), ("é/ü", 2), ("x", 0)):
        got = repeated_text(value, count)
        assert got.equals(pa.array([value] * count, type=pa.string())), (value, count)


def test_a_track_run_of_a_parquet_dataset_imports_no_pandas(tmp_path):
    source = tmp_path / "in"
    source.mkdir()
    table = _table(5)
    ids = table.column("track_id").to_pylist()
    ids[2] = "  "  # a blank id: set aside
    table = table.set_column(0, "track_id", pa.array(ids))
    pq.write_table(table, source / "a.parquet", row_group_size=40)
    pq.write_table(_table(4, first=5), source / "b.parquet", row_group_size=40)
    # a track partitioned by its id, as a Spark writer leaves it: the id is the folder's
    one = _table(1, first=9)
    (source / "track_id=t9").mkdir()
    pq.write_table(one.drop_columns(["track_id"]), source / "track_id=t9" / "c.parquet")
    csv = tmp_path / "in.csv"  # (and a CSV file through Arrow's reader and writer)
    pacsv.write_csv(_table(3, first=20), csv)
    code = (
        "import sys\n"
        "from torchsvs.cli import main\n"
        f"main(['track', {str(source)!r}, '-o', {str(tmp_path / 'out')!r}, '--estimator', 'ks',"
        " '--meas-std', '50', '--quiet', '--time-unit', 's'])\n"
        f"main(['track', {str(csv)!r}, '-o', {str(tmp_path / 'out.csv')!r}, '--estimator', 'ks',"
        " '--meas-std', '50', '--quiet', '--time-unit', 's'])\n"
        "assert 'pandas' not in sys.modules, 'pandas imported'\n"
        "print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
    out = pq.read_table(tmp_path / "out" / "a.parquet")
    assert len(out) == len(table)
    partitioned = pq.read_table(tmp_path / "out" / "track_id=t9" / "c.parquet")
    assert set(partitioned.column("track_id").to_pylist()) == {"t9"} and len(partitioned) == 30
    assert np.isfinite(to_numpy(partitioned.column("x"), np.nan)).all()
    assert len(pacsv.read_csv(tmp_path / "out.csv")) == 90


@pytest.mark.parametrize("kind", KINDS, ids=str)
def test_from_numpy_leaves_empty_where_not_valid_as_pyarrows_mask(kind):
    values = _values(kind, 37)
    valid = np.ones(37, dtype=bool)
    valid[[0, 8, 9, 36]] = False
    got = from_numpy(values, kind, valid=valid)
    assert got.equals(pa.array(values, type=kind, mask=~valid)) and got.null_count == 4
    assert from_numpy(values, kind, valid=np.ones(37, dtype=bool)).null_count == 0

"""Reading and writing at the speed of Arrow, and Parquet datasets in and out.

The fast paths (:func:`~torchsvs.datasets.rows.track_codes` on dictionary-encoded ids,
:func:`~torchsvs.datasets.steps.group_rows` on a sorted block, :func:`~torchsvs.datasets.
writing.nan_as_null`) are checked against the plain computation they replace; a directory of
Parquet files (``torchsvs track DIR -o OUTDIR``) against the same rows as one file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from torchsvs.cli import main
from torchsvs.datasets.ids import track_codes
from torchsvs.datasets.reading import track_blocks
from torchsvs.datasets.rows import Columns, ParsedRows
from torchsvs.datasets.steps import group_rows
from torchsvs.datasets.writing import nan_as_null

# --- track ids: each distinct id read once ---


def _codes_oracle(values: list[str | None]) -> tuple[list[int], list[str]]:
    """Ids numbered in order of first appearance, blank (whitespace only) or missing: -1."""
    known: dict[str, int] = {}
    codes = []
    for v in values:
        if v is None or v.strip() == "":
            codes.append(-1)
        else:
            codes.append(known.setdefault(v, len(known)))
    return codes, list(known)


@pytest.mark.parametrize("seed", range(5))
def test_track_codes_match_first_appearance_in_every_encoding(seed):
    """Plain text, dictionary-encoded, and chunks with their own dictionaries (a Parquet file's
    row groups) give the same codes: ids in order of first appearance, blanks and nulls -1."""
    gen = np.random.default_rng(seed)
    pool = ["a", "b", " ", "", None, "c", " a", "d\t", "e"]
    values = [pool[i] for i in gen.integers(0, len(pool), 200)]
    cuts = sorted(gen.integers(0, 201, 3).tolist())
    chunks = [values[a:b] for a, b in zip([0, *cuts], [*cuts, 200], strict=True)]
    expected = _codes_oracle(values)
    plain = pa.chunked_array([pa.array(c, pa.string()) for c in chunks], type=pa.string())
    per_chunk = pa.chunked_array(
        [pc.dictionary_encode(pa.array(c, pa.string())) for c in chunks],
        type=pa.dictionary(pa.int32(), pa.string()),
    )
    for column in (plain, pc.dictionary_encode(plain), per_chunk):
        codes, ids = track_codes(column)
        assert codes.tolist() == expected[0] and ids == expected[1]
    numbers = pa.chunked_array([pa.array([7, 7, None, 3, 7])])
    assert track_codes(numbers)[0].tolist() == [0, 0, -1, 1, 0]
    assert track_codes(numbers)[1] == ["7", "3"]


# --- grouping a sorted block without sorting ---


def _rows(code, time, position, extra=None) -> ParsedRows:
    code = np.asarray(code, dtype=np.int64)
    position = np.asarray(position, dtype=np.float64)
    ids = [f"t{k}" for k in range(int(code.max(initial=-1)) + 1)]
    return ParsedRows(
        code,
        ids,
        np.asarray(time, dtype=np.float64),
        position,
        extra or {},
        np.zeros(len(code), dtype=bool),
    )


def test_sorted_block_steps_are_its_rows():
    """Rows already by track and time: each row is its own step, with its values (-0.0 read
    as 0.0 and a non-finite extra as missing, as the averaging path gives them)."""
    position = [[1.0, -0.0], [2.0, np.nan], [3.0, 4.0], [5.0, 6.0]]
    speed = np.array([1.0, np.inf, 2.0, 3.0])
    steps = group_rows(_rows([0, 0, 1, 1], [0, 1, 0, 5], position, {"speed": speed}))
    assert steps.ids == ["t0", "t1"]
    assert steps.start.tolist() == [0, 2] and steps.length.tolist() == [2, 2]
    assert steps.row_step.tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(steps.position, np.array(position))
    assert not np.signbit(steps.position[0, 1])
    np.testing.assert_array_equal(steps.extra["speed"], [1.0, np.nan, 2.0, 3.0])
    assert steps.report.notes.get("out_of_order", 0) == 0


def test_unsorted_and_sorted_blocks_give_the_same_steps():
    """The same rows, one track's two rows swapped: the sorting path counts the row out of
    order and ends at the steps the sorted block gives at once."""
    position = [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0], [4.5, 4.5]]
    sorted_steps = group_rows(_rows([0, 0, 1, 1, 1], [0, 1, 0, 1, 1], position))
    swapped = group_rows(
        _rows([0, 0, 1, 1, 1], [1, 0, 0, 1, 1], [position[1], position[0], *position[2:]])
    )
    assert swapped.report.notes["out_of_order"] == 1
    for steps in (sorted_steps, swapped):
        assert steps.report.notes["duplicate_time"] == 1
        np.testing.assert_array_equal(steps.position, [[1, 1], [2, 2], [3, 3], [4.25, 4.25]])
        np.testing.assert_array_equal(steps.time, [0, 1, 0, 1])
    assert swapped.row_step.tolist() == [1, 0, 2, 3, 3]


# --- writing: NaN as empty ---


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_nan_as_null_is_pyarrows_from_pandas(dtype):
    gen = np.random.default_rng(1)
    for n in (0, 1, 7, 8, 9, 1001):
        for share in (0.0, 0.3, 1.0):
            values = gen.normal(size=n).astype(dtype)
            values[gen.random(n) < share] = np.nan
            ours, theirs = nan_as_null(values), pa.array(values, from_pandas=True)
            ours.validate(full=True)
            assert ours.type == theirs.type and ours.null_count == theirs.null_count
            assert ours.equals(theirs)


def test_whole_or_streamed_is_decided_by_rows(tmp_path, monkeypatch):
    """A Parquet file by the rows its metadata counts (not its bytes: Parquet packs 10 M rows
    in 120 MB), a CSV file by its size, a dataset by its largest file."""
    from torchsvs.datasets import reading

    monkeypatch.setattr(reading, "WHOLE_ROWS", 60)
    pq.write_table(_table(2), tmp_path / "two.parquet")  # 60 rows
    pq.write_table(_table(3), tmp_path / "three.parquet")
    assert reading.reads_whole(tmp_path / "two.parquet")
    assert not reading.reads_whole(tmp_path / "three.parquet")
    assert not reading.reads_whole(tmp_path)
    (tmp_path / "three.parquet").unlink()
    assert reading.reads_whole(tmp_path)
    (tmp_path / "a.csv").write_text("x" * 40 * 61)
    assert not reading.reads_whole(tmp_path / "a.csv")


# --- Parquet datasets: a directory in, a directory out ---


def _table(tracks: int, steps: int = 30, first: int = 0, seed: int = 0) -> pa.Table:
    """Straight tracks in metres (ids ``t<first>...``), rows of each track together."""
    gen = np.random.default_rng(seed)
    t = np.arange(steps, dtype=float)
    start = gen.normal(0, 1e3, (tracks, 1, 2))
    v = gen.normal(0, 50, (tracks, 1, 2))
    z = start + v * t[None, :, None] + gen.normal(0, 30, (tracks, steps, 2))
    ids = np.repeat([f"t{k}" for k in range(first, first + tracks)], steps)
    return pa.table(
        {
            "track_id": pa.array(ids.tolist(), pa.string()),
            "time": np.tile(t, tracks),
            "x": z[..., 0].ravel(),
            "y": z[..., 1].ravel(),
        }
    )


def _track(*args: object) -> None:
    main(["track", *map(str, args), "--estimator", "ks", "--meas-std", "30", "--q", "1"])


def _dataset(root: Path) -> list[pa.Table]:
    """Three files (two hive partitions, an empty one) and files a dataset reader skips."""
    parts = [_table(4, first=0), _table(3, first=4, seed=1), _table(0)]
    names = ["part=0/a.parquet", "part=1/b.parquet", "part=1/c.parquet"]
    for table, name in zip(parts, names, strict=True):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, root / name)
    (root / "_SUCCESS").write_text("")
    (root / "_temporary").mkdir()
    pq.write_table(_table(1, first=99), root / "_temporary" / "x.parquet")
    return parts


def test_directory_in_directory_out_matches_one_file(tmp_path, capsys):
    """A dataset's output: one file per input file under its relative name, rows as read, and
    the same rows as the input written as one file gives (settings given: the estimates do not
    depend on which tracks share a block)."""
    source = tmp_path / "in"
    parts = _dataset(source)
    pq.write_table(pa.concat_tables(parts), tmp_path / "all.parquet")
    _track(source, "-o", tmp_path / "out")
    # a dataset's settings come from its first files (here all), and the run says so
    said = "settings: read off all 2 of the dataset's files with rows (7 tracks)"
    assert said in capsys.readouterr().err
    _track(tmp_path / "all.parquet", "-o", tmp_path / "all_out.parquet")
    assert "dataset's" not in capsys.readouterr().err
    written = sorted(str(p.relative_to(tmp_path / "out")) for p in (tmp_path / "out").rglob("*.*"))
    assert written == ["part=0/a.parquet", "part=1/b.parquet", "part=1/c.parquet"]
    outputs = [pq.read_table(tmp_path / "out" / name) for name in written]
    for table, out in zip(parts, outputs, strict=True):
        assert len(out) == len(table)
        assert out.column("track_id").equals(table.column("track_id").cast(pa.string()))
    whole = pq.read_table(tmp_path / "all_out.parquet")
    assert pa.types.is_string(whole.schema.field("track_id").type)
    assert pa.concat_tables(outputs).equals(whole)
    assert (tmp_path / "out.summary.json").exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_a_dataset_of_small_files_is_planned_on_as_many_tracks_as_one_file(tmp_path, capsys):
    """Settings read off the data (noise, q): a dataset's first files are taken until the
    sample is full, so small files give the estimates of the same rows in one file (planned on
    its first file alone, two tracks of twelve, the noise read differed); a larger dataset
    stops at the file that fills the sample, and says which."""
    source = tmp_path / "in"
    source.mkdir()
    parts = [_table(2, first=2 * k, seed=k) for k in range(6)]
    for k, table in enumerate(parts):
        pq.write_table(table, source / f"f{k}.parquet")
    pq.write_table(pa.concat_tables(parts), tmp_path / "all.parquet")
    main(["track", str(source), "-o", str(tmp_path / "out"), "--estimator", "ks"])
    err = capsys.readouterr().err
    main(
        [
            "track",
            str(tmp_path / "all.parquet"),
            "-o",
            str(tmp_path / "all.out.parquet"),
            "--estimator",
            "ks",
        ]
    )
    outputs = [pq.read_table(tmp_path / "out" / f"f{k}.parquet") for k in range(6)]
    assert pa.concat_tables(outputs).equals(pq.read_table(tmp_path / "all.out.parquet"))
    assert "settings: read off all 6 of the dataset's files with rows (12 tracks)" in err
    capsys.readouterr()
    main(
        [
            "track",
            str(source),
            "-o",
            str(tmp_path / "out5"),
            "--estimator",
            "ks",
            "--fit-tracks",
            "5",
        ]
    )
    said = "settings: read off the dataset's first 3 files, f0.parquet to f2.parquet (6 tracks)"
    assert said in capsys.readouterr().err


def test_a_partition_value_gives_the_id(tmp_path, capsys):
    """A dataset partitioned by track id: the files lack the id column, the path gives it."""
    source = tmp_path / "in"
    table = _table(3)
    for k in range(3):
        rows = table.filter(pc.equal(table.column("track_id"), f"t{k}")).drop_columns(["track_id"])
        (source / f"track_id=t{k}").mkdir(parents=True)
        pq.write_table(rows, source / f"track_id=t{k}" / "part-0.parquet")
    _track(source, "-o", tmp_path / "out")
    ids = [
        pq.read_table(p).column("track_id") for p in sorted((tmp_path / "out").rglob("*.parquet"))
    ]
    assert [c.unique().to_pylist() for c in ids] == [["t0"], ["t1"], ["t2"]]


def test_a_track_in_two_files_stops_the_run_and_leaves_the_output(tmp_path, capsys):
    """A track whose rows are in two files: refused, naming it and both files; an earlier
    output directory (replaced only once a run completes) is left as it was."""
    source = tmp_path / "in"
    source.mkdir()
    pq.write_table(_table(3), source / "a.parquet")
    pq.write_table(_table(2, first=2, seed=1), source / "b.parquet")  # t2 again
    target = tmp_path / "out"
    target.mkdir()
    (target / "earlier.txt").write_text("kept")
    with pytest.raises(SystemExit, match=r"track 't2': its rows are in two files.*a\.parquet.*b\."):
        _track(source, "-o", target, "--force")
    assert [p.name for p in target.iterdir()] == ["earlier.txt"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    with pytest.raises(SystemExit, match=r"output: .*out' exists; pass --force"):
        _track(source, "-o", target)


def test_dataset_paths_are_checked_before_anything_runs(tmp_path, capsys):
    source = tmp_path / "in"
    source.mkdir()
    with pytest.raises(SystemExit, match=r"input: the directory .* holds no Parquet file"):
        _track(source, "-o", tmp_path / "out")
    pq.write_table(_table(2), source / "a.parquet")
    pq.write_table(_table(2, first=2).drop_columns(["y"]), source / "b.parquet")
    with pytest.raises(SystemExit, match=r"output: .* lie one inside the other"):
        _track(source, "-o", source / "out")
    (tmp_path / "file.parquet").write_text("")
    with pytest.raises(
        SystemExit, match=r"output: .*file\.parquet' is a file; .* name a directory"
    ):
        _track(source, "-o", tmp_path / "file.parquet", "--force")
    with pytest.raises(SystemExit, match=r"path: .*b\.parquet' has no column \['y'\]"):
        _track(source, "-o", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_dataset_streams_file_by_file(tmp_path):
    """Blocks never mix files, and each knows its file (the output's file is chosen by it)."""
    source = tmp_path / "in"
    source.mkdir()
    pq.write_table(_table(5), source / "a.parquet", row_group_size=40)
    pq.write_table(_table(4, first=5), source / "b.parquet", row_group_size=40)
    blocks = list(track_blocks(source, Columns(time_unit="s"), block_rows=64))
    assert len(blocks) > 2
    for block in blocks:
        assert block.path is not None
        ids = set(block.table.column("track_id").to_pylist())
        assert ids <= (
            {f"t{k}" for k in range(5)}
            if block.path.name == "a.parquet"
            else {f"t{k}" for k in range(5, 9)}
        )
    assert sum(len(b.table) for b in blocks) == 9 * 30
    assert os.path.basename(str(blocks[-1].path)) == "b.parquet"


def test_processes_refuse_a_dataset_naming_the_option(tmp_path, capsys):
    """--processes reads one file whole on rank 0: a directory is refused before any process
    starts, naming the option and where a dataset runs."""
    source = tmp_path / "in"
    source.mkdir()
    pq.write_table(_table(3), source / "a.parquet")
    with pytest.raises(SystemExit) as stop:
        _track(source, "-o", tmp_path / "out", "--processes", "2")
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "argument --processes" in err and "directory" in err and "Spark or Dask" in err
    assert not (tmp_path / "out").exists()


def test_a_write_that_fails_beside_the_estimating_stops_the_run_and_leaves_the_output(
    tmp_path, monkeypatch
):
    """Writing runs in a thread of its own beside the estimating of the next file: a write's
    error (a disk full at the second file) still stops the run with that error, and an
    earlier output directory is left as it was, with no temporary one beside it."""
    from torchsvs.datasets import EstimateWriter

    source = tmp_path / "in"
    source.mkdir()
    for k in range(3):
        pq.write_table(_table(2, first=2 * k, seed=k), source / f"part-{k}.parquet")
    target = tmp_path / "out"
    target.mkdir()
    (target / "earlier.txt").write_text("kept")
    calls = []
    write = EstimateWriter.write

    def failing(self, table, path=None):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return write(self, table, path)

    monkeypatch.setattr(EstimateWriter, "write", failing)
    with pytest.raises(OSError, match="No space left on device"):
        _track(source, "-o", target, "--force")
    assert len(calls) == 2  # nothing written after the failure
    assert [p.name for p in target.iterdir()] == ["earlier.txt"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_the_median_interval_is_numpys_nanmedian():
    """The first step's interval (a track's median one): one sort of the padded rows, the
    same numbers as np.nanmedian (the middle two's mean for an even count), 1 without any."""
    import warnings

    from torchsvs.datasets.steps import median_interval

    gen = np.random.default_rng(1)
    for _ in range(300):
        dt = gen.exponential(3.0, (int(gen.integers(1, 20)), int(gen.integers(1, 12))))
        dt[gen.random(dt.shape) < gen.random()] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (all-NaN rows)
            expected = np.where(np.isfinite(dt).any(axis=1), np.nanmedian(dt, axis=1), 1.0)
        assert np.array_equal(median_interval(dt), expected)
    assert np.array_equal(median_interval(np.zeros((3, 0))), np.ones(3))  # one step each

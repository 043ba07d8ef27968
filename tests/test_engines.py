"""Spark (local mode) and Dask (a distributed LocalCluster) give the estimates of one process:
:func:`~torchsvs.track_table.track_table` on the whole table, value for value, with each
track's rows wherever the engine's input put them (torchsvs.engines)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pyarrow.csv as pcsv
import pytest

from tests.test_track_cli import _simulated_csv
from torchsvs.datasets import Columns
from torchsvs.recipes import Settings
from torchsvs.track_plan import TrackPlan, plan_tracks
from torchsvs.track_table import track_table

COLUMNS = Columns("id", "t")
pytestmark = [
    # PySpark 4.3 on pandas 3: it warns at each pandas conversion, and its Arrow conversion
    # passes pandas' deprecated ``copy`` keyword (third party).
    pytest.mark.filterwarnings("ignore:PySpark does not yet fully support pandas:FutureWarning"),
    pytest.mark.filterwarnings("ignore:The copy keyword is deprecated"),
    # Dask 2026.8's Parquet reader on pandas 3.1 (third party).
    pytest.mark.filterwarnings("ignore:The inplace keyword in DataFrame.reset_index"),
]
#: The exact comparisons: the estimators whose estimates do not depend on a table's other
#: tracks (tests/test_track_table.py), at both output precisions.
CASES = [("ks", "float32"), ("ks", "float64"), ("svss", "float32"), ("svss", "float64")]


@pytest.fixture(scope="module")
def rows(tmp_path_factory) -> pd.DataFrame:
    """30 tracks of 5-60 rows: irregular times, missing values, repeated times, shuffled."""
    path = tmp_path_factory.mktemp("engines") / "in.csv"
    steps = np.random.default_rng(3).integers(5, 60, 30).tolist()
    _simulated_csv(path, tracks=30, steps=steps)
    return pcsv.read_csv(path).to_pandas()


@pytest.fixture(scope="module")
def plans(rows):
    return {
        case: plan_tracks(rows, Settings(estimator=case[0]), columns=COLUMNS, precision=case[1])
        for case in CASES
    }


def _sorted(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows in one order whatever the engine's (every column: repeated times tie on id, t)."""
    return frame.sort_values(list(frame.columns), kind="stable").reset_index(drop=True)


def _same(out: pd.DataFrame, whole: pd.DataFrame) -> None:
    """The same rows (every one once, ids and times unchanged) with the same values, exactly."""
    assert list(out.columns) == list(whole.columns)
    a, b = _sorted(out), _sorted(whole)
    assert len(a) == len(b)
    for name in a.columns:
        left, right = a[name].to_numpy(), b[name].to_numpy()
        if left.dtype.kind == "f":
            assert left.dtype == right.dtype, name
            np.testing.assert_array_equal(left, right, err_msg=name)
        else:
            assert left.tolist() == right.tolist(), name


# Spark --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spark():
    """One local[2] session for the module; its JVM ended with it."""
    pytest.importorskip("pyspark")
    os.environ.setdefault("PYSPARK_PYTHON", sys.executable)
    os.environ.setdefault("SPARK_LOCAL_IP", "127.0.0.1")
    from pyspark import SparkContext
    from pyspark.sql import SparkSession

    session = (
        SparkSession.builder.master("local[2]")
        .appName("torchsvs-tests")
        .config("spark.sql.shuffle.partitions", "3")
        .config("spark.default.parallelism", "2")
        .config("spark.ui.enabled", "false")
        .config("spark.sql.execution.arrow.pyspark.enabled", "true")
        .config("spark.driver.memory", "1g")
        .getOrCreate()
    )
    session.sparkContext.setLogLevel("ERROR")
    yield session
    session.stop()
    gateway = SparkContext._gateway
    if gateway is not None:  # the JVM leaves when its standard input closes
        gateway.shutdown()
        gateway.proc.stdin.close()
        gateway.proc.wait(timeout=30)
        SparkContext._gateway = None
        SparkContext._jvm = None


@pytest.fixture(scope="module")
def spark_rows(spark, rows):
    """The rows in 4 partitions dealt round robin: every track split over them."""
    frame = spark.createDataFrame(rows).repartition(4)
    parts = frame.rdd.glom().map(lambda p: sorted({r["id"] for r in p})).collect()
    assert sum(len(p) for p in parts) > rows["id"].nunique()  # tracks do span partitions
    return frame


@pytest.mark.parametrize("case", CASES)
def test_spark_gives_the_estimates_of_one_process(spark, spark_rows, rows, plans, case):
    """Tracks split over partitions get their whole-track estimates, exactly; the parts' runs
    add up to the whole's row counts."""
    from torchsvs.engines.spark import SparkRuns, track_spark

    plan = plans[case]
    whole = track_table(rows, plan)
    runs = SparkRuns(spark)
    out = track_spark(spark_rows, plan, runs=runs).toPandas()
    _same(out, whole.table)
    run = runs.run(plan)
    assert run.report.total == whole.run.report.total == len(rows)
    assert run.report.measurement == whole.run.report.measurement
    assert run.report.tracks == whole.run.report.tracks
    assert run.accuracy is not None


def test_spark_takes_a_timestamp_time_column(spark, rows):
    """Spark's own time type, TIMESTAMP (a Parquet timestamp with a zone): building the output
    schema failed on an assert (pyspark's to_arrow_type wants a zone), where the other engines
    read it (an outside probe). The estimates are those of one process on the same times."""
    from pyspark.sql import functions as F

    from torchsvs.engines.spark import track_spark

    stamped = rows.assign(t=pd.to_datetime(1.7e9 + rows["t"], unit="s", utc=True).dt.round("ms"))
    plan = plan_tracks(stamped, Settings(estimator="ks"), columns=COLUMNS, precision="float64")
    frame = spark.createDataFrame(rows.assign(t=(1.7e12 + rows["t"] * 1e3).round())).withColumn(
        "t", F.timestamp_millis(F.col("t").cast("long"))
    )
    assert dict(frame.dtypes)["t"] == "timestamp"
    out = track_spark(frame, plan).toPandas()
    whole = track_table(stamped, plan).table
    key = ["id", "t", "x", "y"]
    got = out.assign(t=pd.to_datetime(out["t"]).dt.tz_localize(None))[key]
    want = whole.assign(t=whole["t"].dt.tz_convert(None))[key]
    both = got.sort_values(key).reset_index(drop=True), want.sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(*both, check_dtype=False, check_exact=False, atol=1e-6)


def _with_noise_column(rows: pd.DataFrame) -> tuple[pd.DataFrame, TrackPlan]:
    """The rows with each track's σ in a ``sigma`` column (10, 30 or 90 m by track), and the
    plan that runs each track at its own (``--noise-col sigma``)."""
    codes = rows["id"].astype("category").cat.codes.to_numpy()
    noisy = rows.assign(sigma=np.array([10.0, 30.0, 90.0])[codes % 3])
    columns = Columns("id", "t", extra=("sigma",))
    return noisy, plan_tracks(noisy, Settings("ks", noise_column="sigma"), columns=columns)


def test_spark_runs_each_track_at_its_own_noise_as_one_process(spark, rows):
    """A noise column reaches Spark's parts with the positions: the estimates of one process,
    exactly, with every track split over partitions."""
    from torchsvs.engines.spark import track_spark

    noisy, plan = _with_noise_column(rows)
    frame = spark.createDataFrame(noisy).repartition(4)
    _same(track_spark(frame, plan).toPandas(), track_table(noisy, plan).table)


def test_spark_groups_give_the_same(spark, spark_rows, rows, plans):
    """groupBy(bucket).applyInPandas: the same rows and estimates as one process; a run
    computed twice (two actions) counts every row once."""
    from torchsvs.engines.spark import SparkRuns, track_spark

    plan = plans[("svss", "float64")]
    runs = SparkRuns(spark)
    out = track_spark(spark_rows, plan, method="group", buckets=5, runs=runs)
    _same(out.toPandas(), track_table(rows, plan).table)
    assert out.count() == len(rows)
    run = runs.run(plan)
    assert run.report.total == len(rows)
    assert len(runs.parts) <= 5


def test_spark_streams_whole_tracks(spark, spark_rows, rows, plans):
    """Calls of a few rows each (tracks span Arrow batches and calls): the same estimates."""
    from torchsvs.engines.spark import track_spark

    spark.conf.set("spark.sql.execution.arrow.maxRecordsPerBatch", "17")
    try:
        plan = plans[("ks", "float64")]
        out = track_spark(spark_rows, plan, rows_per_call=40, buckets=2).toPandas()
    finally:
        spark.conf.unset("spark.sql.execution.arrow.maxRecordsPerBatch")
    _same(out, track_table(rows, plan).table)


def test_spark_samples_whole_tracks(spark, spark_rows, rows):
    from torchsvs.engines.spark import plan_spark, sample_tracks

    sample = sample_tracks(spark_rows, COLUMNS, tracks=8, seed=1)
    ids = set(sample["id"])
    assert 1 <= len(ids) <= 8
    assert len(sample) == rows["id"].isin(ids).sum()  # every row of a sampled track
    plan = plan_spark(spark_rows, Settings(estimator="ks"), columns=COLUMNS, tracks=8)
    assert plan.settings.meas_var is not None and plan.precision in ("float32", "float64")


def test_spark_bad_input_names_the_argument(spark, spark_rows, rows, plans):
    from torchsvs.engines.spark import SparkRuns, track_spark

    plan = plans[("ks", "float64")]
    with pytest.raises(ValueError, match=r"^df: columns \['x'\] of the plan not in the data"):
        track_spark(spark_rows.drop("x"), plan)
    with pytest.raises(TypeError, match="^plan: expected a TrackPlan"):
        track_spark(spark_rows, plan.settings)
    with pytest.raises(TypeError, match="^df: expected a pyspark.sql.DataFrame"):
        track_spark(rows, plan)
    with pytest.raises(ValueError, match="^method: expected one of"):
        track_spark(spark_rows, plan, method="udf")
    with pytest.raises(ValueError, match="^buckets: expected a positive int"):
        track_spark(spark_rows, plan, buckets=0)
    with pytest.raises(ValueError, match="^rows_per_call: expected a positive int"):
        track_spark(spark_rows, plan, rows_per_call=0)
    with pytest.raises(TypeError, match="^spark: expected a SparkSession"):
        SparkRuns(rows)


# Dask ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dask_client():
    """A distributed LocalCluster in this process (two worker threads). Its HTTP server on a
    free port (":0"): without an address the scheduler tries 8787 and warns when another
    test process holds it (an error here, under pytest -n 2)."""
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


@pytest.fixture(scope="module")
def dask_rows(rows):
    """The rows in 4 partitions of consecutive rows: every track split over them."""
    import dask.dataframe as dd

    frame = dd.from_pandas(rows, npartitions=4, sort=False)
    ids = [set(frame.get_partition(k).compute()["id"]) for k in range(4)]
    assert sum(len(p) for p in ids) > rows["id"].nunique()
    return frame


@pytest.mark.parametrize("case", CASES)
def test_dask_gives_the_estimates_of_one_process(dask_client, dask_rows, rows, plans, case):
    from torchsvs.engines.dask import track_dask

    plan = plans[case]
    out = track_dask(dask_rows, plan).compute()
    _same(out, track_table(rows, plan).table)


def test_dask_run_comes_with_the_estimates(dask_client, dask_rows, rows, plans, tmp_path):
    """with_run: the parts' runs from the same tasks (one compute); written as Parquet, the
    rows read back are the estimates of one process; the id as index needs no shuffle."""
    import dask
    import dask.dataframe as dd

    from torchsvs.engines.dask import parquet_to_parquet, track_dask

    plan = plans[("svss", "float32")]
    whole = track_table(rows, plan)
    frame, run = track_dask(dask_rows, plan, with_run=True)
    parts, total = dask.compute(frame.to_delayed(), run)
    _same(pd.concat(parts), whole.table)
    assert total.report.total == len(rows) and total.report.tracks == whole.run.report.tracks
    assert total.accuracy is not None
    assert "out_of_order" not in total.report.notes  # (the shuffle's order, not the input's)
    indexed = dd.from_pandas(rows.set_index("id").sort_index(), npartitions=3)
    _same(track_dask(indexed, plan).compute(), whole.table)
    source = tmp_path / "in"
    dask_rows.to_parquet(source, write_index=False)
    run, seconds = parquet_to_parquet(str(source), str(tmp_path / "out"), plan)
    _same(pd.read_parquet(tmp_path / "out"), whole.table)
    assert run.report.total == len(rows) and seconds["run"] > 0


def test_tracks_split_between_parts_are_said_so(dask_client, dask_rows, rows, plans):
    """``partitioned=True`` on parts that cut tracks (a reader splitting a file by row group:
    100 tracks read as 118, 39.5 m off one process, without a word; an outside probe): the
    run warns, counting the parts' ids against the distinct ones; shuffled by id, it does
    not."""
    import dask

    from torchsvs.engines.dask import track_dask

    plan = plans[("ks", "float32")]
    frame, run = track_dask(dask_rows, plan, partitioned=True, with_run=True)
    cut = dask.compute(frame.to_delayed(), run)[1]
    said = [w for w in cut.warnings if w.startswith("tracks split between parts")]
    assert said and f"about {rows['id'].nunique()} distinct" in said[0], cut.warnings
    frame, run = track_dask(dask_rows, plan, with_run=True)
    whole = dask.compute(frame.to_delayed(), run)[1]
    assert not any(w.startswith("tracks split between parts") for w in whole.warnings)


def test_the_id_sketch_counts_distinct_ids_within_its_error():
    """The sketch behind that warning: exact up to 2^16 ids, HyperLogLog beyond (a relative
    standard error of 0.8%); 5% of 300,000 tracks split is found, none split is not."""
    from torchsvs.engines.id_sketch import IdSketch, split_warning

    ids = np.arange(300_000)
    parts = [IdSketch.of(ids[k::3]) for k in range(3)]
    whole = parts[0]
    for part in parts[1:]:
        whole.merge(part)
    distinct, error = whole.distinct()
    assert whole.exact is None and abs(distinct - 300_000) < 4 * error < 0.04 * 300_000
    assert split_warning(whole) is None
    whole.merge(IdSketch.of(ids[:15_000]))  # (5% counted in two parts)
    assert split_warning(whole) is not None
    few = IdSketch.of([f"t{k}" for k in range(50)])
    few.merge(IdSketch.of(["t1", "t2", None]))
    assert few.distinct() == (50.0, 0.0) and few.counted == 52 and split_warning(few) is not None


def test_dask_bad_input_names_the_argument(dask_rows, rows, plans):
    from torchsvs.engines.dask import track_dask

    plan = plans[("ks", "float64")]
    with pytest.raises(ValueError, match=r"^ddf: columns \['x'\] of the plan not in the data"):
        track_dask(dask_rows.drop(columns=["x"]), plan)
    with pytest.raises(TypeError, match="^plan: expected a TrackPlan"):
        track_dask(dask_rows, "ks")
    with pytest.raises(TypeError, match="^ddf: expected a dask.dataframe.DataFrame"):
        track_dask(rows, plan)
    with pytest.raises(ValueError, match="^npartitions: expected a positive int"):
        track_dask(dask_rows, plan, npartitions=0)  # (ran, an outside probe)


def test_engines_import_neither_spark_nor_dask_until_run():
    """torchsvs and its engines' modules load without Spark or Dask (a user of one engine need
    not install the other)."""
    code = (
        "import sys, torchsvs, torchsvs.engines.spark, torchsvs.engines.dask, torchsvs.track_table;"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pyspark', 'dask', "
        "'distributed')))"
    )
    found = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert found.stdout.strip() == "[]"


def test_dask_runs_each_track_at_its_own_noise_as_one_process(dask_client, rows):
    """A noise column (each row's σ: ``--noise-col``) is carried to the parts with the
    positions, and each track's noise class is its own whatever part holds it: the estimates
    of one process, exactly."""
    import dask.dataframe as dd

    from torchsvs.engines.dask import track_dask

    noisy, plan = _with_noise_column(rows)
    frame = dd.from_pandas(noisy, npartitions=4, sort=False)
    whole = track_table(noisy, plan).table
    assert "sigma" not in whole.columns
    _same(track_dask(frame, plan).compute(), whole)

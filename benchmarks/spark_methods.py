"""``track_spark``'s two ways to Spark on ``local[2]``: ``method="map"`` (shuffle by id,
``mapInArrow``) against ``method="group"`` (``groupBy(bucket).applyInArrow``), Parquet in and
out through :func:`torchsvs.engines.spark.parquet_to_parquet`, the Kalman smoother planned once
on 500 whole tracks; after a warm-up run (the Python workers import torch), each way twice, in
turns; with ``--by-id`` also grouped by the track id itself (one call per track). Prints the
wall seconds of each run (the numbers in ``docs/guide/engines.md``).

    python -m benchmarks.spark_methods TRACKS STEPS [--by-id]
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from torchsvs.recipes import Settings


def write_tracks(path: str, tracks: int, steps: int) -> None:
    """Constant-velocity tracks at 1 s, noise 20 m, rows shuffled."""
    gen = np.random.default_rng(0)
    t = np.tile(np.arange(steps, dtype=float), tracks)
    ids = np.repeat([f"trk{k:06d}" for k in range(tracks)], steps)
    v = np.repeat(gen.normal(0, 30, (tracks, 2)), steps, 0)
    p0 = np.repeat(gen.normal(0, 1e3, (tracks, 2)), steps, 0)
    pos = p0 + v * t[:, None] + gen.normal(0, 20, (tracks * steps, 2))
    table = pa.table({"track_id": ids, "time": t, "x": pos[:, 0], "y": pos[:, 1]})
    pq.write_table(table.take(gen.permutation(tracks * steps)), path, row_group_size=1 << 16)


def main(tracks: int, steps: int, by_id: bool) -> None:
    os.environ.setdefault("PYSPARK_PYTHON", sys.executable)
    os.environ.setdefault("SPARK_LOCAL_IP", "127.0.0.1")
    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    from pyspark.sql import SparkSession

    from torchsvs.engines.parts import estimate_part
    from torchsvs.engines.spark import parquet_to_parquet, plan_spark, spark_schema

    spark = (
        SparkSession.builder.master("local[2]")
        .config("spark.ui.enabled", "false")
        .config("spark.sql.shuffle.partitions", "4")
        .config("spark.driver.memory", "2g")
        .getOrCreate()
    )
    spark.sparkContext.setLogLevel("ERROR")
    folder = tempfile.mkdtemp()
    source = os.path.join(folder, "in.parquet")
    write_tracks(source, tracks, steps)
    frame = spark.read.parquet(source)
    plan = plan_spark(frame, Settings(estimator="ks"), tracks=500)
    ways = {
        "map, 4 partitions": {},
        "group, 4 buckets": dict(method="group", buckets=4),
        "group, 16 buckets": dict(method="group", buckets=16),
        "map, 16 partitions": dict(buckets=16),
    }
    parquet_to_parquet(spark, source, os.path.join(folder, "warm"), plan)
    for _ in range(2):
        for name, options in ways.items():
            start = time.perf_counter()
            run, _ = parquet_to_parquet(spark, source, os.path.join(folder, "out"), plan, **options)
            assert run.report.total == tracks * steps
            print(f"{name}: {time.perf_counter() - start:.2f} s", flush=True)
    if by_id:
        schema = spark_schema(frame, plan)

        def one_track(table: pa.Table) -> pa.Table:
            return estimate_part(table, plan)[0]

        start = time.perf_counter()
        out = frame.groupBy("track_id").applyInArrow(one_track, schema)
        out.write.mode("overwrite").parquet(os.path.join(folder, "by_id"))
        print(f"grouped by id: {time.perf_counter() - start:.2f} s", flush=True)
    spark.stop()


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), "--by-id" in sys.argv)

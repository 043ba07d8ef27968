"""Smoothing a Spark DataFrame of track rows (:func:`track_spark`), with a plan settled once on
the driver (:func:`plan_spark`, on whole tracks sampled by id: :func:`sample_tracks`).

Every track's rows must reach one call whole. ``method="map"`` (the default) shuffles the
rows by track id (``repartition(n, id)``), sorts each partition by id and streams it through
``mapInArrow`` (``mapInPandas``' Arrow twin: no pandas), cut into tables of about
``rows_per_call`` rows at track boundaries, so memory stays bounded whatever a partition's
size. ``method="group"`` is the other convention, ``groupBy(bucket).applyInArrow``, where the
bucket is a hash of the id modulo ``buckets``: each call gets a whole bucket (many tracks) at
once. Grouping by the id itself would make one call per track, far slower. Both give the same
rows and estimates; "map" is the default: its memory does not grow with a bucket's size (see
the guide, "Datasets on Spark and Dask").

The run's summary (row counts, the truth-free error estimate, warnings) is gathered while Spark
computes the output, in an accumulator (:class:`SparkRuns`) keyed by part, so a task run again
or an output computed twice adds nothing twice.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

from torchsvs.datasets import Columns
from torchsvs.datasets.tables import SAMPLE_TRACKS
from torchsvs.engines.parts import (
    check_count,
    check_plan,
    estimate_part,
    merged_run,
)
from torchsvs.recipes import Settings
from torchsvs.track_plan import TrackPlan, check_columns, plan_columns, plan_tracks
from torchsvs.track_run import TrackRun
from torchsvs.track_table import output_schema

METHODS = ("map", "group")
#: Rows per call of ``method="map"`` (whole tracks: a call may hold more).
ROWS_PER_CALL = 1 << 18
#: The hidden column of ``method="group"``'s buckets.
BUCKET = "__torchsvs_bucket"


def sample_tracks(
    df: Any, columns: Columns | None = None, *, tracks: int = SAMPLE_TRACKS, seed: int = 0
) -> Any:
    """About ``tracks`` whole tracks of ``df``, picked by id, as a pandas DataFrame on the
    driver: the sample to plan on. A plan made on the first rows (``df.limit(n)``) would see
    cut tracks, and read a different noise off them. Costs two actions: the ids' count (one
    column) and the sample's rows."""
    from pyspark.sql import functions as F

    ident = (columns or Columns()).track_id
    check_spark(df, "df")
    if ident not in df.columns:
        raise ValueError(f"columns: the track id {ident!r} not in df (its columns: {df.columns})")
    if not isinstance(tracks, int) or tracks < 1:
        raise ValueError(f"tracks: expected a positive int, got {tracks!r}")
    ids = df.select(ident).distinct()
    count = ids.count()
    # a little more than asked, so the limit (not the draw) sets the sample's size
    fraction = min(1.0, 1.2 * tracks / max(count, 1))
    picked = ids.sample(fraction=fraction, seed=seed).limit(tracks)
    return df.join(F.broadcast(picked), on=ident, how="left_semi").toPandas()


def plan_spark(
    df: Any,
    settings: Settings | None = None,
    *,
    columns: Columns | None = None,
    tracks: int = SAMPLE_TRACKS,
    seed: int = 0,
    **options: Any,
) -> TrackPlan:
    """:func:`~torchsvs.track_plan.plan_tracks` on ``tracks`` whole tracks of ``df``
    (:func:`sample_tracks`); ``options``: ``fit``, ``fit_options``, ``precision``, ... of
    ``plan_tracks``."""
    sample = sample_tracks(df, columns, tracks=tracks, seed=seed)
    return plan_tracks(sample, settings, columns=columns, **options)


def check_spark(df: Any, name: str) -> None:
    """A TypeError naming ``name`` unless ``df`` is a Spark DataFrame (classic or Connect)."""
    kind = type(df)
    if not (kind.__module__.startswith("pyspark.sql") and kind.__name__ == "DataFrame"):
        raise TypeError(f"{name}: expected a pyspark.sql.DataFrame, got {kind.__name__}")


def spark_schema(df: Any, plan: TrackPlan, covariance: bool = False) -> Any:
    """The Spark schema of :func:`track_spark`'s output: the id and time fields of ``df`` as
    they are, then the estimates (:func:`~torchsvs.track_table.output_schema`)."""
    from pyspark.sql.pandas.types import from_arrow_schema, to_arrow_type
    from pyspark.sql.types import StructType

    cols = plan.columns
    fields = {f.name: f for f in df.schema.fields}
    ident, stamp = fields[cols.track_id], fields[cols.time]
    # (the id and time fields are kept as they are: their Arrow types only shape the rest; a
    # TIMESTAMP needs a zone to convert, any zone, where none failed on an assert)
    ident_type, stamp_type = (to_arrow_type(f.dataType, timezone="UTC") for f in (ident, stamp))
    arrow = output_schema(plan, ident_type, stamp_type, covariance)
    estimates = from_arrow_schema(arrow).fields[2:]
    return StructType([ident, stamp, *estimates])


def track_spark(
    df: Any,
    plan: TrackPlan,
    *,
    covariance: bool = False,
    method: str = "map",
    buckets: int | None = None,
    partitioned: bool = False,
    rows_per_call: int = ROWS_PER_CALL,
    accuracy: bool = True,
    threads: int | None = 1,
    runs: SparkRuns | None = None,
) -> Any:
    """The rows of ``df`` with their estimates, as a lazy Spark DataFrame (nothing runs until an
    action: ``.write.parquet(path)``): the id and time as given, then the columns of
    :func:`~torchsvs.track_table.track_table` (in no particular row order, as Spark goes).

    Args:
        df: track rows with the plan's columns (others are dropped), any order and
            partitioning.
        plan: settled once on the driver (:func:`plan_spark`); it travels to the executors in
            the task's closure (pickled once per task, a few kB).
        covariance: also give each estimate's covariance (``cov_<a>_<b>``).
        method: ``"map"``, tracks shuffled by id then streamed through ``mapInArrow``, or
            ``"group"``, ``groupBy(bucket).applyInArrow`` (see the module's docstring).
        buckets: ``"map"``: the partitions the rows are shuffled into; ``"group"``: the
            buckets (one call each, held in memory whole: aim at a few hundred thousand
            rows each). Default: ``spark.sql.shuffle.partitions``.
        partitioned: ``"map"`` only: every track is in one partition of ``df`` already (read
            from a dataset written partitioned by track); no shuffle, only a sort.
        rows_per_call: ``"map"``: rows per call (whole tracks), bounds a task's memory.
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`).
        threads: torch threads per task (Spark runs a task per core); None leaves torch's.
        runs: gathers the parts' runs as the output is computed (:class:`SparkRuns`).
    """
    check_spark(df, "df")
    check_plan(plan)
    check_columns(df.columns, plan, "df")
    if method not in METHODS:
        raise ValueError(f"method: expected one of {list(METHODS)}, got {method!r}")
    check_count(buckets, "buckets", optional=True)
    check_count(rows_per_call, "rows_per_call")
    if runs is not None and not isinstance(runs, SparkRuns):
        raise TypeError(f"runs: expected SparkRuns or None, got {type(runs).__name__}")
    schema = spark_schema(df, plan, covariance)
    ident = plan.columns.track_id
    rows = df.select(*plan_columns(plan))
    count = buckets or int(df.sparkSession.conf.get("spark.sql.shuffle.partitions"))
    accumulator = None if runs is None else runs.accumulator
    options = dict(
        covariance=covariance,
        accuracy=accuracy,
        threads=threads,
        shuffled=True,  # (the rows sorted by id at least: their order is not the input's)
    )
    if method == "group":
        from pyspark.sql import functions as F

        keyed = rows.withColumn(BUCKET, F.abs(F.xxhash64(F.col(ident)) % count))
        return keyed.groupBy(BUCKET).applyInArrow(_group_call(plan, options, accumulator), schema)
    if not partitioned:
        rows = rows.repartition(count, ident)
    stream = _map_call(plan, options, accumulator, rows_per_call)
    return rows.sortWithinPartitions(ident).mapInArrow(stream, schema)


def _group_call(plan: TrackPlan, options: dict[str, Any], accumulator: Any) -> Any:
    """``applyInArrow``'s function: one bucket's rows (whole tracks) → their estimates."""

    def call(key: Any, table: Any) -> Any:
        out, run = estimate_part(table.drop_columns([BUCKET]), plan, **options)
        if accumulator is not None:
            accumulator.add({("group", key[0].as_py()): run})
        return out

    return call


def _map_call(plan: TrackPlan, options: dict[str, Any], accumulator: Any, rows: int) -> Any:
    """``mapInArrow``'s function: a partition's batches, sorted by id, cut into tables of
    about ``rows`` rows at track boundaries → their estimates."""

    def call(batches: Iterator[Any]) -> Iterator[Any]:
        from pyspark import TaskContext

        context = TaskContext.get()
        part = -1 if context is None else context.partitionId()
        total: TrackRun | None = None
        for table in whole_tracks(batches, plan.columns.track_id, rows):
            out, run = estimate_part(table, plan, **options)
            if total is None:
                total = run
            else:
                total.merge(run)
                total.seconds += run.seconds
            yield from out.to_batches()
        if accumulator is not None and total is not None:
            accumulator.add({("map", part): total})

    return call


def whole_tracks(batches: Iterator[Any], ident: str, rows: int) -> Iterator[Any]:
    """Arrow record batches of rows sorted by ``ident`` (a track's rows may span batches) as
    tables of whole tracks of at least ``rows`` rows (the last one fewer): each cut is made
    before the rows of the last track seen, which wait for the next batches."""
    import pyarrow as pa
    import pyarrow.compute as pc

    pending: list[Any] = []
    count = 0
    for batch in batches:
        if not batch.num_rows:
            continue
        pending.append(batch)
        count += batch.num_rows
        if count < rows:
            continue
        table = pa.Table.from_batches(pending)
        last = table.column(ident)[-1]
        # rows without an id sort first and belong to no track: no need to keep them whole
        tail = pc.sum(pc.equal(table.column(ident), last)).as_py() if last.is_valid else 0
        cut = table.num_rows - tail
        if cut == 0:  # one track so far: wait for its end
            continue
        yield table.slice(0, cut)
        rest = table.slice(cut)
        pending = rest.to_batches() if rest.num_rows else []
        count = rest.num_rows
    if pending:
        yield pa.Table.from_batches(pending)


class SparkRuns:
    """The runs of :func:`track_spark`'s parts, gathered while Spark computes its output (an
    accumulator: no action of its own), added up by :meth:`run` on the driver.

    Each part's run is kept under its part's key (``"map"``: its partition; ``"group"``: its
    bucket), so a task run again, or an output computed by two actions, replaces a part's
    run instead of adding it twice. Read it after the action that wrote the output. Needs the
    classic Spark API (an accumulator: not Spark Connect).
    """

    def __init__(self, spark: Any) -> None:
        context = getattr(spark, "sparkContext", None)
        if context is None or not hasattr(context, "accumulator"):
            raise TypeError(
                f"spark: expected a SparkSession with a sparkContext (not Spark Connect), got "
                f"{type(spark).__name__}"
            )
        self.accumulator = context.accumulator({}, _PartRuns())

    @property
    def parts(self) -> dict[Any, TrackRun]:
        """The parts' runs so far, by part."""
        return dict(self.accumulator.value)

    def run(self, plan: TrackPlan, accuracy: bool = True) -> TrackRun:
        """The dataset's run: the parts' added up, checked (its warnings)."""
        parts = self.parts
        return merged_run(check_plan(plan), (parts[k] for k in sorted(parts)), accuracy)


class _PartRuns:
    """The accumulator's rule (an ``AccumulatorParam`` by its methods): runs by part, where
    adding replaces a part's run."""

    def zero(self, value: Any) -> dict[Any, TrackRun]:
        return {}

    def addInPlace(self, value1: Any, value2: Any) -> dict[Any, TrackRun]:  # noqa: N802
        value1.update(value2)
        return value1


def parquet_to_parquet(
    spark: Any,
    source: str,
    target: str,
    plan: TrackPlan,
    *,
    covariance: bool = False,
    mode: str = "overwrite",
    **options: Any,
) -> tuple[TrackRun, dict[str, float]]:
    """A Parquet dataset (a file or a directory) smoothed into a Parquet directory:
    ``spark.read.parquet`` → :func:`track_spark` → ``write.parquet``, one action; returns the
    run (:class:`SparkRuns`) and the wall seconds of the action (``"run"``: reading,
    shuffling, estimating, writing, pipelined) beside the tasks' estimating seconds, added
    up over tasks (``"estimate_tasks"``) and their calls' (``"calls_tasks"``)."""
    runs = SparkRuns(spark)
    frame = spark.read.parquet(source)
    out = track_spark(frame, plan, covariance=covariance, runs=runs, **options)
    start = time.perf_counter()
    out.write.mode(mode).parquet(target)
    wall = time.perf_counter() - start
    run = runs.run(plan, options.get("accuracy", True))
    seconds = {
        "run": wall,
        "estimate_tasks": run.estimate_seconds,
        "calls_tasks": run.seconds,
    }
    return run, seconds

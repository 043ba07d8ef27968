"""Smoothing a Dask DataFrame of track rows (:func:`track_dask`): every partition estimated by
:func:`~torchsvs.track_table.track_table` with one plan settled once, after a shuffle by track
id so that no track spans two partitions (a track split over two partitions would be estimated
twice, in halves).

The run's summary (row counts, the truth-free error estimate, warnings) comes from the same
tasks as the estimates with ``with_run=True``: compute both in one ``dask.compute``, the output
as delayed objects (``dask.compute(out.to_parquet(path, compute=False).to_delayed(), run)``:
Dask does not compute its DataFrames' expressions and delayed objects together) and the
tracks are estimated once.
"""

from __future__ import annotations

import time
from typing import Any

from torchsvs.engines.parts import (
    check_count,
    check_plan,
    estimate_part,
    merged_run,
)
from torchsvs.track_plan import TrackPlan, check_columns, plan_columns
from torchsvs.track_run import TrackRun
from torchsvs.track_table import output_schema


def check_dask(ddf: Any, name: str) -> None:
    """A TypeError naming ``name`` unless ``ddf`` is a Dask DataFrame."""
    kind = type(ddf)
    if not (kind.__module__.startswith("dask") and kind.__name__ == "DataFrame"):
        raise TypeError(f"{name}: expected a dask.dataframe.DataFrame, got {kind.__name__}")


def by_track(ddf: Any, ident: str, npartitions: int | None = None) -> Any:
    """``ddf`` with every track's rows in one partition: a hash shuffle on the id column (no
    sort: cheaper than ``set_index``), into ``npartitions`` (default: as many as it has)."""
    return ddf.shuffle(on=ident, npartitions=npartitions or ddf.npartitions)


def dask_meta(ddf: Any, plan: TrackPlan, covariance: bool = False) -> Any:
    """The empty pandas DataFrame of :func:`track_dask`'s output (its ``meta``): the id and
    time as they come back from Arrow, then the estimates
    (:func:`~torchsvs.track_table.output_schema`)."""
    import pyarrow as pa

    cols = plan.columns
    head = pa.Table.from_pandas(ddf._meta[[cols.track_id, cols.time]], preserve_index=False)
    schema = output_schema(plan, head.schema.field(0).type, head.schema.field(1).type, covariance)
    return schema.empty_table().to_pandas()


def track_dask(
    ddf: Any,
    plan: TrackPlan,
    *,
    covariance: bool = False,
    accuracy: bool = True,
    partitioned: bool = False,
    npartitions: int | None = None,
    threads: int | None = 1,
    with_run: bool = False,
) -> Any:
    """The rows of ``ddf`` with their estimates, as a lazy Dask DataFrame (nothing runs until
    it is computed or written: ``.to_parquet(path)``): the id and time as given, then the
    columns of :func:`~torchsvs.track_table.track_table`, each partition's rows in their
    order, with a fresh index.

    Args:
        ddf: track rows with the plan's columns (others are dropped); the id may be the index
            (``set_index(id)``: with known divisions no shuffle is needed).
        plan: settled once on a sample (:func:`~torchsvs.track_plan.plan_tracks`); it goes
            to the workers with the tasks.
        covariance: also give each estimate's covariance (``cov_<a>_<b>``).
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`).
        partitioned: every track is in one partition of ``ddf`` already: no shuffle
            (:func:`by_track`).
        npartitions: of the shuffle (default: as many as ``ddf`` has).
        threads: torch threads per task (a worker runs a task per thread); None leaves
            torch's.
        with_run: also give the run (a ``dask.delayed`` :class:`~torchsvs.track_run.TrackRun`,
            the parts' added up), from the same tasks: ``(frame, run)``; compute ``run``
            together with the output's ``to_delayed()`` (see the module's docstring).
    """
    check_dask(ddf, "ddf")
    check_plan(plan)
    check_count(npartitions, "npartitions", optional=True)
    ident = plan.columns.track_id
    if ddf.index.name == ident and ident not in ddf.columns:
        partitioned = partitioned or bool(ddf.known_divisions)
        ddf = ddf.reset_index()
    check_columns(list(ddf.columns), plan, "ddf")
    rows = ddf[plan_columns(plan)]
    if not partitioned:
        rows = by_track(rows, ident, npartitions)
    meta = dask_meta(rows, plan, covariance)
    options = dict(
        covariance=covariance, accuracy=accuracy, threads=threads, shuffled=not partitioned
    )
    if not with_run:
        return rows.map_partitions(_part_table, plan, options, meta=meta, align_dataframes=False)
    import dask
    import dask.dataframe as dd

    results = [dask.delayed(_part)(part, plan, options) for part in rows.to_delayed()]
    frame = dd.from_delayed([r[0] for r in results], meta=meta, verify_meta=False)
    run = dask.delayed(merged_run)(plan, [r[1] for r in results], accuracy)
    return frame, run


def _part(frame: Any, plan: TrackPlan, options: dict[str, Any]) -> tuple[Any, TrackRun]:
    return estimate_part(frame, plan, **options)


def _part_table(frame: Any, plan: TrackPlan, options: dict[str, Any]) -> Any:
    return estimate_part(frame, plan, **options)[0]


def parquet_to_parquet(
    source: str, target: str, plan: TrackPlan, *, covariance: bool = False, **options: Any
) -> tuple[TrackRun, dict[str, float]]:
    """A Parquet dataset (a file or a directory) smoothed into a Parquet directory:
    ``dd.read_parquet`` → :func:`track_dask` → ``to_parquet``, one ``dask.compute`` on the
    current scheduler (a ``distributed.Client`` if one is open); returns the run and the wall
    seconds of the compute (``"run"``: reading, shuffling, estimating, writing) beside the
    tasks' estimating seconds added up (``"estimate_tasks"``) and their calls'
    (``"calls_tasks"``)."""
    import dask
    import dask.dataframe as dd

    frame, run = track_dask(
        dd.read_parquet(source), plan, covariance=covariance, with_run=True, **options
    )
    write = frame.to_parquet(target, compute=False, write_index=False).to_delayed()
    start = time.perf_counter()
    _, total = dask.compute(write, run)
    wall = time.perf_counter() - start
    seconds = {
        "run": wall,
        "estimate_tasks": total.estimate_seconds,
        "calls_tasks": total.seconds,
    }
    return total, seconds

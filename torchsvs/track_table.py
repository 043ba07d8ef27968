"""One table of track rows in, the same rows with their estimates out (:func:`track_table`).

This is the unit every engine calls: ``torchsvs track`` on each block of a file
(:func:`~torchsvs.tracking.track_file`), Spark on each group of tracks and Dask on each partition
(:mod:`torchsvs.engines`). It is pure: what it estimates with is an argument, a
:class:`~torchsvs.track_plan.TrackPlan` settled once on a sample, so a table's estimates do not
depend on which other tracks it holds, nor on where it runs. Every track's rows must be in the
table (any order); a track split over two tables would be estimated twice, in halves.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from torchsvs.accuracy import RiskTotals
from torchsvs.datasets import TrackBlock
from torchsvs.datasets.breaks import split_at_breaks
from torchsvs.datasets.tables import block_of, is_pandas, to_pandas_like
from torchsvs.datasets.writing import output_names
from torchsvs.estimating import estimate_group
from torchsvs.step_estimates import StepEstimates, group_batch
from torchsvs.track_plan import TrackPlan, check_columns, interval_warning, precision_warning
from torchsvs.track_run import BlockEstimates, TrackRun


class TableResult(NamedTuple):
    """What :func:`track_table` gives back."""

    table: Any  #: the rows with their estimates (a pandas DataFrame for one, else Arrow)
    run: TrackRun  #: what the call did: rows, error estimate, warnings (its summary)


def track_table(
    data: Any,
    plan: TrackPlan,
    *,
    covariance: bool = False,
    accuracy: bool = True,
    max_cells: int = 1 << 19,
    estimator: nn.Module | None = None,
    check: bool = True,
) -> TableResult:
    """Estimates every track of a table of rows, all its tracks batched, with what ``plan``
    settled (:func:`~torchsvs.track_plan.plan_tracks`).

    Args:
        data: a ``pandas.DataFrame`` or ``pyarrow.Table`` of rows (any order; every row of a
            track in it), with the columns the plan names (others are ignored).
        plan: the columns, settings and parameters to estimate with.
        covariance: also give the covariance of every estimate (``cov_<a>_<b>``).
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`).
        max_cells: padded steps (tracks × steps) per estimator call: bounds memory.
        estimator: ``plan.estimator()`` built already (a caller with many tables builds it
            once).
        check: warn in the run where the estimate is not clearly better than the measurements
            (:meth:`~torchsvs.track_run.TrackRun.check`); an engine whose parts add up to one
            run checks the sum instead.

    Returns:
        The same rows with their estimates: the id and time as given, then the columns of
        ``torchsvs track``'s output (:func:`~torchsvs.datasets.estimate_table`; a pandas
        DataFrame for one, an Arrow table otherwise, with no index), and the run's summary.
    """
    start = time.perf_counter()
    names = list(data.columns) if is_pandas(data) else getattr(data, "column_names", None)
    if names is not None:  # (a table's: a block read here was checked as it was read)
        check_columns(names, plan, "data")
    block = block_of(data, plan.columns)
    run = new_run(plan, accuracy)
    found = estimate_block(
        block,
        plan,
        estimator or plan.estimator(),
        run,
        covariance=covariance,
        accuracy=accuracy,
        max_cells=max_cells,
    )
    out = found.table(block, plan.precision)
    if check:
        run.check()
    run.seconds = time.perf_counter() - start
    return TableResult(to_pandas_like(out, data) if is_pandas(data) else out, run)


def new_run(plan: TrackPlan, accuracy: bool = True) -> TrackRun:
    """An empty run of ``plan`` (its error estimate's totals where ``accuracy``)."""
    assert plan.settings.meas_var is not None
    risk = RiskTotals(len(plan.settings.meas_var)) if accuracy else None
    return TrackRun(settings=plan.settings, fit=plan.fit, risk=risk)


def estimate_block(
    block: TrackBlock,
    plan: TrackPlan,
    estimator: nn.Module,
    run: TrackRun,
    *,
    covariance: bool = False,
    accuracy: bool = True,
    max_cells: int = 1 << 19,
    progress: Any = None,
) -> BlockEstimates:
    """A block's estimates, group by group of tracks of similar length
    (:func:`~torchsvs.estimating.estimate_group`), counted into ``run``; ``progress`` (a tqdm
    bar) hears each group's tracks."""
    if plan.settings.track_breaks:  # (the block itself: its writing reads the same tracks)
        block.steps = split_at_breaks(block.steps)[0]
    steps = block.steps
    for warning in (precision_warning(plan, steps), interval_warning(plan, steps)):
        if warning is None:
            continue
        topic = warning.split(":", 1)[0]  # ("precision", "time": once a run, whatever numbers)
        if not any(w.split(":", 1)[0] == topic for w in run.warnings):
            run.warnings.append(warning)
    meas_std = plan.meas_std
    found = BlockEstimates.empty(steps, covariance, plan.settings.screens)
    tick, cpu = time.perf_counter(), time.process_time()

    def one(item: tuple[int, np.ndarray]) -> StepEstimates:
        position, group = item
        batch = group_batch(steps, group, position, plan.dtype)
        estimates = estimate_group(estimator, batch, meas_std, covariance, accuracy, plan.settings)
        found.place(estimates)  # (on this group's thread, beside the others)
        return estimates

    groups = list(enumerate(steps.batches(max_cells)))
    with group_threads(len(groups)) as run_groups:
        for (_, group), estimates in zip(groups, run_groups(one, groups), strict=True):
            found.add(estimates, placed=True)
            if progress is not None:
                progress.update(len(group))
    run.estimate_seconds += time.perf_counter() - tick
    run.estimate_cpu_seconds += time.process_time() - cpu
    run.add_block(found, steps)
    return found


@contextlib.contextmanager
def group_threads(groups: int) -> Iterator[Any]:
    """A ``map`` for a block's groups: in order, on as many threads at once as torch's intra-op
    count (the run's ``--threads``), each group on one intra-op thread while the block runs
    (process-wide; restored after). A group's passes are compiled loops and large numpy and
    torch operations that release the GIL, and a group's results depend on its tracks alone
    (its random draws are seeded by its position), so they are the same on any thread.
    Measured on 10 M rows (2 cores, 2 groups a block): 0.84× the wall of one group at a time
    with torch's two threads each."""
    workers = min(torch.get_num_threads(), groups)
    if workers <= 1:
        yield map
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        # (an error or an interrupt while its results are read: map cancels the groups not
        # started, so they are dropped, not run)
        with ThreadPoolExecutor(workers) as pool:
            yield pool.map
    finally:
        torch.set_num_threads(before)


def output_schema(plan: TrackPlan, id_type: Any, time_type: Any, covariance: bool = False) -> Any:
    """The ``pyarrow.Schema`` of :func:`track_table`'s output for input id and time columns of
    these Arrow types (what an engine declares before any part has run)."""
    import pyarrow as pa

    cols = plan.columns
    assert cols.position is not None
    names, cov_names = output_names(cols)
    m = len(cols.position)
    kind = pa.float32() if plan.precision == "float32" else pa.float64()
    order = range(2 * m) if not cols.geodetic else [*range(0, 2 * m, 2), *range(1, 2 * m, 2)]
    fields = [pa.field(cols.track_id, id_type), pa.field(cols.time, time_type)]
    fields += [pa.field(names[j], kind) for j in order]
    if covariance:
        fields += [
            pa.field(f"cov_{cov_names[a]}_{cov_names[b]}", kind)
            for a in range(2 * m)
            for b in range(a, 2 * m)
        ]
    if plan.settings.screens:
        fields.append(pa.field("outlier", pa.bool_()))
    return pa.schema(fields)

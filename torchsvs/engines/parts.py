"""What the engines share: their arguments checked before anything runs, one part of a dataset
estimated (:func:`estimate_part`) and its run kept small, the parts' runs added up
(:func:`merged_run`). No Spark or Dask here: a part is a pandas DataFrame."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

from torch import nn

from torchsvs.engines.id_sketch import IdSketch, split_warning
from torchsvs.track_plan import TrackPlan
from torchsvs.track_run import TrackRun
from torchsvs.track_table import new_run, track_table

#: Per-track error estimates each part hands back: its worst this many. The run's worst this
#: many tracks are then exactly the dataset's (each is among its own part's worst), and what
#: the driver holds stays bounded by parts × this, whatever the number of tracks.
TRACKS_PER_PART = 100


def check_plan(plan: Any) -> TrackPlan:
    """``plan`` itself, or a TypeError naming it."""
    if not isinstance(plan, TrackPlan):
        raise TypeError(
            "plan: expected a TrackPlan (torchsvs.track_plan.plan_tracks on a sample), got "
            f"{type(plan).__name__}"
        )
    return plan


def check_count(value: Any, name: str, optional: bool = False) -> None:
    """A ValueError naming ``name`` unless ``value`` is a positive int (or None, ``optional``)."""
    if optional and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        expected = "a positive int or None" if optional else "a positive int"
        raise ValueError(f"{name}: expected {expected}, got {value!r}")


def set_threads(threads: int | None) -> None:
    """Torch's threads in a worker: an engine runs one task per core already, and a task on
    every core would oversubscribe them."""
    if threads is not None:
        import torch

        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


_built = threading.local()


def estimator_of(plan: TrackPlan) -> nn.Module:
    """``plan.estimator()``, built once per plan in each worker thread (its last plan's
    kept): a thread's calls reuse it, and no lock is needed for a cache shared by threads
    (an estimator itself may be shared: ``tests/test_track_table.py`` runs four threads on
    one)."""
    last = getattr(_built, "last", None)
    if last is None or last[0] is not plan:
        last = _built.last = (plan, plan.estimator())
    return last[1]


def estimate_part(
    frame: Any,
    plan: TrackPlan,
    *,
    covariance: bool = False,
    accuracy: bool = True,
    max_cells: int = 1 << 19,
    threads: int | None = 1,
    shuffled: bool = False,
) -> tuple[Any, TrackRun]:
    """One part's rows with their estimates (:func:`~torchsvs.track_table.track_table`,
    unchecked: the sum of the parts is checked) and its run, with the worst
    :data:`TRACKS_PER_PART` per-track error estimates. Where the engine ``shuffled`` the rows
    to bring each track's together, their order is the shuffle's, not the input's: the run
    counts none out of order (Dask's counted 1-3 of rows in time order; an outside probe)."""
    set_threads(threads)
    result = track_table(
        frame,
        plan,
        covariance=covariance,
        accuracy=accuracy,
        max_cells=max_cells,
        estimator=estimator_of(plan),
        check=False,
    )
    run = result.run
    if shuffled:
        run.report.notes.pop("out_of_order", None)
    run.keep_worst(TRACKS_PER_PART)
    ids = (
        frame[plan.columns.track_id]
        if hasattr(frame, "columns")
        else frame.column(plan.columns.track_id)
    )
    run.parts_ids = IdSketch.of(ids)
    return result.table, run


def merged_run(plan: TrackPlan, runs: Iterable[TrackRun], accuracy: bool = True) -> TrackRun:
    """The parts' runs added up to the dataset's (:meth:`~torchsvs.track_run.TrackRun.merge`),
    then checked; its ``seconds`` are the parts' added up (task time, not the wall's)."""
    total = new_run(plan, accuracy)
    for run in runs:
        total.merge(run)
        total.seconds += run.seconds
    total.keep_worst(TRACKS_PER_PART)
    total.check()
    split = None if total.parts_ids is None else split_warning(total.parts_ids)
    if split is not None:
        total.warnings.insert(0, split)
    return total

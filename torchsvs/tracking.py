"""Tracking recorded files: the loop behind ``torchsvs track``.

A file is read in blocks of complete tracks (:func:`~torchsvs.datasets.track_blocks`); what
the user left open is settled on the first block (:func:`~torchsvs.track_plan.plan_tracks`: read
off the data, tuned with ``--fit``, chosen with ``auto``); each block is then estimated as one
table (:func:`~torchsvs.track_table.estimate_block`, the unit the engines call too) and written.
Every run estimates its own error without truth (:mod:`torchsvs.accuracy`) and warns where it
is not clearly below the measurements' (:class:`~torchsvs.track_run.TrackRun`, which also holds
the run's summary).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import chain
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchsvs.datasets import Columns, EstimateWriter
from torchsvs.datasets.paths import check_output
from torchsvs.datasets.reading import ReadAhead, TrackBlock
from torchsvs.datasets.tables import SAMPLE_TRACKS, joined, sample_taken
from torchsvs.recipes import Settings
from torchsvs.track_plan import TrackPlan, plan_tracks
from torchsvs.track_run import TrackRun, summary_path, write_summary
from torchsvs.track_table import estimate_block, new_run


def track_file(
    source: str | Path,
    target: str | Path,
    settings: Settings,
    *,
    columns: Columns | None = None,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    covariance: bool = False,
    whole: bool | None = None,
    block_rows: int = 1 << 18,
    max_cells: int = 1 << 19,
    dtype: torch.dtype = torch.float32,
    precision: str = "auto",
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    accuracy: bool = True,
    summary: bool = True,
    blocks: ReadAhead | None = None,
) -> TrackRun:
    """Estimates every track of a file and writes one output row per input row.

    The file is read in blocks of complete tracks (``whole=None``: the whole file at once when
    it is small, :func:`~torchsvs.datasets.reading.reads_whole`, else streamed; streaming needs
    each track's rows contiguous). Settings
    the user left open are read off the first block
    (:func:`~torchsvs.fitting.defaults.complete_settings`); with ``fit`` the estimator is tuned
    on the first block's tracks (up to ``fit_options["tracks"]``) without truth before anything
    is written. Each block is estimated in groups of tracks of similar
    length of at most ``max_cells`` padded steps, so memory stays bounded.

    Args:
        source, target: input and output files (``.csv`` or ``.parquet`` each), or a
            directory of Parquet files and the output directory (one file per input file:
            :class:`~torchsvs.datasets.EstimateWriter`).
        settings: the estimator and whatever of its settings are known.
        columns: the input's column names.
        fit: tune the estimator on the data first (:func:`~torchsvs.fitting.tuning.self_tune`).
        fit_options: keyword arguments of the fit.
        checkpoint: load the estimator's parameters from this file (``--save`` output or a
            Lightning checkpoint of :class:`~torchsvs.training.EstimatorModule`).
        save: save the settings and the (fitted) parameters here.
        covariance: also write the covariance of every estimate.
        whole: read the whole file at once (True), stream it (False) or decide by rows (None).
        block_rows: rows per block when streaming.
        max_cells: padded steps per estimator call.
        dtype: of the computation (positions are centred per track, so float32 keeps its
            resolution on large coordinates).
        precision: of the estimates written: ``"float32"``, ``"float64"`` or ``"auto"``
            (float32 where it keeps positions to a hundredth of the noise:
            :func:`~torchsvs.track_plan.output_precision`).
        progress: show a progress bar (tqdm, on stderr).
        log: where to print what was read off the data (default: nowhere).
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`: one
            more estimator pass on probed measurements) and warn where it is not clearly
            below the measurements'.
        summary: write the run's summary as JSON next to the output (:func:`summary_path`).
        blocks: ``source``'s blocks, already being read (a :class:`~torchsvs.datasets.reading.
            ReadAhead` started before torch was imported: ``torchsvs track``), which then set
            the columns, ``whole`` and ``block_rows``, and which the run closes; else read here
            with ``columns``, ``whole`` and ``block_rows``.
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    say = log or (lambda _: None)
    check_output(target, "target", inputs=(source,), force=True)  # never over the input
    phases = dict.fromkeys(("reading", "settings", "estimating", "writing", "waiting"), 0.0)
    run: TrackRun | None = None
    plan: TrackPlan | None = None
    estimator: nn.Module | None = None
    bar: Any = None
    # Reading the next blocks and writing the last one run beside the estimating, each in a
    # thread of its own (Arrow's reading and writing, numpy and torch release the GIL).
    if blocks is None:
        blocks = ReadAhead(source, columns, block_rows=block_rows, whole=whole)
    elif blocks.path != Path(source):
        raise ValueError(
            f"blocks: expected the reading of {str(source)!r}, got {str(blocks.path)!r}"
        )
    with blocks, EstimateWriter(target, source) as writer:
        behind = WriteBehind(writer, phases)
        try:
            sample: list[TrackBlock] = []  # the first blocks, held until the plan is made
            tracks = int((fit_options or {}).get("tracks", SAMPLE_TRACKS))
            for block in chain(blocks, [None]):
                if plan is None:
                    if block is not None:
                        sample.append(block)
                        if not sample_taken(sample, tracks):
                            continue
                    tick = time.perf_counter()
                    plan = plan_tracks(
                        joined(sample),
                        settings,
                        fit=fit,
                        fit_options=fit_options,
                        checkpoint=checkpoint,
                        save=save,
                        dtype=dtype,
                        precision=precision,
                        log=say,
                    )
                    phases["settings"] += time.perf_counter() - tick
                    if Path(source).is_dir():  # (a dataset: say on what)
                        say(sample_line(sample, source, block is None))
                    estimator = plan.estimator()
                    run = new_run(plan, accuracy)
                    # disable=None: no bar where stderr is not a terminal (it would stay in a log)
                    bar = tqdm(
                        desc="tracks",
                        unit=" tracks",
                        disable=None if progress else True,
                        leave=False,
                    )
                elif block is not None:
                    sample = [block]
                for part in sample:
                    assert run is not None and estimator is not None
                    found = estimate_block(
                        part,
                        plan,
                        estimator,
                        run,
                        covariance=covariance,
                        accuracy=accuracy,
                        max_cells=max_cells,
                        progress=bar,
                    )
                    behind.write(found, part, plan.precision)
                sample = []
        finally:  # the last write done before the writer closes; the bar cleared before
            # anything else is printed (an error's too)
            behind.close()
            if bar is not None:
                bar.close()
    assert run is not None, "track_blocks yields a block or raises"
    phases["reading"] = blocks.reading
    phases["waiting"] += blocks.waiting
    phases["estimating"] = run.estimate_seconds
    run.phases = phases
    run.check()
    run.seconds = time.perf_counter() - start
    if summary:
        write_summary(run, summary_path(target))
    return run


def sample_line(sample: list[TrackBlock], dataset: str | Path, everything: bool) -> str:
    """What a ``dataset``'s settings were read off: its first files (:func:`~torchsvs.datasets.
    tables.sample_taken`), named, with their tracks; ``everything``: all its files."""
    files = [os.path.relpath(b.path, dataset) for b in sample if b.path is not None]
    files = list(dict.fromkeys(files))
    tracks = sum(b.steps.num_tracks for b in sample)
    if everything:
        held = f"{len(files)} of the dataset's files with rows"
        return f"settings: read off all {held} ({tracks:,} tracks)"
    named = files[0] if len(files) == 1 else f"{files[0]} to {files[-1]}"
    which = "first file" if len(files) == 1 else f"first {len(files)} files"
    return (
        f"settings: read off the dataset's {which}, {named} ({tracks:,} tracks), and kept "
        "for the others"
    )


class WriteBehind:
    """Writes each block's estimates with ``writer`` in a thread of its own while the caller
    goes on: one block in writing at a time, in order; ``phases["writing"]`` adds the writes'
    seconds, ``phases["waiting"]`` the seconds the caller waited for one to end. A write's
    error is raised at the next :meth:`write` or at :meth:`close`."""

    def __init__(self, writer: EstimateWriter, phases: dict[str, float]) -> None:
        self.writer, self.phases = writer, phases
        self.pool = ThreadPoolExecutor(1)
        self.pending: Future[None] | None = None

    def write(self, found: Any, block: Any, precision: str) -> None:
        self.wait()
        self.pending = self.pool.submit(self._write, found, block, precision)

    def _write(self, found: Any, block: Any, precision: str) -> None:
        tick = time.perf_counter()
        self.writer.write(found.table(block, precision), block.path)
        self.phases["writing"] += time.perf_counter() - tick

    def wait(self) -> None:
        if self.pending is None:
            return
        tick = time.perf_counter()
        pending, self.pending = self.pending, None
        try:
            pending.result()
        finally:
            self.phases["waiting"] += time.perf_counter() - tick

    def close(self) -> None:
        """Waits for the last write (raising its error) and ends the thread."""
        try:
            self.wait()
        finally:
            self.pool.shutdown()

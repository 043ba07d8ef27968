"""``torchsvs track --processes N``: a track file estimated by ``N`` processes, as Lightning's
``Trainer.predict`` with ``strategy="ddp"`` on CPU (gloo).

The launching process (rank 0) reads the whole file (:class:`TrackFileDataModule`) in a
thread while Lightning starts the other processes, and sends them the tracks' steps; every
process cuts them into the groups of tracks that :func:`~torchsvs.tracking.track_file`
estimates one call at a time, and Lightning's distributed sampler gives each process a disjoint
share of the groups.
Rank 0 reads the settings off the data (and fits, if asked) once and broadcasts them with the
estimator's parameters (:class:`TrackPredictor`), so every process estimates with the same
ones; the estimates are gathered on rank 0 (:class:`GatherEstimates`), which writes the file.
Each group is estimated exactly as in one process, so the output is the same file, byte for
byte.
"""

from __future__ import annotations

import os
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.strategies import DDPStrategy
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from torchsvs.accuracy import RiskTotals
from torchsvs.datasets import Columns, EstimateWriter, TrackBlock, TrackSteps, track_blocks
from torchsvs.datasets.breaks import split_at_breaks
from torchsvs.estimating import estimate_group
from torchsvs.recipes import Settings
from torchsvs.step_estimates import GroupBatch, StepEstimates, group_batch
from torchsvs.track_plan import TrackPlan, plan_tracks
from torchsvs.track_run import BlockEstimates, TrackRun, summary_path, write_summary
from torchsvs.training.quiet import quiet_lightning, tool_trainer


class TrackGroups(Dataset["GroupBatch | None"]):
    """The groups of a block's tracks (:meth:`~torchsvs.datasets.TrackSteps.batches`), each
    item one estimator call: the group padded and centred (:func:`~torchsvs.step_estimates.
    group_batch`), ``z [B, T, m]`` in ``dtype``. Items past the last group (up to ``length``)
    are ``None``: Lightning's distributed sampler needs an item for every process."""

    def __init__(
        self,
        steps: TrackSteps,
        groups: Sequence[np.ndarray],
        dtype: torch.dtype,
        length: int = 0,
    ) -> None:
        self.steps, self.groups, self.dtype = steps, list(groups), dtype
        self.length = max(length, len(self.groups))

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> GroupBatch | None:
        if index >= len(self.groups):
            return None
        return group_batch(self.steps, self.groups[index], index, self.dtype)


class TrackFileDataModule(L.LightningDataModule):
    """A track file for ``Trainer.predict``, as :class:`TrackGroups`.

    Only rank 0 reads the file: :meth:`start_reading` reads it in a thread while the trainer
    launches the other processes (their interpreters and imports take seconds), and
    :meth:`setup` sends them the tracks' steps (without the raw rows, which only rank 0 writes
    back). Two processes reading the same file at once on two cores took longer than one.

    Args:
        source: a ``.csv`` or ``.parquet`` track file, read whole (any row order).
        columns: its column names.
        block_rows: rows per block while reading.
        max_cells: padded steps (``B × T``) per group, as in
            :func:`~torchsvs.tracking.track_file`.

    Its batches are float64 (padded and centred as :func:`~torchsvs.step_estimates.group_batch`
    does); :class:`TrackPredictor` casts them to its estimator's dtype, as ``track_file`` casts
    once (the IMM runs in float64 whatever dtype is asked for, and a float32 batch cast up
    would have lost the digits).
    """

    def __init__(
        self,
        source: str | Path,
        columns: Columns | None = None,
        block_rows: int = 1 << 18,
        max_cells: int = 1 << 19,
    ) -> None:
        super().__init__()
        self.source, self.columns = source, columns
        self.block_rows, self.max_cells = block_rows, max_cells
        self.block: TrackBlock | None = None  #: the rows read (rank 0 only)
        self._steps: TrackSteps | None = None
        self.groups: list[np.ndarray] = []
        self._reader: threading.Thread | None = None
        self._read_error: BaseException | None = None
        self.read_seconds = 0.0  #: setup's wait for the file (and the steps' transfer)
        self.setup_time = 0.0  #: perf_counter() when setup began (every process had started)

    @property
    def steps(self) -> TrackSteps:
        assert self._steps is not None, "setup() reads the file"
        return self._steps

    def _read(self) -> None:
        try:
            self.block = next(
                track_blocks(self.source, self.columns, block_rows=self.block_rows, whole=True)
            )
        except BaseException as error:  # raised again in setup, in the caller's thread
            self._read_error = error

    def start_reading(self) -> None:
        """Reads the file in a thread, to overlap the launch of the other processes."""
        if self._reader is None and self.block is None:
            self._reader = threading.Thread(target=self._read, name="read-tracks", daemon=True)
            self._reader.start()

    def setup(self, stage: str | None = None) -> None:
        if self._steps is not None:
            return
        tick = self.setup_time = time.perf_counter()
        trainer = self.trainer
        rank = trainer.global_rank if trainer is not None else 0
        processes = trainer.world_size if trainer is not None else 1
        steps: TrackSteps | None = None
        if rank == 0:
            if self._reader is None:
                self._read()
            else:
                self._reader.join()
            if self._read_error is not None:
                raise self._read_error
            assert self.block is not None
            # (split before the plan reads it: its q is read off the parts)
            self.block.steps = split_at_breaks(self.block.steps)[0]
            steps = self.block.steps
        if processes > 1:
            assert trainer is not None
            # Raw-row bookkeeping stays on rank 0, the one process that writes.
            sent = None if steps is None else replace(steps, row_step=steps.row_step[:0])
            received = trainer.strategy.broadcast(sent, src=0)
            steps = steps if rank == 0 else received
        assert steps is not None
        self._steps = steps
        self.groups = list(steps.batches(self.max_cells))
        self.read_seconds = time.perf_counter() - tick

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        return batch  # CPU only; the batch holds arrays and a dataclass Lightning need not copy

    def predict_dataloader(self) -> DataLoader:
        processes = self.trainer.world_size if self.trainer is not None else 1
        groups = TrackGroups(self.steps, self.groups, torch.float64, processes)
        # Batches of one group, so the sampler (and the prediction writer) see group indices.
        return DataLoader(groups, batch_size=1, collate_fn=_only)


def _only(items: list[GroupBatch | None]) -> GroupBatch | None:
    return items[0]


class TrackPredictor(L.LightningModule):
    """The estimator of ``torchsvs track`` for ``Trainer.predict`` on a
    :class:`TrackFileDataModule`; :meth:`predict_step` gives a group's
    :class:`~torchsvs.step_estimates.StepEstimates`.

    The estimator is built in :meth:`setup`, once the file is read: rank 0 completes the
    settings from the data, fits (``fit``: :func:`~torchsvs.training.self_tune`, on rank 0
    only, while the other processes wait), loads ``checkpoint`` and saves to ``save``
    (:func:`~torchsvs.track_plan.prepare_estimator`), then broadcasts the settings and the
    estimator's parameters to the other processes.

    Args:
        settings: the estimator and whatever of its settings are known.
        fit, fit_options, checkpoint, save, covariance: as for
            :func:`~torchsvs.tracking.track_file`.
        dtype: of the computation.
        log: where rank 0 prints what was read off the data (default: nowhere).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        fit: bool = False,
        fit_options: dict[str, Any] | None = None,
        checkpoint: str | Path | None = None,
        save: str | Path | None = None,
        covariance: bool = False,
        dtype: torch.dtype = torch.float32,
        precision: str = "auto",
        log: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__()
        self.precision = precision
        self.plan: TrackPlan | None = None
        self.settings, self.fit, self.fit_options = settings, fit, fit_options
        self.checkpoint, self.save, self.covariance = checkpoint, save, covariance
        self.compute_dtype, self.say = dtype, log
        self.estimator: nn.Module | None = None
        self.meas_std: Tensor | None = None
        self.fit_summary: Any = None
        self.prepare_seconds = 0.0

    def setup(self, stage: str) -> None:
        if self.estimator is not None:
            return
        tick = time.perf_counter()
        data = self.trainer.datamodule  # type: ignore[attr-defined]
        plan: TrackPlan | None = None
        if self.trainer.global_rank == 0:
            assert data.block is not None
            plan = plan_tracks(
                data.block,
                self.settings,
                fit=self.fit,
                fit_options=self.fit_options,
                checkpoint=self.checkpoint,
                save=self.save,
                dtype=self.compute_dtype,
                precision=self.precision,
                log=self.say,
            )
        plan = self.trainer.strategy.broadcast(plan, src=0)
        assert plan is not None
        self.plan, self.settings, self.fit_summary = plan, plan.settings, plan.fit
        self.estimator, self.meas_std = plan.estimator(), plan.meas_std
        self.compute_dtype = plan.dtype
        self.prepare_seconds = time.perf_counter() - tick

    def predict_step(self, batch: GroupBatch | None, batch_idx: int) -> StepEstimates | None:
        """The group's estimates (``None`` for a filler item of :class:`TrackGroups`)."""
        assert self.estimator is not None and self.meas_std is not None
        if batch is None:
            return None
        if batch.tracks.z.dtype != self.compute_dtype:
            batch = batch._replace(tracks=batch.tracks.to(self.compute_dtype))
        return estimate_group(
            self.estimator, batch, self.meas_std, self.covariance, settings=self.settings
        )


class GatherEstimates(BasePredictionWriter):
    """Collects every process's :class:`~torchsvs.step_estimates.StepEstimates` on rank 0 at the
    end of the predict epoch (``parts``; empty on the other ranks), and times the epoch."""

    def __init__(self) -> None:
        super().__init__(write_interval="epoch")
        self.parts: list[StepEstimates] = []
        self.estimate_seconds = self.estimate_cpu_seconds = self.gather_seconds = 0.0
        self._tick = self._cpu = 0.0

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._tick, self._cpu = time.perf_counter(), time.process_time()

    def write_on_epoch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        predictions: Sequence[Any],
        batch_indices: Sequence[Any],
    ) -> None:
        tick = time.perf_counter()
        self.estimate_seconds = tick - self._tick
        self.estimate_cpu_seconds = time.process_time() - self._cpu
        local = [part for part in predictions if part is not None]
        if trainer.world_size == 1:
            self.parts = local
            return
        rank0 = trainer.global_rank == 0
        shares: list[Any] | None = [None] * trainer.world_size if rank0 else None
        torch.distributed.gather_object(local, shares, dst=0)
        self.parts = [part for share in shares for part in share] if shares is not None else []
        self.gather_seconds = time.perf_counter() - tick


def check_processes(processes: Any) -> int:
    """``processes`` if it is an integer ``>= 1``, else ``ValueError`` naming it."""
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes: expected an integer >= 1, got {processes!r}")
    return processes


def predict_file(
    source: str | Path,
    target: str | Path,
    settings: Settings,
    *,
    processes: int = 2,
    columns: Columns | None = None,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    covariance: bool = False,
    block_rows: int = 1 << 18,
    max_cells: int = 1 << 19,
    dtype: torch.dtype = torch.float32,
    precision: str = "auto",
    threads: int = 1,
    log: Callable[[str], None] | None = None,
) -> TrackRun | None:
    """:func:`~torchsvs.tracking.track_file` (the whole file read at once) in ``processes``
    processes: ``Trainer.predict`` with ``strategy="ddp"`` (gloo) on CPU.

    Lightning's DDP launcher starts processes 1 to ``N - 1`` by running the command that started
    this one again (``sys.argv``), so call this from a script or the ``torchsvs track`` command
    (every process must reach the call with the same arguments), not from an interactive
    session; ``torchsvs track`` starts them itself, before its imports
    (:class:`torchsvs.track_command.OtherRanks`), and Lightning joins them. ``fit`` runs once,
    on rank 0, inside the run; the other processes receive the fitted parameters. Rank 0 holds
    the whole file in memory, the others its tracks' steps.

    Args:
        processes: processes to run (1: the same path in this process alone).
        threads: intra-op threads of each process (``OMP_NUM_THREADS`` of the launched ones).
        others: as for :func:`~torchsvs.tracking.track_file`.

    Returns:
        What the run did, on rank 0; ``None`` on the other processes.
    """
    check_processes(processes)
    start = time.perf_counter()
    before = torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")
    # The launched processes inherit the environment; Lightning leaves a set value alone.
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    data = TrackFileDataModule(source, columns, block_rows, max_cells)
    if os.environ.get("LOCAL_RANK", "0") == "0":  # the launching process (Lightning's ranks
        data.start_reading()  # 1..N-1 run this function again with LOCAL_RANK set)
    module = TrackPredictor(
        settings,
        fit=fit,
        fit_options=fit_options,
        checkpoint=checkpoint,
        save=save,
        covariance=covariance,
        dtype=dtype,
        precision=precision,
        log=log,
    )
    gather = GatherEstimates()
    strategy: Any = DDPStrategy(process_group_backend="gloo") if processes > 1 else "auto"
    try:
        # No banners about GPUs and process groups, no tips, on every run.
        with quiet_lightning():
            trainer = tool_trainer(
                devices=processes,
                strategy=strategy,
                inference_mode=False,  # the estimators run under no_grad, as in one process
                callbacks=[gather],
            )
            with warnings.catch_warnings():
                # Loading workers would copy the file into more processes; the groups are ready.
                warnings.filterwarnings("ignore", ".*does not have many workers.*")
                # Lightning 2.6 on torch 2.13, at every run: not the user's to act on.
                warnings.filterwarnings("ignore", ".*LeafSpec.*", FutureWarning)
                trainer.predict(module, datamodule=data, return_predictions=True)
    finally:
        torch.set_num_threads(before[0])
        if before[1] is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = before[1]
    if trainer.global_rank != 0:
        return None
    tick = time.perf_counter()
    steps = data.steps
    found = BlockEstimates.empty(steps, covariance, module.settings.screens)
    for part in gather.parts:
        if part.position not in found.groups:  # a sampler that evens out ranks repeats groups
            found.add(part)
    if len(found.groups) != len(data.groups):
        raise RuntimeError(f"estimated {len(found.groups)} of {len(data.groups)} groups of tracks")
    run = TrackRun(settings=module.settings, fit=module.fit_summary)
    if found.risk:
        assert module.settings.meas_var is not None
        run.risk = RiskTotals(len(module.settings.meas_var))
    run.add_block(found, steps)
    run.check()
    assert data.block is not None
    with EstimateWriter(target) as writer:
        assert module.plan is not None
        writer.write(found.table(data.block, module.plan.precision))
    run.estimate_seconds = gather.estimate_seconds
    run.estimate_cpu_seconds = gather.estimate_cpu_seconds
    run.seconds = time.perf_counter() - start
    run.phases = {
        "start-up": data.setup_time - start,  # the trainer, the processes, the process group
        "reading": data.read_seconds,
        "settings": module.prepare_seconds,
        "estimating": gather.estimate_seconds,
        "gathering": gather.gather_seconds,
        "writing": time.perf_counter() - tick,
    }
    write_summary(run, summary_path(target))
    return run

"""Tracking recorded files: the loop behind ``torchsvs track``.

A file is read in blocks of complete tracks (:func:`~torchsvs.datasets.track_blocks`); the
estimator is built from the settings (:mod:`torchsvs.recipes`) with what the user left open read
off the first block (:func:`torchsvs.fitting.defaults.complete_settings`), tuned on the file
itself with ``--fit`` (:func:`torchsvs.fitting.tuning.self_tune`) or chosen among several with
``auto`` (:mod:`torchsvs.selection`); each block is then estimated group by group
(:func:`torchsvs.estimating.estimate_group`) and written. Every run estimates its own error
without truth (:mod:`torchsvs.accuracy`) and warns where it is not clearly below the
measurements' (:class:`~torchsvs.track_run.TrackRun`, which also holds the run's summary).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from torchsvs.accuracy import RiskTotals
from torchsvs.datasets import (
    Columns,
    EstimateWriter,
    RecordedTracks,
    TrackSteps,
    track_blocks,
)
from torchsvs.datasets.paths import check_output
from torchsvs.datasets.reading import reads_whole
from torchsvs.estimating import (
    estimate_group,
    group_batch,
    lowered_noise,
)
from torchsvs.fitting.defaults import (
    complete_settings,
    screened,
    settings_note,
    with_q_curve,
)
from torchsvs.fitting.tuning import self_tune
from torchsvs.recipes import (
    Settings,
    compute_dtype,
    make_estimator,
    make_model,
)
from torchsvs.selection import choose_estimator
from torchsvs.track_run import BlockEstimates, TrackRun, short, summary_path, write_summary

Item = TypeVar("Item")


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
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    accuracy: bool = True,
    summary: bool = True,
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
        progress: show a progress bar (tqdm, on stderr).
        log: where to print what was read off the data (default: nowhere).
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`: one
            more estimator pass on probed measurements) and warn where it is not clearly
            below the measurements'.
        summary: write the run's summary as JSON next to the output (:func:`summary_path`).
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    say = log or (lambda _: None)
    check_output(target, "target", inputs=(source,), force=True)  # never over the input
    if whole is None:
        whole = reads_whole(source)
    run = TrackRun()
    run.phases = dict.fromkeys(("reading", "settings", "estimating", "writing"), 0.0)
    estimator: nn.Module | None = None
    bar: Any = None
    try:
        with EstimateWriter(target, source) as writer:
            blocks = track_blocks(source, columns, block_rows=block_rows, whole=whole)
            for block in timed(blocks, run.phases, "reading"):
                steps = block.steps
                if estimator is None:
                    tick = time.perf_counter()
                    estimator, settings, run.fit = prepare_estimator(
                        steps, settings, fit, fit_options, checkpoint, save, say
                    )
                    run.phases["settings"] += time.perf_counter() - tick
                    dtype = compute_dtype(settings.estimator, dtype)
                    estimator = estimator.to(dtype)
                    run.settings = settings
                    assert settings.meas_var is not None
                    run.risk = RiskTotals(len(settings.meas_var)) if accuracy else None
                    # disable=None: no bar where stderr is not a terminal (it would stay in a log)
                    bar = tqdm(
                        desc="tracks",
                        unit=" tracks",
                        disable=None if progress else True,
                        leave=False,
                    )
                assert run.settings is not None and run.settings.meas_var is not None
                meas_std = torch.tensor(run.settings.meas_var, dtype=dtype).sqrt()
                found = BlockEstimates.empty(steps, covariance, run.settings.screens)
                tick, cpu = time.perf_counter(), time.process_time()
                for position, group in enumerate(steps.batches(max_cells)):
                    batch = group_batch(steps, group, position, dtype)
                    found.add(
                        estimate_group(
                            estimator, batch, meas_std, covariance, accuracy, run.settings
                        )
                    )
                    bar.update(len(group))
                run.estimate_seconds += time.perf_counter() - tick
                run.estimate_cpu_seconds += time.process_time() - cpu
                run.add_block(found, steps)
                tick = time.perf_counter()
                writer.write(found.table(block), block.path)
                run.phases["writing"] += time.perf_counter() - tick
    finally:  # the bar cleared before anything else is printed, an error too
        if bar is not None:
            bar.close()
    run.phases["estimating"] = run.estimate_seconds
    run.report.notes = +run.report.notes
    run.check()
    run.seconds = time.perf_counter() - start
    if summary:
        write_summary(run, summary_path(target))
    return run


def timed(items: Iterable[Item], phases: dict[str, float], name: str) -> Iterator[Item]:
    """The items of ``items``, adding the seconds spent producing each to ``phases[name]``."""
    source = iter(items)
    while True:
        tick = time.perf_counter()
        item = next(source, None)
        phases[name] = phases.get(name, 0.0) + time.perf_counter() - tick
        if item is None:
            return
        yield item


def _sample_tracks(steps: Any, fit_options: dict[str, Any] | None) -> np.ndarray:
    """The tracks the settings are read off (and a fit runs on): up to ``tracks`` of the first
    block, spread evenly over it."""
    limit = int((fit_options or {}).get("tracks", 2000))
    count = steps.num_tracks
    if count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(np.int64))


def prepare_estimator(
    steps: TrackSteps,
    settings: Settings,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    say: Callable[[str], None] | None = None,
) -> tuple[nn.Module, Settings, Any]:
    """The estimator of ``torchsvs track`` for a block's tracks: the settings left open read
    off them (:func:`~torchsvs.fitting.defaults.complete_settings`, on up to
    ``fit_options["tracks"]`` tracks spread over the block, their isolated outliers set aside
    first: :func:`~torchsvs.fitting.defaults.screened`), then fitted, loaded from
    ``checkpoint``, saved to ``save``, as asked. Where the noise was read off the data and the
    Kalman smoother on the sample is not clearly below the measurements, all of it is done
    again at the low end of that reading (:func:`~torchsvs.estimating.lowered_noise`), and
    ``say`` hears only the reading kept.

    Returns:
        The estimator (float64), the settings it was built from, and the fit's summary (or
        ``None``).
    """
    given = settings
    say = say or (lambda _: None)
    sample = steps.pad(_sample_tracks(steps, fit_options), torch.float64)
    open_q = settings.q is None
    options = dict(fit_options or {})
    options.pop("tracks", None)
    # What the first reading says is printed only if the run keeps it: a lowered noise reads
    # (and fits) again, and its own lines replace these (each line once, none of settings
    # the run does not use).
    first: list[str] = []
    settings, clean, summary = _settled(settings, sample, fit, options, first.append)
    low = lowered_noise(settings, clean) if checkpoint is None else None
    if low is None:
        for line in first:
            say(line)
    else:
        assert settings.meas_var is not None
        read = [v**0.5 for v in settings.meas_var]
        say(
            f"noise: at {short(read)} m (read off the data) the Kalman smoother's error is not "
            f"clearly below the measurements'; running at the low end of that reading, "
            f"{short([v**0.5 for v in low])} m"
        )
        lowered = replace(
            given,
            meas_var=low,
            noise="data",
            meas_std_se=settings.meas_std_se,
            noise_spread=settings.noise_spread,
            noise_lowered_from=read,
        )
        settings, clean, summary = _settled(lowered, sample, fit, options, say)
    if open_q and checkpoint is None:
        settings = with_q_curve(settings, clean)
    estimator = make_estimator(settings, make_model(settings))
    if checkpoint is not None:
        load_parameters(estimator, checkpoint)
    if save is not None:
        torch.save({"settings": asdict(settings), "state_dict": estimator.state_dict()}, save)
    return estimator, settings, summary


def _settled(
    settings: Settings,
    sample: RecordedTracks,
    fit: bool,
    options: dict[str, Any],
    say: Callable[[str], None],
) -> tuple[Settings, RecordedTracks, Any]:
    """The settings left open read off ``sample`` without its isolated outliers, then fitted
    or chosen (``--estimator auto``); the screened sample, and the fit's summary."""
    settings, sample, _ = screened(settings, sample)
    if settings.estimator != "auto":
        settings = complete_settings(settings, sample)
        say(settings_note(settings))
    summary: Any = None
    if settings.estimator == "auto":
        auto_options = dict(options)
        auto_options.pop("known_noise", None)
        summary = choose_estimator(settings, sample, say=say, **auto_options)
        settings = summary.settings
        say(summary.summary())
    elif fit:
        summary = self_tune(settings, sample, **options)
        settings = summary.settings
        say(summary.summary())
    return settings, sample, summary


def load_parameters(estimator: nn.Module, path: str | Path) -> None:
    """Loads an estimator's parameters from a ``--save`` file or a Lightning checkpoint of
    :class:`~torchsvs.training.EstimatorModule` (keys ``estimator.*``)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "state_dict" not in state:
        raise ValueError(f"checkpoint: {str(path)!r} holds no state_dict")
    weights = state["state_dict"]
    prefix = "estimator."
    if any(k.startswith(prefix) for k in weights):
        weights = {k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)}
    try:
        estimator.load_state_dict(weights)
    except RuntimeError as err:
        raise ValueError(
            f"checkpoint: {str(path)!r} does not fit the estimator built from these settings "
            f"({type(estimator).__name__}): {err}"
        ) from err


def saved_settings(path: str | Path) -> Settings:
    """The settings stored by ``--save``."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "settings" not in state:
        raise ValueError(f"checkpoint: {str(path)!r} holds no torchsvs settings (a --save file)")
    return Settings(**state["settings"])

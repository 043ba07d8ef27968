"""Recorded tracks as padded batches ``[B, T, m]`` (:class:`RecordedTracks`), made from the
steps of a file's rows (:func:`padded_batch`), with priors from their first measurements
(:func:`with_prior`); a whole file as one batch (:func:`read_tracks`).

Tracks of different lengths are padded at the end with missing measurements, which no estimator
reads as information (a padded step is a pure prediction after the track's last step, so
filters and the smoothers' backward passes leave the real steps unchanged).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets.priors import two_point_prior
from torchsvs.datasets.reading import TrackBlock, track_blocks
from torchsvs.datasets.rows import Columns, RowReport
from torchsvs.datasets.steps import TrackSteps, as_rows, median_interval


@dataclass
class RecordedTracks:
    """A padded batch of recorded tracks: what an estimator needs, and what maps results back.

    The estimators' prior is one step before ``z[:, 0]``; ``dt[:, 0]`` is the interval from it
    (the track's median interval). ``x0, P0`` are in the layout of
    :class:`~torchsvs.models.ConstantVelocity` (position, velocity per axis), or ``None`` until
    :func:`~torchsvs.datasets.two_point_prior` fills them.
    """

    z: Tensor  #: [B, T, m] measurements, NaN where missing or padded
    dt: Tensor  #: [B, T] interval ending at each step (s)
    time: Tensor  #: [B, T] float64 seconds of each step as read, NaN where padded
    lengths: Tensor  #: [B] int64 real steps of each track
    ids: list[str]  #: track ids
    x0: Tensor | None = None  #: [B, 2m] prior mean
    P0: Tensor | None = None  #: [B, 2m, 2m] prior covariance
    extra: dict[str, Tensor] = field(default_factory=dict)  #: [B, T] extra columns
    truth: Tensor | None = None  #: [B, T, k] true states, where a dataset has them
    steps: Tensor | None = None  #: [B, T] int64 flat step index (for writing back), -1 padded
    never_observed: Tensor | None = None  #: [B, m] bool: axes a track never observes
    source: Any = None  #: where the tracks were read (:class:`TrackSource`)

    def __len__(self) -> int:
        return self.z.shape[0]

    @property
    def mask(self) -> Tensor:
        """``[B, T]`` True at the real (not padded) steps."""
        return torch.arange(self.z.shape[1])[None, :] < self.lengths[:, None]

    def subset(self, index: Sequence[int] | Tensor) -> RecordedTracks:
        """The tracks at ``index`` (trimmed to their longest length)."""
        idx = torch.as_tensor(index, dtype=torch.int64)
        T = int(self.lengths[idx].max()) if len(idx) else 1

        def pick(x: Tensor | None) -> Tensor | None:
            if x is None:
                return None
            x = x[idx]
            return x[:, :T] if x.ndim >= 2 and x.shape[1] == self.z.shape[1] else x

        return replace(
            self,
            z=pick(self.z),  # type: ignore[arg-type]
            dt=pick(self.dt),  # type: ignore[arg-type]
            time=pick(self.time),  # type: ignore[arg-type]
            lengths=self.lengths[idx],
            ids=[self.ids[i] for i in idx.tolist()],
            x0=None if self.x0 is None else self.x0[idx],
            P0=None if self.P0 is None else self.P0[idx],
            extra={k: pick(v) for k, v in self.extra.items()},  # type: ignore[misc]
            truth=pick(self.truth),
            steps=pick(self.steps),
            never_observed=None if self.never_observed is None else self.never_observed[idx],
            source=None
            if self.source is None
            else replace(self.source, tracks=self.source.tracks[idx.numpy()]),
        )

    def to(self, dtype: torch.dtype) -> RecordedTracks:
        """The floating tensors (but ``time``) in ``dtype``."""

        def cast(x: Tensor | None) -> Tensor | None:
            return None if x is None else x.to(dtype)

        return replace(
            self,
            z=self.z.to(dtype),
            dt=self.dt.to(dtype),
            x0=cast(self.x0),
            P0=cast(self.P0),
            extra={k: v.to(dtype) for k, v in self.extra.items()},
            truth=cast(self.truth),
        )


def padded_batch(
    steps: TrackSteps, tracks: Sequence[int] | np.ndarray, dtype: torch.dtype = torch.float64
) -> RecordedTracks:
    """The tracks ``tracks`` of ``steps`` as one padded batch (without priors)."""
    index = np.asarray(tracks, dtype=np.int64)
    lengths = steps.length[index]
    T = int(lengths.max(initial=1))
    # flat[b, t]: flat step index, or -1 past the end of track b
    offsets = np.arange(T)[None, :]
    flat = steps.start[index][:, None] + offsets
    if not bool((lengths == T).all()):  # (tracks of one length, a group's usual case: none)
        flat = np.where(offsets < lengths[:, None], flat, -1)
    pad = np.flatnonzero(flat < 0)  # the padded cells of [B × T]
    # (np.take, and the padding set by index: several times faster than indexing the rows of
    # a 2-D array and choosing by a mask)
    inside = np.maximum(flat, 0) if len(pad) else flat
    z = np.take(steps.position, inside, axis=0)
    as_rows(z.reshape(-1, z.shape[-1]))[pad] = as_rows(np.full((1, z.shape[-1]), np.nan))
    time = np.take(steps.time, inside)
    extra = {k: np.take(v, inside) for k, v in steps.extra.items()}
    for values in (time, *extra.values()):
        values.reshape(-1)[pad] = np.nan
    dt = np.diff(time, axis=1)
    first = median_interval(dt)
    dt = np.concatenate([first[:, None], dt], axis=1)
    dt = np.where(np.isfinite(dt), dt, first[:, None])  # padding continues the usual pace

    def tensor(a: np.ndarray, kind: torch.dtype = dtype) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(kind)

    return RecordedTracks(
        z=tensor(z),
        dt=tensor(dt),
        time=tensor(time, torch.float64),
        lengths=torch.from_numpy(lengths.copy()),
        ids=[steps.ids[i] for i in index],
        extra={k: tensor(v) for k, v in extra.items()},
        steps=torch.from_numpy(flat),
    )


def windows(tracks: RecordedTracks, length: int, burn_in: int = 0) -> tuple[RecordedTracks, Tensor]:
    """Cuts tracks into windows of ``length`` steps for fitting, and says which steps to score.

    Consecutive windows of a track overlap by ``burn_in`` steps; a window's first ``burn_in``
    steps (where an estimator started from the window's own prior is still settling) are not
    scored, except in a track's first window, so every real step is scored exactly once.
    ``dt[:, 0]`` of a window is the interval from the step before it. Priors are not carried
    over (fill them with :func:`~torchsvs.datasets.with_prior`); ids become ``"id@start"``.

    Returns:
        The windows (a :class:`RecordedTracks` of ``N`` tracks, ``T = length``) and
        ``scored [N, T]``.
    """
    if length < 2 or not 0 <= burn_in < length:
        raise ValueError(
            "length, burn_in: expected length >= 2 and 0 <= burn_in < length, "
            f"got {length}, {burn_in}"
        )
    stride = length - burn_in
    rows, starts = [], []
    for b, L in enumerate(tracks.lengths.tolist()):
        start = 0
        while True:
            rows.append(b)
            starts.append(start)
            if start + length >= L:
                break
            start += stride
    index = torch.tensor(rows, dtype=torch.int64)
    first = torch.tensor(starts, dtype=torch.int64)
    T = tracks.z.shape[1]
    offsets = first[:, None] + torch.arange(length)[None, :]  # [N, length]
    inside = offsets < tracks.lengths[index][:, None]
    at = offsets.clamp_max(T - 1)

    def take(x: Tensor) -> Tensor:
        picked = x[index[:, None], at]
        fill = (
            torch.full_like(picked, float("nan"))
            if x.is_floating_point()
            else torch.full_like(picked, -1)
        )
        shape = inside.shape + (1,) * (picked.ndim - 2)
        return torch.where(inside.view(shape), picked, fill)

    dt = tracks.dt[index[:, None], at]
    dt = torch.where(inside, dt, dt[:, :1])  # padding keeps a finite pace
    scored = inside & ((torch.arange(length)[None, :] >= burn_in) | (first[:, None] == 0))
    cut = RecordedTracks(
        z=take(tracks.z),
        dt=dt,
        time=take(tracks.time),
        lengths=inside.sum(dim=1),
        ids=[f"{tracks.ids[b]}@{s}" for b, s in zip(rows, starts, strict=True)],
        extra={k: take(v) for k, v in tracks.extra.items()},
        truth=None if tracks.truth is None else take(tracks.truth),
    )
    return cut, scored


@dataclass
class TrackSource:
    """Where a padded batch came from, to write estimates back row by row."""

    block: TrackBlock
    tracks: np.ndarray  #: [B] the batch's tracks among the block's


def read_tracks(
    path: str | Path,
    columns: Columns | None = None,
    meas_std: float | Sequence[float] | None = None,
    dtype: torch.dtype = torch.float64,
) -> tuple[RecordedTracks, RowReport]:
    """A whole track file as one padded batch with priors from its first measurements.

    Args:
        path: a ``.csv`` or ``.parquet`` file.
        columns: its column names (default ``track_id, time, x, y[, z]``).
        meas_std: measurement noise standard deviation (one number or one per axis) for the
            priors; ``None`` estimates it from the data (:func:`~torchsvs.datasets.estimate_noise`).
        dtype: of the measurement tensors.

    Returns:
        The tracks (``source`` set, for :func:`~torchsvs.datasets.write_estimates`) and the row
        report.
    """
    block = next(track_blocks(path, columns, whole=True))
    everything = np.arange(block.steps.num_tracks)
    tracks = with_prior(padded_batch(block.steps, everything, dtype), meas_std)
    tracks.source = TrackSource(block, everything)
    report = block.steps.report
    report.notes.update(short_track_notes(tracks))
    report.notes = +report.notes
    return tracks, report


def short_track_notes(tracks: RecordedTracks, seen: Tensor | None = None) -> dict[str, int]:
    """How many tracks observe an axis only once, or never (the prior's fix-ups); ``seen``:
    the observations per axis ``[B, m]``, where counted already."""
    if seen is None:
        seen = (~torch.isnan(tracks.z)).sum(dim=1)  # [B, m] observations per axis
    return {
        "tracks_single_point_axis": int((seen == 1).any(dim=-1).sum()),
        "tracks_axis_never_observed": int((seen == 0).any(dim=-1).sum()),
    }


def meas_variance(tracks: RecordedTracks, meas_std: float | Sequence[float] | None) -> Tensor:
    """Measurement variance per axis ``[m]``: from ``meas_std``, or estimated from the data."""
    m = tracks.z.shape[-1]
    if meas_std is None:
        from torchsvs.datasets.noise_estimate import estimate_noise

        return estimate_noise(tracks.z, tracks.dt).meas_var
    std = torch.as_tensor(meas_std, dtype=tracks.z.dtype).reshape(-1)
    if (
        std.numel() not in (1, m)
        or not bool((std > 0).all())
        or not bool(torch.isfinite(std).all())
    ):
        raise ValueError(
            f"meas_std: expected one standard deviation > 0 or one per axis ({m}), "
            f"got {std.tolist()}"
        )
    return std.expand(m).square()


def with_prior(
    tracks: RecordedTracks,
    meas_std: float | Sequence[float] | Tensor | None = None,
    inflation: float | None = None,
) -> RecordedTracks:
    """The tracks with ``x0, P0`` from two-point differencing (:func:`two_point_prior`);
    ``meas_std`` as for :func:`read_tracks`, or a tensor of standard deviations per axis."""
    var = meas_std.square() if isinstance(meas_std, Tensor) else meas_variance(tracks, meas_std)
    kwargs = {} if inflation is None else {"inflation": inflation}
    prior = two_point_prior(tracks.z, tracks.dt, var, **kwargs)
    return replace(tracks, x0=prior.x0, P0=prior.P0, never_observed=prior.never_observed)

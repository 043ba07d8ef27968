"""Recorded tracks as padded batches: rows grouped into steps, steps padded into ``[B, T, m]``.

Rows of one track are sorted by time; rows sharing a time become one step (their observed
values averaged); the interval ending at each step is the time since the step before. Tracks of
different lengths are padded at the end with missing measurements, which no estimator reads as
information (a padded step is a pure prediction after the track's last step, so filters and the
smoothers' backward passes leave the real steps unchanged).
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets.rows import ParsedRows, RowReport


@dataclass
class TrackSteps:
    """Rows grouped into the steps of their tracks, flat over all steps of all tracks.

    Track ``k`` owns steps ``start[k] : start[k] + length[k]``, in time order.
    """

    ids: list[str]  #: [K] the id of each track
    start: np.ndarray  #: [K] int64 first step of each track
    length: np.ndarray  #: [K] int64 steps of each track
    time: np.ndarray  #: [S] float64 seconds of each step
    position: np.ndarray  #: [S, m] float64 mean observed value of each step, NaN if none
    extra: dict[str, np.ndarray]  #: [S] float64 each, mean over the step's rows
    row_step: np.ndarray  #: [R] int64 step of each row read, -1 where set aside
    report: RowReport
    #: [K, 2] latitude, longitude (degrees) of each track's local frame where the file's
    #: positions are WGS 84 (positions are then east, north (m)[, altitude]), else None
    reference: np.ndarray | None = None

    @property
    def num_tracks(self) -> int:
        return len(self.ids)

    def batches(self, max_cells: int = 1 << 22) -> Iterator[np.ndarray]:
        """Track indices in groups of similar length with at most ``max_cells`` padded steps
        (``B × T``) each (a single longer track gets a group of its own): little padding and
        bounded memory whatever the mix of lengths."""
        order = np.argsort(self.length, kind="stable")
        first = 0
        while first < len(order):
            last = first + 1
            # Sorted by length, so the group's width is its last track's length.
            while last < len(order) and (last + 1 - first) * self.length[order[last]] <= max_cells:
                last += 1
            yield np.sort(order[first:last])
            first = last

    def pad(
        self, tracks: Sequence[int] | np.ndarray, dtype: torch.dtype = torch.float64
    ) -> RecordedTracks:
        """The tracks ``tracks`` as one padded batch (without priors)."""
        index = np.asarray(tracks, dtype=np.int64)
        lengths = self.length[index]
        T = int(lengths.max(initial=1))
        # steps[b, t]: flat step index, or -1 past the end of track b
        offsets = np.arange(T)[None, :]
        steps = self.start[index][:, None] + offsets
        if bool((lengths == T).all()):  # tracks of one length (a group's usual case): no padding
            z, time = self.position[steps], self.time[steps]
            extra = {k: v[steps] for k, v in self.extra.items()}
        else:
            steps = np.where(offsets < lengths[:, None], steps, -1)
            valid = steps >= 0
            flat = np.where(valid, steps, 0)
            z = np.where(valid[..., None], self.position[flat], np.nan)
            time = np.where(valid, self.time[flat], np.nan)
            extra = {k: np.where(valid, v[flat], np.nan) for k, v in self.extra.items()}
        dt = np.diff(time, axis=1)
        first = _median_interval(dt)
        dt = np.concatenate([first[:, None], dt], axis=1)
        dt = np.where(np.isfinite(dt), dt, first[:, None])  # padding continues the usual pace

        def tensor(a: np.ndarray, kind: torch.dtype = dtype) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(kind)

        return RecordedTracks(
            z=tensor(z),
            dt=tensor(dt),
            time=tensor(time, torch.float64),
            lengths=torch.from_numpy(lengths.copy()),
            ids=[self.ids[i] for i in index],
            extra={k: tensor(v) for k, v in extra.items()},
            steps=torch.from_numpy(steps),
        )


def _median_interval(dt: np.ndarray) -> np.ndarray:
    """Each track's median interval between steps (of an even count, the mean of the middle
    two, as ``np.nanmedian``), ``1.0`` for a track of one step. One sort of the rows, the
    missing last: ``np.nanmedian`` is 3-20× slower on a padded batch."""
    if dt.shape[1] == 0:  # tracks of one step: no interval
        return np.ones(dt.shape[0])
    finite = np.isfinite(dt)
    n = dt.shape[1]
    if bool(finite.all()):  # every interval known: the two middle ones, without a full sort
        middle = np.partition(dt, sorted({(n - 1) // 2, n // 2}), axis=1)
        return (middle[:, (n - 1) // 2] + middle[:, n // 2]) / 2
    n = finite.sum(axis=1)
    ordered = np.sort(np.where(finite, dt, np.inf), axis=1)
    rows = np.arange(len(dt))
    low = ordered[rows, np.maximum(n - 1, 0) // 2]
    high = ordered[rows, n // 2]
    return np.where(n > 0, (low + high) / 2, 1.0)


def group_rows(rows: ParsedRows, contiguous: bool = False) -> TrackSteps:
    """Groups parsed rows into tracks and steps, counting every row's fate (:class:`RowReport`).

    Args:
        rows: one block of parsed rows.
        contiguous: require each track's rows to be contiguous in the block (what streaming a
            file track by track relies on); a track whose rows are split raises ``ValueError``.
    """
    R, m = rows.position.shape
    report = RowReport(total=R)
    code, time = rows.track_code, rows.time
    has_id = code >= 0
    has_time = np.isfinite(time)
    report.set_aside["no_track_id"] += R - _count(has_id)
    report.set_aside["no_time"] += _count(has_id & ~has_time)
    report.notes["non_numeric_value"] += _count(rows.non_numeric)
    if rows.invalid is not None:
        report.notes["invalid_coordinate"] += _count(rows.invalid)
    if contiguous:
        check_contiguous(code, rows.track_ids)

    # Column by column: numpy's reductions along a short last axis are slow.
    missing = [np.isnan(rows.position[:, j]) for j in range(m)]
    some = ~functools.reduce(np.logical_and, missing, np.ones(R, dtype=bool))
    candidate = has_id & has_time
    # A track needs one observed position to start from.
    seen = np.zeros(len(rows.track_ids), dtype=bool)
    seen[code[candidate & some]] = True
    no_position = candidate & ~seen[np.maximum(code, 0)]
    report.set_aside["track_without_position"] += _count(no_position)
    keep = candidate & ~no_position
    everything = bool(keep.all())
    placed = np.arange(R) if everything else np.flatnonzero(keep)

    # Tracks one after the other (codes number ids in order of first appearance), each in
    # time order, as a sorted file has them: grouped without sorting.
    c, t = (code, time) if everything else (code[placed], time[placed])
    same = c[1:] == c[:-1]
    in_order = not (same & (t[1:] < t[:-1])).any() and not (c[1:] < c[:-1]).any()
    if in_order:
        order = placed
    else:
        # Out of order: earlier than the track's previous row in the file.
        by_track = placed[np.argsort(c, kind="stable")]
        earlier = time[by_track][1:] < time[by_track][:-1]
        report.notes["out_of_order"] += _count(
            (code[by_track][1:] == code[by_track][:-1]) & earlier
        )
        order = placed[np.lexsort((t, c))]
        c, t = code[order], time[order]
        same = c[1:] == c[:-1]
    new_step = np.ones(len(order), dtype=bool)
    new_step[1:] = ~same | (t[1:] != t[:-1])
    merged = len(order) - _count(new_step)
    report.notes["duplicate_time"] += merged
    if merged == 0:  # one row per step: each step's mean is its row's value
        S = len(order)
        step_of = np.arange(S)
        # + 0.0: -0.0 becomes 0.0, as the sums below make it
        position = (rows.position if in_order and everything else rows.position[order]) + 0.0
        extra = {}
        for name, values in rows.extra.items():
            v = values[order]
            extra[name] = np.where(np.isfinite(v), v + 0.0, np.nan)
        step_time, step_code = t, c
    else:
        step_of = np.cumsum(new_step) - 1
        S = int(step_of[-1]) + 1 if len(order) else 0
        position = _step_means(step_of, rows.position[order], S)
        extra = {
            name: _step_means(step_of, values[order, None], S, finite=True)[:, 0]
            for name, values in rows.extra.items()
        }
        step_time, step_code = t[new_step], c[new_step]
    new_track = np.ones(S, dtype=bool)
    new_track[1:] = step_code[1:] != step_code[:-1]
    start = np.flatnonzero(new_track)
    length = np.diff(np.append(start, S))
    kept_codes = step_code[start]

    if everything and in_order:  # every row placed, in file order
        row_step = step_of
    else:
        row_step = np.full(R, -1, dtype=np.int64)
        row_step[order] = step_of
    partial = some & functools.reduce(np.logical_or, missing, np.zeros(R, dtype=bool))
    report.measurement = _count(some[placed])
    report.prediction = len(placed) - report.measurement
    report.notes["partial_position"] += _count(partial[placed])
    report.tracks = len(start)
    report.set_aside = +report.set_aside  # drop zero counts
    report.notes = +report.notes
    report.check()
    return TrackSteps(
        ids=[rows.track_ids[k] for k in kept_codes],
        start=start.astype(np.int64),
        length=length.astype(np.int64),
        time=step_time,
        position=position,
        extra=extra,
        row_step=row_step,
        report=report,
        reference=None if rows.reference is None else rows.reference[kept_codes],
    )


def _count(mask: np.ndarray) -> int:
    """How many entries of ``mask`` are true (numpy's fastest count, as a Python int)."""
    return int(np.count_nonzero(mask))


def _step_means(
    step_of: np.ndarray, values: np.ndarray, S: int, finite: bool = False
) -> np.ndarray:
    """``[S, n]`` mean of each step's observed values of ``values [r, n]`` (not NaN; with
    ``finite``, finite), NaN where none is."""
    out = np.empty((S, values.shape[1]))
    for j in range(values.shape[1]):
        ok = np.isfinite(values[:, j]) if finite else ~np.isnan(values[:, j])
        total = np.bincount(step_of, np.where(ok, values[:, j], 0.0), S)
        count = np.bincount(step_of, ok.astype(np.float64), S)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, j] = np.where(count > 0, total / count, np.nan)
    return out


def track_runs(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of rows of one track (rows without an id skipped): the row each run starts at
    and its track code."""
    rows = np.flatnonzero(code >= 0) if (code < 0).any() else np.arange(len(code))
    c = code[rows]
    first = np.flatnonzero(c[1:] != c[:-1]) + 1
    first = np.concatenate([[0], first]) if len(c) else first
    return rows[first], c[first]


def check_contiguous(code: np.ndarray, track_ids: Sequence[str]) -> None:
    """Raises ``ValueError`` naming the first track whose rows are not contiguous."""
    starts, run_codes = track_runs(code)
    if len(run_codes) == len(np.unique(run_codes)):
        return
    _, first = np.unique(run_codes, return_index=True)
    repeated = np.setdiff1d(np.arange(len(run_codes)), first)[0]
    raise ValueError(
        f"track {track_ids[run_codes[repeated]]!r}: its rows are not contiguous (it starts "
        f"again at row {starts[repeated]} of the block after rows of other tracks); streaming "
        "reads a file track by track, so sort it by track id, or read it whole (torchsvs track "
        "--in-memory)"
    )


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
    source: Any = (
        None  #: where the tracks were read (:class:`~torchsvs.datasets.reading.TrackSource`)
    )

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

"""Rows grouped into the steps of their tracks (:class:`TrackSteps`, :func:`group_rows`), flat
over all steps of all tracks: what a block of a track file becomes once read, before any track
is padded into a batch (:func:`torchsvs.datasets.tracks.padded_batch`).

Rows of one track are sorted by time; rows sharing a time become one step (their observed
values averaged); the interval ending at each step is the time since the step before. Reading
needs numpy alone, not torch, so a file can be read while torch is imported (``torchsvs
track``: :class:`~torchsvs.datasets.reading.ReadAhead`).
"""

from __future__ import annotations

import bisect
import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

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

    @property
    def track_of_step(self) -> np.ndarray:
        """``[S]`` int64 the track each step belongs to."""
        return np.repeat(np.arange(self.num_tracks), self.length)

    def batches(self, max_cells: int = 1 << 22) -> Iterator[np.ndarray]:
        """Track indices in groups of similar length with at most ``max_cells`` padded steps
        (``B × T``) each (:func:`length_batches`)."""
        return length_batches(self.length, max_cells)


def join_steps(parts: Sequence[TrackSteps]) -> TrackSteps:
    """The tracks of ``parts`` (blocks of distinct tracks) as one :class:`TrackSteps`, in order:
    each part's steps (and rows) after the previous part's, its counts added."""
    if len(parts) == 1:
        return parts[0]
    report = RowReport()
    for part in parts:
        report.add(part.report)
    shifted = list(zip(parts, np.cumsum([0] + [len(p.time) for p in parts[:-1]]), strict=True))
    references = [p.reference for p in parts if p.reference is not None]
    return TrackSteps(
        ids=[i for p in parts for i in p.ids],
        start=np.concatenate([p.start + s for p, s in shifted]),
        length=np.concatenate([p.length for p in parts]),
        time=np.concatenate([p.time for p in parts]),
        position=np.concatenate([p.position for p in parts]),
        extra={k: np.concatenate([p.extra[k] for p in parts]) for k in parts[0].extra},
        row_step=np.concatenate(
            [np.where(p.row_step >= 0, p.row_step + s, -1) for p, s in shifted]
        ),
        report=report,
        reference=np.concatenate(references) if references else None,
    )


def length_batches(lengths: np.ndarray, max_cells: int) -> Iterator[np.ndarray]:
    """Indices of tracks of ``lengths [B]`` in groups of similar length (each sorted) with at
    most ``max_cells`` padded steps (``B × T``) each (a single longer track gets a group of its
    own): little padding and bounded memory whatever the mix of lengths."""
    order = np.argsort(lengths, kind="stable")
    width = lengths[order].tolist()
    first = 0
    while first < len(order):
        # Sorted by length, so the group's width is its last track's length and its cells
        # (tracks × width) grow with each track taken: the first track that would overflow
        # ends the group (found by bisection; the group takes at least one track).
        last = (
            bisect.bisect_right(
                range(first + 1, len(order)),
                max_cells,
                key=lambda k: (k + 1 - first) * width[k],
            )
            + first
            + 1
        )
        yield np.sort(order[first:last])
        first = last


def as_rows(a: np.ndarray) -> np.ndarray:
    """``a [N, ...]`` (C-contiguous) as ``[N]`` items of one row each, a view: numpy indexes a
    1-D array of items several times faster than the rows of a 2-D one (a group's placing and
    padding set rows by index)."""
    row = a.itemsize * int(np.prod(a.shape[1:], dtype=np.int64))
    if not a.flags.c_contiguous or a.ndim < 2 or row == 0:
        raise ValueError(f"a: expected a C-contiguous array [N, ...] of rows, got {a.shape}")
    return a.reshape(len(a), row // a.itemsize).view(np.dtype((np.void, row))).reshape(len(a))


def median_interval(dt: np.ndarray) -> np.ndarray:
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
    if rows.time_unlike is None:
        report.set_aside["no_time"] += _count(has_id & ~has_time)
    else:
        unlike = rows.time_unlike
        report.set_aside["time_unlike_its_track"] += _count(has_id & unlike)
        report.set_aside["no_time"] += _count(has_id & ~has_time & ~unlike)
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

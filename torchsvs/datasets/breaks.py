"""Breaks in a track: one report where the track jumps to another object and stays there (two
tracks' ids swapped, a track handed to the wrong target), split into two tracks.

No motion model follows a jump of 30 noise levels between two reports that each side's path
agrees on: a smoother spreads it over the reports around it, and the file's process noise,
read off every track, rises to follow it. Two such swaps among 80 tracks at 2 s (σ 10 m, jumps
of 300-2,000 m) took the file's ``q`` from 0.16 to 1,381 and the 76 clean tracks from 4.5 to
7.8 m; the swapped track came out 3 times its measurements' error.

A break before report ``i`` is read off each report's miss off the line through the two
reports before it (``left``) and off the line through the two after it (``right``): a step
``J`` in the path makes ``left`` at report ``i`` and ``right`` at report ``i - 1`` about ``J``,
while report ``i`` lies on the line after it and report ``i - 1`` on the line before it
(:data:`STRAY_SHARE`). An isolated outlier misses both lines, a turn both a little over a few
reports, and lines through reports at any intervals keep to irregular times (two tracks'
swapped ids join reports 0.1 s apart). A break is where both misses are :data:`BREAK_LEVEL`
times the typical ``left`` miss around it (the mean over the reports 3 to :data:`REACH` away: the
step's own do not count). White noise reaches that level once in e^100 reports.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from torchsvs.datasets.rows import RowReport
from torchsvs.datasets.steps import TrackSteps

#: A break's misses over the typical miss around it (3.1 σ under white noise alone).
BREAK_LEVEL = 12.0
#: At a break, the first report after it lies on the line of the two after it, and the last
#: before on the line of the two before, within this share of the jump.
STRAY_SHARE = 0.25
#: A line through two reports is carried at most this many times their interval beyond them.
REACH_RATIO = 2.0
#: A break is between reports at most this many times the mean interval around it apart (a
#: gap of minutes is motion unseen: 7 of 20 airliners at irregular 1-10 s reports broke there).
GAP_FACTOR = 2.0
#: The typical miss around a break is the mean over the reports 3 to this many away on either
#: side, of its track (a track of fewer than ``2 REACH + 1`` reports has no break).
REACH = 10


def break_steps(steps: TrackSteps) -> np.ndarray:
    """``[b]`` int64 the flat steps at which a track jumps to another path (module docstring),
    each the first step of the track's part after the break."""
    position = steps.position
    seen = np.isfinite(position).all(1)
    track = steps.track_of_step
    at = np.flatnonzero(seen)
    n = len(at)
    if n < 7:
        return np.zeros(0, dtype=np.int64)
    p, t, k = position[at], steps.time[at], track[at]
    dt = np.diff(t)
    same = np.append((k[1:] == k[:-1]) & (dt > 0), False)  # [n] report x and x + 1 one track
    gap = np.where(same[:-1], dt, 1.0)
    # each report's miss off the line of the two before it (left) and the two after (right)
    left = np.full(n, np.inf)
    right = np.full(n, np.inf)
    # (a line through two reports much closer in time than the one it reaches misses by their
    # noise times the ratio: not judged, NaN; jittered times put 40 breaks in 144,000 reports)
    forward, backward = gap[1:] / gap[:-1], gap[:-1] / gap[1:]
    ahead = p[1:-1] + (p[1:-1] - p[:-2]) * forward[:, None]  # at 2 .. n - 1
    left[2:] = np.where(forward <= REACH_RATIO, np.sqrt(((p[2:] - ahead) ** 2).sum(1)), np.nan)
    back = p[1:-1] - (p[2:] - p[1:-1]) * backward[:, None]  # at 0 .. n - 3
    right[:-2] = np.where(backward <= REACH_RATIO, np.sqrt(((p[:-2] - back) ** 2).sum(1)), np.nan)
    # a break before report i: reports i - 3 .. i + 2 of one track
    run = same[:-5] & same[1:-4] & same[2:-3] & same[3:-2] & same[4:-1]  # i = 3 .. n - 3
    i = np.arange(3, n - 2)
    jump = np.minimum(left[i], right[i - 1])
    step = run & (right[i] < STRAY_SHARE * jump) & (left[i - 1] < STRAY_SHARE * jump)
    i, jump = i[step], jump[step]
    if not len(i):
        return np.zeros(0, dtype=np.int64)
    # the typical miss around: reports 3 .. REACH away on either side, all of the same track
    offsets = np.concatenate([np.arange(-REACH, -2), np.arange(3, REACH + 1)])
    around = i[:, None] + offsets
    inside = (around >= 0).all(1) & (around < n).all(1)
    around = np.clip(around, 0, n - 1)
    inside &= (k[around] == k[i, None]).all(1) & np.isfinite(left[around]).all(1)
    # across a gap the path moves unseen: only a jump between reports as close as usual
    usual = gap[np.clip(around, 0, n - 2)].mean(1)
    found = inside & (jump > BREAK_LEVEL * left[around].mean(1))
    found &= gap[i - 1] <= GAP_FACTOR * usual
    # and beyond the path's own reach between reports (positions rounded to 10 m lie exactly on
    # lines, so that a rounding step of 10 m missed them by 12 times their typical miss)
    moved = np.sqrt((np.diff(p, axis=0) ** 2).sum(1))
    found &= jump > BREAK_LEVEL / 4 * moved[np.clip(around, 0, n - 2)].mean(1)
    return at[i[found]]


def some_tracks(steps: TrackSteps, tracks: np.ndarray) -> TrackSteps:
    """The steps of ``tracks`` (indices, in that order) alone, as steps of their own (no rows:
    what a plan reads its sample off, not what is written)."""
    length = steps.length[tracks]
    start = np.zeros(len(tracks), dtype=np.int64)
    start[1:] = np.cumsum(length)[:-1]
    flat = np.repeat(steps.start[tracks] - start, length) + np.arange(int(length.sum()))
    return TrackSteps(
        ids=[steps.ids[k] for k in tracks.tolist()],
        start=start,
        length=length.astype(np.int64),
        time=steps.time[flat],
        position=steps.position[flat],
        extra={name: values[flat] for name, values in steps.extra.items()},
        row_step=np.zeros(0, dtype=np.int64),
        report=RowReport(),
        reference=None if steps.reference is None else steps.reference[tracks],
    )


def split_at_breaks(steps: TrackSteps) -> tuple[TrackSteps, int]:
    """The tracks split at their breaks (:func:`break_steps`), each part after a break a track
    of its own, named ``ID (part 2)`` and on, the breaks counted in their report's notes
    (``track_breaks``), and how many breaks. The rows keep their steps: the output is written
    with the ids read."""
    breaks = break_steps(steps)
    if not len(breaks):
        return steps, 0
    steps.report.notes["track_breaks"] += len(breaks)
    track = steps.track_of_step
    starts = np.union1d(steps.start[steps.length > 0], breaks)
    owner = track[starts]
    ends = np.append(starts[1:], len(steps.time))
    # a track's parts: its own starts in order (the first keeps the track's id)
    index = np.arange(len(starts))
    first = np.ones(len(starts), dtype=bool)
    first[1:] = owner[1:] != owner[:-1]
    number = index - np.maximum.accumulate(np.where(first, index, 0))
    ids = [
        steps.ids[o] if n == 0 else f"{steps.ids[o]} (part {n + 1})"
        for o, n in zip(owner.tolist(), number.tolist(), strict=True)
    ]
    empty = np.flatnonzero(steps.length == 0)  # (tracks without steps keep their place last)
    split = replace(
        steps,
        ids=ids + [steps.ids[e] for e in empty],
        start=np.concatenate([starts, steps.start[empty]]).astype(np.int64),
        length=np.concatenate([ends - starts, steps.length[empty]]).astype(np.int64),
        reference=None
        if steps.reference is None
        else np.concatenate([steps.reference[owner], steps.reference[empty]]),
    )
    return split, len(breaks)

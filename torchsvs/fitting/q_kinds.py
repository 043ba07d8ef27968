"""Kinds of motion in a file of tracks, so that each track's own ``q`` is shrunk toward tracks
like it rather than toward the whole file's.

A track's SURE curve over the factors on the file's ``q`` is noisy for a short track, so its
choice is shrunk toward a pooled curve (:func:`~torchsvs.fitting.noise.track_q_factors`). Pooled
over the whole file, that curve is the curve of whatever moves most: in a file of ships (2 m/s,
10 s reports), cars and aircraft, the aircraft's risk, in m² and steep at low factors, outweighed
each ship's own, and every ship kept the file's ``q`` (0.93 of the measurements' error against
0.36 in a file of their own). Pooled by kind, each track is shrunk toward its own kind's curve,
and that, where its kind holds few positions, toward the file's.

A track's kind is the pair (its reporting interval, its speed over several reports), each on a
grid of half a decade: what sets the ``q`` a smoother wants, read off positions and times alone
and steady over a short track where its own curve is not. The speed is a chord's over
:data:`CHORD_STEPS` reports, so that the noise of one report's displacement (σ√2 a report)
does not make a parked car look like a moving one.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: Bins per decade of the interval and of the speed.
BINS_PER_DECADE = 2
#: Reports a chord of the speed spans (fewer on a shorter track: its whole length).
CHORD_STEPS = 8
#: The code of a track with no kind (fewer than two positions): shrunk toward the file's curve.
NO_KIND = -(1 << 40)
#: A kind's pooled curve counts ``N / (N + SHRINK_KIND)`` against the file's (``N`` its scored
#: position components in the sample): a kind of two tracks of 100 two-axis positions halfway.
SHRINK_KIND = 400.0
#: The speed bins' floor (units per second): slower is still.
_SLOWEST = 1e-6


def track_kinds(z: Tensor, dt: Tensor) -> Tensor:
    """``[B]`` int64 each track's kind: its interval's and its speed's bins, one code
    (:data:`NO_KIND` for a track with fewer than two positions).

    Read off chords of :data:`CHORD_STEPS` steps (the whole track where it is shorter), one
    starting every :data:`CHORD_STEPS` steps, both ends observed: the interval is the median
    of their time over their steps (a dropout's gap does not move it), the speed their length
    over their time, summed: a tenth of the work of every step's chord (17 ms per 10^6 rows).

    Args:
        z: ``[B, T, m]`` positions, NaN where missing or padded.
        dt: ``[B, T]`` the interval ending at each step.
    """
    B, T, m = z.shape
    seen = ~torch.isnan(z).any(-1)
    time = dt.to(torch.float64).cumsum(1)
    last = (T - 1) - seen.flip(1).to(torch.int8).argmax(1)  # (0 for a track seen nowhere)
    lag = last.clamp(1, CHORD_STEPS)
    starts = torch.arange(0, T, CHORD_STEPS)
    ahead = (starts[None, :] + lag[:, None]).clamp_max(T - 1)
    valid = (starts[None, :] + lag[:, None] <= last[:, None]) & seen[:, starts]
    valid &= seen.gather(1, ahead)
    far = z.gather(1, ahead.unsqueeze(-1).expand(B, len(starts), m)).to(torch.float64)
    chord = (far - z[:, starts].to(torch.float64)).nan_to_num(0.0).square().sum(-1).sqrt()
    elapsed = time.gather(1, ahead) - time[:, starts]
    valid &= elapsed > 0
    interval = torch.where(valid, elapsed / lag[:, None], math.nan).nanmedian(1).values
    speed = torch.where(valid, chord, 0.0).sum(1) / torch.where(valid, elapsed, 0.0).sum(1)
    kinds = _bin(interval.nan_to_num(1.0)) * (1 << 20)
    kinds = kinds + _bin(speed.nan_to_num(0.0).clamp_min(_SLOWEST))
    return torch.where(valid.any(1), kinds, torch.full_like(kinds, NO_KIND))


def _bin(x: Tensor) -> Tensor:
    return (BINS_PER_DECADE * torch.log10(x.clamp_min(1e-300))).round().to(torch.int64)


def kind_table(risk: Tensor, counts: Tensor, kinds: Tensor) -> list[list[float]] | None:
    """Each kind's pooled curve: rows ``[code, components, *mean SURE per component]`` (one per
    factor of ``risk [F, B]``), or None where the tracks are of one kind (the file's curve is
    theirs)."""
    known = (kinds != NO_KIND) & (counts > 0)
    codes = kinds[known].unique()
    if len(codes) < 2:
        return None
    rows = []
    for code in codes.tolist():
        member = known & (kinds == code)
        n = float(counts[member].sum())
        curve = (risk[:, member].sum(1) / n).tolist()
        rows.append([float(code), n, *curve])
    return rows


def kind_targets(
    kinds: Tensor | None, file_curve: Tensor, table: list[list[float]] | None
) -> Tensor:
    """``[F, B]`` the curve each track is shrunk toward: its kind's (``table``:
    :func:`kind_table`), itself shrunk toward the file's by :data:`SHRINK_KIND`; the file's
    ``[F]`` for a track whose kind the table lacks (or with no table).

    A kind's curve is shrunk toward the file's in shape, not in value: each curve over its
    least, mixed in logs, at the kind's level. The kinds' risks lie orders of magnitude apart
    (aircraft at a ship's ``q``: 10⁴ times their least, the ships' own 24 m²), so that any
    share of the file's values, as they are, decided a ship's choice."""
    F = len(file_curve)
    if kinds is None or not table:
        return file_curve.unsqueeze(1)
    targets = file_curve.unsqueeze(1).repeat(1, len(kinds))
    for row in table:
        member = kinds == int(row[0])
        if not bool(member.any()):
            continue
        curve = torch.tensor(row[2 : 2 + F], dtype=file_curve.dtype)
        weight = row[1] / (row[1] + SHRINK_KIND)
        if float(curve.min()) > 0.0 and float(file_curve.min()) > 0.0:
            shape = weight * (curve / curve.min()).log()
            shape += (1.0 - weight) * (file_curve / file_curve.min()).log()
            target = curve.min() * shape.exp()
        else:  # (a SURE at or below 0, of a few positions: mixed as it is)
            target = weight * curve + (1.0 - weight) * file_curve
        targets[:, member] = target.unsqueeze(1)
    return targets

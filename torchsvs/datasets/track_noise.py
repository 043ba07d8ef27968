"""Each track's measurement noise read off its own positions, every track in one batched fit
(:func:`read_track_noise`), and shrunk towards the file's by how much the tracks differ
(:func:`shrunk_ratios`, empirical Bayes): for files whose tracks come from sensors of different
quality and carry no column of their accuracy (``--noise-col``); and how much the file's tracks
differ in their noise, read off a few of them each alone (:func:`noise_spread`).

The fit is :func:`~torchsvs.datasets.estimate_noise`'s noise-alone fit with one parameter per
track, a scale of the file's variance per axis: the same divided differences, the same
trimming at :data:`~torchsvs.datasets.noise_estimate.CUTOFF` and the same steps set aside
beside a residual beyond :data:`~torchsvs.datasets.noise_estimate.MANEUVER` standard
deviations, started from the median of each track's highest-order residuals. On the
recorded-tracks benchmark's sets of mixed noise (each track's σ from a third to three times the
file's) it read each track within 1-6% (standard deviation of the log) of ``estimate_noise`` on
that track alone, at a fraction of the cost (5,000 rows: 0.03 s against 0.8 s for a loop).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.datasets.differences import ORDERS, difference_residuals
from torchsvs.datasets.noise_estimate import (
    CHI2_MEDIAN,
    CUTOFF,
    MANEUVER,
    _spans,
    _touching,
    estimate_noise,
    truncated_second_moment,
)
from torchsvs.kernels import track_noise as compiled_noise

#: The standard error of a track's ``log σ`` is about this over the root of its kept residuals
#: (orders 2-4, every axis). Measured on 2,000 tracks of white noise on straight paths each, of
#: 20-400 points at regular and irregular times: 1.89-2.13.
SE_SCALE = 2.0
#: Scoring iterations of the fit (each moves a track's scale to the mean of its kept
#: residuals' ``u²/(κ r)``): on 2,000 walkers of mixed noise the readings after 4 were within
#: 3e-5 of those after 8 in the mean of ``log σ`` (0.025 at most, half a track's standard error),
#: where a residual at the cutoff flips in and out; each costs about a tenth of the reading.
ITERATIONS = 4


class TrackNoise(NamedTuple):
    """Each track's noise read off its own positions (:func:`read_track_noise`)."""

    #: [B] float64 ``log σ_b − log σ`` of each track's noise over the file's (half the log of its
    #: variance's ratio); NaN where the track has too few positions to read
    log_ratio: Tensor
    se: Tensor  #: [B] float64 its standard error (:data:`SE_SCALE`); NaN where not read


#: The last readings, by the positions they were read off (the run's plan reads one sample's
#: tracks for each noise class's search of ``q``, the screens and the checks): at most
#: :data:`KEPT_READINGS`, each with weak references to its positions and intervals.
_READ: dict[
    int, tuple[weakref.ref[Tensor], weakref.ref[Tensor], tuple[float, ...], int, TrackNoise]
] = {}
KEPT_READINGS = 4
#: :func:`read_track_noise` reads the tracks of at most this many padded steps at a time.
CHUNK_STEPS = 200_000


def read_track_noise(z: Tensor, dt: Tensor, meas_var: Sequence[float]) -> TrackNoise:
    """Each track's noise variance as a multiple of the file's ``meas_var [m]`` per axis, read
    off its own divided differences (``z [B, T, m]`` NaN where missing, ``dt [B, T]``)."""
    m = z.shape[-1]
    if len(meas_var) != m or not all(v > 0 for v in meas_var):
        raise ValueError(f"meas_var: expected {m} variances > 0, got {list(meas_var)}")
    key = tuple(float(v) for v in meas_var)
    found = _READ.get(id(z))
    if found is not None:
        positions, intervals, of, version, read = found
        if positions() is z and intervals() is dt and of == key and version == z._version:
            return read
    read = _read(z, dt, meas_var)
    for gone in [k for k, v in _READ.items() if v[0]() is None]:
        del _READ[gone]
    while len(_READ) >= KEPT_READINGS:
        del _READ[next(iter(_READ))]
    _READ[id(z)] = (weakref.ref(z), weakref.ref(dt), key, z._version, read)
    return read


def _read(z: Tensor, dt: Tensor, meas_var: Sequence[float]) -> TrackNoise:
    """:func:`read_track_noise` on checked arguments, :data:`CHUNK_STEPS` padded steps of tracks
    at a time (the residuals' indices and the fit's temporaries take some 150 bytes a step)."""
    per = max(1, CHUNK_STEPS // max(1, z.shape[1]))
    if z.shape[0] <= per:
        return _read_chunk(z, dt, meas_var)
    parts = [
        _read_chunk(z[k : k + per], dt[k : k + per], meas_var) for k in range(0, z.shape[0], per)
    ]
    return TrackNoise(*(torch.cat(field) for field in zip(*parts, strict=True)))


def _read_chunk(z: Tensor, dt: Tensor, meas_var: Sequence[float]) -> TrackNoise:
    """:func:`_read` on one chunk of tracks: compiled (:mod:`torchsvs.kernels.track_noise`,
    the same to the bit), else the tensors' fit below."""
    z, dt = z.double(), dt.double()
    compiled = _read_compiled(z, dt, meas_var)
    if compiled is not None:
        return compiled
    B = z.shape[0]
    res = difference_residuals(z, dt, ORDERS)
    nan = torch.full((B,), math.nan, dtype=torch.float64)
    if res.u.numel() == 0:
        return TrackNoise(nan, nan.clone())
    r = torch.as_tensor(list(meas_var), dtype=torch.float64)[res.axis]
    u2 = res.u.square()
    y = u2 / truncated_second_moment(CUTOFF)
    spans = _spans(res)
    top = res.order == res.order.max()
    scale = _medians(u2[top] / r[top], res.track[top], B) / CHI2_MEDIAN
    scale = torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))
    count = torch.zeros(B, dtype=torch.float64)
    for _ in range(ITERATIONS):
        v = scale[res.track] * r
        far = (u2 > MANEUVER**2 * v).unsqueeze(0)
        kept = (u2 <= CUTOFF**2 * v) & ~_touching(spans, far)[0]
        count = _sums(kept.double(), res.track, B)
        ratio = _sums(kept * y / r, res.track, B) / count
        scale = torch.where(torch.isfinite(ratio) & (ratio > 0), ratio, scale)
    read = count > 0
    log_ratio = torch.where(read, 0.5 * scale.log(), nan)
    se = torch.where(read, SE_SCALE / count.clamp_min(1.0).sqrt(), nan)
    return TrackNoise(log_ratio, se)


def _read_compiled(z: Tensor, dt: Tensor, meas_var: Sequence[float]) -> TrackNoise | None:
    """:func:`_read_chunk` compiled; None where it cannot say what the tensors' fit says (the
    loops unavailable, or no stencil of the highest order with enough positions finite)."""
    B, T, _ = z.shape
    nan = torch.full((B,), math.nan, dtype=torch.float64)
    observed = torch.isfinite(z).sum(1)  # [B, m]
    present = [k for k in ORDERS if k < T and bool((observed > k).any())]
    if not present:
        return TrackNoise(nan, nan.clone())
    t = torch.cumsum(dt, dim=1)  # (difference_residuals' times)
    found = compiled_noise.read(
        z, t, meas_var, ORDERS, max(present), truncated_second_moment(CUTOFF), CHI2_MEDIAN,
        CUTOFF, MANEUVER, ITERATIONS,
    )  # fmt: skip
    if found is None or int(found.top_count.sum()) == 0:
        return None
    read = found.kept > 0
    log_ratio = torch.where(read, 0.5 * found.scale.log(), nan)
    se = torch.where(read, SE_SCALE / found.kept.clamp_min(1.0).sqrt(), nan)
    return TrackNoise(log_ratio, se)


def spread_of(read: TrackNoise) -> tuple[float, float] | None:
    """``(μ, τ)``: the weighted mean of the tracks' ``log σ`` ratios and their between-track
    standard deviation beyond their own standard errors
    (:func:`between_spread`, as
    :func:`~torchsvs.datasets.noise_spread`); None where fewer than 4 tracks were read."""
    ok = torch.isfinite(read.log_ratio) & torch.isfinite(read.se) & (read.se > 0)
    if int(ok.sum()) < 4:
        return None
    mean, tau = between_spread(read.log_ratio[ok], read.se[ok].square().reciprocal())
    return mean, tau or 0.0


def shrunk_ratios(read: TrackNoise, mean: float, tau: float) -> Tensor:
    """``[B]`` float64 each track's noise variance over the file's: its reading pulled towards
    ``mean`` by the share of its error in its spread, ``log σ_b = μ + τ²/(τ² + se_b²) (ℓ_b − μ)``
    (the posterior mean of a normal prior ``N(μ, τ²)``), ``exp(2 μ)`` where not read."""
    keep = tau**2 / (tau**2 + read.se.square())
    log_sigma = mean + keep * (read.log_ratio - mean)
    log_sigma = torch.where(torch.isfinite(log_sigma), log_sigma, torch.full_like(log_sigma, mean))
    return (2.0 * log_sigma).exp()


def _sums(x: Tensor, group: Tensor, B: int) -> Tensor:
    return torch.zeros(B, dtype=torch.float64).index_add_(0, group, x.double())


def _medians(x: Tensor, group: Tensor, B: int) -> Tensor:
    """``[B]`` the (lower) median of ``x`` in each group, NaN for a group without any."""
    out = torch.full((B,), math.nan, dtype=torch.float64)
    if x.numel() == 0:
        return out
    order = torch.argsort(x, stable=True)
    order = order[torch.argsort(group[order], stable=True)]  # by group, each in rising order
    values = x[order].double()
    counts = torch.bincount(group, minlength=B)
    starts = counts.cumsum(0) - counts
    some = counts > 0
    out[some] = values[(starts + (counts - 1) // 2)[some]]
    return out


#: :func:`noise_spread` reads at most this many tracks, of at least this many observed points.
SPREAD_TRACKS = 48
SPREAD_POINTS = 40


def noise_spread(
    z: Tensor, dt: Tensor, max_tracks: int = SPREAD_TRACKS, min_points: int = SPREAD_POINTS
) -> float | None:
    r"""How much the noise read off each track alone differs between tracks, beyond what their
    own standard errors explain: the between-track standard deviation :math:`\tau` of
    :math:`\log\hat\sigma` (a relative spread; DerSimonian & Laird's moment estimator over every
    track and axis, each axis about its own level, weights :math:`1/se^2` from
    :func:`estimate_noise`'s jackknife). Pooled about one level, axes of different noise read
    as tracks that differ: a drone's 5, 5 and 10 m read 33%.

    One sensor and a model that follows the targets give :math:`\tau \approx 0`. A large
    :math:`\tau` says that one noise level does not fit the file: the tracks' sensors differ, or
    some tracks hold motion the model does not follow at their report rate (circling gliders at
    30 s), which :func:`estimate_noise` cannot tell from noise, so the pooled reading can be off
    by about that much. Reads up to ``max_tracks`` tracks of at least ``min_points`` observed
    positions, spread over the batch; None where fewer than 4 qualify.

    References:
        DerSimonian, Laird, "Meta-analysis in clinical trials", Control. Clin. Trials 7(3):
        177-188, 1986. doi:10.1016/0197-2456(86)90046-2
    """
    points = (~z.isnan().any(-1)).sum(1)
    usable = torch.nonzero(points >= min_points).flatten()
    if usable.numel() < 4:
        return None
    if usable.numel() > max_tracks:
        usable = usable[torch.linspace(0, usable.numel() - 1, max_tracks).round().long()]
    logs, weights, axes = [], [], []
    for b in usable.tolist():
        try:
            found = estimate_noise(z[b : b + 1], dt[b : b + 1])
        except ValueError:
            continue
        if found.meas_std_se is None:
            continue
        std = found.meas_var.double().sqrt()
        rel = found.meas_std_se.double() / std  # the standard error of log σ
        ok = torch.isfinite(rel) & (rel > 0) & (std > 0)
        logs.append(std[ok].log())
        weights.append(rel[ok].square().reciprocal())
        axes.append(torch.nonzero(ok).flatten())
    if len(logs) < 4:
        return None
    # (each axis about its own level: a sensor's altitude noise is not a spread between tracks)
    return between_spread(torch.cat(logs), torch.cat(weights), torch.cat(axes))[1]


def between_spread(y: Tensor, w: Tensor, group: Tensor | None = None) -> tuple[float, float | None]:
    """``(μ, τ)`` of values ``y [n]`` with weights ``w [n]`` (their inverse variances): the
    weighted mean and the standard deviation between them beyond their own errors
    (DerSimonian & Laird's moment estimator), ``τ`` None where the weights leave no degree of
    freedom. With ``group [n]`` (int64, ``0..G-1``) each group about its own mean, the
    spread within the groups (``Q`` over ``n − G`` degrees of freedom)."""
    mean = (w * y).sum() / w.sum()
    if group is None:
        Q = float((w * (y - mean).square()).sum())
        scale = float(w.sum() - w.square().sum() / w.sum())
        tau = math.sqrt(max(0.0, (Q - (y.numel() - 1)) / scale)) if scale > 0 else None
        return float(mean), tau
    G = int(group.max()) + 1
    total = torch.zeros(G, dtype=w.dtype).index_add_(0, group, w)
    own = torch.zeros(G, dtype=w.dtype).index_add_(0, group, w * y) / total
    Q = float((w * (y - own[group]).square()).sum())
    squares = torch.zeros(G, dtype=w.dtype).index_add_(0, group, w.square())
    scale = float((total - squares / total).sum())
    free = y.numel() - G
    tau = math.sqrt(max(0.0, (Q - free) / scale)) if scale > 0 and free > 0 else None
    return float(mean), tau


#: :func:`within_spread` reads pieces of this many observed positions (each track of at least
#: two cut into at most :data:`MOST_PIECES` of equal count).
PIECE_POINTS = 80
MOST_PIECES = 8


class WithinSpread(NamedTuple):
    """How the noise read off pieces of the tracks changes within them (:func:`within_spread`)."""

    #: the standard deviation of ``log σ`` between a track's pieces beyond their own standard
    #: errors, pooled over the tracks (each track about its own level)
    tau: float
    #: the pieces' noise variance over the file's, their mean weighted by their positions
    mean_ratio: float
    low: float  #: the quietest tenth of the pieces' ``σ`` over the file's
    high: float  #: the noisiest tenth's


def pieces(
    z: Tensor, dt: Tensor, size: int = PIECE_POINTS, max_tracks: int = SPREAD_TRACKS
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Up to ``max_tracks`` tracks of ``z [B, T, m]`` with at least ``2 size`` observed
    positions (spread over the batch), each cut into ``min(n // size, MOST_PIECES)`` runs of
    steps of equal count of observed positions: ``[P, L, m]`` positions (NaN past a piece's
    end), ``[P, L]`` intervals (1 past its end), ``[P]`` int64 the track of each piece and
    ``[P]`` its observed positions; empty where no track is that long."""
    observed = ~z.isnan().all(-1)
    counts = observed.sum(1)
    usable = torch.nonzero(counts >= 2 * size).flatten()
    if usable.numel() > max_tracks:
        usable = usable[torch.linspace(0, usable.numel() - 1, max_tracks).round().long()]
    spans: list[tuple[int, int, int, int]] = []  # (track, first step, end step, positions)
    for b in usable.tolist():
        steps = torch.nonzero(observed[b]).flatten()
        n = len(steps)
        k = min(n // size, MOST_PIECES)
        cuts = [j * n // k for j in range(k + 1)]
        for j in range(k):
            first, last = int(steps[cuts[j]]), int(steps[cuts[j + 1] - 1])
            spans.append((b, first, last + 1, cuts[j + 1] - cuts[j]))
    m = z.shape[-1]
    length = max((end - first for _, first, end, _ in spans), default=0)
    pz = z.new_full((len(spans), length, m), math.nan)
    pdt = dt.new_ones(len(spans), length)
    for p, (b, first, end, _) in enumerate(spans):
        pz[p, : end - first] = z[b, first:end]
        pdt[p, : end - first] = dt[b, first:end]
    track = torch.tensor([s[0] for s in spans], dtype=torch.int64)
    points = torch.tensor([s[3] for s in spans], dtype=torch.float64)
    return pz, pdt, track, points


def within_spread(
    z: Tensor, dt: Tensor, meas_var: Sequence[float], size: int = PIECE_POINTS
) -> WithinSpread | None:
    r"""How much the noise changes within the tracks: each track's :func:`pieces` read alone
    (:func:`read_track_noise`, as multiples of ``meas_var``) and the spread of their
    :math:`\log\sigma` within the tracks beyond their own standard errors
    (:func:`between_spread`, each track about its own level, so tracks of different sensors
    do not count). A sensor whose noise grows from 5 to 40 m halfway reads :math:`\tau` about
    1.3; white noise on the benchmark's recorded kinds at most 0.15. None where fewer than 4
    pieces are read or no track has two."""
    pz, pdt, track, points = pieces(z, dt, size)
    if len(track) < 4:
        return None
    read = read_track_noise(pz.double(), pdt.double(), meas_var)
    ok = torch.isfinite(read.log_ratio) & torch.isfinite(read.se) & (read.se > 0)
    kept = track[ok]
    if kept.numel() < 4 or not bool((torch.bincount(kept) >= 2).any()):
        return None
    _, group = torch.unique(kept, return_inverse=True)
    logs = read.log_ratio[ok]
    _, tau = between_spread(logs, read.se[ok].square().reciprocal(), group)
    weights = points[ok] / points[ok].sum()
    mean_ratio = float((weights * (2.0 * logs).exp()).sum())
    sigma = logs.exp()
    low, high = (float(torch.quantile(sigma, p)) for p in (0.1, 0.9))
    return WithinSpread(tau or 0.0, mean_ratio, low, high)

r"""An upper bound on the measurement noise from the positions' smallest changes
(:func:`ceiling_reading`): where more of them are small than noise at the reading allows, the
reading is motion between reports.

Anderson's inequality: for noise :math:`n` with a symmetric unimodal density (a Gaussian of any
covariance) and any shift :math:`m` independent of it, :math:`P(n + m \in C) \le P(n \in C)` for
every convex set :math:`C` symmetric about 0. A divided-difference residual of the positions
(:func:`~torchsvs.datasets.differences.difference_residuals`, unit noise gain) is noise plus the
motion's share, so the share of residuals within a ball of radius :math:`\varepsilon` is at
most noise's alone, whatever the motion: motion only spreads them. The residuals' quantiles
thus bound the noise from above, each axis group together (a target standing or going straight
is still on every axis at once, which noise is not). Buses reported every 30-45 s, σ 3-10 m,
read 42-49 m of noise off their stops and corners (:func:`~torchsvs.datasets.estimate_noise`):
a 5 m sensor's smallest 2% of their first differences bound it at 13.7 m.

Noise whose level or shape changes along the tracks (a third to three times the file's from
track to track; a radar's range and cross-range errors, turning with its bearing) puts more
residuals near 0 than one level and shape do; the bound is then read twice, against the file's
reading and with each residual whitened by the noise covariance read about it
(:data:`WINDOW`), and the lower ratio stands (:func:`ceiling_reading`). Noise whose level
changes from row to row reads above it all the same: the check that acts on it asks the
covariance two reports apart too (:func:`~torchsvs.datasets.noise_lags.motion_checked`).

References:
    Anderson, "The integral of a symmetric unimodal function over a symmetric convex set and
    some probability inequalities", Proc. AMS 6(2):170-176, 1955. doi:10.2307/2032333
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.datasets.differences import ORDERS, Residuals, difference_residuals
from torchsvs.datasets.noise_estimate import CUTOFF, truncated_second_moment
from torchsvs.datasets.track_noise import read_track_noise

#: The shares of the residuals (the smallest) whose radius bounds the noise
#: (:func:`ceiling_reading`), each only where at least :data:`LEAST_BELOW` residuals fall below it.
SHARES = (0.005, 0.01, 0.02, 0.05, 0.1)
#: ... so that the quantile is read within some 7% (half the relative error of the count).
LEAST_BELOW = 50
#: Residuals below this (in units of the noise reading) are left out: positions repeated or
#: interpolated, on a line to within rounding (the traffic package's flights, resampled to 5 s:
#: half their second differences), where noise puts 1 in 2 million.
ON_LINE = 1e-3
#: The orders of the residuals tested: the first differences (a target standing still), the
#: second (one going straight at a steady speed).
TEST_ORDERS = (1, 2)


class Ceiling(NamedTuple):
    """The bound of :func:`ceiling_reading`."""

    #: the noise reading over the most noise the smallest residuals allow (above 1: more small
    #: residuals than noise at the reading makes, whatever the motion)
    ratio: float
    order: int  #: the residuals' order at which it was read
    share: float  #: the share of the smallest residuals whose radius it is
    residuals: int  #: the residuals of that order


def ceiling_reading(z: Tensor, dt: Tensor, meas_var: Tensor) -> Ceiling | None:
    """The noise reading ``meas_var [m]`` (per axis of ``z [B, T, m]``, NaN where missing;
    ``dt [B, T]`` the intervals) over the largest noise that the residuals' smallest
    :data:`SHARES` allow (module docstring), the highest over :data:`TEST_ORDERS` and shares:
    read against the file's reading and whitened by the noise covariance about each residual
    (:func:`_local_whitening`), the lower of the two. None where no share has
    :data:`LEAST_BELOW` residuals below it."""
    var = meas_var.to(torch.float64)
    z = z.to(torch.float64)
    z = torch.where(torch.isnan(z).any(-1, keepdim=True), math.nan, z)  # (whole positions)
    B, m = z.shape[0], z.shape[-1]
    res = difference_residuals(z, dt.to(torch.float64), tuple(sorted({*TEST_ORDERS, *ORDERS})))
    if res.u.numel() == 0:
        return None
    u, keys = _stacked(res, var.sqrt(), m)  # [N, m] in units of the reading, [N, 3]
    own = torch.ones(B, dtype=torch.float64)
    if (var > 0).all():
        log_ratio = read_track_noise(z, dt, var.tolist()).log_ratio
        own = torch.where(torch.isfinite(log_ratio), log_ratio.exp(), own)
    tested = torch.isin(keys[:, 1], torch.tensor(TEST_ORDERS))
    whiten = _local_whitening(u, keys, own, tested, z.shape[1])
    u, order = u[tested], keys[tested, 1]
    best: Ceiling | None = None
    for k in TEST_ORDERS:
        # (positions on a line to within a thousandth of the noise are repeated or interpolated
        # reports, not noise: left out)
        sel = (order == k) & torch.isfinite(u).all(1) & (u.norm(dim=1) > ON_LINE)
        found = [
            _ratio(u[sel].norm(dim=1), m),
            _ratio(torch.einsum("nij,nj->ni", whiten[sel], u[sel]).norm(dim=1), m),
        ]
        if found[0] is None or found[1] is None:
            continue
        ratio, share = min(found[0], found[1])
        if best is None or ratio > best.ratio:
            best = Ceiling(ratio, k, share, int(sel.sum()))
    return best


def _stacked(res: Residuals, sigma: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """The residuals of every axis of one stencil side by side, over the reading's σ
    (``[N, m]``), and their stencil's track, order and first step (``[N, 3]``): the axes'
    stencils are alike where every position is observed whole."""
    key = torch.stack([res.track, res.order, res.first], dim=1)
    first = res.axis == 0
    keys = key[first]
    columns = []
    for a in range(m):
        on = res.axis == a
        columns.append(res.u[on] / sigma[a])
    return torch.stack(columns, dim=1), keys


#: Steps either side of a residual whose core residuals read its local noise covariance.
WINDOW = 16


def _local_whitening(u: Tensor, keys: Tensor, own: Tensor, rows: Tensor, T: int) -> Tensor:
    """``[n, m, m]``: the whitening of each residual ``rows`` picks (of ``u [N, m]``, in units
    of the reading) by the covariance of the Gaussian core of the residuals of orders
    :data:`~torchsvs.datasets.differences.ORDERS` within :data:`WINDOW` steps of it in its
    track (``keys [N, 3]``: track, order, first step; the core within
    :data:`~torchsvs.datasets.noise_estimate.CUTOFF` times its track's own level ``own [B]``):
    the noise's level and shape there (a radar's errors turn with its bearing); none (the
    identity) where too few."""
    B, m = own.numel(), u.shape[1]
    track, order, first = keys.unbind(1)
    high = order >= min(ORDERS)
    core = high & (u.abs() <= CUTOFF * own[track].unsqueeze(1)).all(1) & torch.isfinite(u).all(1)
    at = (track * T + first)[core]
    sums = torch.zeros(B * T, m, m, dtype=torch.float64)
    sums.index_add_(0, at, u[core].unsqueeze(2) * u[core].unsqueeze(1))
    counts = torch.zeros(B * T, dtype=torch.float64).index_add_(
        0, at, torch.ones_like(at, dtype=torch.float64)
    )
    pad = torch.nn.functional.pad
    cs = pad(sums.view(B, T, m * m).cumsum(1), (0, 0, 1, 0))
    cc = pad(counts.view(B, T).cumsum(1), (1, 0))
    track, first = track[rows], first[rows]
    lo = (first - WINDOW).clamp(0, T)
    hi = (first + WINDOW + 1).clamp(0, T)
    s = (cs[track, hi] - cs[track, lo]).view(-1, m, m)
    n = cc[track, hi] - cc[track, lo]
    cov = s / n.clamp_min(1).view(-1, 1, 1) / truncated_second_moment(CUTOFF)
    eye = torch.eye(m, dtype=torch.float64)
    factor, info = torch.linalg.cholesky_ex(cov)
    ok = (n >= 10 * m) & (info == 0)
    factor = torch.where(ok.view(-1, 1, 1), factor, eye)
    return torch.linalg.inv(factor)


def _ratio(radius: Tensor, m: int) -> tuple[float, float] | None:
    """The largest ratio over :data:`SHARES` of noise's radius quantile (unit noise per axis,
    ``m`` axes) over the residuals' (all above :data:`ON_LINE`), and its share; None where no
    share has enough below."""
    n = radius.numel()
    shares = [q for q in SHARES if q * n >= LEAST_BELOW]
    if not shares:
        return None
    found = torch.quantile(radius, torch.tensor(shares, dtype=torch.float64))
    ratios = [(_noise_radius(q, m) / float(r), q) for q, r in zip(shares, found, strict=True)]
    return max((ratio for ratio in ratios if math.isfinite(ratio[0])), default=None)


def _noise_radius(q: float, m: int) -> float:
    """The radius within which unit white noise on ``m`` axes falls with probability ``q``: χ's
    quantile with ``m`` degrees of freedom, by bisection of the regularized lower incomplete
    gamma function, :math:`P(m/2, r^2/2) = q`."""
    low, high = 0.0, 1.0
    while _chi_cdf(high, m) < q:
        high *= 2.0
    for _ in range(60):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if _chi_cdf(mid, m) < q else (low, mid)
    return 0.5 * (low + high)


def _chi_cdf(radius: float, m: int) -> float:
    """χ's distribution function with ``m`` degrees of freedom at ``radius``."""
    half = torch.tensor([0.5 * m, 0.5 * radius * radius], dtype=torch.float64)
    return float(torch.special.gammainc(half[0], half[1]))

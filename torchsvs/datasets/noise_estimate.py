"""The measurement noise per axis read off the data before any estimator runs, robust to
maneuvers, with its standard error (:func:`estimate_noise`; how much it differs between tracks
is :func:`torchsvs.datasets.track_noise.noise_spread`). It reads the divided differences of
:mod:`torchsvs.datasets.differences`, on padded batches ``z [B, T, m]`` with per-step intervals
``dt [B, T]``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.datasets.differences import ORDERS, Residuals, difference_residuals
from torchsvs.estimator import threads_for
from torchsvs.kernels import track_noise as compiled_noise


class NoiseFreeError(ValueError):
    """The positions carry no noise to read (:func:`estimate_noise`)."""


class NoiseEstimate(NamedTuple):
    """Noise levels read off the data (:func:`estimate_noise`)."""

    meas_var: Tensor  #: [m] measurement noise variance per axis
    #: power spectral density of a nearly-constant-velocity model (units²/s³) that the
    #: short-scale differences show, maneuvers included: a starting point, not the smoother's
    #: (:func:`torchsvs.fitting.noise.smoother_q`)
    q: float
    triplets: int  #: how many residuals it fitted (difference stencils of every order and axis)
    #: [m] standard error of the measurement noise standard deviation ``meas_var.sqrt()``
    meas_std_se: Tensor | None = None
    #: the share (0 to 1) of the fit with white acceleration in ``meas_var`` (the rest: the fit
    #: of noise alone); 1 where the data show white acceleration and it fits every order
    white_acceleration: float = 0.0
    #: [m] where the covariance of second differences two reports apart contradicts the
    #: reading (:func:`~torchsvs.datasets.noise_lags.motion_checked`): that covariance over what
    #: noise at the reading makes (1 where the reading is noise; ``meas_std_se`` then takes in
    #: the difference) on the axes it contradicts, NaN on the others
    lag_ratio: Tensor | None = None
    #: [m] where more of the positions' smallest changes are small than noise at the reading
    #: allows (:func:`~torchsvs.datasets.noise_ceiling.ceiling_reading`): the most noise
    #: (standard deviation) they allow on the axes they contradict, NaN on the others
    #: (``meas_std_se`` then reaches 0 on those axes)
    noise_ceiling: Tensor | None = None

    @property
    def contradicted(self) -> bool:
        """Whether the reading is contradicted as motion between reports on some axis
        (``lag_ratio`` or ``noise_ceiling``, :func:`~torchsvs.datasets.noise_lags.
        motion_checked`)."""
        return self.lag_ratio is not None or self.noise_ceiling is not None


#: Positions whose differences are at most this share of their magnitude carry no noise to read:
#: float rounding of positions on smooth paths (noise-free, simulated or interpolated data).
NOISE_FREE = 1e-9
#: Residuals beyond this many standard deviations are set aside (:func:`estimate_noise`).
CUTOFF = 3.0
#: A residual beyond this many standard deviations marks a maneuver: every residual that shares
#: a time step with it is set aside too (:func:`estimate_noise`).
MANEUVER = 4.5
#: Median of the χ² distribution with one degree of freedom: ``median(u²) / CHI2_MEDIAN`` is the
#: variance of a Gaussian ``u`` (Rousseeuw & Croux 1993).
CHI2_MEDIAN = 0.4549364231195724
#: Relative change of the variances at which the fit stops (the set of residuals it keeps can
#: flip one residual back and forth: a change far below the standard error).
TOLERANCE = 1e-4
#: Scoring iterations of a fit at most (it converges by a factor of about 10 an iteration).
ITERATIONS = 30
#: Scoring iterations of each jackknife refit, from the full fit.
JACKKNIFE_STEPS = 3
#: Groups of the delete-a-group jackknife behind the standard errors (:func:`estimate_noise`).
JACKKNIFE_GROUPS = 20
#: Steps per block of the jackknife's groups (successive residuals are correlated over a
#: stencil's width, at most five steps).
JACKKNIFE_BLOCK = 16
#: At most this many residuals are fitted (whole blocks drawn at random, seeded): 20,000 rows of
#: two axes, a standard error near 0.5% of σ.
MAX_RESIDUALS = 120_000
#: The white-acceleration fit's share in :func:`estimate_noise` (:func:`_white_weight`) grows
#: from 0 to 1 as σ̂ falls below the noise-alone fit's by these many standard errors of the
#: difference: on tracks that maneuver all the time the two differ by 4 or so on a few hundred
#: rows, with the white fit a quarter low, while tracks of the CV model show 10 and more.
WHITE_LOWER = (5.0, 8.0)
#: ... as its standard error falls from these many times the noise-alone fit's ...
WHITE_COST = (3.0, 2.0)
#: ... and as the worst order's mean of u²/(κ v) comes within these many standard errors of 1.
WHITE_MISFIT = (4.0, 2.0)


#: Where the noise alone fit's lowest order reads a variance this many times the higher orders'
#: and by this many standard errors, :func:`estimate_noise` reads the noise off the higher ones
#: (:func:`_lowest_reads_motion`): 10% in σ.
LOWEST_EXCESS = 1.21
LOWEST_ERRORS = 3.0


#: :func:`estimate_noise` reads the noise off each order's stencils of the least motion term
#: ``b`` alone too, this share of them (:func:`_short_stencils`); where that reads less by more
#: than this many standard errors of the difference (with at least this many residuals an
#: axis), the difference joins the estimate's standard error.
SHORT_SHARE = 0.1
SHORT_ERRORS = 3.0
SHORT_LEAST = 100


def truncated_second_moment(cutoff: float) -> float:
    r""":math:`E[Z^2 \mid |Z| < c] = 1 - 2c\,\varphi(c)/(2\Phi(c) - 1)` of a standard normal."""
    density = math.exp(-0.5 * cutoff**2) / math.sqrt(2 * math.pi)
    return 1.0 - 2.0 * cutoff * density / math.erf(cutoff / math.sqrt(2))


class _Spans(NamedTuple):
    """The residuals' stencils as intervals of one order-preserving numbering of the (track,
    step) pairs that begin or end one: two stencils share a step exactly when their intervals
    overlap, and the numbering is no longer than twice the residuals."""

    first: Tensor  #: [N] int64
    last: Tensor  #: [N] int64
    size: int


def _spans(res: Residuals) -> _Spans:
    stride = int(res.last.max()) + 1 if res.last.numel() else 1
    ends = torch.cat([res.track * stride + res.first, res.track * stride + res.last])
    _, rank = torch.unique(ends, return_inverse=True)
    N = res.u.numel()
    return _Spans(rank[:N], rank[N:], int(rank.max()) + 1 if N else 0)


def _touching(spans: _Spans, far: Tensor) -> Tensor:
    """``[G, N]`` whether a residual's stencil shares a step with a ``far [G, N]`` one's (any
    axis of the same track)."""
    G = far.shape[0]
    if not bool(far.any()):
        return torch.zeros_like(far)
    # +1 where a far stencil starts, -1 after it ends; a running sum marks what it covers.
    edges = torch.zeros(G, spans.size + 1, dtype=torch.float64)
    weight = far.to(torch.float64)
    edges.scatter_add_(1, spans.first.expand(G, -1), weight)
    edges.scatter_add_(1, (spans.last + 1).expand(G, -1), -weight)
    marked = (edges.cumsum(-1) > 0.5).to(torch.float64)
    seen = torch.cat([torch.zeros(G, 1, dtype=torch.float64), marked.cumsum(-1)], -1)
    return (seen[:, spans.last + 1] - seen[:, spans.first]) > 0.5


class _Fit(NamedTuple):
    """Trimmed Gaussian fits: the full fit (``G = 1``) or the jackknife's refits."""

    r: Tensor  #: [G, m]
    q: Tensor  #: [G]
    #: [G, K] mean of u²/(κ v) over each order's kept residuals: 1 where the model fits it
    orders: Tensor
    #: [G] the fit put an axis's variance at or below 0 (white acceleration explaining it all)
    boundary: Tensor


class _Design(NamedTuple):
    """The regression of :func:`_trimmed_fit`: ``u²/κ`` on one column per axis (and ``b`` when
    white acceleration is fitted)."""

    y: Tensor  #: [N] u²/κ
    cols: Tensor  #: [N, p]
    products: Tensor  #: [N, p²] the columns' outer products
    b_scale: float  #: the ``b`` column is ``b / b_scale``
    white: bool
    u2: Tensor  #: [N] u²
    orders: Tensor  #: [K] the orders present, ascending
    order_index: Tensor  #: [N] int64 each residual's order's place among them


def _design(res: Residuals, m: int, white: bool, cutoff: float) -> _Design:
    b_scale = float(res.b.median().clamp_min(1e-300))
    cols = torch.nn.functional.one_hot(res.axis, m).double()
    if white:
        cols = torch.cat([cols, (res.b / b_scale)[:, None]], 1)
    products = (cols.unsqueeze(-1) * cols.unsqueeze(-2)).flatten(1)
    u2 = res.u.square()
    y = u2 / truncated_second_moment(cutoff)
    orders = res.order.unique()
    return _Design(
        y, cols, products, b_scale, white, u2, orders, torch.searchsorted(orders, res.order)
    )


def _kept(
    spans: _Spans, u2: Tensor, v: Tensor, include: Tensor, cutoff: float, maneuver: float
) -> Tensor:
    """``[G, N]`` the residuals (of those in ``include [G, N]``) a fit of variances
    ``v [G, N]`` keeps: within ``cutoff`` standard deviations, and sharing no step with one
    beyond ``maneuver``."""
    far = (u2 > maneuver**2 * v) & include
    return (u2 <= cutoff**2 * v) & include & ~_touching(spans, far)


def _scoring_step(d: _Design, A: Tensor, rhs: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """``(r [G, m], q [G])`` solving the weighted normal equations ``A [G, p, p]``,
    ``rhs [G, p]``, with ``q ≥ 0`` (a negative ``q`` refits the axes alone)."""
    sol = _solve(A, rhs)
    q = torch.zeros(A.shape[0], dtype=torch.float64)
    if d.white:
        negative = sol[:, m] < 0
        if bool(negative.any()):
            sol[negative, :m] = _solve(A[negative, :m, :m], rhs[negative, :m])
        q = (sol[:, m] / d.b_scale).clamp_min(0.0)
    return sol[:, :m], q


def _per_order(res: Residuals, ratio: Tensor, kept: Tensor) -> Tensor:
    """``[G, K]`` the mean of ``ratio [G, N]`` over each order's ``kept`` residuals."""
    return torch.stack(
        [
            (ratio * (res.order == k)).sum(-1) / (kept * (res.order == k)).sum(-1).clamp_min(1)
            for k in res.order.unique()
        ],
        -1,
    )


class _Sums(NamedTuple):
    """A scoring step's sums over the kept residuals of each of ``G`` fits."""

    A: Tensor  #: [G, p, p] the normal equations' matrix, Σ w cols colsᵀ with w = 1/v²
    rhs: Tensor  #: [G, p] their right-hand side, Σ w (u²/κ) cols
    orders: Tensor | None  #: [G, K] the mean of u²/(κ v) over each order's kept residuals


def _sums(
    res: Residuals,
    d: _Design,
    spans: _Spans,
    r: Tensor,
    q: Tensor,
    group: Tensor | None,
    cutoff: float,
    maneuver: float,
    per_order: bool = False,
) -> _Sums:
    """The sums of a scoring step of the fits of ``r [G, m]``, ``q [G]`` on the residuals
    (``group``: each fit ``g`` without the residuals of ``group == g``; None: one fit of all),
    compiled (:func:`~torchsvs.kernels.track_noise.trimmed_sums`, one pass per fit) or by
    these tensor operations; with ``per_order`` also each order's mean of ``u²/(κ v)``."""
    G, p = r.shape[0], d.cols.shape[1]
    found = compiled_noise.trimmed_sums(
        d.u2, d.y, res.b, d.cols, res.axis, spans.first, spans.last, spans.size,
        d.order_index, len(d.orders), group, r, q, cutoff, maneuver,
    )  # fmt: skip
    if found is not None:
        orders = found.ratio / found.kept.clamp_min(1) if per_order else None
        return _Sums(found.A, found.rhs, orders)
    if group is None:
        include = torch.ones(1, res.u.numel(), dtype=torch.bool)
    else:
        include = group != torch.arange(G)[:, None]  # [G, N]
    v = r[:, res.axis] + res.b * q[:, None]
    kept = _kept(spans, d.u2, v, include, cutoff, maneuver)
    w = kept / v.square()
    orders = _per_order(res, kept * d.y / v, kept) if per_order else None
    return _Sums((w @ d.products).view(G, p, p), (w * d.y) @ d.cols, orders)


def _iterate(
    res: Residuals,
    m: int,
    d: _Design,
    start: tuple[Tensor, Tensor],
    group: Tensor | None,
    spans: _Spans,
    cutoff: float,
    maneuver: float,
    iterations: int,
) -> _Fit:
    """Scoring iterations of the trimmed Gaussian fit from ``start`` (``r [G, m], q [G]``;
    ``group``: each fit ``g`` on the residuals outside ``group == g``, None: one fit of all),
    until the variances change by less than :data:`TOLERANCE` or ``iterations`` are done."""
    r, q = start
    G = r.shape[0]
    boundary = torch.zeros(G, dtype=torch.bool)
    for _ in range(iterations):
        sums = _sums(res, d, spans, r, q, group, cutoff, maneuver)
        new_r, new_q = _scoring_step(d, sums.A, sums.rhs, m)
        # An axis with nothing kept stays as it was; one whose variance the fit puts at or below
        # 0 (q explains it all) stays too, and the fit is flagged: not a solution.
        inside = new_r > 0
        boundary = (~inside & (sums.A.diagonal(dim1=-2, dim2=-1)[:, :m] > 0)).any(-1)
        new_r = torch.where(inside, new_r, r)
        change = max(
            float(((new_r - r).abs() / r).amax()),
            float(((new_q - q).abs() * res.b.amax() / r.amin(-1)).amax()),
        )
        r, q = new_r, new_q
        if change < TOLERANCE:
            break
    orders = _sums(res, d, spans, r, q, group, cutoff, maneuver, per_order=True).orders
    assert orders is not None
    return _Fit(r, q, orders, boundary)


def _trimmed_fit(
    res: Residuals, m: int, d: _Design, cutoff: float, maneuver: float, spans: _Spans
) -> _Fit:
    """The trimmed Gaussian fit of :func:`estimate_noise` (white acceleration or noise alone
    by the design ``d``) from the robust start: the median of the highest order's ``u²`` over
    the χ²₁ median, ``q = 0``."""
    u2 = res.u.square()
    top = res.order == res.order.max()
    r = torch.stack([u2[top & (res.axis == j)].median() / CHI2_MEDIAN for j in range(m)])
    r = r.clamp_min(float(u2[u2 > 0].min()))  # (half the residuals exactly 0: quantised)
    start = (r.view(1, m), torch.zeros(1, dtype=torch.float64))
    return _iterate(res, m, d, start, None, spans, cutoff, maneuver, ITERATIONS)


def _jackknife(
    res: Residuals,
    m: int,
    d: _Design,
    fit: _Fit,
    group: Tensor,
    groups: int,
    spans: _Spans,
    cutoff: float,
    maneuver: float,
) -> _Fit:
    """The fit without each of the ``groups`` groups (``group [N]``): :data:`JACKKNIFE_STEPS`
    scoring iterations from the full fit (which converges by a factor of about 10 an
    iteration, so the refits are within a thousandth of their own fixed points)."""
    start = (fit.r.expand(groups, m), fit.q.expand(groups))
    return _iterate(res, m, d, start, group, spans, cutoff, maneuver, JACKKNIFE_STEPS)


def _solve(A: Tensor, rhs: Tensor) -> Tensor:
    """Least-squares solutions of ``A [G, p, p] x = rhs [G, p]`` (a singular ``A``: an axis
    whose residuals were all left out by a jackknife group)."""
    return torch.linalg.lstsq(A, rhs.unsqueeze(-1), driver="gelsd").solution.squeeze(-1)


def _jackknife_se(values: Tensor) -> Tensor:
    """The delete-a-group jackknife's standard error from the ``[G, ...]`` leave-one-out values
    (Efron & Stein 1981)."""
    G = values.shape[0]
    return ((G - 1) / G * (values - values.mean(0)).square().sum(0)).sqrt()


def estimate_noise(
    z: Tensor,
    dt: Tensor,
    orders: tuple[int, ...] = ORDERS,
    cutoff: float = CUTOFF,
    maneuver: float = MANEUVER,
) -> NoiseEstimate:
    r"""Measurement noise per axis from the data, robust to maneuvers, with its standard error.

    Every residual of :func:`difference_residuals` (orders ``orders`` over successive observed
    positions) has variance :math:`r_{axis}` under white measurement noise and a path of
    degree below its order; white acceleration adds :math:`b\,q`, and a maneuver adds to it
    too, the less the higher the order where the path is smooth (a turn's ``k``-th
    differences fall like :math:`(\omega h)^{k-1}`).

    **The fit** is the Gaussian likelihood of the residuals within ``cutoff`` standard
    deviations, by iteratively reweighted least squares of :math:`u^2/\kappa` on the model
    variance with weights :math:`1/v^2` (Fisher scoring for variance components), where
    :math:`\kappa = E[Z^2 \mid |Z| < c]` (:func:`truncated_second_moment`) undoes the truncation
    of the Gaussian core. A residual beyond ``maneuver`` standard deviations (noise alone: 7e-6
    of them) marks a maneuver, and every residual sharing a step with it is set aside: the
    turn's other residuals, smaller but not noise. The fit starts from the median of the highest
    order's :math:`u^2` over the χ²₁ median (a scale of 50% breakdown, Rousseeuw & Croux 1993),
    so the maneuvers never steer it.

    **Noise alone or white acceleration.** The fit is made twice: with :math:`v = r` (noise
    alone) and with :math:`v = r + b\,q` (the white acceleration of
    :class:`~torchsvs.models.ConstantVelocity`; ``r`` and ``q`` are told apart by the orders'
    and the intervals' different ``b``). A maneuver that is smooth but not small at the lower
    orders looks like white acceleration there, and the second fit then extrapolates ``r``
    below the truth (to a quarter of it on tracks that maneuver all the time), while the first
    only errs upwards, by what motion the orders leave (``b q`` under white acceleration: 10%
    on σ where the acceleration moves the target more than the noise in one step). So the
    estimate is the first fit, moved towards the second (in log σ) only as far as the data
    show white acceleration (:func:`_white_weight`): σ clearly below the first fit's in units
    of the paired jackknife's standard error of the difference, a standard error not much
    above the first fit's, and every order fitted (the mean of :math:`u^2/(\kappa v)` over its
    kept residuals within a few standard errors of 1). The share moves continuously, so that
    dropping a few rows never switches fits.

    **The standard errors** come from a delete-a-group jackknife (Efron & Stein 1981) over
    :data:`JACKKNIFE_GROUPS` groups of blocks of :data:`JACKKNIFE_BLOCK` steps (successive
    residuals are correlated over a stencil's width); they are the statistical error, not a
    bound on what a maneuver the fit cannot tell from noise adds. Larger data are fitted on
    :data:`MAX_RESIDUALS` residuals in whole blocks drawn at random (seeded). The jackknife's
    refits are :data:`JACKKNIFE_STEPS` scoring iterations from the full fit (it converges by a
    factor of about ten an iteration). Where the stencils of the least motion read a noise
    surely lower (:func:`_short_stencils`: reports far apart, a target that maneuvers), the
    difference joins the standard error: the maneuver the fit could not tell from noise.

    Args:
        z: measurements ``[B, T, m]``, NaN where missing.
        dt: intervals ``[B, T]``.
        orders: orders of the divided differences.
        cutoff: residuals beyond this many standard deviations of the fit are set aside.
        maneuver: a residual beyond this many standard deviations sets aside its neighbours.

    Returns:
        :class:`NoiseEstimate`; its ``q`` is the white-acceleration fit's (at least a
        thousandth of the noise over a median interval), a starting point: the smoother's
        ``q`` is :func:`torchsvs.fitting.noise.smoother_q`'s.

    References:
        Rousseeuw, Croux, "Alternatives to the median absolute deviation", JASA 88(424):
        1273-1283, 1993. doi:10.1080/01621459.1993.10476408

        Efron, Stein, "The jackknife estimate of variance", Ann. Statist. 9(3):586-596, 1981.
        doi:10.1214/aos/1176345462
    """
    if z.ndim != 3 or dt.shape != z.shape[:2]:
        raise ValueError(
            f"z, dt: expected [B, T, m] and [B, T], got {tuple(z.shape)}, {tuple(dt.shape)}"
        )
    if not orders or any(isinstance(k, bool) or not isinstance(k, int) or k < 2 for k in orders):
        raise ValueError(f"orders: expected integers >= 2, got {orders!r}")
    if not 0 < cutoff <= maneuver:
        raise ValueError(
            f"cutoff, maneuver: expected 0 < cutoff <= maneuver, got {cutoff!r}, {maneuver!r}"
        )
    moving = changing_tracks(z)
    if bool(moving.any()) and not bool(moving.all()):  # a still track's repeats tell no noise
        z, dt = z[moving], dt[moving]
    with threads_for(1, 1):  # a chain of small vector operations: one intra-op thread
        return _estimate(z, dt, orders, cutoff, maneuver)


def changing_tracks(z: Tensor) -> Tensor:
    """``[B]`` bool the tracks of ``z [B, T, m]`` (NaN: missing) whose observed positions are
    not all one and the same: a parked beacon, a moored ship's receiver holding its fix, repeat
    one position exactly, and 40% of tracks doing so made the noise read 1e-13 m for 5 m (the
    Gaussian core of the differences is theirs), so that nothing was smoothed."""
    low = torch.where(torch.isnan(z), math.inf, z).amin(1)
    high = torch.where(torch.isnan(z), -math.inf, z).amax(1)
    return (high > low).any(-1)


def _estimate(
    z: Tensor,
    dt: Tensor,
    orders: tuple[int, ...],
    cutoff: float,
    maneuver: float,
    white_fit: bool = True,
) -> NoiseEstimate:
    """:func:`estimate_noise` on checked arguments (``white_fit``: the estimate may move towards
    the white-acceleration fit; not where the lowest order read a maneuver)."""
    m, T = z.shape[-1], z.shape[1]
    res = difference_residuals(z, dt, orders)
    per_axis = torch.bincount(res.axis[res.order == max(orders)], minlength=m)
    if int(per_axis.min()) < 3:
        raise ValueError(
            "z: too few observed positions in a row to estimate the noise; "
            "give the measurement noise (meas_std) and q explicitly"
        )
    scale = float(z[torch.isfinite(z)].abs().max())
    if float(res.u[res.order == max(orders)].abs().median()) <= NOISE_FREE * scale:
        raise NoiseFreeError(
            "z: most positions lie exactly on smooth paths (noise-free or interpolated data), "
            "there is no measurement noise to read; give it (meas_std) and q explicitly"
        )
    # Blocks of successive steps of a track: the jackknife's units, and the sample's.
    _, block = torch.unique(res.track * (T + 1) + res.first // JACKKNIFE_BLOCK, return_inverse=True)
    blocks = int(block.max()) + 1
    shuffled = torch.randperm(blocks, generator=torch.Generator().manual_seed(0))[block]
    if res.u.numel() > MAX_RESIDUALS:
        keep = shuffled < blocks * MAX_RESIDUALS // res.u.numel()
        res = Residuals(*(field[keep] for field in res))
        shuffled = shuffled[keep]
    groups = min(JACKKNIFE_GROUPS, int(shuffled.unique().numel()))
    group = shuffled % groups
    spans = _spans(res)
    fits: dict[bool, tuple[_Fit, _Fit]] = {}
    for with_q in (False, True):
        d = _design(res, m, with_q, cutoff)
        full = _trimmed_fit(res, m, d, cutoff, maneuver, spans)
        fits[with_q] = full, _jackknife(res, m, d, full, group, groups, spans, cutoff, maneuver)
    (alone, alone_jack), (white, white_jack) = fits[False], fits[True]
    weight = 0.0
    if white_fit and groups >= 2 and not bool(white.boundary.any() or white_jack.boundary.any()):
        weight = _white_weight(alone, alone_jack, white, white_jack)
    if weight == 0.0 and groups >= 2 and _lowest_reads_motion(alone, alone_jack):
        # a maneuver at the lowest order: the higher orders read the noise, alone (a target
        # that maneuvers all the time; with two orders left this does not apply again)
        return _estimate(z, dt, tuple(sorted(orders))[1:], cutoff, maneuver, white_fit=False)
    # log σ of each axis and of each jackknife refit, the two fits blended by the weight
    log_sigma = (1 - weight) * alone.r.log() / 2 + weight * white.r.clamp_min(1e-300).log() / 2
    log_jack = (1 - weight) * alone_jack.r.log() / 2 + weight * white_jack.r.clamp_min(
        1e-300
    ).log() / 2
    sigma = log_sigma.exp()[0]
    se = _jackknife_se(log_jack.exp()) if groups >= 2 else torch.full((m,), math.nan)
    short = _short_stencils(res, m, group, groups, cutoff, maneuver, log_jack.exp())
    if short is not None:  # (the estimate stands, as uncertain as the two differ)
        se = torch.hypot(se, (sigma - short).clamp_min(0.0))
    h = float(dt[:, 1:][torch.isfinite(dt[:, 1:])].median()) if T > 1 else 1.0
    q = max(float(white.q[0]), 1e-3 * float(sigma.square().mean()) / h**3)
    return NoiseEstimate(sigma.square().to(z.dtype), q, int(res.u.numel()), se.to(z.dtype), weight)


def _lowest_reads_motion(fit: _Fit, jack: _Fit) -> bool:
    """Whether the noise-alone fit's lowest order reads a variance (its mean of ``u²/(κ v)``)
    surely and clearly above the higher orders': :data:`LOWEST_EXCESS` times theirs, by
    :data:`LOWEST_ERRORS` standard errors (the jackknife's, paired by group). Noise reads the
    same at every order; a smooth maneuver the lowest order does not annihilate reads there.
    Aircraft at 200 m/s on 5 s reports in standard-rate turns (1 g) with σ 30 m: order 2 read
    50 m and orders 3-7 30 m; the fit of orders 2-4 read 36 m, five of its standard errors off,
    and the error estimate came out at 0.4-0.65 times the truth with no warning. On the
    benchmark's kinds (aircraft on 1-10 s and irregular reports, ships, people, cars, drones, σ
    1-100 m) the orders agree within 4%."""
    if fit.orders.shape[-1] < 3:
        return False
    excess = fit.orders[0, 0].log() - fit.orders[0, 1:].mean().log()
    jack_excess = jack.orders[:, 0].log() - jack.orders[:, 1:].mean(-1).log()
    se = float(_jackknife_se(jack_excess))
    return float(excess) > math.log(LOWEST_EXCESS) and float(excess) > LOWEST_ERRORS * se


def _short_stencils(
    res: Residuals,
    m: int,
    group: Tensor,
    groups: int,
    cutoff: float,
    maneuver: float,
    jack_sigma: Tensor,
) -> Tensor | None:
    """The noise-alone fit on the shortest stencils alone (``σ [m]``) where it is surely below
    the estimate (``jack_sigma [G, m]``: its jackknife
    refits, the same groups), else None: then the estimate's standard error takes in the
    difference (:func:`estimate_noise`), so that the guards that read the noise's uncertainty
    act on it (``sample_accuracy.lowered_noise`` runs at the low end, the error estimate warns).

    Motion adds to a residual's variance the more the longer its stencil (``b``, of white
    acceleration), and at reports far apart a maneuvering target's motion is not what the
    white-acceleration fit extrapolates (every order misfits): both fits then read it as noise,
    with a jackknife error that knows nothing of it. The residuals with ``b`` among each
    order's :data:`SHORT_SHARE` smallest show the least of it. Measured on aircraft at
    irregular report times (4-34 s apart) with σ 25 m: both fits read 42-50 m ± 2, the
    shortest tenth 27-29 m; every estimator ran at the reading above the measurements' error
    (1.01-1.28×), its error estimate 1.2-1.8× its true error, and nothing warned. With the
    difference in the standard error the Kalman smoother ran at the low end (27-29 m): 0.965×
    the measurements, its error estimate 1.06× the truth. The estimate itself stands: at σ
    50 m the shortest tenth read 52-56 m, the estimate 68-74 m, and the smoother at the
    reading's low end (48 m) was 1.01-1.02× the one run before at 55-57 m. On a regular grid an
    order's stencils are alike and this never applies; on the benchmarks' other sets (aircraft
    and simulated vehicles, σ 1-250 m) it applied on none."""
    short = torch.zeros_like(res.u, dtype=torch.bool)
    for k in res.order.unique():
        of = res.order == k
        short |= of & (res.b <= torch.quantile(res.b[of], SHORT_SHARE))
    counts = torch.bincount(res.axis[short], minlength=m)
    if bool(short.all()) or int(counts.min()) < SHORT_LEAST or groups < 2:
        return None
    part = Residuals(*(field[short] for field in res))
    spans = _spans(part)
    d = _design(part, m, False, cutoff)
    full = _trimmed_fit(part, m, d, cutoff, maneuver, spans)
    jack = _jackknife(part, m, d, full, group[short], groups, spans, cutoff, maneuver)
    below = jack_sigma.mean(1) - jack.r.sqrt().mean(1)  # paired by group
    lower = float(jack_sigma.mean() - full.r.sqrt().mean())
    if not lower > SHORT_ERRORS * float(_jackknife_se(below)):
        return None
    return full.r.sqrt()[0]


def _ramp(x: float, zero: float, one: float) -> float:
    """0 at ``zero``, 1 at ``one``, linear between (either order)."""
    return min(max((x - zero) / (one - zero), 0.0), 1.0)


def _white_weight(alone: _Fit, alone_jack: _Fit, white: _Fit, white_jack: _Fit) -> float:
    """The share of the white-acceleration fit in :func:`estimate_noise`: the product of ramps
    (:data:`WHITE_LOWER`, :data:`WHITE_COST`, :data:`WHITE_MISFIT`), a continuous choice, so
    that a few rows more or less never switch the estimate from one fit to the other."""
    # σ (the mean over the axes) of both fits, and its difference, paired by group.
    jack_alone, jack_white = alone_jack.r.sqrt().mean(1), white_jack.r.sqrt().mean(1)
    spread = float(_jackknife_se(jack_alone - jack_white))
    lower = float(alone.r.sqrt().mean() - white.r.sqrt().mean()) / max(spread, 1e-300)
    cost = float(_jackknife_se(jack_white)) / max(float(_jackknife_se(jack_alone)), 1e-300)
    misfit = float(((white.orders - 1.0).abs() / _jackknife_se(white_jack.orders)).amax())
    if not math.isfinite(misfit):
        return 0.0
    return _ramp(lower, *WHITE_LOWER) * _ramp(cost, *WHITE_COST) * _ramp(misfit, *WHITE_MISFIT)

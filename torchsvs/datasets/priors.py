"""What the measurements say before any estimator runs: priors and noise levels.

* :func:`two_point_prior`: the estimators' prior ``x0, P0`` from each track's first two observed
  positions (two-point differencing).
* :func:`estimate_noise`: the measurement noise variance per axis, with its standard error, from
  divided differences of the positions (:func:`difference_residuals`), robust to maneuvers.

Both work on padded batches ``z [B, T, m]`` with per-step intervals ``dt [B, T]``; the prior is
in the layout of :class:`~torchsvs.models.ConstantVelocity` (position, velocity per axis).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.estimator import threads_for

#: Default factor on the two-point covariance (see :func:`two_point_prior`).
PRIOR_INFLATION = 4.0


class Prior(NamedTuple):
    """A prior one step before ``z[:, 0]`` and what it could not see."""

    x0: Tensor  #: [B, 2m] mean, (position, velocity) per axis
    P0: Tensor  #: [B, 2m, 2m] covariance
    single_point: Tensor  #: [B, m] bool: the axis is observed once (velocity prior 0, wide)
    never_observed: Tensor  #: [B, m] bool: the axis is never observed


def _first_two(observed: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Indices of the first and second observed step per ``[B, m]`` and whether they exist."""
    T = observed.shape[1]
    index = torch.arange(T).view(1, T, 1).expand_as(observed)
    big = torch.full_like(index, T)
    first = torch.where(observed, index, big).amin(dim=1)  # [B, m]
    later = observed & (index > first.unsqueeze(1))
    second = torch.where(later, index, big).amin(dim=1)
    return first.clamp_max(T - 1), second.clamp_max(T - 1), first < T, second < T


def two_point_prior(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float,
    inflation: float = PRIOR_INFLATION,
    speed_std: float | None = None,
) -> Prior:
    r"""The prior from each track's first two observed positions (two-point differencing).

    Per axis, with the first two observed positions :math:`z_a, z_b` at times
    :math:`t_a < t_b` and :math:`\Delta = t_b - t_a`, the velocity is
    :math:`v = (z_b - z_a)/\Delta` and the position at the prior's time :math:`t_p` (one step,
    ``dt[:, 0]``, before the first step) is :math:`p = z_a + v (t_p - t_a) = (1 - c) z_a + c z_b`,
    :math:`c = (t_p - t_a)/\Delta`. With measurement variance :math:`r`, their covariance is

    .. math::
        \mathrm{Var}\,p = r\,((1-c)^2 + c^2),\quad \mathrm{Cov}(p, v) = r\,(2c - 1)/\Delta,
        \quad \mathrm{Var}\,v = 2r/\Delta^2

    (Bar-Shalom, Li, Kirubarajan 2001, Sec. 5.5.3, moved to :math:`t_p`). The estimator then
    reads :math:`z_a, z_b` again, so the covariance is multiplied by ``inflation`` (default 4):
    the prior then holds a quarter of their information and counting it twice barely matters,
    while the mean starts the filter where the data are. Axes are independent (the diagonal of
    ``meas_var``).

    Fix-ups, flagged in the result: an axis observed once gets velocity 0 with standard deviation
    ``speed_std`` (default: the largest two-point speed among the batch's tracks, or ten
    measurement standard deviations per median interval if there is none); an axis never
    observed gets mean 0 and unit variance (its estimates are not meaningful; writers mark them
    NaN).

    Args:
        z: measurements ``[B, T, m]``, NaN where missing.
        dt: intervals ``[B, T]`` (``dt[:, 0]`` from the prior to the first step).
        meas_var: measurement noise variance per axis, a number or ``[m]``.
        inflation: factor on the two-point covariance, ≥ 1.
        speed_std: velocity standard deviation of an axis observed once.

    Returns:
        :class:`Prior` with ``x0 [B, 2m]`` and ``P0 [B, 2m, 2m]`` in the dtype of ``z``.

    References:
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley, 2001. doi:10.1002/0471221279
    """
    if z.ndim != 3 or dt.shape != z.shape[:2]:
        raise ValueError(
            f"z, dt: expected [B, T, m] and [B, T], got {tuple(z.shape)}, {tuple(dt.shape)}"
        )
    if not inflation >= 1.0:
        raise ValueError(f"inflation: expected a factor >= 1, got {inflation!r}")
    B, T, m = z.shape
    dtype = z.dtype
    r = torch.as_tensor(meas_var, dtype=dtype).expand(m)
    if not bool((r > 0).all()) or not bool(torch.isfinite(r).all()):
        raise ValueError(f"meas_var: expected finite variances > 0, got {r.tolist()}")
    observed = ~torch.isnan(z)
    # Step times relative to the prior's time t_p = 0.
    t = torch.cumsum(dt.to(torch.float64), dim=1).unsqueeze(-1).expand(B, T, m)
    first, second, has_first, has_second = _first_two(observed)

    def at(x: Tensor, index: Tensor) -> Tensor:
        return x.gather(1, index.unsqueeze(1)).squeeze(1)  # [B, m]

    t_a, t_b = at(t, first), at(t, second)
    z_filled = z.nan_to_num(0.0)
    z_a, z_b = at(z_filled, first), at(z_filled, second)

    both = has_first & has_second
    delta = torch.where(both, t_b - t_a, torch.ones_like(t_a)).to(dtype)
    v = torch.where(both, (z_b - z_a) / delta, torch.zeros_like(z_a))
    c = torch.where(both, -t_a.to(dtype) / delta, torch.zeros_like(delta))
    pos = torch.where(both, (1 - c) * z_a + c * z_b, z_a)

    if speed_std is None:
        speeds = v.abs()[both]
        median_dt = dt.median(dim=1).values.to(dtype)
        fallback = (10.0 * r.sqrt().unsqueeze(0) / median_dt.unsqueeze(1)).amax()
        speed_std = float(speeds.max()) if speeds.numel() else float(fallback)
        speed_std = max(speed_std, 1e-12)
    var_p = torch.where(both, r * ((1 - c) ** 2 + c**2), r.expand(B, m))
    cov_pv = torch.where(both, r * (2 * c - 1) / delta, torch.zeros_like(delta))
    var_v = torch.where(both, 2 * r / delta**2, torch.full_like(delta, speed_std**2))
    # Mean 0, unit variance where the axis is never seen; at a single point the position is the
    # point itself (t_p is before it, but its velocity is unknown: var_v covers the offset).
    single = has_first & ~has_second
    t_a_d = t_a.to(dtype)
    var_p = torch.where(single, r + var_v * t_a_d**2, var_p)
    cov_pv = torch.where(single, -var_v * t_a_d, cov_pv)
    pos = torch.where(has_first, pos, torch.zeros_like(pos))
    var_p = torch.where(has_first, var_p, torch.ones_like(var_p))
    var_v = torch.where(has_first, var_v, torch.ones_like(var_v))

    x0 = torch.stack([pos, v], dim=-1).reshape(B, 2 * m)
    blocks = torch.stack(
        [torch.stack([var_p, cov_pv], -1), torch.stack([cov_pv, var_v], -1)], -2
    )  # [B, m, 2, 2]
    P0 = torch.zeros(B, 2 * m, 2 * m, dtype=dtype)
    for j in range(m):
        P0[:, 2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = blocks[:, j]
    P0 = P0 * torch.where(has_first, inflation, 1.0).repeat_interleave(2, dim=1).unsqueeze(-1)
    P0 = 0.5 * (P0 + P0.mT)
    return Prior(x0, P0, single, ~has_first)


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


#: Orders of the divided differences the measurement noise is read from (:func:`estimate_noise`).
ORDERS = (2, 3, 4)
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


class Residuals(NamedTuple):
    """Normalised difference residuals of the measurements (:func:`difference_residuals`)."""

    u: Tensor  #: [N] residual, variance ``r_axis + b q`` (unit noise gain)
    b: Tensor  #: [N] its variance per unit ``q`` of white acceleration (s³)
    axis: Tensor  #: [N] int64 its axis
    order: Tensor  #: [N] int64 its order
    track: Tensor  #: [N] int64 its track
    first: Tensor  #: [N] int64 the step of its stencil's first point
    last: Tensor  #: [N] int64 the step of its stencil's last point


def _observed_first(z: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per ``(track, axis)`` the observed positions, their times and their steps moved to the
    front in time order (``[B·m, T]`` each), and their count ``[B·m]``."""
    B, T, m = z.shape
    zz = z.permute(0, 2, 1).reshape(B * m, T)
    tt = t.unsqueeze(1).expand(B, m, T).reshape(B * m, T)
    observed = torch.isfinite(zz)
    order = torch.argsort((~observed).to(torch.int8), dim=1, stable=True)
    return zz.gather(1, order), tt.gather(1, order), order, observed.sum(dim=1)


def difference_residuals(z: Tensor, dt: Tensor, orders: tuple[int, ...] = ORDERS) -> Residuals:
    r"""Divided differences of order ``k`` over each ``k + 1`` successive observed positions of
    an axis, at their own time stamps, scaled to unit noise gain.

    The ``k``-th divided difference has weights :math:`w_j = 1/\prod_{l \ne j}(t_j - t_l)` and
    annihilates polynomials of degree below ``k``; with :math:`c = w/\lVert w\rVert` the residual
    :math:`u = \sum_j c_j z_j` of white noise of variance :math:`r` has variance :math:`r`.
    Motion adds to it: a path of degree below ``k`` adds nothing, and white acceleration of
    spectral density :math:`q` (the model of :class:`~torchsvs.models.ConstantVelocity`,
    :math:`x(t) = x_0 + v_0 t + \int (t - s)_+ w(s)\,ds`) adds :math:`b\,q` with
    :math:`b = \int K(s)^2 ds` for the Peano kernel :math:`K(s) = \sum_j c_j (t_j - s)_+` of the
    stencil. :math:`K` is linear between the time stamps and zero outside them, so
    :math:`b = \sum_l h_l (K_l^2 + K_l K_{l+1} + K_{l+1}^2)/3` exactly, with
    :math:`K_l = \sum_{j>l} c_j (t_j - t_l)`. For ``k = 2`` this is the three-point residual of
    Gasser, Sroka & Jennen-Steinmetz (1986), :math:`\rho = z_1 - (h_2 z_0 + h_1 z_2)/H` over its
    noise gain :math:`\sqrt{1 + (h_1/H)^2 + (h_2/H)^2}`, and :math:`b = h_1^2 h_2^2/(3H)` over
    the gain squared.

    References:
        Gasser, Sroka, Jennen-Steinmetz, "Residual variance and residual pattern in nonlinear
        regression", Biometrika 73(3):625-633, 1986. doi:10.1093/biomet/73.3.625
    """
    B, T, m = z.shape
    t = torch.cumsum(dt.to(torch.float64), dim=1)
    zc, tc, steps, count = _observed_first(z.to(torch.float64), t)
    rows = torch.arange(B * m)
    out: dict[str, list[Tensor]] = {key: [] for key in Residuals._fields}
    for k in orders:
        if T <= k:
            continue
        n = T - k
        valid = torch.arange(n).unsqueeze(0) + k < count.unsqueeze(1)  # [B·m, n]
        times = torch.stack([tc[:, j : j + n] for j in range(k + 1)], -1)[valid]  # [N, k+1]
        values = torch.stack([zc[:, j : j + n] for j in range(k + 1)], -1)[valid]
        times = times - times[:, :1]  # relative to the stencil's start (precision)
        gaps = times.unsqueeze(-1) - times.unsqueeze(-2) + torch.eye(k + 1, dtype=times.dtype)
        w = 1.0 / gaps.prod(dim=-1)  # (the diagonal's 1 stands for the missing l = j)
        c = w / w.norm(dim=-1, keepdim=True)
        later = torch.triu(torch.ones(k + 1, k + 1, dtype=c.dtype), diagonal=1)  # [l, j]: j > l
        knots = (c.unsqueeze(-2) * (times.unsqueeze(-2) - times.unsqueeze(-1)) * later).sum(-1)
        h = times[:, 1:] - times[:, :-1]
        k0, k1 = knots[:, :-1], knots[:, 1:]
        b = (h * (k0.square() + k0 * k1 + k1.square())).sum(-1) / 3.0
        u = (c * values).sum(-1)
        ok = torch.isfinite(u) & torch.isfinite(b)
        row = rows.unsqueeze(1).expand(-1, n)[valid][ok]
        out["u"].append(u[ok])
        out["b"].append(b[ok])
        out["axis"].append(row % m)
        out["order"].append(torch.full_like(row, k))
        out["track"].append(row // m)
        out["first"].append(steps[:, :n][valid][ok])
        out["last"].append(steps[:, k : k + n][valid][ok])
    if not out["u"]:
        empty, none = torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.int64)
        return Residuals(empty, empty, none, none, none, none, none)
    return Residuals(*(torch.cat(out[key]) for key in Residuals._fields))


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


def _design(res: Residuals, m: int, white: bool, cutoff: float) -> _Design:
    b_scale = float(res.b.median().clamp_min(1e-300))
    cols = torch.nn.functional.one_hot(res.axis, m).double()
    if white:
        cols = torch.cat([cols, (res.b / b_scale)[:, None]], 1)
    products = (cols.unsqueeze(-1) * cols.unsqueeze(-2)).flatten(1)
    y = res.u.square() / truncated_second_moment(cutoff)
    return _Design(y, cols, products, b_scale, white)


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


def _iterate(
    res: Residuals,
    m: int,
    d: _Design,
    start: tuple[Tensor, Tensor],
    include: Tensor,
    spans: _Spans,
    cutoff: float,
    maneuver: float,
    iterations: int,
) -> _Fit:
    """Scoring iterations of the trimmed Gaussian fit from ``start`` (``r [G, m], q [G]``) on
    the residuals of each row of ``include [G, N]``, until the variances change by less than
    :data:`TOLERANCE` or ``iterations`` are done."""
    u2 = res.u.square()
    r, q = start
    G, p = include.shape[0], d.cols.shape[1]
    boundary = torch.zeros(G, dtype=torch.bool)
    for _ in range(iterations):
        v = r[:, res.axis] + res.b * q[:, None]
        w = _kept(spans, u2, v, include, cutoff, maneuver) / v.square()
        A = (w @ d.products).view(G, p, p)
        new_r, new_q = _scoring_step(d, A, (w * d.y) @ d.cols, m)
        # An axis with nothing kept stays as it was; one whose variance the fit puts at or below
        # 0 (q explains it all) stays too, and the fit is flagged: not a solution.
        inside = new_r > 0
        boundary = (~inside & (A.diagonal(dim1=-2, dim2=-1)[:, :m] > 0)).any(-1)
        new_r = torch.where(inside, new_r, r)
        change = max(
            float(((new_r - r).abs() / r).amax()),
            float(((new_q - q).abs() * res.b.amax() / r.amin(-1)).amax()),
        )
        r, q = new_r, new_q
        if change < TOLERANCE:
            break
    v = r[:, res.axis] + res.b * q[:, None]
    kept = _kept(spans, u2, v, include, cutoff, maneuver)
    return _Fit(r, q, _per_order(res, kept * d.y / v, kept), boundary)


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
    everything = torch.ones(1, res.u.numel(), dtype=torch.bool)
    return _iterate(res, m, d, start, everything, spans, cutoff, maneuver, ITERATIONS)


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
    include = group != torch.arange(groups)[:, None]  # [G, N]
    start = (fit.r.expand(groups, m), fit.q.expand(groups))
    return _iterate(res, m, d, start, include, spans, cutoff, maneuver, JACKKNIFE_STEPS)


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
    factor of about ten an iteration).

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
    with threads_for(1, 1):  # a chain of small vector operations: one intra-op thread
        return _estimate(z, dt, orders, cutoff, maneuver)


def _estimate(
    z: Tensor, dt: Tensor, orders: tuple[int, ...], cutoff: float, maneuver: float
) -> NoiseEstimate:
    """:func:`estimate_noise` on checked arguments."""
    m, T = z.shape[-1], z.shape[1]
    res = difference_residuals(z, dt, orders)
    per_axis = torch.bincount(res.axis[res.order == max(orders)], minlength=m)
    if int(per_axis.min()) < 3:
        raise ValueError(
            "z: too few observed positions in a row to estimate the noise; "
            "give the measurement noise (meas_std) and q explicitly"
        )
    scale = float(z[torch.isfinite(z)].abs().max())
    if float(res.u[res.order == max(orders)].abs().median()) <= 1e-9 * scale:
        raise ValueError(
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
    if groups >= 2 and not bool(white.boundary.any() or white_jack.boundary.any()):
        weight = _white_weight(alone, alone_jack, white, white_jack)
    # log σ of each axis and of each jackknife refit, the two fits blended by the weight
    log_sigma = (1 - weight) * alone.r.log() / 2 + weight * white.r.clamp_min(1e-300).log() / 2
    log_jack = (1 - weight) * alone_jack.r.log() / 2 + weight * white_jack.r.clamp_min(
        1e-300
    ).log() / 2
    sigma = log_sigma.exp()[0]
    se = _jackknife_se(log_jack.exp()) if groups >= 2 else torch.full((m,), math.nan)
    h = float(dt[:, 1:][torch.isfinite(dt[:, 1:])].median()) if T > 1 else 1.0
    q = max(float(white.q[0]), 1e-3 * float(sigma.square().mean()) / h**3)
    return NoiseEstimate(sigma.square().to(z.dtype), q, int(res.u.numel()), se.to(z.dtype), weight)


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


#: :func:`noise_spread` reads at most this many tracks, of at least this many observed points.
SPREAD_TRACKS = 48
SPREAD_POINTS = 40


def noise_spread(
    z: Tensor, dt: Tensor, max_tracks: int = SPREAD_TRACKS, min_points: int = SPREAD_POINTS
) -> float | None:
    r"""How much the noise read off each track alone differs between tracks, beyond what their
    own standard errors explain: the between-track standard deviation :math:`\tau` of
    :math:`\log\hat\sigma` (a relative spread; DerSimonian & Laird's moment estimator over every
    track and axis, weights :math:`1/se^2` from :func:`estimate_noise`'s jackknife).

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
    logs, weights = [], []
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
    if len(logs) < 4:
        return None
    y, w = torch.cat(logs), torch.cat(weights)
    mean = (w * y).sum() / w.sum()
    Q = float((w * (y - mean).square()).sum())
    scale = float(w.sum() - w.square().sum() / w.sum())
    return math.sqrt(max(0.0, (Q - (y.numel() - 1)) / scale)) if scale > 0 else None

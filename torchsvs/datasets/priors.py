"""The estimators' prior before any estimator runs: :func:`two_point_prior`, the mean and
covariance ``x0, P0`` from each track's first two observed positions (two-point differencing).

Works on padded batches ``z [B, T, m]`` with per-step intervals ``dt [B, T]``; the prior is in
the layout of :class:`~torchsvs.models.ConstantVelocity` (position, velocity per axis). The
measurement noise it needs is given or read off the data (:mod:`torchsvs.datasets.noise_estimate`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

#: Default factor on the two-point covariance (see :func:`two_point_prior`).
PRIOR_INFLATION = 4.0


class Prior(NamedTuple):
    """A prior one step before ``z[:, 0]`` and what it could not see."""

    x0: Tensor  #: [B, 2m] mean, (position, velocity) per axis
    P0: Tensor  #: [B, 2m, 2m] covariance
    single_point: Tensor  #: [B, m] bool: the axis is observed once (velocity prior 0, wide)
    never_observed: Tensor  #: [B, m] bool: the axis is never observed


def first_observed_two(observed: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Indices of the first and second observed step per ``[B, m]`` and whether they exist."""
    T = observed.shape[1]
    count = observed.cumsum(1, dtype=torch.int32)  # observed steps up to each step
    first, second = (count == 0).sum(1), (count <= 1).sum(1)  # the steps before each
    return first.clamp_max(T - 1), second.clamp_max(T - 1), first < T, second < T


def _two_points(z: Tensor, dt: Tensor) -> tuple[Tensor, ...]:
    """:func:`first_observed_two` of ``z``'s observed components, and their times ``t_a,
    t_b`` (float64 ``[B, m]``) from the prior's time ``t_p = 0``. Most tracks have their
    first two steps observed on every axis: theirs are read off those two steps (the same
    sums as the cumulative sum's), the whole track is scanned for the others only."""
    B, T, m = z.shape
    dt64 = dt.to(torch.float64)
    if T < 2:
        return _scanned_two_points(z, dt64)
    plain = ~torch.isnan(z[:, :2]).any(2).any(1)  # [B]
    t_a = dt64[:, 0]
    t_b = t_a + dt64[:, 1]
    found = (
        torch.zeros(B, m, dtype=torch.int64),
        torch.ones(B, m, dtype=torch.int64),
        torch.ones(B, m, dtype=torch.bool),
        torch.ones(B, m, dtype=torch.bool),
        t_a.unsqueeze(1).repeat(1, m),
        t_b.unsqueeze(1).repeat(1, m),
    )
    other = torch.nonzero(~plain).flatten()
    if len(other):
        for whole, part in zip(found, _scanned_two_points(z[other], dt64[other]), strict=True):
            whole[other] = part
    return found


def _scanned_two_points(z: Tensor, dt64: Tensor) -> tuple[Tensor, ...]:
    """:func:`_two_points` by scanning every step of every track."""
    t = torch.cumsum(dt64, dim=1)
    first, second, has_first, has_second = first_observed_two(~torch.isnan(z))
    return first, second, has_first, has_second, t.gather(1, first), t.gather(1, second)


def _weights(
    has_first: Tensor, has_second: Tensor, t_a: Tensor, t_b: Tensor, dtype: torch.dtype
) -> tuple[Tensor, Tensor, Tensor]:
    """Where both points exist, their interval ``Δ`` (else 1) and the weight ``c`` of the
    second in the prior's position, ``p = (1 - c) z_a + c z_b`` (else 0)."""
    both = has_first & has_second
    delta = torch.where(both, t_b - t_a, torch.ones_like(t_a)).to(dtype)
    c = torch.where(both, -t_a.to(dtype) / delta, torch.zeros_like(delta))
    return both, delta, c


def prior_tangents(z: Tensor, dt: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """How :func:`two_point_prior`'s mean moves with each axis's first and second observed
    position: ``[B, m]`` each, ``∂p/∂z_a, ∂v/∂z_a, ∂p/∂z_b, ∂v/∂z_b`` (``p = (1 - c) z_a + c
    z_b``, ``v = (z_b - z_a)/Δ``; an axis observed once has ``p = z_a``, ``v = 0``; one never
    observed, zeros). Its covariance does not depend on the positions."""
    _, _, has_first, has_second, t_a, t_b = _two_points(z, dt)
    both, delta, c = _weights(has_first, has_second, t_a, t_b, z.dtype)
    zero = torch.zeros_like(c)
    return (
        torch.where(both, 1 - c, has_first.to(z.dtype)),
        torch.where(both, -1 / delta, zero),
        c,
        torch.where(both, 1 / delta, zero),
    )


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
    first, second, has_first, has_second, t_a, t_b = _two_points(z, dt)

    def at(index: Tensor) -> Tensor:  # [B, m] (0 where the axis has no such step)
        return z.gather(1, index.unsqueeze(1)).squeeze(1).nan_to_num(0.0)

    z_a, z_b = at(first), at(second)

    both, delta, c = _weights(has_first, has_second, t_a, t_b, dtype)
    v = torch.where(both, (z_b - z_a) / delta, torch.zeros_like(z_a))
    pos = torch.where(both, (1 - c) * z_a + c * z_b, z_a)

    if speed_std is None:
        speeds = v.abs()[both]
        if speeds.numel():
            speed_std = float(speeds.max())
        else:
            median_dt = dt.median(dim=1).values.to(dtype)
            speed_std = float((10.0 * r.sqrt().unsqueeze(0) / median_dt.unsqueeze(1)).amax())
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

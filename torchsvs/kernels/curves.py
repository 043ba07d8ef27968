"""The nearly-constant-velocity Kalman smoother's SURE curves and positions, compiled
(``cpp/curves.h``): what :mod:`torchsvs.fitting.noise` reads off the smoother at many values
of ``q`` (each track's SURE curve) and what the outlier screen and ``track``'s Kalman
estimates read at one (the smoothed means and the positions' variances), without writing the
full results the estimator's own pass writes (a ``[B, T, 2m, 2m]`` covariance a step, and one
result per value of ``q``).

Per axis (a position-only corrector with diagonal ``R``, a prior without cross-axis
covariance: the axes decouple) the Kalman filter's step is ``axis_step.h``'s and the fixed-
interval RTS recursion ``axis_smoother.h``'s: the formulas the estimator's compiled loops run
(:class:`~torchsvs.smoothers.RTSSmoother` of :class:`~torchsvs.filters.KalmanFilter` on
:class:`~torchsvs.models.ConstantVelocity`), held to it by ``tests/test_curves_kernel.py``.
Both functions return ``None`` where the compiled loops are unavailable; callers then run the
estimator.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.kernels import build


def _prior_axes(x0: Tensor, P0: Tensor) -> list[Tensor]:
    """``[B, m]`` each: the prior's position, velocity, and covariance ``a, b, c`` per axis."""
    diagonal = P0.diagonal(dim1=-2, dim2=-1)
    above = P0.diagonal(offset=1, dim1=-2, dim2=-1)
    return [x0[:, 0::2], x0[:, 1::2], diagonal[:, 0::2], above[:, 0::2], diagonal[:, 1::2]]


def _call(
    z: Tensor,
    dt: Tensor,
    weight: Tensor,
    x0: Tensor,
    P0: Tensor,
    r: Tensor,
    q: Tensor,
    smoothed: bool,
    risk: Tensor | None,
    mean: Tensor | None = None,
    var: Tensor | None = None,
    tangents: Sequence[Tensor] = (),
    first_two: Tensor | None = None,
    chunk: int = 1,
    sums: Tensor | None = None,
    student: Tensor | None = None,
    max_leverage: float = 1.0,
    step_risk: Tensor | None = None,
) -> None:
    B, T, m = z.shape
    K = q.shape[1]
    shape = (B, T, m)
    views = [
        z,
        dt.unsqueeze(-1).expand(shape),
        weight,
        *(x.unsqueeze(1).expand(shape) for x in _prior_axes(x0, P0)),
        r.reshape(1, 1, m).expand(shape),
        q.unsqueeze(-1).expand(B, K, m),  # (its step stride is the factor's)
        *(x.unsqueeze(1).expand(shape) for x in tangents),
    ]
    inputs = build.pointers(views)
    strides = build.strides(views)
    outputs = (risk, mean, var, first_two, sums, student, step_risk)
    pointer = [None if x is None else x.data_ptr() for x in outputs]
    build.function("kalman_curves", z.dtype)(
        B, T, m, K, int(smoothed), build.threads(B, T * K), inputs, strides, *pointer[:4],
        chunk, pointer[4], pointer[5], max_leverage, pointer[6],
    )  # fmt: skip


def _usable(*tensors: Tensor) -> bool:
    with torch.no_grad():
        return build.usable(*tensors)


def sure_risks(
    z: Tensor,
    dt: Tensor,
    counted: Tensor,
    x0: Tensor,
    P0: Tensor,
    r: Tensor,
    q: Tensor,
    smoothed: bool = True,
) -> Tensor | None:
    """``[K, B]`` each track's SURE of the smoothed (else filtered) positions
    (``noise._sure_of``'s terms summed over the ``counted [B, T, m]`` components) for each of
    its ``q [B, K]``: ``z [B, T, m]`` (NaN: missing), intervals ``dt [B, T]``, the prior ``x0
    [B, 2m]``, ``P0 [B, 2m, 2m]`` (block-diagonal by axis), measurement variances ``r [m]``;
    all of one dtype. ``None`` where the compiled loops are unavailable."""
    B, T, m = z.shape
    weight = counted.to(z.dtype)
    if not _usable(z, dt, weight, x0, P0, r, q):
        return None
    risk = torch.empty(q.shape[1], B, m, dtype=z.dtype)
    _call(z, dt, weight, x0, P0, r, q, smoothed, risk)
    return risk.sum(-1)


class Positions(NamedTuple):
    """What :func:`positions` gives."""

    mean: Tensor  #: [B, T, 2m] the means (position, velocity per axis)
    var: Tensor  #: [B, T, m] the positions' variances
    #: [B, m, 2] with ``tangents``: the position estimate's derivative by the measurement at
    #: each axis's first and second observation (through the prior too), NaN where none
    first_two: Tensor | None = None
    #: [B, C, m, 3] with ``chunk``: SURE's sums over each track's chunks of that many steps
    #: (squared residual, divergence, count: :func:`~torchsvs.accuracy.terms_of_sums`)
    sums: Tensor | None = None
    #: [B, T] with ``step_risk``: each step's SURE, its observed components' ``(z − x̂)² − r +
    #: 2 r ∂x̂/∂z`` summed (the divergence as in ``sums``), 0 where none is observed
    step_risk: Tensor | None = None


def positions(
    z: Tensor,
    dt: Tensor,
    x0: Tensor,
    P0: Tensor,
    r: Tensor,
    q: Tensor,
    smoothed: bool = True,
    tangents: Sequence[Tensor] | None = None,
    chunk: int | None = None,
    step_risk: Tensor | None = None,
) -> Positions | None:
    """The smoother's (filter's) means and positions' variances with each track's ``q [B]``
    (other arguments as :func:`sure_risks`'); with ``tangents`` (how the prior's mean moves
    with each axis's first and second observation, :func:`~torchsvs.datasets.priors.
    prior_tangents`) also the estimate's derivative by those two measurements, and with them
    and ``chunk`` SURE's sums over each track's chunks of ``chunk`` steps, and with them each
    step's SURE written to ``step_risk`` (``[B, T]`` of ``z``'s dtype, contiguous: a buffer
    the caller keeps, as a pass's risks are stacked). ``None`` where the compiled loops are
    unavailable."""
    B, T, m = z.shape
    if not _usable(z, dt, x0, P0, r, q, *(tangents or ())):
        return None
    mean = build.fresh((B, T, 2 * m), z.dtype)
    var = build.fresh((B, T, m), z.dtype)
    first_two = None if tangents is None else torch.empty(B, m, 2, dtype=z.dtype)
    if chunk is not None and (tangents is None or chunk < 1):
        raise ValueError(f"chunk: expected steps >= 1 with the tangents, got {chunk!r}")
    sums = None
    if chunk is not None:
        sums = torch.empty(B, -(-T // chunk), m, 3, dtype=z.dtype)
    if step_risk is not None and (
        tangents is None
        or step_risk.shape != (B, T)
        or step_risk.dtype != z.dtype
        or not step_risk.is_contiguous()
    ):
        raise ValueError(
            f"step_risk: expected a contiguous [{B}, {T}] {z.dtype} buffer and the tangents, "
            f"got {tuple(step_risk.shape)} {step_risk.dtype}"
        )
    weight = torch.zeros((), dtype=z.dtype).expand(B, T, m)
    _call(
        z, dt, weight, x0, P0, r, q.reshape(B, 1), smoothed, None, mean, var,
        tangents or (), first_two, chunk or 1, sums, step_risk=step_risk,
    )  # fmt: skip
    return Positions(mean, var, first_two, sums, step_risk)


def studentized(
    z: Tensor,
    dt: Tensor,
    x0: Tensor,
    P0: Tensor,
    r: Tensor,
    q: float,
    max_leverage: float,
) -> Tensor | None:
    """``[B, T, m]`` the smoother's studentized squared residual per axis, ``(z − x̂)² / (r (1 −
    h))`` with the leverage ``h = P_pp / r`` (``1 − h`` floored at 1e-12), NaN where ``z`` is
    missing or ``h`` is above ``max_leverage``: what the outlier screen sums over the axes
    (:func:`~torchsvs.fitting.outliers.outlier_distances`), without the means (arguments as
    :func:`sure_risks`', one ``q`` for all tracks). ``None`` where the compiled loops are
    unavailable."""
    B, T, m = z.shape
    q_all = torch.full((B, 1), float(q), dtype=z.dtype)
    if not _usable(z, dt, x0, P0, r, q_all):
        return None
    student = build.fresh((B, T, m), z.dtype)
    weight = torch.zeros((), dtype=z.dtype).expand(B, T, m)
    _call(z, dt, weight, x0, P0, r, q_all, True, None, student=student, max_leverage=max_leverage)
    return student

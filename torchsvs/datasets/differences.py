"""Divided differences of the positions at their own time stamps: the residuals the
measurement noise is read from (:func:`~torchsvs.datasets.noise_estimate.estimate_noise`)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchsvs.kernels import track_noise as compiled_noise

#: Orders of the divided differences the measurement noise is read from
#: (:func:`~torchsvs.datasets.noise_estimate.estimate_noise`).
ORDERS = (2, 3, 4)


class Residuals(NamedTuple):
    """Normalised difference residuals of the measurements (:func:`difference_residuals`)."""

    u: Tensor  #: [N] residual, variance ``r_axis + b q`` (unit noise gain)
    b: Tensor  #: [N] its variance per unit ``q`` of white acceleration (s³)
    axis: Tensor  #: [N] int64 its axis
    order: Tensor  #: [N] int64 its order
    track: Tensor  #: [N] int64 its track
    first: Tensor  #: [N] int64 the step of its stencil's first point
    last: Tensor  #: [N] int64 the step of its stencil's last point


def observed_first(z: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
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
    z, t = z.to(torch.float64), torch.cumsum(dt.to(torch.float64), dim=1)
    compiled = _compiled(z, t, orders)
    if compiled is not None:
        return compiled
    zc, tc, steps, count = observed_first(z, t)
    out: dict[str, list[Tensor]] = {key: [] for key in Residuals._fields}
    for k in orders:
        if T <= k:
            continue
        n = T - k
        valid = torch.arange(n).unsqueeze(0) + k < count.unsqueeze(1)  # [B·m, n]
        # Each stencil's k + 1 points as k + 1 vectors over the stencils ([N] each, in the
        # order of ``valid``'s rows): the stencils as [N, k+1, k+1] tensors were hundreds of MB
        # on a large sample, and its memory traffic most of the time.
        row, col = valid.nonzero(as_tuple=True)
        start = tc[row, col]
        times = [tc[row, col + j] - start for j in range(k + 1)]  # from the stencil's start
        values = [zc[row, col + j] for j in range(k + 1)]
        c = unit_weights(times)
        # the Peano kernel at each knot l: K_l = sum_{j > l} c_j (t_j - t_l)
        knots = [
            functools.reduce(torch.add, [c[j] * (times[j] - times[l]) for j in range(l + 1, k + 1)])
            if l < k
            else torch.zeros_like(start)
            for l in range(k + 1)
        ]
        b = (
            functools.reduce(
                torch.add,
                [
                    (times[l + 1] - times[l])
                    * (knots[l].square() + knots[l] * knots[l + 1] + knots[l + 1].square())
                    for l in range(k)
                ],
            )
            / 3.0
        )
        u = functools.reduce(torch.add, [cj * zj for cj, zj in zip(c, values, strict=True)])
        ok = torch.isfinite(u) & torch.isfinite(b)
        row, col = row[ok], col[ok]
        out["u"].append(u[ok])
        out["b"].append(b[ok])
        out["axis"].append(row % m)
        out["order"].append(torch.full_like(row, k))
        out["track"].append(row // m)
        out["first"].append(steps[row, col])
        out["last"].append(steps[row, col + k])
    return _joined(out)


def unit_weights(times: list[Tensor]) -> list[Tensor]:
    """The divided difference's weights over a stencil's ``k + 1`` time stamps (each a tensor
    over the stencils), at unit noise gain: ``c_j = w_j / ‖w‖``,
    ``w_j = 1 / ∏_{l ≠ j} (t_j − t_l)`` (:func:`difference_residuals`)."""
    k = len(times) - 1
    w = [
        1.0 / functools.reduce(torch.mul, [times[j] - times[l] for l in range(k + 1) if l != j])
        for j in range(k + 1)
    ]
    norm = _sqrt(functools.reduce(torch.add, [x * x for x in w]))
    return [x / norm for x in w]


def _joined(out: dict[str, list[Tensor]]) -> Residuals:
    if not out["u"]:
        empty, none = torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.int64)
        return Residuals(empty, empty, none, none, none, none, none)
    return Residuals(*(torch.cat(out[key]) for key in Residuals._fields))


def _sqrt(x: Tensor) -> Tensor:
    """The correctly rounded square root (torch's float64 one is not, on about 1% of values:
    the compiled residuals' then differ in the last bit)."""
    return torch.from_numpy(np.sqrt(x.numpy()))


def _compiled(z: Tensor, t: Tensor, orders: tuple[int, ...]) -> Residuals | None:
    """:func:`difference_residuals` compiled (:func:`torchsvs.kernels.track_noise.residuals`,
    the same to the bit), in its order; None where the compiled loops are unavailable."""
    found = compiled_noise.residuals(z, t, orders)
    if found is None:
        return None
    _, T, m = z.shape
    out: dict[str, list[Tensor]] = {key: [] for key in Residuals._fields}
    for o, k in enumerate(orders):
        if T <= k:
            continue
        row, col = found.ok[o].nonzero(as_tuple=True)
        at = (o * found.ok.shape[1] + row) * T + col
        out["u"].append(found.u.view(-1)[at])
        out["b"].append(found.b.view(-1)[at])
        out["axis"].append(row % m)
        out["order"].append(torch.full_like(row, k))
        out["track"].append(row // m)
        out["first"].append(found.first.view(-1)[at])
        out["last"].append(found.last.view(-1)[at])
    return _joined(out)

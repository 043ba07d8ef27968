"""The measurement noise read off the positions, compiled (``cpp/track_noise.h``): the divided
differences it is read from (:func:`residuals`,
:func:`torchsvs.datasets.differences.difference_residuals`'s) and each track's own reading
(:func:`read`, :func:`torchsvs.datasets.track_noise.read_track_noise`'s fit), track by track
in one pass, where the tensor code runs some hundred operations over every residual (10^6
rows: about 3 s of it); and the sums of each scoring step of
:func:`~torchsvs.datasets.noise_estimate.estimate_noise`'s trimmed fit, every jackknife refit in
one pass (:func:`trimmed_sums`, ``cpp/noise_fit.h``). The tensor code is the home of the
formulas and the path where these return ``None``; ``tests/test_track_noise.py`` holds the two
equal to the bit (the fit's sums to the last bits: they sum in another order).
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.kernels import build

#: The highest order of divided differences the compiled loops hold (``cpp/track_noise.h``'s
#: ``kMaxOrder``): higher ones run the tensor code.
MAX_ORDER = 7
#: The most fits :func:`trimmed_sums` takes at once (``cpp/noise_fit.h``'s ``kMaxFits``).
MAX_FITS = 64


def _compilable(z: Tensor, t: Tensor, orders: Sequence[int]) -> bool:
    return (
        z.dtype == torch.float64 and all(1 <= k <= MAX_ORDER for k in orders) and build.usable(z, t)
    )


class Reading(NamedTuple):
    """What :func:`read` gives, per track."""

    scale: Tensor  #: [B] float64 the noise's variance over ``r`` after the last iteration
    kept: Tensor  #: [B] float64 the residuals kept in the last iteration
    top_count: Tensor  #: [B] int64 the residuals of the top order


def read(
    z: Tensor,
    t: Tensor,
    r: Sequence[float],
    orders: Sequence[int],
    top: int,
    kappa: float,
    chi2_median: float,
    cutoff: float,
    maneuver: float,
    iterations: int,
) -> Reading | None:
    """Each track's noise scale on ``z [B, T, m]`` (NaN: missing) at the times ``t [B, T]``
    (the intervals' running sums) with the variances ``r [m]``, from the divided differences of
    ``orders`` and the lower median of the ``top`` order's (all float64; the fit's constants as
    :mod:`torchsvs.datasets.track_noise` names them). ``None`` where the compiled loops are
    unavailable (or an order is above :data:`MAX_ORDER`)."""
    if not _compilable(z, t, orders):
        return None
    B, T, m = z.shape
    z, t = z.contiguous(), t.contiguous()
    r64 = torch.tensor(list(r), dtype=torch.float64)
    order = torch.tensor(list(orders), dtype=torch.int64)
    scale = torch.empty(B, dtype=torch.float64)
    kept = torch.empty(B, dtype=torch.float64)
    top_count = torch.empty(B, dtype=torch.int64)
    lib = build.library()
    assert lib is not None
    lib.track_noise_f64(
        B, T, m, build.threads(B, T), z.data_ptr(), t.data_ptr(), r64.data_ptr(),
        order.data_ptr(), len(order), top, kappa, chi2_median, cutoff**2, maneuver**2,
        ctypes.c_int(iterations), scale.data_ptr(), kept.data_ptr(), top_count.data_ptr(),
    )  # fmt: skip
    return Reading(scale, kept, top_count)


class Stencils(NamedTuple):
    """What :func:`residuals` gives: ``[K, B m, T]`` each, at ``[order, lane, stencil]``."""

    u: Tensor  #: float64 the residual
    b: Tensor  #: float64 its variance per unit q of white acceleration
    first: Tensor  #: int64 the step of its stencil's first point
    last: Tensor  #: int64 and of its last
    ok: Tensor  #: bool a stencil there whose u and b are finite


def residuals(z: Tensor, t: Tensor, orders: Sequence[int]) -> Stencils | None:
    """The divided differences of each of ``orders`` over the observed positions of every lane
    (track axis, ``lane = track m + axis``) of ``z [B, T, m]`` (NaN: missing) at the times ``t
    [B, T]`` (float64). ``None`` where the compiled loops are unavailable (or an order is
    above :data:`MAX_ORDER`)."""
    if not _compilable(z, t, orders):
        return None
    B, T, m = z.shape
    z, t = z.contiguous(), t.contiguous()
    order = torch.tensor(list(orders), dtype=torch.int64)
    shape = (len(order), B * m, T)
    u, b = torch.empty(shape, dtype=torch.float64), torch.empty(shape, dtype=torch.float64)
    first, last = torch.empty(shape, dtype=torch.int64), torch.empty(shape, dtype=torch.int64)
    ok = torch.empty(shape, dtype=torch.bool)
    lib = build.library()
    assert lib is not None
    lib.difference_residuals_f64(
        B, T, m, build.threads(B, T), z.data_ptr(), t.data_ptr(), order.data_ptr(), len(order),
        u.data_ptr(), b.data_ptr(), first.data_ptr(), last.data_ptr(), ok.data_ptr(),
    )  # fmt: skip
    return Stencils(u, b, first, last, ok)


class TrimmedSums(NamedTuple):
    """What :func:`trimmed_sums` gives, per group ``g`` of ``G``."""

    A: Tensor  #: [G, p, p] Σ w cols colsᵀ over the kept residuals
    rhs: Tensor  #: [G, p] Σ w y cols
    ratio: Tensor  #: [G, K] Σ y / v over each order's kept residuals
    kept: Tensor  #: [G, K] how many each order keeps


def trimmed_sums(
    u2: Tensor,
    y: Tensor,
    b: Tensor,
    cols: Tensor,
    axis: Tensor,
    first: Tensor,
    last: Tensor,
    steps: int,
    order: Tensor,
    orders: int,
    group: Tensor | None,
    r: Tensor,
    q: Tensor,
    cutoff: float,
    maneuver: float,
) -> TrimmedSums | None:
    """One scoring step's sums of :func:`torchsvs.datasets.noise_estimate.estimate_noise`'s
    trimmed fit for each of the ``G`` fits of ``r [G, m]``, ``q [G]`` (a jackknife's refit
    ``g`` leaves out the residuals of ``group == g``; ``group`` None: one fit of all):
    ``u2``, ``y``, ``b`` ``[N]`` float64, ``cols [N, p]``, and int64 ``axis``, ``first``,
    ``last`` (the stencils' steps numbered ``0..steps-1``) and ``order`` (``0..orders-1``)
    ``[N]``. ``None`` where the compiled loops are unavailable (or ``G`` is above
    :data:`MAX_FITS`)."""
    if not build.usable(u2, y, b, cols, r, q) or u2.dtype != torch.float64 or len(r) > MAX_FITS:
        return None
    N, p = cols.shape
    G, m = r.shape
    A = torch.empty(G, p, p, dtype=torch.float64)
    rhs = torch.empty(G, p, dtype=torch.float64)
    ratio = torch.empty(G, orders, dtype=torch.float64)
    kept = torch.empty(G, orders, dtype=torch.float64)
    inputs = [x.contiguous() for x in (u2, y, b, cols, axis, first, last, order)]
    grouped = group.contiguous() if group is not None else None
    r, q = r.contiguous(), q.contiguous()
    lib = build.library()
    assert lib is not None
    failed = lib.trimmed_sums_f64(
        N, G, m, p, orders, steps, *(x.data_ptr() for x in inputs),
        None if grouped is None else grouped.data_ptr(), r.data_ptr(), q.data_ptr(),
        cutoff**2, maneuver**2, A.data_ptr(), rhs.data_ptr(), ratio.data_ptr(), kept.data_ptr(),
    )  # fmt: skip
    assert failed == 0, "at most MAX_FITS fits"
    return TrimmedSums(A, rhs, ratio, kept)

r"""The Kalman filter and RTS smoother of each axis as associative scans over time.

Särkkä and García-Fernández (2021) write the filter and the smoother as prefix "sums" of
per-step elements under associative operators, so a track of ``T`` steps needs ``O(log T)``
sequential rounds of large elementwise operations instead of ``T`` small steps: for a few long
tracks (recorded flights: a dozen tracks of thousands of steps) that is what keeps a CPU busy.
Here for the two-state axes of :mod:`torchsvs.kernels.axes` (2×2 blocks, element by element:
:mod:`torchsvs.kernels.blocks`).

Filtering elements (Lemma 8 of the paper), with ``S = H Q Hᵀ + R``, ``K = Q Hᵀ S⁻¹``:

.. math::
    A_k = (I - K H) F_k,\ b_k = K y_k,\ C_k = (I - K H) Q_k,\
    \eta_k = F_k^T H^T S^{-1} y_k,\ J_k = F_k^T H^T S^{-1} H F_k

(the first step instead carries the prior's Kalman update, with ``A = J = 0``, ``η = 0``),
combined as

.. math::
    M = (I + C_i J_j)^{-1}:\ A_{ij} = A_j M A_i,\ b_{ij} = A_j M (b_i + C_i \eta_j) + b_j,\
    C_{ij} = A_j M C_i A_j^T + C_j,

    \eta_{ij} = A_i^T M^T (\eta_j - J_j b_i) + \eta_i,\ J_{ij} = A_i^T M^T J_j A_i + J_i

(``(I + J_j C_i)⁻¹ = Mᵀ`` since ``C`` and ``J`` are symmetric); the prefix up to ``k`` holds the
filtered mean in ``b`` and covariance in ``C``. Smoothing elements (Lemma 10),
``E_k = P_k F_{k+1}^T P_{k+1|k}^{-1}``, ``g_k = m_k - E_k m_{k+1|k}``,
``L_k = P_k - E_k P_{k+1|k} E_k^T`` (the last: ``E = 0``, ``g = m``, ``L = P``), combined as
``(E_i E_j, E_i g_j + g_i, E_i L_j E_iᵀ + L_i)`` from the end.

A missing measurement makes ``H = 0``: the element is a pure prediction. Results equal the
sequential recursions up to rounding (tested to 1e-9 in float64).

References:
    Särkkä, García-Fernández, "Temporal parallelization of Bayesian smoothers", IEEE Trans.
    Automatic Control 66(1), 2021. doi:10.1109/TAC.2020.2976316
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchsvs.kernels.blocks import (
    Mat2,
    Sym2,
    full,
    inverse,
    inverse_general,
    matmul,
    matvec,
    symmetric_part,
    transpose,
)

Elements = tuple[Tensor, ...]


def prefer_scan(tracks: int, steps: int) -> bool:
    """Whether an associative scan over time beats the step-by-step tensor loop: for few, long
    tracks (its ``O(log T)`` rounds do several times the arithmetic of the loop, which pays only
    where the loop's cost is the per-step overhead of small operations). The compiled loops
    beat both; this choice is for the tensor loops (:func:`~torchsvs.kernels.eager_loops`, no
    compiler, higher derivatives)."""
    return steps >= 64 and tracks * 16 <= steps * 4 + 4096


def associative_scan(
    combine: Callable[[Elements, Elements], Elements], elems: Elements
) -> Elements:
    """Inclusive prefix combination along time (dim 1) of ``[B, T, ...]`` tensors:
    ``out_k = e_0 ⊗ e_1 ⊗ ... ⊗ e_k`` for an associative ``combine(earlier, later)``, in
    ``O(log T)`` rounds (pairs are combined, the half-length problem is solved, the rest filled
    in)."""
    steps = elems[0].shape[1]
    if steps < 2:
        return elems
    pairs = steps // 2
    reduced = combine(
        tuple(x[:, 0 : 2 * pairs : 2] for x in elems), tuple(x[:, 1 : 2 * pairs : 2] for x in elems)
    )
    odd = associative_scan(combine, reduced)  # prefixes ending at steps 1, 3, 5, ...
    rest = combine(tuple(x[:, : (steps - 1) // 2] for x in odd), tuple(x[:, 2::2] for x in elems))
    even = tuple(torch.cat([x[:, :1], r], dim=1) for x, r in zip(elems, rest, strict=True))
    out = []
    for e, o in zip(even, odd, strict=True):
        merged = e.new_empty(e.shape[0], steps, *e.shape[2:])
        merged[:, 0::2] = e
        merged[:, 1::2] = o
        out.append(merged)
    return tuple(out)


def _combine_filter(i: Elements, j: Elements) -> Elements:
    A_i, b_i, C_i, eta_i, J_i = (
        Mat2(*i[:4]),
        (i[4], i[5]),
        Sym2(*i[6:9]),
        (i[9], i[10]),
        Sym2(*i[11:14]),
    )
    A_j, b_j, C_j, eta_j, J_j = (
        Mat2(*j[:4]),
        (j[4], j[5]),
        Sym2(*j[6:9]),
        (j[9], j[10]),
        Sym2(*j[11:14]),
    )
    CJ = matmul(full(C_i), full(J_j))
    M = inverse_general(Mat2(1 + CJ.a, CJ.b, CJ.c, 1 + CJ.d))
    AjM = matmul(A_j, M)
    A = matmul(AjM, A_i)
    Ceta = matvec(full(C_i), eta_j)
    b = matvec(AjM, (b_i[0] + Ceta[0], b_i[1] + Ceta[1]))
    C = symmetric_part(matmul(matmul(AjM, full(C_i)), transpose(A_j)))
    AiTMT = matmul(transpose(A_i), transpose(M))
    Jb = matvec(full(J_j), b_i)
    eta = matvec(AiTMT, (eta_j[0] - Jb[0], eta_j[1] - Jb[1]))
    J = symmetric_part(matmul(matmul(AiTMT, full(J_j)), A_i))
    return (
        *A,
        b[0] + b_j[0],
        b[1] + b_j[1],
        C.a + C_j.a,
        C.b + C_j.b,
        C.c + C_j.c,
        eta[0] + eta_i[0],
        eta[1] + eta_i[1],
        J.a + J_i.a,
        J.b + J_i.b,
        J.c + J_i.c,
    )


def filter_scan(
    position: Tensor,
    observed: Tensor,
    noise: Tensor,
    x0: tuple[Tensor, Tensor],
    P0: Sym2,
    Q: Sym2,
    interval: Tensor,
) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """Filtered means ``(p, v)`` and covariances of position-only Kalman filters per axis.

    A deliberate twin of the Kalman branch of :func:`torchsvs.kernels.axes._forward_step`
    (the first element is the prior's Kalman update, in the scan's standard form ``P − K S Kᵀ``
    where the loop has Joseph's: the last bits differ, so it is not shared); the tensor loop
    runs it only for few, long tracks (:func:`prefer_scan`).
    ``tests/test_kernels.py::test_time_scan_on_few_long_tracks_equals_general_path`` holds
    it to the general path to 1e-8.

    Args:
        position: measurements ``[B, T, m]`` (0 where missing); observed: ``[B, T, m]`` float 0/1.
        noise: ``R`` per axis with 1 where missing, ``[B, T, m]`` or ``[m]``.
        x0, P0: the prior one step before the first measurement, ``[B, m]`` each.
        Q: process noise per step (``[B, T, 1]`` or 0-d each); interval: ``T`` per step, same.
    """
    B, steps, m = position.shape
    f, y = observed, position
    T = interval.expand(B, steps, 1)
    Qa, Qb, Qc = (x.expand(B, steps, 1) for x in Q)
    R = noise.expand(B, steps, m)
    # Steps after the first: the model's own elements.
    S = f * Qa + R
    k1, k2 = f * Qa / S, f * Qb / S
    A = Mat2(1 - k1, (1 - k1) * T, -k2, 1 - k2 * T)
    b = (k1 * y, k2 * y)
    C = Sym2(Qa - k1 * k1 * S, Qb - k1 * k2 * S, Qc - k2 * k2 * S)
    u, w = f * y / S, f / S
    eta, J = (u, T * u), Sym2(w, w * T, w * T * T)
    # The first step: the prior's prediction and update (A = 0, η = 0, J = 0).
    T0 = T[:, 0]
    pp, vp = x0[0] + T0 * x0[1], x0[1]
    bT = P0.b + T0 * P0.c
    a1, b1, c1 = P0.a + T0 * (P0.b + bT) + Qa[:, 0], bT + Qb[:, 0], P0.c + Qc[:, 0]
    f0, y0 = f[:, 0], y[:, 0]
    S0 = f0 * a1 + R[:, 0]
    g1, g2 = f0 * a1 / S0, f0 * b1 / S0
    e0 = f0 * (y0 - pp)
    first = (
        *(torch.zeros_like(y0),) * 4,
        pp + g1 * e0,
        vp + g2 * e0,
        a1 - g1 * g1 * S0,
        b1 - g1 * g2 * S0,
        c1 - g2 * g2 * S0,
        *(torch.zeros_like(y0),) * 5,
    )
    elems = tuple(
        torch.cat([head.unsqueeze(1), x[:, 1:]], dim=1)
        for head, x in zip(first, (*A, *b, *C, *eta, *J), strict=True)
    )
    out = associative_scan(_combine_filter, elems)
    return (out[4], out[5]), Sym2(out[6], out[7], out[8])


def _combine_smoother(later: Elements, earlier: Elements) -> Elements:
    """``earlier ⊗ later`` for the smoother's suffix scan (arguments in scan order)."""
    E_i, g_i, L_i = Mat2(*earlier[:4]), (earlier[4], earlier[5]), Sym2(*earlier[6:9])
    E_j, g_j, L_j = Mat2(*later[:4]), (later[4], later[5]), Sym2(*later[6:9])
    E = matmul(E_i, E_j)
    g = matvec(E_i, g_j)
    L = symmetric_part(matmul(matmul(E_i, full(L_j)), transpose(E_i)))
    return (*E, g[0] + g_i[0], g[1] + g_i[1], L.a + L_i.a, L.b + L_i.b, L.c + L_i.c)


def smoother_scan(
    mean: tuple[Tensor, Tensor],
    cov: Sym2,
    pred_mean: tuple[Tensor, Tensor],
    pred_cov: Sym2,
    interval: Tensor,
) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """Fixed-interval RTS means and covariances per axis from a filter pass (``[B, T, m]``)."""
    B, steps, m = mean[0].shape
    T = interval.expand(B, steps, 1)[:, 1:]
    P = Sym2(*(x[:, :-1] for x in cov))
    Pp = Sym2(*(x[:, 1:] for x in pred_cov))
    # E = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]].
    E = matmul(Mat2(P.a + T * P.b, P.b, P.b + T * P.c, P.c), full(inverse(Pp)))
    Em = matvec(E, (pred_mean[0][:, 1:], pred_mean[1][:, 1:]))
    g = (mean[0][:, :-1] - Em[0], mean[1][:, :-1] - Em[1])
    EPE = symmetric_part(matmul(matmul(E, full(Pp)), transpose(E)))
    L = Sym2(P.a - EPE.a, P.b - EPE.b, P.c - EPE.c)
    zero = torch.zeros_like(mean[0][:, -1:])
    last = (zero, zero, zero, zero, mean[0][:, -1:], mean[1][:, -1:], *(x[:, -1:] for x in cov))
    elems = tuple(torch.cat([x, l], dim=1) for x, l in zip((*E, *g, *L), last, strict=True))
    flipped = tuple(x.flip(1) for x in elems)
    out = tuple(x.flip(1) for x in associative_scan(_combine_smoother, flipped))
    return (out[4], out[5]), Sym2(out[6], out[7], out[8])

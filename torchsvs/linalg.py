"""Numerical building blocks shared by every estimator: one home for each formula.

All functions broadcast over leading batch axes and use column-vector math on the last axes
(a matrix ``A`` of shape ``[..., n, n]`` acts on a vector ``x`` of shape ``[..., n]`` as ``A @ x``).
Covariances are never inverted explicitly: solves go through a Cholesky factor.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor


def holds_inf(x: Tensor) -> bool:
    """Whether ``x`` holds ±inf (NaN aside). A sum that skips NaN is finite unless an element
    is infinite or the sum overflows: one pass without temporaries, and an exact look only
    then (``isinf(x).any()`` costs about 30× as much on a large batch)."""
    x = x.detach()
    return not bool(torch.isfinite(x.nansum())) and bool(torch.isinf(x).any())


def holds_nan(x: Tensor) -> bool:
    """Whether ``x`` holds a NaN: its sum is NaN then, and otherwise only when partial sums
    overflow to both infinities (then an exact look)."""
    x = x.detach()
    return bool(torch.isnan(x.sum())) and bool(torch.isnan(x).any())


def seen_from_here_on(seen: Tensor) -> Tensor:
    """``seen [B, T, ...]`` (bool: a measurement at the step) as whether one is at the step or
    any later one: ``False`` on a padded batch's steps after a track's last measurement."""
    return seen.flip(1).to(torch.int8).cummax(1).values.flip(1).bool()


def symmetrize(P: Tensor) -> Tensor:
    """``(P + Pᵀ) / 2``: removes the asymmetry that rounding adds to a covariance."""
    return 0.5 * (P + P.mT)


def matvec(A: Tensor, x: Tensor) -> Tensor:
    """``A @ x`` for ``A [..., r, c]`` and ``x [..., c]``."""
    return (A @ x.unsqueeze(-1)).squeeze(-1)


#: Set while a compiled step runs (:mod:`torchsvs.kernels.compiled`): :func:`cholesky` then
#: does not branch on its data; a factor that fails is NaN, and the step runs again eagerly.
BRANCH_FREE = {"cholesky": False}


def cholesky(S: Tensor) -> Tensor:
    """Lower Cholesky factor of a symmetric positive definite matrix.

    Adds a small relative jitter only where the plain factorisation fails (for example a
    float32 covariance that rounding left semi-definite), so well-conditioned inputs are
    factored exactly and gradients stay those of ``torch.linalg.cholesky``.
    """
    L, info = torch.linalg.cholesky_ex(S)
    if BRANCH_FREE["cholesky"]:
        return torch.where((info == 0)[..., None, None], L, torch.nan)
    if not bool((info > 0).any()):
        return L
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    scale = S.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1.0)[..., None, None]
    eps = torch.finfo(S.dtype).eps
    for power in (1, 2, 3, 4):
        L, info = torch.linalg.cholesky_ex(S + eye * scale * eps * 10.0**power)
        if not bool((info > 0).any()):
            return L
    raise torch.linalg.LinAlgError("matrix is not positive definite, even with jitter")


def psd_solve(S: Tensor, B: Tensor) -> Tensor:
    """``S⁻¹ B`` for symmetric positive definite ``S [..., m, m]`` and ``B [..., m, k]``."""
    return torch.cholesky_solve(B, cholesky(S))


def right_psd_solve(A: Tensor, S: Tensor) -> Tensor:
    """``A S⁻¹`` for ``A [..., k, m]`` and symmetric positive definite ``S [..., m, m]``."""
    return psd_solve(S, A.mT).mT


def joseph_update(P: Tensor, K: Tensor, H: Tensor, R: Tensor) -> Tensor:
    """Joseph-form covariance update ``(I − KH) P (I − KH)ᵀ + K R Kᵀ``.

    Valid for any gain ``K``, optimal or not: that is why the SVSF uses it too (Eq. (28),
    left side, Chen et al. 2020); the short form ``(I − KH) P`` holds only for the Kalman gain.

    Args:
        P: prior covariance ``[..., n, n]``.
        K: gain ``[..., n, m]``.
        H: measurement matrix ``[..., m, n]``.
        R: measurement noise covariance ``[..., m, m]``.
    """
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    A = eye - K @ H
    return symmetrize(A @ P @ A.mT + K @ R @ K.mT)


def gaussian_log_density(residual: Tensor, L: Tensor, count: Tensor | float) -> Tensor:
    """``log N(r; 0, L Lᵀ) = −½ (|L⁻¹ r|² + log det(L Lᵀ) + count · log 2π)``: the library's one
    Gaussian log-density (the KF's log-likelihood, the innovation NLL, particle weights).

    Args:
        residual: ``r [..., m]``; missing components zero (with a unit row/column in ``L``).
        L: lower Cholesky factor ``[..., m, m]``, broadcastable against ``residual``.
        count: components that count toward the normalising constant (observed ones; ``0``
            leaves the constant out).
    """
    white = torch.linalg.solve_triangular(L, residual.unsqueeze(-1), upper=False).squeeze(-1)
    log_det = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return -0.5 * (white.square().sum(-1) + log_det + count * math.log(2 * math.pi))


def mixture_moments(
    weights: Tensor, means: Sequence[Tensor], covs: Sequence[Tensor]
) -> tuple[Tensor, Tensor]:
    """Mean and covariance of the Gaussian mixture ``Σ_k w_k N(x_k, P_k)`` (moment matching):
    ``x = Σ_k w_k x_k``, ``P = Σ_k w_k (P_k + (x_k − x)(x_k − x)ᵀ)``, the spread of the means
    included; the IMM's mixing and combination and its smoother's collapse.

    Args:
        weights: ``[..., K]``, summing to 1 over the last axis.
        means: ``K`` tensors ``[..., n]``; covs: ``K`` tensors ``[..., n, n]`` (terms added in
            order).
    """
    K = len(means)
    x = mixture_mean(weights, means)
    P = weights[..., 0, None, None] * (covs[0] + _outer(means[0] - x))
    for k in range(1, K):
        P = P + weights[..., k, None, None] * (covs[k] + _outer(means[k] - x))
    return x, symmetrize(P)


def sum_in_order(terms: Sequence[Tensor]) -> Tensor:
    """The sum of ``terms``, added in order (``torch.stack(terms).sum(0)`` may add in another
    order and change the last bits; the IMM's and the road tracker's sums are pinned to them)."""
    total = terms[0]
    for term in terms[1:]:
        total = total + term
    return total


def mixture_mean(weights: Tensor, means: Sequence[Tensor]) -> Tensor:
    """``Σ_k w_k x_k`` for ``weights [..., K]`` and ``K`` means ``[..., n]`` (added in order):
    :func:`mixture_moments`' mean, alone."""
    x = weights[..., 0, None] * means[0]
    for k in range(1, len(means)):
        x = x + weights[..., k, None] * means[k]
    return x


def _outer(d: Tensor) -> Tensor:
    return d.unsqueeze(-1) * d.unsqueeze(-2)


def svsf_gain_ratio(e_prior: Tensor, e_post_prev: Tensor, psi: Tensor, gamma: Tensor) -> Tensor:
    """Diagonal of the SVSF gain, ``(|e_{k+1|k}| + γ|e_{k|k}|) · sat(e_{k+1|k}/ψ) / e_{k+1|k}``.

    Eq. (23), Chen et al. 2020, written without the division by the innovation: with ``sat``
    the clamp to ``[−1, 1]`` of Eq. (6), ``sat(e/ψ)/e = 1/max(|e|, ψ)`` (the singularity at
    ``e = 0`` is removable), so the ratio is ``(|e_{k+1|k}| + γ|e_{k|k}|) / max(|e_{k+1|k}|, ψ)``,
    finite with finite gradients at ``e = 0``. The gain is then ``K = H⁺ diag(ratio)``.

    Args:
        e_prior: a-priori innovation ``e_{k+1|k}``, ``[..., m]``.
        e_post_prev: previous a-posteriori innovation ``e_{k|k}`` (the memory), ``[..., m]``.
        psi: boundary layer widths ψ, broadcastable to ``[..., m]``, positive.
        gamma: memory (convergence rate) γ in ``[0, 1)``, broadcastable.
    """
    magnitude = e_prior.abs()
    return (magnitude + gamma * e_post_prev.abs()) / torch.maximum(magnitude, psi)


#: How the variable boundary layer inflates its prior beyond the limit
#: (:func:`boundary_inflation`).
INFLATIONS = ("innovation", "gain")


def boundary_inflation(
    excess: Tensor,
    error: Tensor,
    limit: Tensor,
    a: Tensor,
    r: Tensor,
    seen: Tensor,
    inflation: str = "innovation",
    max_gain: float = 0.999,
) -> Tensor:
    """The prior's inflation ``λ ≥ 1`` of the variable boundary layer
    (:class:`~torchsvs.filters.VariableBoundarySVSF`), ``[...]`` from ``[..., m]`` components:
    1 while every ``Ē_i ≤ ψ_i √(a_i + r_i)``, else the least ``λ`` that puts every
    component's innovation on the layer's edge (``"innovation"``: ``Ē_i² = ψ_i² (λ a_i + r_i)``)
    or gives it Gadsden & Habibi's gain beyond the limit (``"gain"``:
    ``g_i = k_i max(1, Ē_i / max(k_i |e_i|, ψ_i √(a_i + r_i)))``, ``k_i = a_i / (a_i + r_i)``,
    reached by ``λ = r_i g_i / ((1 − g_i) a_i)``); a gain above ``max_gain`` is not asked for.

    Args:
        excess: ``Ē = |e_{k+1|k}| + γ|e_{k|k}|``; error: ``|e_{k+1|k}|``.
        limit: ψ in innovation standard deviations, broadcastable.
        a: ``(H P Hᵀ)_ii`` of the prior; r: ``R_ii``.
        seen: the observed components (the others ask for nothing).
    """
    a = torch.where(seen, a, torch.ones_like(a))
    most = r * max_gain / ((1.0 - max_gain) * a)  # the λ of the largest gain
    if inflation == "innovation":
        each = ((excess / limit).square() - r) / a
    else:
        k = a / (a + r)
        ratio = excess / torch.maximum(k * error, limit * (a + r).sqrt())
        wanted = (k * torch.clamp_min(ratio, 1.0)).clamp_max(max_gain)
        each = r * wanted / ((1.0 - wanted) * a)
    each = torch.where(seen, torch.minimum(each, most), torch.zeros_like(each))
    return each.amax(-1).clamp_min(1.0)


def has_orthonormal_rows(H: Tensor) -> bool:
    """Whether ``H [m, n]`` has ``H Hᵀ = I`` exactly (a selection of state components, or the
    identity of a full-state artificial measurement)."""
    eye = torch.eye(H.shape[0], dtype=H.dtype, device=H.device)
    return bool(torch.equal(H @ H.mT, eye))


def masked_pinv(H: Tensor, mask: Tensor | None = None, orthonormal: bool | None = None) -> Tensor:
    """Moore-Penrose pseudo-inverse ``(D H)⁺`` of ``H [..., m, n]`` with the rows of missing
    components zeroed (``D = diag(mask)``, ``mask [..., m]`` True where observed, ``None``: all).

    When ``H`` has orthonormal rows (:func:`has_orthonormal_rows`; ``orthonormal`` says so when
    the caller knows, else a constant ``[m, n]`` is checked), ``(D H)⁺ = Hᵀ D`` exactly, without
    an SVD per track and step.
    """
    masked = H if mask is None else H * mask.to(H.dtype).unsqueeze(-1)
    if orthonormal is None and H.ndim == 2:
        orthonormal = has_orthonormal_rows(H)
    if orthonormal:
        return masked.mT
    return torch.linalg.pinv(masked)


def mask_measurement(H: Tensor, R: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Removes missing measurement components without changing shapes.

    Rows of ``H`` for missing components become zero and ``R`` becomes block diagonal with the
    observed block and an identity on the missing ones, so ``S = H P Hᵀ + R`` stays invertible,
    a gain built from ``S⁻¹`` gets zero columns there and ``log det S`` is that of the observed
    block: the same as dropping the rows, with a batch-friendly fixed shape.

    Args:
        H: ``[..., m, n]``; R: ``[..., m, m]``; mask: ``[..., m]`` boolean, True where observed.

    Returns:
        Masked ``H [..., m, n]`` and ``R [..., m, m]`` broadcast to the batch shape of ``mask``.
    """
    return H * mask.to(H.dtype).unsqueeze(-1), mask_covariance(R, mask)


def mask_covariance(R: Tensor, mask: Tensor) -> Tensor:
    """``R`` with an identity on the missing components (see :func:`mask_measurement`)."""
    both = mask.unsqueeze(-1) & mask.unsqueeze(-2)
    eye = torch.eye(mask.shape[-1], dtype=R.dtype, device=R.device)
    return torch.where(both, R, eye)


def log_divisor(log_total: Tensor) -> tuple[Tensor, Tensor]:
    """``log_total`` (a normaliser in log space) with ``-inf`` replaced by 0, and where it was
    ``-inf``: dividing by a total of probability 0 would give NaN, so the caller divides by 1
    there and sets those quotients itself."""
    zero = torch.isneginf(log_total)
    return torch.where(zero, torch.zeros_like(log_total), log_total), zero

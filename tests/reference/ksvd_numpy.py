"""Float64 NumPy reference ("oracle") for the K-SVD filter and an exact measurement update.

Written only from the paper

    Bermúdez Ordoñez, Arnaldo Valdés, Gómez Comendador, "Engineering Applications of Adaptive
    Kalman Filtering Based on Singular Value Decomposition (SVD)", Appl. Sci. 10(15):5168, 2020
    (``/work/shared/papers/ksvd-bermudez-2020.txt``), Sec. 4 and Algorithm 1,

not from torchsvs. Single track, plain loops, written for clarity. Conventions as in
``svs_numpy.py``: ``z [T, m]`` with NaN for a missing component, the prior ``x0, P0`` one step
before ``z[0]``, each step predicts then updates, constant ``F, H, Q, R``.

Readings decided here:

* The covariance is kept as ``P = U D² Uᵀ`` (Eq. (17)); Algorithm 1's initialisation is the SVD
  of ``P0`` itself (``P0 = U diag(σ) Uᵀ``, ``D0 = diag(√σ)``).
* Time update, Eqs. (20)-(23): the SVD of the pre-array ``[D Uᵀ Fᵀ; (Q^{1/2})ᵀ]`` (``Ψ = I``),
  with ``Q^{1/2}`` any factor ``Q^{1/2} Q^{1/2}ᵀ = Q`` (here NumPy's Cholesky factor); its right
  factor and singular values are ``U⁻`` and ``D⁻``.
* Measurement update, Eqs. (31)-(44): ``R⁻¹ = L Lᵀ`` is the Cholesky factor of the inverse
  (Eq. (31), formed literally with ``np.linalg.inv``); the SVD of ``[Lᵀ H U⁻; D⁻⁻¹]`` gives
  ``V*``, ``D*``; ``U⁺ = U⁻ V*``, ``D⁺ = D*⁻¹``; ``K = U⁺ D⁺² U⁺ᵀ Hᵀ L Lᵀ`` (Eq. (43)) and
  ``x⁺ = x⁻ + K (z − H x⁻)`` (Eq. (44)).
* A missing component is left out: the update uses the observed rows of ``H`` and the observed
  block of ``R``; with nothing observed the posterior is the prediction.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

__all__ = ["ksvd_filter", "exact_information_update"]


def _time_update(U: np.ndarray, D: np.ndarray, F: np.ndarray, Q: np.ndarray):
    pre = np.vstack([np.diag(D) @ U.T @ F.T, np.linalg.cholesky(Q).T])  # Eq. (20)
    _, s, Vt = np.linalg.svd(pre)  # Eq. (21)
    return Vt.T, s  # Eq. (23): U⁻ = V, D⁻ = D'


def _measurement_update(U: np.ndarray, D: np.ndarray, H: np.ndarray, R: np.ndarray):
    L = np.linalg.cholesky(np.linalg.inv(R))  # Eq. (31)
    pre = np.vstack([L.T @ H @ U, np.diag(1.0 / D)])  # Eq. (32)
    _, s, Vt = np.linalg.svd(pre)  # Eq. (33)
    U_post, D_post = U @ Vt.T, 1.0 / s  # Eqs. (37)-(38)
    K = U_post @ np.diag(D_post**2) @ U_post.T @ H.T @ L @ L.T  # Eq. (43)
    return U_post, D_post, K


def ksvd_filter(
    z: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
    F: np.ndarray,
    H: np.ndarray,
    Q: np.ndarray,
    R: np.ndarray,
) -> dict[str, np.ndarray]:
    """Algorithm 1 (without the adaptive R of Eqs. (29)-(30)): ``mean``, ``cov``,
    ``pred_mean``, ``pred_cov`` and ``gain`` (``[T, n, m]``, zero columns where missing)."""
    T, m = z.shape
    n = x0.shape[0]
    Uc, sigma, _ = np.linalg.svd(P0)
    U, D = Uc, np.sqrt(sigma)
    x = x0.copy()
    out = {k: [] for k in ("mean", "cov", "pred_mean", "pred_cov", "gain")}
    for t in range(T):
        x = F @ x  # Eq. (5)
        U, D = _time_update(U, D, F, Q)
        out["pred_mean"].append(x.copy())
        out["pred_cov"].append(U @ np.diag(D**2) @ U.T)
        seen = ~np.isnan(z[t])
        gain = np.zeros((n, m))
        if seen.any():
            H_o, R_o = H[seen], R[np.ix_(seen, seen)]
            U, D, K = _measurement_update(U, D, H_o, R_o)
            x = x + K @ (z[t, seen] - H_o @ x)  # Eq. (44)
            gain[:, seen] = K
        out["mean"].append(x.copy())
        out["cov"].append(U @ np.diag(D**2) @ U.T)
        out["gain"].append(gain)
    return {k: np.stack(v) for k, v in out.items()}


def _inverse(A: list[list[Fraction]]) -> list[list[Fraction]]:
    """Gauss-Jordan inverse in exact rational arithmetic."""
    n = len(A)
    M = [row[:] + [Fraction(int(i == j)) for j in range(n)] for i, row in enumerate(A)]
    for col in range(n):
        pivot = next(r for r in range(col, n) if M[r][col] != 0)
        M[col], M[pivot] = M[pivot], M[col]
        scale = M[col][col]
        M[col] = [v / scale for v in M[col]]
        for r in range(n):
            if r != col and M[r][col] != 0:
                factor = M[r][col]
                M[r] = [a - factor * b for a, b in zip(M[r], M[col], strict=True)]
    return [row[n:] for row in M]


def exact_information_update(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``(P⁻¹ + Hᵀ R⁻¹ H)⁻¹`` (Eq. (26)) in exact rational arithmetic from the float64 entries
    of ``P``, ``H``, ``R`` (each taken as the exact binary fraction it is), rounded to float64
    once at the end: the exact posterior of the problem the filter was given."""

    def exact(A: np.ndarray) -> list[list[Fraction]]:
        return [[Fraction(float(v)) for v in row] for row in np.atleast_2d(A)]

    def mul(A, B):
        return [
            [
                sum((a * b for a, b in zip(row, col, strict=True)), Fraction(0))
                for col in zip(*B, strict=True)
            ]
            for row in A
        ]

    Hx, Rinv, Pinv = exact(H), _inverse(exact(R)), _inverse(exact(P))
    HtRH = mul(mul([list(c) for c in zip(*Hx, strict=True)], Rinv), Hx)
    info = [[a + b for a, b in zip(r1, r2, strict=True)] for r1, r2 in zip(Pinv, HtRH, strict=True)]
    return np.array([[float(v) for v in row] for row in _inverse(info)])

"""Float64 NumPy reference of the adaptive measurement covariance, Eqs. (29)-(30) of

    Bermúdez Ordoñez, Arnaldo Valdés, Gómez Comendador, "Engineering Applications of Adaptive
    Kalman Filtering Based on Singular Value Decomposition (SVD)", Appl. Sci. 10(15):5168, 2020
    (``/work/shared/papers/ksvd-bermudez-2020.txt``)

written from the paper, one track, plain loops, and a Kalman filter that takes a per-step R.

Readings (the paper leaves them open; torchsvs/filters/adaptive.py states the same):

* ``S^i_k`` is the last ``window`` samples of component ``i`` ending at ``z_k`` (``lag = 1``:
  at ``z_{k-1}``); samples before the first step do not exist.
* ``diff`` is taken between adjacent samples that are both observed (NaN: missing).
* ``std`` is MATLAB's: about the mean, divided by ``count - 1``; ``σ = std(diff(S))/√2``.
* ``σ`` below ``floor`` is raised to it; with fewer than ``least`` differences the component
  keeps the model's R; a component with an estimate has no covariance with any other.
"""

from __future__ import annotations

import numpy as np


def adaptive_R(
    z: np.ndarray, R: np.ndarray, window: int, floor: float, least: int, lag: int = 0
) -> np.ndarray:
    """``R_k`` for every step of ``z [T, m]``: ``[T, m, m]``."""
    T, m = z.shape
    out = np.empty((T, m, m))
    for k in range(T):
        last = k - lag  # the segment's last sample
        first = last - window + 1
        Rk = R.copy()
        for i in range(m):
            diffs = []
            for j in range(max(first, 0) + 1, last + 1):
                a, b = z[j - 1, i], z[j, i]
                if not (np.isnan(a) or np.isnan(b)):
                    diffs.append(b - a)
            if len(diffs) < least:
                continue
            sigma = np.std(np.array(diffs), ddof=1) / np.sqrt(2.0)  # Eq. (30)
            sigma = max(sigma, floor)
            Rk[i, :] = 0.0
            Rk[:, i] = 0.0
            Rk[i, i] = sigma**2  # Eq. (29)
        out[k] = Rk
    return out


def kalman_filter(
    z: np.ndarray,
    F: np.ndarray,
    H: np.ndarray,
    Q: np.ndarray,
    R_seq: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The textbook KF (no missing values) with ``R_seq[k]`` at step ``k``: means and covs."""
    x, P = x0.copy(), P0.copy()
    means, covs = [], []
    n = len(x0)
    for k in range(z.shape[0]):
        x = F @ x
        P = F @ P @ F.T + Q
        S = H @ P @ H.T + R_seq[k]
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (z[k] - H @ x)
        A = np.eye(n) - K @ H
        P = A @ P @ A.T + K @ R_seq[k] @ K.T
        means.append(x.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs)

"""Float64 NumPy reference for the separate-modeling (SM) initialisation of Zhang & Zhou (2022).

Written from the paper's text (Sec. 4 (i): "the chord length between position measurements at
two adjacent times is used to approximate the target traveling distance", "the base state is
formulated according to the two-point differencing procedure", the unscented transform of
Julier & Uhlmann with ``2n + 1`` symmetric sigma points, "for the NCV model the acceleration
component ... is zero and the elements related to the acceleration in the covariance are
zero"), with the readings documented in ``torchsvs/filters/separate/``. One track, plain
loops over sigma points, for clarity.

Layout of the augmented state: ``[s, ds, (dds,) x_l, r_x, y_l, r_y, s_l]``.
"""

from __future__ import annotations

import numpy as np


def three_point(Z: np.ndarray, T2: float, T3: float, acceleration: str) -> np.ndarray:
    """The augmented state from stacked measurements ``Z = [x1, y1, x2, y2, x3, y3]``.

    ``acceleration``: ``"none"`` (NCV layout ``[s, ds, eta]``), ``"zero"`` (NCV embedded in
    the NCA layout) or ``"difference"`` (NCA: the second difference of the chord lengths).
    """
    p1, p2, p3 = np.array(Z[0:2]), np.array(Z[2:4]), np.array(Z[4:6])
    d12 = np.hypot(*(p2 - p1))
    d23 = np.hypot(*(p3 - p2))
    s = d12 + d23  # arc length counted from the first measurement
    ds = d23 / T3  # two-point differencing of the latest pair
    base = [s, ds]
    if acceleration == "difference":
        base.append((d23 / T3 - d12 / T2) / T3)
    elif acceleration == "zero":
        base.append(0.0)
    direction = (p3 - p1) / np.hypot(*(p3 - p1))
    eta = [p1[0], direction[0], p1[1], direction[1], 0.0]
    return np.array(base + eta)


def unscented_prior(
    z: np.ndarray,
    R: np.ndarray,
    T2: float,
    T3: float,
    acceleration: str,
    kappa: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of ``three_point`` over the noise of ``z[:3]`` (``[3, 2]``) by the
    unscented transform with ``P_Z = diag(R, R, R)``."""
    Z = np.asarray(z, dtype=np.float64)[:3].reshape(6)
    n = Z.size
    P = np.zeros((n, n))
    for i in range(3):
        P[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = R
    root = np.linalg.cholesky((n + kappa) * P)
    points = [Z]
    weights = [kappa / (n + kappa)]
    for i in range(n):
        points.append(Z + root[:, i])
        weights.append(1.0 / (2.0 * (n + kappa)))
    for i in range(n):
        points.append(Z - root[:, i])
        weights.append(1.0 / (2.0 * (n + kappa)))
    images = [three_point(p, T2, T3, acceleration) for p in points]
    mean = np.zeros_like(images[0])
    for w, g in zip(weights, images, strict=True):
        mean += w * g
    cov = np.zeros((mean.size, mean.size))
    for w, g in zip(weights, images, strict=True):
        cov += w * np.outer(g - mean, g - mean)
    return mean, cov

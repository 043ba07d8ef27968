"""A general linear-Gaussian model with fixed matrices."""

from __future__ import annotations

from torch import Tensor

from torchsvs.constraints import ArrayLike, SPDMatrix, as_tensor
from torchsvs.models.base import LinearModel


class LinearGaussian(LinearModel):
    r"""Time-invariant linear-Gaussian model (Eq. (1), Chen et al. 2020).

    .. math::
        x_t = F x_{t-1} + w_t,\quad w_t \sim N(0, Q);\qquad z_t = H x_t + v_t,\quad v_t \sim N(0, R)

    Args:
        F: transition ``[n, n]``.
        H: measurement matrix ``[m, n]``.
        Q: process noise covariance ``[n, n]``, symmetric positive definite.
        R: measurement noise covariance ``[m, m]``, symmetric positive definite.
        learn_noise: store Q and R as learnable Cholesky factors (else fixed buffers).
    """

    uses_dt = False
    F: Tensor
    H: Tensor

    def __init__(
        self, F: ArrayLike, H: ArrayLike, Q: ArrayLike, R: ArrayLike, learn_noise: bool = False
    ) -> None:
        super().__init__()
        F_t, H_t = as_tensor(F, "F"), as_tensor(H, "H")
        if F_t.ndim != 2 or F_t.shape[0] != F_t.shape[1]:
            raise ValueError(f"F: expected a square matrix [n, n], got shape {tuple(F_t.shape)}")
        n = F_t.shape[0]
        if H_t.ndim != 2 or H_t.shape[1] != n:
            raise ValueError(f"H: expected shape [m, {n}], got {tuple(H_t.shape)}")
        self.state_dim, self.meas_dim = n, H_t.shape[0]
        self.register_buffer("F", F_t)
        self.register_buffer("H", H_t)
        self.Q = SPDMatrix(Q, "Q", learn=learn_noise)
        self.R = SPDMatrix(R, "R", learn=learn_noise)
        if self.Q.raw.shape != (n, n):
            raise ValueError(f"Q: expected shape [{n}, {n}], got {tuple(self.Q.raw.shape)}")
        m = self.meas_dim
        if self.R.raw.shape != (m, m):
            raise ValueError(f"R: expected shape [{m}, {m}], got {tuple(self.R.raw.shape)}")

    def transition(self, dt: Tensor | None = None) -> Tensor:
        return self.F

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        return self.Q()

    def meas_matrix(self) -> Tensor:
        return self.H

    def meas_cov(self) -> Tensor:
        return self.R()

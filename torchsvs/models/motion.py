"""Kinematic motion models for target tracking."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive, SPDMatrix, as_tensor
from torchsvs.models.base import LinearModel


class ConstantVelocity(LinearModel):
    r"""Nearly constant velocity ("uniform motion") model, Eqs. (43)-(48), Chen et al. 2020.

    State ``[x, vx, y, vy]`` (Eq. (44); per axis position then velocity, ``ndim`` axes),
    position-only measurements (Eq. (45)). Per axis, with interval :math:`T` and power spectral
    density :math:`q` (``L`` in Eq. (48)):

    .. math::
        F = \begin{bmatrix}1 & T\\ 0 & 1\end{bmatrix},\qquad
        Q = q\begin{bmatrix}T^3/3 & T^2/2\\ T^2/2 & T\end{bmatrix},\qquad
        H = \begin{bmatrix}1 & 0\end{bmatrix}

    Args:
        ndim: number of spatial axes (2 for the papers' plane).
        dt: default sampling interval ``T`` in seconds; a per-step ``dt [B, T]`` passed to an
            estimator overrides it.
        q: power spectral density of the white-noise acceleration, > 0.
        r: measurement noise: a variance (scalar), per-axis variances ``[ndim]`` or a covariance
            ``[ndim, ndim]``.
        learn_noise: learn ``q`` (through its log) and ``R`` (through its Cholesky factor).
        learn_q, learn_r: learn only one of them (each defaults to ``learn_noise``): tuning ``q``
            on data whose sensor noise is known keeps ``R`` fixed.

    References:
        Chen, Xu, Yan, Li, "A Novel Smooth Variable Structure Smoother for Robust Estimation",
        Sensors 20(6):1781, 2020. doi:10.3390/s20061781
    """

    uses_dt = True
    H: Tensor

    def __init__(
        self,
        ndim: int = 2,
        dt: float = 1.0,
        q: float = 0.16,
        r: ArrayLike = 1.0,
        learn_noise: bool = False,
        learn_q: bool | None = None,
        learn_r: bool | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(ndim, int) or ndim < 1:
            raise ValueError(f"ndim: expected a positive integer, got {ndim!r}")
        if not (isinstance(dt, (int, float)) and dt > 0):
            raise ValueError(f"dt: expected a positive number, got {dt!r}")
        self.ndim = ndim
        self.state_dim, self.meas_dim = 2 * ndim, ndim
        self.dt = float(dt)
        self.q = Positive(q, "q", learn=learn_noise if learn_q is None else learn_q)
        r_t = as_tensor(r, "r")
        if r_t.ndim == 0:
            r_t = r_t * torch.eye(ndim, dtype=r_t.dtype)
        elif r_t.ndim == 1:
            if r_t.shape[0] != ndim:
                raise ValueError(f"r: expected {ndim} per-axis variances, got {tuple(r_t.shape)}")
            r_t = torch.diag(r_t)
        self.R = SPDMatrix(r_t, "r", learn=learn_noise if learn_r is None else learn_r)
        if self.R.raw.shape != (ndim, ndim):
            raise ValueError(f"r: expected shape [{ndim}, {ndim}], got {tuple(self.R.raw.shape)}")
        H = torch.zeros(ndim, 2 * ndim, dtype=r_t.dtype)
        H[torch.arange(ndim), 2 * torch.arange(ndim)] = 1.0
        self.register_buffer("H", H)

    @property
    def position_index(self) -> list[int]:
        """State indices of the positions (the measured components)."""
        return [2 * i for i in range(self.ndim)]

    @property
    def velocity_index(self) -> list[int]:
        """State indices of the velocities."""
        return [2 * i + 1 for i in range(self.ndim)]

    def _interval(self, dt: Tensor | None) -> Tensor:
        if dt is None:
            return torch.tensor(self.dt, dtype=self.H.dtype, device=self.H.device)
        return dt.to(self.H.dtype)

    def _per_axis(self, block: Tensor) -> Tensor:
        """Block-diagonal ``[..., 2·ndim, 2·ndim]`` from one 2×2 block ``[..., 2, 2]``."""
        lead, m = block.shape[:-2], self.ndim
        # kron(I, block) over the trailing axes: index (2i+a, 2j+b) = δ_ij block[a, b].
        full = block.new_zeros(*lead, m, 2, m, 2)
        full.diagonal(dim1=-4, dim2=-2).copy_(block.unsqueeze(-1).expand(*lead, 2, 2, m))
        return full.reshape(*lead, 2 * m, 2 * m)

    def transition(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        one, zero = torch.ones_like(T), torch.zeros_like(T)
        block = torch.stack([torch.stack([one, T], -1), torch.stack([zero, one], -1)], -2)
        return self._per_axis(block)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        block = torch.stack(
            [torch.stack([T**3 / 3, T**2 / 2], -1), torch.stack([T**2 / 2, T], -1)], -2
        )
        return self.q().to(block.dtype) * self._per_axis(block)

    def meas_matrix(self) -> Tensor:
        return self.H

    def meas_cov(self) -> Tensor:
        return self.R()

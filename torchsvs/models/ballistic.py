"""The ballistic re-entry model of Gadsden, Habibi, Kirubarajan 2012, Sec. 5.1."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, SPDMatrix, as_tensor
from torchsvs.models.base import StateSpaceModel


class BallisticReentry(StateSpaceModel):
    r"""A ballistic object falling through the atmosphere, tracked by a radar below it.

    State ``[h, v, β]``: altitude (m), speed (m/s, positive downward) and ballistic coefficient.
    Drag and gravity act on the object (Eqs. (36)-(39)), discretised as Eq. (40):

    .. math::
        x_{k+1} = F x_k - G\,[D(x_k) - g] + w_k,\quad
        F = \begin{bmatrix}1 & -T & 0\\ 0 & 1 & 0\\ 0 & 0 & 1\end{bmatrix},\quad
        G = \begin{bmatrix}0 \\ T \\ 0\end{bmatrix},\quad
        D(x) = \frac{g\,\rho(x_1)\,x_2^2}{2 x_3},\quad \rho(h) = \gamma e^{-\eta h}

    with ``Q`` of Eq. (44) and position-and-speed measurements ``z = [h, v] + v_k`` (Eqs.
    (45)-(46)). The paper's values (its digit groups read as thousands): ``T = 0.1`` s,
    ``q1 = 10⁴``, ``q2 = 10``, ``R = diag(10⁴, 10³)``, ``g = 9.81``, ``γ = 1.754``,
    ``η = 1.49·10⁻⁴``.

    Args:
        dt: sampling interval ``T`` (s).
        gravity: ``g`` used by the model (the scenario's gravity error doubles it in the truth or
            the model; see :func:`~torchsvs.scenarios.ballistic_scenario`).
        q1, q2: process noise intensities of the dynamics and of the ballistic coefficient.
        r: measurement noise variances ``[2]`` or covariance ``[2, 2]``.
        density, decay: ``γ`` and ``η`` of the air density.

    References:
        Gadsden, Habibi, Kirubarajan, "The Smooth Particle Variable Structure Filter", Trans.
        CSME 36(2), 2012 · Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to
        Tracking and Navigation", Wiley 2001.
    """

    uses_dt = True

    def __init__(
        self,
        dt: float = 0.1,
        gravity: float = 9.81,
        q1: float = 1e4,
        q2: float = 10.0,
        r: ArrayLike = (1e4, 1e3),
        density: float = 1.754,
        decay: float = 1.49e-4,
    ) -> None:
        super().__init__()
        if not dt > 0:
            raise ValueError(f"dt: expected a positive number, got {dt!r}")
        self.state_dim, self.meas_dim = 3, 2
        self.dt, self.gravity, self.q1, self.q2 = float(dt), float(gravity), float(q1), float(q2)
        self.density, self.decay = float(density), float(decay)
        r_t = as_tensor(r, "r")
        self.R = SPDMatrix(torch.diag(r_t) if r_t.ndim == 1 else r_t, "r", learn=False)

    def _interval(self, dt: Tensor | None, like: Tensor) -> Tensor:
        if dt is None:
            return torch.tensor(self.dt, dtype=like.dtype)
        return dt.to(like.dtype)

    def drag(self, x: Tensor) -> Tensor:
        """``D(x)`` of Eq. (43), ``[..., 3] → [...]``."""
        rho = self.density * torch.exp(-self.decay * x[..., 0])
        return self.gravity * rho * x[..., 1].square() / (2.0 * x[..., 2])

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        T = self._interval(dt, x)  # 0-d, or [B] for per-track intervals
        altitude = x[..., 0] - T * x[..., 1]
        speed = x[..., 1] - T * (self.drag(x) - self.gravity)
        return torch.stack([altitude, speed, x[..., 2]], dim=-1)

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        """Analytic ``∂f/∂x``: with ``∂D/∂h = −ηD``, ``∂D/∂v = 2D/v``, ``∂D/∂β = −D/β``."""
        T = self._interval(dt, x)
        D = self.drag(x)
        one, zero = torch.ones_like(D), torch.zeros_like(D)
        T = T.expand_as(D)
        rows = [
            torch.stack([one, -T, zero], -1),
            torch.stack([T * self.decay * D, 1.0 - 2.0 * T * D / x[..., 1], T * D / x[..., 2]], -1),
            torch.stack([zero, zero, one], -1),
        ]
        return torch.stack(rows, -2)

    def h(self, x: Tensor) -> Tensor:
        return x[..., :2]

    def h_jacobian(self, x: Tensor) -> Tensor:
        return torch.eye(3, dtype=x.dtype)[:2].expand(x.shape[0], 2, 3)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        T = torch.tensor(self.dt, dtype=torch.float64) if dt is None else dt.to(torch.float64)
        zero = torch.zeros_like(T)
        q1, q2 = self.q1, self.q2
        rows = [
            torch.stack([q1 * T**3 / 3, q1 * T**2 / 2, zero], -1),
            torch.stack([q1 * T**2 / 2, q1 * T, zero], -1),
            torch.stack([zero, zero, q2 * T], -1),
        ]
        return torch.stack(rows, -2)

    def meas_cov(self) -> Tensor:
        return self.R()

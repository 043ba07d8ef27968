"""Sensor models: non-linear measurements of a kinematic state (slant ranges to stations)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, as_tensor
from torchsvs.models.base import StateSpaceModel
from torchsvs.models.motion import ConstantVelocity, _measurement_noise


class SlantRanges(StateSpaceModel):
    r"""Nearly constant velocity in the plane measured by slant ranges to fixed stations: the
    DME-DME navigation of Example 4, Bermúdez Ordoñez et al. 2020 (after Brown & Hwang 2012).

    State ``[x, vx, y, vy]`` (:class:`~torchsvs.models.ConstantVelocity`'s layout; the paper
    orders it ``[x, y, vx, vy]``, Eqs. (62)-(63)), moving as that model does (its ``F`` and
    ``Q``; the paper's ``Q`` (Eq. (65)) is the discrete white-noise acceleration form of the same
    motion). Station ``i`` at ``(x_i, y_i)`` measures the range, Eqs. (47)-(48):

    .. math::
        z_i = \sqrt{(x - x_i)^2 + (y - y_i)^2 + h^2},\qquad
        \frac{\partial z_i}{\partial x} = \frac{x - x_i}{z_i} = \sin\theta_i,\quad
        \frac{\partial z_i}{\partial y} = \frac{y - y_i}{z_i} = \cos\theta_i

    (Eqs. (55)-(58): the line-of-sight direction cosines, ``θ_i`` the bearing of the aircraft
    from station ``i``, clockwise from the y axis; ``h = 0`` as printed, ``height`` for a true
    slant range of an aircraft above the stations' plane). ``H`` (Eq. (60)) is singular where
    the lines of sight are collinear, on the line through two stations: between them the
    direction across that line is unobserved (the DOP peak of the paper's Figs. 21-23).

    There is no ``position_index``: the SVSF's finite-difference velocity would read the
    ranges as positions (pass ``artificial=None`` for the ``H⁺`` mode).

    Args:
        stations: station positions ``[k, 2]`` in metres (k ≥ 1; two for DME-DME).
        dt: default sampling interval ``T`` in seconds (a per-step ``dt`` overrides it).
        q: power spectral density of the white-noise acceleration per axis (m²/s³), > 0.
        r: range noise: a variance (m²), per-station variances ``[k]`` or a covariance ``[k, k]``.
        height: the aircraft's height above the stations (m), ``≥ 0``.
        learn_noise: learn ``q`` (through its log) and ``R`` (through its Cholesky factor).

    Attributes:
        motion: the :class:`~torchsvs.models.ConstantVelocity` of the state (its ``q`` is this
            model's).

    References:
        Bermúdez Ordoñez, Arnaldo Valdés, Gómez Comendador, Appl. Sci. 10(15):5168, 2020,
        Example 4, Eqs. (47)-(65). doi:10.3390/app10155168 ·
        Brown, Hwang, "Introduction to Random Signals and Applied Kalman Filtering", 4th ed.,
        Wiley 2012.
    """

    uses_dt = True
    stations: Tensor
    state_dim = 4

    def __init__(
        self,
        stations: Sequence[Sequence[float]] | Tensor,
        dt: float = 2.0,
        q: float = 1.0,
        r: ArrayLike = 1.0,
        height: float = 0.0,
        learn_noise: bool = False,
    ) -> None:
        super().__init__()
        where = as_tensor(cast(Any, stations), "stations")
        if where.ndim != 2 or where.shape[1] != 2 or where.shape[0] < 1:
            raise ValueError(
                f"stations: expected positions [k, 2] with k >= 1, got shape {tuple(where.shape)}"
            )
        if not bool(torch.isfinite(where).all()):
            raise ValueError("stations: contains NaN or inf")
        if isinstance(height, bool) or not isinstance(height, (int, float)) or not height >= 0:
            raise ValueError(f"height: expected a number >= 0, got {height!r}")
        self.meas_dim = where.shape[0]
        self.motion = ConstantVelocity(ndim=2, dt=dt, q=q, learn_q=learn_noise)
        self.dt = self.motion.dt
        self.height = float(height)
        self.R = _measurement_noise(r, self.meas_dim, learn_noise)
        self.register_buffer("stations", where)

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self.motion.f(x, dt)

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self.motion.f_jacobian(x, dt)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        return self.motion.process_noise(dt)

    def _offsets(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``x − x_i``, ``y − y_i`` and the ranges, ``[..., k]`` each."""
        stations = self.stations.to(x.dtype)
        dx = x[..., 0:1] - stations[:, 0]
        dy = x[..., 2:3] - stations[:, 1]
        return dx, dy, (dx.square() + dy.square() + self.height**2).sqrt()

    def h(self, x: Tensor) -> Tensor:
        return self._offsets(x)[2]

    def h_jacobian(self, x: Tensor) -> Tensor:
        dx, dy, rng = self._offsets(x)
        J = x.new_zeros(*x.shape[:-1], self.meas_dim, 4)
        J[..., 0] = dx / rng  # sin θ_i, Eqs. (55), (57)
        J[..., 2] = dy / rng  # cos θ_i, Eqs. (56), (58)
        return J

    def meas_cov(self) -> Tensor:
        return self.R()

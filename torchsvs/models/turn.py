"""The coordinated turn in the horizontal plane with a nearly-constant-velocity vertical axis."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike
from torchsvs.models.base import StateSpaceModel
from torchsvs.models.motion import ConstantVelocity, CoordinatedTurn, _measurement_noise

#: Where the planar turn's ``[x, vx, y, vy, ω]`` and the vertical ``[z, vz]`` sit in the state.
_PLANE, _VERTICAL = [0, 1, 2, 3, 6], [4, 5]


class CoordinatedTurn3D(StateSpaceModel):
    r"""Nearly coordinated turn in the horizontal plane, nearly constant velocity in height:
    state ``[x, vx, y, vy, z, vz, ω]`` (:class:`~torchsvs.models.ConstantVelocity`'s
    three-axis layout, then the turn rate ω in rad/s, positive counter-clockwise seen from
    above), position measurements ``[x, y, z]``.

    The horizontal components follow :class:`~torchsvs.models.CoordinatedTurn` (Bar-Shalom, Li,
    Kirubarajan 2001, Sec. 11.7: its ``f``, analytic Jacobian and ``Q = Γ diag(q, q, q_ω) Γᵀ``
    on ``[x, vx, y, vy, ω]``); the vertical ``[z, vz]`` is one axis of
    :class:`~torchsvs.models.ConstantVelocity` (white acceleration of spectral density
    ``q_vertical``), independent of the turn. Aircraft turn in the horizontal plane and climb
    or descend slowly, so this is the turn model of a three-axis track; the CV model's
    three-axis state nests in it (an IMM's ``embedding`` ``[[0, ..., 5], [0, ..., 6]]``).

    Args:
        dt: default sampling interval ``T`` in seconds (a per-step ``dt`` overrides it).
        q: variance of the horizontal white acceleration per axis (m²/s⁴), > 0.
        q_turn: variance of the turn-rate noise (rad²/s⁴), > 0.
        q_vertical: spectral density of the vertical white acceleration (m²/s³), > 0.
        r: position measurement noise: a variance, per-axis variances ``[3]`` or ``[3, 3]``.
        learn_noise, learn_q, learn_r: learn ``q``, ``q_turn`` and ``q_vertical`` (through
            their logs) and ``R`` (through its Cholesky factor), as for
            :class:`~torchsvs.models.CoordinatedTurn`.

    Attributes:
        plane: the :class:`~torchsvs.models.CoordinatedTurn` of the horizontal components (its
            ``q`` and ``q_turn`` are this model's).
        vertical: the one-axis :class:`~torchsvs.models.ConstantVelocity` of the height (its
            ``q`` is ``q_vertical``).

    References:
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley 2001, Sec. 11.7. doi:10.1002/0471221279 ·
        Li, Jilkov, "Survey of maneuvering target tracking. Part I: Dynamic models", IEEE Trans.
        Aerosp. Electron. Syst. 39(4), 2003, Sec. V. doi:10.1109/TAES.2003.1261132
    """

    uses_dt = True
    H: Tensor
    ndim = 3
    state_dim, meas_dim = 7, 3

    def __init__(
        self,
        dt: float = 1.0,
        q: float = 1.0,
        q_turn: float = 1e-4,
        q_vertical: float = 1.0,
        r: ArrayLike = 1.0,
        learn_noise: bool = False,
        learn_q: bool | None = None,
        learn_r: bool | None = None,
    ) -> None:
        super().__init__()
        learn_process = learn_noise if learn_q is None else learn_q
        self.plane = CoordinatedTurn(dt=dt, q=q, q_turn=q_turn, learn_q=learn_process)
        self.vertical = ConstantVelocity(ndim=1, dt=dt, q=q_vertical, learn_q=learn_process)
        self.dt = self.plane.dt
        self.R = _measurement_noise(r, 3, learn_noise if learn_r is None else learn_r)
        H = torch.zeros(3, 7, dtype=self.R.raw.dtype)
        H[0, 0] = H[1, 2] = H[2, 4] = 1.0
        self.register_buffer("H", H)

    @property
    def position_index(self) -> list[int]:
        """State indices of the positions (the measured components)."""
        return [0, 2, 4]

    @property
    def velocity_index(self) -> list[int]:
        """State indices of the velocities."""
        return [1, 3, 5]

    @property
    def turn_rate_index(self) -> int:
        """State index of the turn rate ω."""
        return 6

    def _f_with(self, x: Tensor, plane: Tensor, dt: Tensor | None) -> Tensor:
        F_v = self.vertical.transition(dt).to(x.dtype)
        if F_v.ndim > 2:  # a per-track interval [B]: one 2 × 2 block per track
            F_v = F_v.expand(*x.shape[:-1], 2, 2)
        height = (F_v @ x[..., _VERTICAL].unsqueeze(-1)).squeeze(-1)
        return torch.cat([plane[..., :4], height, plane[..., 4:]], dim=-1)

    def _jacobian_with(self, x: Tensor, plane_jacobian: Tensor, dt: Tensor | None) -> Tensor:
        J = x.new_zeros(*x.shape[:-1], 7, 7)
        plane = torch.tensor(_PLANE)
        J[..., plane[:, None], plane[None, :]] = plane_jacobian
        F_v = self.vertical.transition(dt).to(x.dtype)
        J[..., 4:6, 4:6] = F_v.expand(*x.shape[:-1], 2, 2)
        return J

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self._f_with(x, self.plane.f(x[..., _PLANE], dt), dt)

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self._jacobian_with(x, self.plane.f_jacobian(x[..., _PLANE], dt), dt)

    def linearize(
        self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``f(x)`` and ``F`` with the horizontal turn's terms evaluated once
        (:meth:`CoordinatedTurn.linearize`)."""
        plane, plane_jacobian = self.plane.linearize(x[..., _PLANE], dt)
        return self._f_with(x, plane, dt), self._jacobian_with(x, plane_jacobian, dt)

    def h(self, x: Tensor) -> Tensor:
        return x[..., [0, 2, 4]]

    def h_jacobian(self, x: Tensor) -> Tensor:
        return self.H.to(x.dtype).expand(x.shape[0], -1, -1)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        Q_plane = self.plane.process_noise(dt)
        Q_height = self.vertical.process_noise(dt).to(Q_plane.dtype)
        Q = Q_plane.new_zeros(*Q_plane.shape[:-2], 7, 7)
        plane = torch.tensor(_PLANE)
        Q[..., plane[:, None], plane[None, :]] = Q_plane
        Q[..., 4:6, 4:6] = Q_height
        return Q

    def meas_cov(self) -> Tensor:
        return self.R()

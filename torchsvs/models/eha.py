"""The electrohydrostatic actuator (EHA) of Gadsden, Habibi, Kirubarajan 2012, Sec. 5.2."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, as_tensor
from torchsvs.models.base import StateSpaceModel


class ElectrohydrostaticActuator(StateSpaceModel):
    r"""EHA with its effective bulk modulus as an augmented state, Eqs. (49)-(56).

    State ``[x₁, x₂, x₃, x₄]`` = position (m), velocity (m/s), acceleration (m/s²) and effective
    bulk modulus ``β_e`` (Pa); input ``u`` (one channel); all three kinematic states are
    measured (``z = x₁..₃ + v``):

    .. math::
        x_{1,k+1} = x_1 + T x_2,\quad x_{2,k+1} = x_2 + T x_3,\quad x_{4,k+1} = x_4,

        x_{3,k+1} = (1 - T\varphi_3 - T\varphi_2 x_4)\,x_3 - T\varphi_1 x_4 x_2 + G_E T x_4 u

    with ``G_E = 2D_pA_E/(MV_0)``, ``φ₁ = 2A_E²/(MV_0)``, ``φ₂ = L/V_0``, ``φ₃ = B_E/M`` (Eqs.
    (53)-(56)). Eq. (51) as printed omits ``x₄`` in the ``φ₁`` term; the transfer function Eq. (48)
    has it (``2β_eA_E²/(MV_0)``), and so does this model.

    Noise: the paper writes ``Q = 5 W Wᵀ`` and ``R = 5 V Vᵀ`` with ``W = [1e-4, 1e-3, 0.1, 0]``,
    ``V = [1e-4, 1e-3, 0.1]``, which are singular (rank one); the workable reading, used here,
    is ``Q = 5 diag(W²)``, ``R = 5 diag(V²)``. ``Q₄₄ = 0`` would freeze the modulus estimate of
    every Kalman-type filter (the paper notes the EKF needed a much larger ``Q₄₄``), so the
    modulus gets a random walk of ``modulus_std`` Pa per step (our choice, stated).

    Args:
        dt: sampling interval ``T`` (s), 0.001 in the paper.
        area, friction, displacement, leakage, mass, volume: Table 3's ``A_E, B_E, D_p, L, M, V_0``.
        w_max, v_max: the noise amplitudes ``W_max[:3]`` and ``V_max``.
        modulus_std: random-walk standard deviation of the bulk modulus per step (Pa).

    References:
        Gadsden, Habibi, Kirubarajan, Trans. CSME 36(2), 2012, Sec. 5.2 · Habibi, "The smooth
        variable structure filter", Proc. IEEE 95(5), 2007.
    """

    uses_dt = True
    input_dim = 1
    Q: Tensor
    R: Tensor

    def __init__(
        self,
        dt: float = 0.001,
        area: float = 3.37e-4,
        friction: float = 1260.0,
        displacement: float = 6.69e-3,
        leakage: float = 5e-12,
        mass: float = 20.0,
        volume: float = 8.5e-5,
        w_max: ArrayLike = (1e-4, 1e-3, 0.1),
        v_max: ArrayLike = (1e-4, 1e-3, 0.1),
        modulus_std: float = 1e6,
    ) -> None:
        super().__init__()
        if not dt > 0:
            raise ValueError(f"dt: expected a positive number, got {dt!r}")
        self.state_dim, self.meas_dim = 4, 3
        self.dt = float(dt)
        self.gain = 2.0 * displacement * area / (mass * volume)  # G_E, Eq. (53)
        self.phi1 = 2.0 * area**2 / (mass * volume)  # Eq. (54)
        self.phi2 = leakage / volume  # Eq. (55)
        self.phi3 = friction / mass  # Eq. (56)
        w = as_tensor(w_max, "w_max")
        v = as_tensor(v_max, "v_max")
        if w.shape != (3,) or v.shape != (3,):
            raise ValueError("w_max, v_max: expected three amplitudes each")
        q = torch.cat([5.0 * w.square(), torch.tensor([float(modulus_std) ** 2], dtype=w.dtype)])
        self.register_buffer("Q", torch.diag(q))
        self.register_buffer("R", torch.diag(5.0 * v.square()))

    def _interval(self, dt: Tensor | None, like: Tensor) -> Tensor:
        return torch.tensor(self.dt, dtype=like.dtype) if dt is None else dt.to(like.dtype)

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        T = self._interval(dt, x)
        drive = torch.zeros_like(x[..., 0]) if u is None else u[..., 0].to(x.dtype)
        x1, x2, x3, x4 = x.unbind(-1)
        accel = (
            (1.0 - T * self.phi3 - T * self.phi2 * x4) * x3
            - T * self.phi1 * x4 * x2
            + self.gain * T * x4 * drive
        )
        return torch.stack([x1 + T * x2, x2 + T * x3, accel, x4], dim=-1)

    def h(self, x: Tensor) -> Tensor:
        return x[..., :3]

    def h_jacobian(self, x: Tensor) -> Tensor:
        return torch.eye(4, dtype=x.dtype)[:3].expand(x.shape[0], 3, 4)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        return self.Q

    def meas_cov(self) -> Tensor:
        return self.R

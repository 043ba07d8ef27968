r"""Mileage-coordinate models of road targets and the separate-modeling (SM) augmented model.

Zhang & Zhou (2022) model a target constrained to a road *separately*: its dynamics in mileage
coordinates (the travelled arc length ``s`` and its derivatives, 1-D) and the shape of its
trajectory as a function of ``s``. The paper's equations were lost in text extraction; they are
rebuilt here from its text and the standard literature (Bar-Shalom, Li, Kirubarajan 2001; Li &
Jilkov 2003). Equation numbers are the paper's where its text refers to them, inferred
otherwise (marked "inferred").

**Dynamics in mileage coordinates**, Eq. (1):

.. math::
    \mathbf x_{k+1} = F_k \mathbf x_k + \Gamma_k v_k,\qquad v_k \sim N(0, q^2),

with ``q`` the standard deviation of a scalar white noise in m/s² for both models (the paper
gives both as "0.008 m/s²"):

* NCV, Eqs. (2)-(3) (inferred): :math:`\mathbf x_k = [s_k, \dot s_k]'`,
  :math:`F_k = \begin{bmatrix}1 & T\\0 & 1\end{bmatrix}`,
  :math:`\Gamma_k = [T^2/2,\ T]'`: the discrete white noise acceleration model (Bar-Shalom et
  al. 2001, Sec. 6.3.2, Eq. (6.3.2-4)); ``v_k`` is the acceleration over the interval.
* NCA, Eqs. (4)-(5) (inferred): :math:`\mathbf x_k = [s_k, \dot s_k, \ddot s_k]'`,
  :math:`F_k = \begin{bmatrix}1 & T & T^2/2\\0 & 1 & T\\0 & 0 & 1\end{bmatrix}`,
  :math:`\Gamma_k = [T^2/2,\ T,\ 1]'`: the discrete Wiener process acceleration model (Sec.
  6.3.3, Eq. (6.3.3-4)); ``v_k`` is the acceleration increment over the interval, in m/s² as
  the paper's unit says (a white-jerk gain ``[T³/6, T²/2, T]'`` would make it m/s³).

Eqs. (6)-(10) are the IMM of the two (mode set, Markov transition matrix ``Π``, initial
probabilities, hybrid system); the IMM itself is a filter, not part of a model.

**Measurements** depend on the Cartesian position only, Eq. (11):
:math:`z_k = [x_k, y_k]' + w_k`, :math:`w_k \sim N(0, R)`, :math:`R = \mathrm{diag}(\sigma_x^2,
\sigma_y^2)`. With a known road, ``x = f_x(s)``, ``y = f_y(s)`` (Eq. (12)); without one, the
trajectory over a sliding window of the latest ``k_m`` measurements is the straight line
(first-degree polynomial in ``s``) of Eq. (13):

.. math::
    x = x_l + r_x (s - s_l),\qquad y = y_l + r_y (s - s_l),

with start point :math:`(x_l, y_l)`, direction :math:`(r_x, r_y)` and start arc length
:math:`s_l` of the window. The function is the *natural* parameterisation of the line (``s``
is arc length), so the direction is a unit vector, :math:`r_x^2 + r_y^2 = 1`.

**Augmented system.** The unknown coefficients form the parameter vector
:math:`\eta = [x_l, r_x, y_l, r_y, s_l]'` (this layout) and augment the base state, Eq. (14):
:math:`\mathbf x^a_k = [\mathbf x_k', \eta_k']'`. Substituting (13) into (11) gives the
measurement equation Eq. (15), nonlinear (bilinear) in the augmented state:

.. math::
    z_k = h(\mathbf x^a_k) + w_k,\qquad
    h(\mathbf x^a) = \begin{bmatrix} x_l + r_x (s - s_l)\\ y_l + r_y (s - s_l)\end{bmatrix},

    \frac{\partial h}{\partial (s, x_l, r_x, y_l, r_y, s_l)} =
    \begin{bmatrix} r_x & 1 & s - s_l & 0 & 0 & -r_x\\
                    r_y & 0 & 0 & 1 & s - s_l & -r_y\end{bmatrix}

(zero for the speed and acceleration). The parameters propagate with an identity transition
and an artificial process noise, Eq. (16):

.. math::
    \mathbf x^a_{k+1} = \begin{bmatrix}F_k & 0\\ 0 & I_5\end{bmatrix}\mathbf x^a_k +
    \begin{bmatrix}\Gamma_k v_k\\ v^\eta_k\end{bmatrix},\qquad
    Q^a_k = \begin{bmatrix} q^2\Gamma_k\Gamma_k' & 0\\ 0 & \sigma_\eta^2 I_5\end{bmatrix},

with :math:`\sigma_\eta` = 1e-5 (straight road), 0.001 (circular arc), 0.002 (curves) in the
paper. In an NCV-NCA IMM the NCV mode has no acceleration: the paper says "for the NCV model,
the acceleration component ... is zero and the elements related to the acceleration in the
covariance are zero". :class:`~torchsvs.SeparateModelingTracker` keeps each mode in its own
state and lets the IMM's embedding count the NCV mode's acceleration as that zero in the
combined estimate, while mixing it without bias (its docstring). The NCV model can also be
embedded in the NCA layout :math:`[s, \dot s, \ddot s, \eta']'` with the acceleration row and
column of ``F`` and ``Γ`` zero (``embed_acceleration``), so that it maps any acceleration to 0
and adds no noise to it; mixed as a state of its own, that zero pulls the NCA mode's
acceleration towards 0 (zero padding, the tracker's ``mixing="zero"``).

References:
    Zhang Zhuanhua, Zhou Gongjian, on separate modeling of target trajectory shape and dynamic
    characteristics, Journal of Systems Engineering and Electronics 33(5), 2022
    (``papers/separate-modeling-zhang-zhou-2022.txt``) · Bar-Shalom, Li, Kirubarajan,
    "Estimation with Applications to Tracking and Navigation", Wiley 2001, Sec. 6.3 · Li,
    Jilkov, "Survey of maneuvering target tracking. Part I: dynamic models", IEEE Trans. AES
    39(4), 2003. doi:10.1109/TAES.2003.1261132
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive, SPDMatrix, as_tensor
from torchsvs.models.base import LinearModel, StateSpaceModel

#: Names of the trajectory parameters η, in their order in the augmented state.
ETA_NAMES = ("x_l", "r_x", "y_l", "r_y", "s_l")


def _measurement_cov(r: ArrayLike, dim: int, name: str = "r") -> Tensor:
    """A covariance ``[dim, dim]`` from a variance, per-axis variances or a matrix."""
    r_t = as_tensor(r, name)
    if r_t.ndim == 0:
        return r_t * torch.eye(dim, dtype=r_t.dtype)
    if r_t.ndim == 1:
        if r_t.shape[0] != dim:
            raise ValueError(f"{name}: expected {dim} per-axis variances, got {tuple(r_t.shape)}")
        return torch.diag(r_t)
    if r_t.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape [{dim}, {dim}], got {tuple(r_t.shape)}")
    return r_t


class _Mileage(LinearModel):
    """A 1-D kinematic model of the arc length: ``F``, ``Γ`` from the interval, ``Q = q² ΓΓ'``."""

    uses_dt = True
    H: Tensor

    def __init__(self, order: int, dt: float, q: float, r: float, learn_q: bool) -> None:
        super().__init__()
        if not (isinstance(dt, (int, float)) and dt > 0):
            raise ValueError(f"dt: expected a positive number, got {dt!r}")
        self.state_dim, self.meas_dim = order, 1
        self.dt = float(dt)
        self.q = Positive(q, "q", learn=learn_q)
        self.R = SPDMatrix(_measurement_cov(r, 1), "r", learn=False)
        H = torch.zeros(1, order, dtype=torch.float64)
        H[0, 0] = 1.0
        self.register_buffer("H", H)

    def _interval(self, dt: Tensor | None) -> Tensor:
        if dt is None:
            return torch.tensor(self.dt, dtype=self.H.dtype, device=self.H.device)
        return dt.to(self.H.dtype)

    def transition(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        one, zero = torch.ones_like(T), torch.zeros_like(T)
        if self.state_dim == 2:
            rows = [[one, T], [zero, one]]
        else:
            rows = [[one, T, T**2 / 2], [zero, one, T], [zero, zero, one]]
        return torch.stack([torch.stack(row, -1) for row in rows], -2)

    def noise_gain(self, dt: Tensor | None = None) -> Tensor:
        """``Γ`` of Eq. (3) or (5), ``[*dt.shape, n]``."""
        T = self._interval(dt)
        parts = [T**2 / 2, T] if self.state_dim == 2 else [T**2 / 2, T, torch.ones_like(T)]
        return torch.stack(parts, -1)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        G = self.noise_gain(dt)
        return self.q().to(G.dtype) ** 2 * (G.unsqueeze(-1) * G.unsqueeze(-2))

    def meas_matrix(self) -> Tensor:
        return self.H

    def meas_cov(self) -> Tensor:
        return self.R()


class MileageConstantVelocity(_Mileage):
    r"""Nearly constant velocity (NCV) in mileage coordinates, Eqs. (1)-(3) (inferred).

    State ``[s, ṡ]`` (arc length in m, speed in m/s):

    .. math::
        \mathbf x_{k+1} = \begin{bmatrix}1 & T\\0 & 1\end{bmatrix}\mathbf x_k
        + \begin{bmatrix}T^2/2\\ T\end{bmatrix} v_k,\qquad v_k \sim N(0, q^2)

    (discrete white noise acceleration, Bar-Shalom et al. 2001, Eq. (6.3.2-4)). As a
    :class:`~torchsvs.models.LinearModel` it measures the arc length itself, ``z = s + w``,
    ``w ~ N(0, r)`` (a road whose map gives the mileage); on a road without a map it is the base
    of :class:`SeparateModel`.

    Args:
        dt: sampling interval ``T`` (s); a per-step ``dt`` given to an estimator overrides it.
        q: standard deviation of the white acceleration ``v_k`` (m/s²), > 0 (the paper: 0.008).
        r: variance of a direct mileage measurement (m²).
        learn_q: learn ``q`` (through its log).

    References:
        Zhang, Zhou, J. Syst. Eng. Electron. 33(5), 2022 · Bar-Shalom, Li, Kirubarajan 2001,
        Sec. 6.3.2.
    """

    def __init__(
        self, dt: float = 1.0, q: float = 0.008, r: float = 1.0, learn_q: bool = False
    ) -> None:
        super().__init__(2, dt, q, r, learn_q)


class MileageConstantAcceleration(_Mileage):
    r"""Nearly constant acceleration (NCA) in mileage coordinates, Eqs. (1), (4)-(5) (inferred).

    State ``[s, ṡ, s̈]``:

    .. math::
        \mathbf x_{k+1} = \begin{bmatrix}1 & T & T^2/2\\0 & 1 & T\\0 & 0 & 1\end{bmatrix}
        \mathbf x_k + \begin{bmatrix}T^2/2\\ T\\ 1\end{bmatrix} v_k,\qquad v_k \sim N(0, q^2)

    (discrete Wiener process acceleration, Bar-Shalom et al. 2001, Eq. (6.3.3-4): ``v_k`` is the
    acceleration increment over an interval, in m/s²). Measures ``z = s + w`` as
    :class:`MileageConstantVelocity` does.

    Args:
        dt: sampling interval ``T`` (s).
        q: standard deviation of the acceleration increment ``v_k`` (m/s²), > 0.
        r: variance of a direct mileage measurement (m²).
        learn_q: learn ``q`` (through its log).

    References:
        Zhang, Zhou, J. Syst. Eng. Electron. 33(5), 2022 · Bar-Shalom, Li, Kirubarajan 2001,
        Sec. 6.3.3.
    """

    def __init__(
        self, dt: float = 1.0, q: float = 0.008, r: float = 1.0, learn_q: bool = False
    ) -> None:
        super().__init__(3, dt, q, r, learn_q)


class SeparateModel(StateSpaceModel):
    r"""The SM augmented model: a mileage model augmented by the window's line, Eqs. (13)-(16).

    State layout ``[s, ṡ, (s̈,) x_l, r_x, y_l, r_y, s_l]``: the base state of ``base``
    (``[s, ṡ]`` or ``[s, ṡ, s̈]``), then :math:`\eta` (:data:`ETA_NAMES`): the window's start
    point, unit direction and start arc length. Measurements are Cartesian positions:

    .. math::
        \mathbf x^a_{k+1} = \mathrm{diag}(F_k, I_5)\,\mathbf x^a_k + w^a_k,\quad
        w^a_k \sim N\big(0, \mathrm{diag}(q^2\Gamma_k\Gamma_k', \sigma_\eta^2 I_5)\big)
        \ \text{(Eq. (16))}

        z_k = \begin{bmatrix} x_l + r_x (s_k - s_l)\\ y_l + r_y (s_k - s_l)\end{bmatrix} + w_k,
        \quad w_k \sim N(0, R)\ \text{(Eqs. (13), (15))}

    ``h`` is bilinear; :meth:`h_jacobian` is the analytic Jacobian written in the module
    docstring, ``f`` is linear (:meth:`f_jacobian` is ``diag(F_k, I_5)``). Use it with
    :class:`~torchsvs.ExtendedKalmanFilter` or :class:`~torchsvs.UnscentedKalmanFilter`.

    Nothing in the model keeps the direction a unit vector or ``s_l`` at the window's start: the
    filter estimates them freely and the SM algorithm resets ``η`` by least squares at every
    cycle (:func:`torchsvs.filters.separate.reset.reset_trajectory_parameters`,
    Eqs. (36)-(40); the tracker: :class:`torchsvs.SeparateModelingTracker`).

    Args:
        base: :class:`MileageConstantVelocity` or :class:`MileageConstantAcceleration` (its
            ``dt`` and ``q``; its own mileage measurement is not used).
        eta_std: standard deviation ``σ_η`` of the artificial process noise of ``η``: a number
            or five, one per parameter (the paper: 1e-5 straight road, 0.001 circular arc,
            0.002 curves).
        r: measurement noise: a variance, per-axis variances ``[2]`` or a covariance ``[2, 2]``
            (m²).
        embed_acceleration: with an NCV ``base``, use the NCA layout ``[s, ṡ, s̈, η]`` with the
            acceleration row and column of ``F`` and ``Γ`` zero (``s̈ ↦ 0`` without noise): an
            NCV mode that an IMM mixes with an NCA mode in one state, its zero acceleration
            included (zero padding, biased; the IMM's ``embedding`` of the 7-state NCV mixes
            without bias, module docstring). Ignored (already so) for an NCA base.
        learn_r: learn ``R`` (through its Cholesky factor).

    References:
        Zhang, Zhou, J. Syst. Eng. Electron. 33(5), 2022, Sec. 3.
    """

    uses_dt = True
    base: MileageConstantVelocity | MileageConstantAcceleration
    eta_var: Tensor

    def __init__(
        self,
        base: MileageConstantVelocity | MileageConstantAcceleration,
        eta_std: ArrayLike = 1e-5,
        r: ArrayLike = 1.0,
        embed_acceleration: bool = False,
        learn_r: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(base, _Mileage):
            raise TypeError(
                "base: expected a MileageConstantVelocity or MileageConstantAcceleration, got "
                f"{type(base).__name__}"
            )
        self.base = base
        eta = as_tensor(eta_std, "eta_std")
        if eta.ndim == 0:
            eta = eta.expand(len(ETA_NAMES)).clone()
        if eta.shape != (len(ETA_NAMES),):
            raise ValueError(f"eta_std: expected a number or shape [5], got {tuple(eta.shape)}")
        if not bool(torch.isfinite(eta).all()) or bool((eta <= 0).any()):
            raise ValueError(f"eta_std: expected finite values > 0, got {eta.tolist()}")
        self.register_buffer("eta_var", eta**2)
        self.R = SPDMatrix(_measurement_cov(r, 2), "r", learn=learn_r)
        #: components of the base model's own state (2 for NCV, 3 for NCA)
        self.base_order = base.state_dim
        #: size of the kinematic block in the augmented state (3 when NCV is embedded)
        self.base_dim = 3 if embed_acceleration else base.state_dim
        self.state_dim, self.meas_dim = self.base_dim + len(ETA_NAMES), 2

    @property
    def dt(self) -> float:
        """The base model's sampling interval ``T`` (s)."""
        return self.base.dt

    # --- layout ---

    @property
    def eta_index(self) -> list[int]:
        """State indices of ``η = [x_l, r_x, y_l, r_y, s_l]``."""
        return list(range(self.base_dim, self.state_dim))

    @property
    def has_acceleration(self) -> bool:
        """Whether the layout holds ``s̈`` (an NCA base, or an embedded NCV)."""
        return self.base_dim == 3

    def _block(self, A: Tensor, eta_diag: Tensor) -> Tensor:
        """``diag(A, diag(eta_diag))`` of shape ``[..., n, n]`` from the base block ``A``,
        zero-padded to ``base_dim`` (the embedded NCV's acceleration)."""
        lead = A.shape[:-2]
        out = A.new_zeros(*lead, self.state_dim, self.state_dim)
        k = self.base_order
        out[..., :k, :k] = A
        out.diagonal(dim1=-2, dim2=-1)[..., self.base_dim :] = eta_diag.to(A.dtype)
        return out

    # --- dynamics, Eq. (16) ---

    def transition(self, dt: Tensor | None = None) -> Tensor:
        """``F^a = diag(F_k, I_5)``, ``[*dt.shape, n, n]``."""
        F = self.base.transition(dt)
        return self._block(F, torch.ones(len(ETA_NAMES), dtype=F.dtype))

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        F = self.transition(dt).to(x.dtype)
        return (F @ x.unsqueeze(-1)).squeeze(-1)

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        F = self.transition(dt).to(x.dtype)
        return F.expand(x.shape[0], -1, -1) if F.ndim == 2 else F

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        """``Q^a = diag(q²ΓΓ', σ_η² I_5)``, ``[*dt.shape, n, n]``."""
        return self._block(self.base.process_noise(dt), self.eta_var)

    # --- measurements, Eqs. (13), (15) ---

    def _split(self, x: Tensor) -> tuple[Tensor, ...]:
        b = self.base_dim
        return x[..., 0], x[..., b], x[..., b + 1], x[..., b + 2], x[..., b + 3], x[..., b + 4]

    def h(self, x: Tensor) -> Tensor:
        s, x_l, r_x, y_l, r_y, s_l = self._split(x)
        travelled = s - s_l
        return torch.stack([x_l + r_x * travelled, y_l + r_y * travelled], dim=-1)

    def h_jacobian(self, x: Tensor) -> Tensor:
        """Analytic ``∂h/∂x^a``, ``[..., 2, n]`` (module docstring)."""
        s, _, r_x, _, r_y, s_l = self._split(x)
        travelled = s - s_l
        J = x.new_zeros(*x.shape[:-1], 2, self.state_dim)
        b = self.base_dim
        J[..., 0, 0], J[..., 1, 0] = r_x, r_y
        J[..., 0, b], J[..., 1, b + 2] = 1.0, 1.0
        J[..., 0, b + 1], J[..., 1, b + 3] = travelled, travelled
        J[..., 0, b + 4], J[..., 1, b + 4] = -r_x, -r_y
        return J

    def meas_cov(self) -> Tensor:
        return self.R()

    # --- reading an estimate ---

    def cartesian(self, x: Tensor) -> Tensor:
        r"""Cartesian state ``[x, vx, y, vy]`` (the layout of
        :class:`~torchsvs.models.ConstantVelocity`) of augmented states ``[..., n]``: the
        position :math:`h(\mathbf x^a)` and the velocity :math:`\dot s\,(r_x, r_y)`."""
        position = self.h(x)
        _, _, r_x, _, r_y, _ = self._split(x)
        speed = x[..., 1]
        return torch.stack([position[..., 0], speed * r_x, position[..., 1], speed * r_y], dim=-1)

"""Kinematic motion models for target tracking: nearly constant velocity and acceleration (one
linear block per axis), and the nearly coordinated turn with unknown turn rate."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive, SPDMatrix, as_tensor
from torchsvs.models.base import LinearModel, StateSpaceModel


def _measurement_noise(r: ArrayLike, ndim: int, learn: bool) -> SPDMatrix:
    """``R`` of a position measurement in ``ndim`` axes from a variance (scalar), per-axis
    variances ``[ndim]`` or a covariance ``[ndim, ndim]``."""
    r_t = as_tensor(r, "r")
    if r_t.ndim == 0:
        r_t = r_t * torch.eye(ndim, dtype=r_t.dtype)
    elif r_t.ndim == 1:
        if r_t.shape[0] != ndim:
            raise ValueError(f"r: expected {ndim} per-axis variances, got {tuple(r_t.shape)}")
        r_t = torch.diag(r_t)
    R = SPDMatrix(r_t, "r", learn=learn)
    if R.raw.shape != (ndim, ndim):
        raise ValueError(f"r: expected shape [{ndim}, {ndim}], got {tuple(R.raw.shape)}")
    return R


def _check_interval(dt: float) -> float:
    if isinstance(dt, bool) or not (isinstance(dt, (int, float)) and dt > 0):
        raise ValueError(f"dt: expected a positive number, got {dt!r}")
    return float(dt)


class _PerAxisMotion(LinearModel):
    """``ndim`` independent axes, each with the same ``order``-dimensional linear block
    (position, velocity[, acceleration]) and a position measurement; the state lists the
    blocks axis after axis (``[x, vx, y, vy]`` for ``order = 2``)."""

    uses_dt = True
    H: Tensor
    #: state components per axis
    order: int = 2

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
        if isinstance(ndim, bool) or not isinstance(ndim, int) or ndim < 1:
            raise ValueError(f"ndim: expected a positive integer, got {ndim!r}")
        self.ndim = ndim
        self.state_dim, self.meas_dim = self.order * ndim, ndim
        self.dt = _check_interval(dt)
        self.q = Positive(q, "q", learn=learn_noise if learn_q is None else learn_q)
        self.R = _measurement_noise(r, ndim, learn_noise if learn_r is None else learn_r)
        H = torch.zeros(ndim, self.order * ndim, dtype=self.R.raw.dtype)
        H[torch.arange(ndim), self.order * torch.arange(ndim)] = 1.0
        self.register_buffer("H", H)

    def _component(self, k: int) -> list[int]:
        return [self.order * i + k for i in range(self.ndim)]

    @property
    def position_index(self) -> list[int]:
        """State indices of the positions (the measured components)."""
        return self._component(0)

    @property
    def velocity_index(self) -> list[int]:
        """State indices of the velocities."""
        return self._component(1)

    def _interval(self, dt: Tensor | None) -> Tensor:
        if dt is None:
            return torch.tensor(self.dt, dtype=self.H.dtype, device=self.H.device)
        return dt.to(self.H.dtype)

    def _per_axis(self, block: Tensor) -> Tensor:
        """Block-diagonal ``[..., k·ndim, k·ndim]`` from one ``k × k`` block ``[..., k, k]``."""
        lead, m, k = block.shape[:-2], self.ndim, block.shape[-1]
        # kron(I, block) over the trailing axes: index (k·i+a, k·j+b) = δ_ij block[a, b].
        full = block.new_zeros(*lead, m, k, m, k)
        full.diagonal(dim1=-4, dim2=-2).copy_(block.unsqueeze(-1).expand(*lead, k, k, m))
        return full.reshape(*lead, k * m, k * m)

    def meas_matrix(self) -> Tensor:
        return self.H

    def meas_cov(self) -> Tensor:
        return self.R()


def _matrix(rows: list[list[Tensor]]) -> Tensor:
    """``[..., r, c]`` from nested lists of tensors of one shape ``[...]``."""
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


class ConstantVelocity(_PerAxisMotion):
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

    order = 2

    def transition(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        one, zero = torch.ones_like(T), torch.zeros_like(T)
        return self._per_axis(_matrix([[one, T], [zero, one]]))

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        block = _matrix([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
        return self.q().to(block.dtype) * self._per_axis(block)


class ConstantAcceleration(_PerAxisMotion):
    r"""Nearly constant acceleration model: the continuous Wiener process acceleration (white
    noise jerk) of Bar-Shalom, Li, Kirubarajan 2001, Sec. 6.2.3.

    State ``[x, vx, ax, y, vy, ay]`` (per axis position, velocity, acceleration, ``ndim``
    axes: :class:`ConstantVelocity`'s layout with the acceleration after each velocity),
    position-only measurements. Per axis, with interval :math:`T` and power spectral density
    :math:`q` of the white-noise jerk:

    .. math::
        F = \begin{bmatrix}1 & T & T^2/2\\ 0 & 1 & T\\ 0 & 0 & 1\end{bmatrix},\qquad
        Q = q\begin{bmatrix}T^5/20 & T^4/8 & T^3/6\\ T^4/8 & T^3/3 & T^2/2\\
            T^3/6 & T^2/2 & T\end{bmatrix},\qquad
        H = \begin{bmatrix}1 & 0 & 0\end{bmatrix}

    (``Q = ∫₀ᵀ e^{As} b bᵀ e^{Aᵀs} ds · q`` for the jerk entering the acceleration, ``b =
    [0, 0, 1]ᵀ``). Arguments as for :class:`ConstantVelocity`; ``q`` is the jerk's spectral
    density (m²/s⁵).

    References:
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley 2001, Sec. 6.2.3. doi:10.1002/0471221279 ·
        Li, Jilkov, "Survey of maneuvering target tracking. Part I: Dynamic models", IEEE Trans.
        Aerosp. Electron. Syst. 39(4), 2003. doi:10.1109/TAES.2003.1261132
    """

    order = 3

    @property
    def acceleration_index(self) -> list[int]:
        """State indices of the accelerations."""
        return self._component(2)

    def transition(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        one, zero = torch.ones_like(T), torch.zeros_like(T)
        return self._per_axis(_matrix([[one, T, T**2 / 2], [zero, one, T], [zero, zero, one]]))

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt)
        block = _matrix(
            [
                [T**5 / 20, T**4 / 8, T**3 / 6],
                [T**4 / 8, T**3 / 3, T**2 / 2],
                [T**3 / 6, T**2 / 2, T],
            ]
        )
        return self.q().to(block.dtype) * self._per_axis(block)


#: ``|ωT|`` below which :func:`turn_coefficients` takes the Taylor series (accurate to rounding
#: there in float64; the closed forms have no cancellation above it worse than ~1e-12 relative).
_SERIES_BELOW = 1e-2


def turn_coefficients(a: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""The coordinated turn's coefficients of the turn angle :math:`a = \omega T` and their
    derivatives, smooth through :math:`a = 0` (no division by zero, finite gradients):

    .. math::
        s(a) = \frac{\sin a}{a},\quad c(a) = \frac{1 - \cos a}{a} = \frac{2\sin^2(a/2)}{a},\quad
        s'(a) = \frac{a\cos a - \sin a}{a^2},\quad c'(a) = \frac{a \sin a - 2\sin^2(a/2)}{a^2},

    with their Taylor series ``s = 1 − a²/6 + a⁴/120 − …``, ``c = a/2 − a³/24 + a⁵/720 − …``,
    ``s' = −a/3 + a³/30 − …``, ``c' = 1/2 − a²/8 + a⁴/144 − …`` (four terms) for
    ``|a| < 10⁻²``; the closed forms use a denominator that is 1 there (``torch.where`` with a
    safe denominator), so neither branch divides by zero in the forward or backward pass.
    """
    small = a.abs() < _SERIES_BELOW
    safe = torch.where(small, torch.ones_like(a), a)
    sin, half = torch.sin(safe), torch.sin(safe / 2)
    versine = 2 * half * half  # 1 − cos a without cancellation
    a2 = a * a
    s = torch.where(small, 1 - a2 / 6 * (1 - a2 / 20 * (1 - a2 / 42)), sin / safe)
    c = torch.where(small, a / 2 * (1 - a2 / 12 * (1 - a2 / 30 * (1 - a2 / 56))), versine / safe)
    ds = torch.where(
        small,
        -a / 3 * (1 - a2 / 10 * (1 - a2 / 28 * (1 - a2 / 54))),
        (safe * torch.cos(safe) - sin) / (safe * safe),
    )
    dc = torch.where(
        small,
        0.5 * (1 - a2 / 4 * (1 - a2 / 18 * (1 - a2 / 40))),
        (safe * sin - versine) / (safe * safe),
    )
    return s, c, ds, dc


class _Turn(NamedTuple):
    """The terms of one coordinated-turn step (:meth:`CoordinatedTurn.f` and its Jacobian): the
    interval, ``a = ωT``, the state's components, :func:`turn_coefficients` of ``a``, cos, sin."""

    T: Tensor
    a: Tensor
    px: Tensor
    vx: Tensor
    py: Tensor
    vy: Tensor
    omega: Tensor
    s: Tensor
    c: Tensor
    ds: Tensor
    dc: Tensor
    cos: Tensor
    sin: Tensor


class CoordinatedTurn(StateSpaceModel):
    r"""Nearly coordinated turn with unknown turn rate (Bar-Shalom, Li, Kirubarajan 2001,
    Sec. 11.7): planar state ``[x, vx, y, vy, ω]`` (:class:`ConstantVelocity`'s layout, then the
    turn rate ω in rad/s, positive counter-clockwise), position-only measurements.

    Over an interval :math:`T` the velocity turns by :math:`a = \omega T` (Eq. (11.7.1-4) with
    ω a state component, Sec. 11.7.2):

    .. math::
        f(x) = \begin{bmatrix}
            x + T\,(s(a)\,v_x - c(a)\,v_y)\\
            \cos a\; v_x - \sin a\; v_y\\
            y + T\,(c(a)\,v_x + s(a)\,v_y)\\
            \sin a\; v_x + \cos a\; v_y\\
            \omega\end{bmatrix},\qquad
        s(a) = \frac{\sin a}{a},\; c(a) = \frac{1 - \cos a}{a}

    (so ``T s = sin(ωT)/ω`` and ``T c = (1 − cos ωT)/ω``). As ω → 0 this is the constant
    velocity motion; :func:`turn_coefficients` evaluates ``s``, ``c`` and their derivatives
    smoothly there. The Jacobian (Eqs. (11.7.2-3)-(11.7.2-4); its ω → 0 limit is
    Eq. (11.7.2-7)) is analytic: the first four columns are the transition of the known-rate
    turn, and the last

    .. math::
        \frac{\partial f}{\partial\omega} = \begin{bmatrix}
            T^2 (s'(a)\,v_x - c'(a)\,v_y)\\ -T(\sin a\; v_x + \cos a\; v_y)\\
            T^2 (c'(a)\,v_x + s'(a)\,v_y)\\ T(\cos a\; v_x - \sin a\; v_y)\\ 1\end{bmatrix}.

    Process noise: piecewise-constant white accelerations :math:`v_x, v_y` of variance ``q``
    and a turn-rate increment rate :math:`v_\omega` of variance ``q_turn`` enter through the gain
    of Sec. 11.7.2,

    .. math::
        \Gamma = \begin{bmatrix}T^2/2 & 0 & 0\\ T & 0 & 0\\ 0 & T^2/2 & 0\\ 0 & T & 0\\
            0 & 0 & T\end{bmatrix},\qquad
        Q = \Gamma\,\mathrm{diag}(q, q, q_\omega)\,\Gamma^T

    (rank 3: the filters add it to a positive definite prediction; simulating draws it through
    its eigendecomposition).

    Args:
        dt: default sampling interval ``T`` in seconds; a per-step ``dt [B, T]`` passed to an
            estimator overrides it.
        q: variance of the white acceleration noise per axis (m²/s⁴), > 0.
        q_turn: variance of the turn-rate noise (rad²/s⁴), > 0.
        r: position measurement noise: a variance, per-axis variances ``[2]`` or ``[2, 2]``.
        learn_noise, learn_q, learn_r: learn ``q`` and ``q_turn`` (through their logs) and
            ``R`` (through its Cholesky factor), as for :class:`ConstantVelocity`.

    References:
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley 2001, Sec. 11.7 (pp. 467-470). doi:10.1002/0471221279 ·
        Li, Jilkov, "Survey of maneuvering target tracking. Part I: Dynamic models", IEEE Trans.
        Aerosp. Electron. Syst. 39(4), 2003. doi:10.1109/TAES.2003.1261132
    """

    uses_dt = True
    H: Tensor
    ndim = 2
    state_dim, meas_dim = 5, 2

    def __init__(
        self,
        dt: float = 1.0,
        q: float = 1.0,
        q_turn: float = 1e-4,
        r: ArrayLike = 1.0,
        learn_noise: bool = False,
        learn_q: bool | None = None,
        learn_r: bool | None = None,
    ) -> None:
        super().__init__()
        self.dt = _check_interval(dt)
        learn_process = learn_noise if learn_q is None else learn_q
        self.q = Positive(q, "q", learn=learn_process)
        self.q_turn = Positive(q_turn, "q_turn", learn=learn_process)
        self.R = _measurement_noise(r, 2, learn_noise if learn_r is None else learn_r)
        H = torch.zeros(2, 5, dtype=self.R.raw.dtype)
        H[0, 0] = H[1, 2] = 1.0
        self.register_buffer("H", H)

    @property
    def position_index(self) -> list[int]:
        """State indices of the positions (the measured components)."""
        return [0, 2]

    @property
    def velocity_index(self) -> list[int]:
        """State indices of the velocities."""
        return [1, 3]

    @property
    def turn_rate_index(self) -> int:
        """State index of the turn rate ω."""
        return 4

    def _interval(self, dt: Tensor | None, like: Tensor) -> Tensor:
        if dt is None:
            return torch.tensor(self.dt, dtype=like.dtype, device=like.device)
        return dt.to(like.dtype)

    def _turn(self, x: Tensor, dt: Tensor | None) -> _Turn:
        T = self._interval(dt, x)
        px, vx, py, vy, omega = x.unbind(-1)
        a = omega * T
        s, c, ds, dc = turn_coefficients(a)
        return _Turn(T, a, px, vx, py, vy, omega, s, c, ds, dc, torch.cos(a), torch.sin(a))

    @staticmethod
    def _f(t: _Turn) -> Tensor:
        T, s, c, cos, sin = t.T, t.s, t.c, t.cos, t.sin
        return torch.stack(
            [
                t.px + T * (s * t.vx - c * t.vy),
                cos * t.vx - sin * t.vy,
                t.py + T * (c * t.vx + s * t.vy),
                sin * t.vx + cos * t.vy,
                t.omega,
            ],
            -1,
        )

    @staticmethod
    def _f_jacobian(t: _Turn) -> Tensor:
        s, c, ds, dc, cos, sin, vx, vy = t.s, t.c, t.ds, t.dc, t.cos, t.sin, t.vx, t.vy
        zero, one = torch.zeros_like(t.a), torch.ones_like(t.a)
        T = t.T.expand_as(t.a)
        return _matrix(
            [
                [one, T * s, zero, -T * c, T * T * (ds * vx - dc * vy)],
                [zero, cos, zero, -sin, -T * (sin * vx + cos * vy)],
                [zero, T * c, one, T * s, T * T * (dc * vx + ds * vy)],
                [zero, sin, zero, cos, T * (cos * vx - sin * vy)],
                [zero, zero, zero, zero, one],
            ]
        )

    def f(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self._f(self._turn(x, dt))

    def f_jacobian(self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None) -> Tensor:
        return self._f_jacobian(self._turn(x, dt))

    def linearize(
        self, x: Tensor, dt: Tensor | None = None, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``f(x)`` and ``F`` from one evaluation of the turn's terms (each the same numbers as
        :meth:`f` and :meth:`f_jacobian` give alone): an EKF step asks for both."""
        turn = self._turn(x, dt)
        return self._f(turn), self._f_jacobian(turn)

    def h(self, x: Tensor) -> Tensor:
        return x[..., [0, 2]]

    def h_jacobian(self, x: Tensor) -> Tensor:
        return self.H.to(x.dtype).expand(x.shape[0], -1, -1)

    def process_noise(self, dt: Tensor | None = None) -> Tensor:
        T = self._interval(dt, self.H)
        gain = torch.zeros(*T.shape, 5, 3, dtype=T.dtype, device=T.device)
        gain[..., [0, 2], [0, 1]] = (T * T / 2).unsqueeze(-1)
        gain[..., [1, 3], [0, 1]] = T.unsqueeze(-1)
        gain[..., 4, 2] = T
        q = self.q().to(T.dtype)
        variances = torch.stack([q, q, self.q_turn().to(T.dtype)])
        return (gain * variances) @ gain.mT

    def meas_cov(self) -> Tensor:
        return self.R()

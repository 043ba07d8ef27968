"""Artificial measurements: full-state pseudo-measurements built from the measurement history.

When the state has more components than the measurement (n > m), the SVSF corrects the
unmeasured components only through an "artificial" measurement of them (Sec. 2 and Eq. (51),
Chen et al. 2020). An artificial measurement is a callable
``(z [B, T, m], model, dt, u) -> (y [B, T, n'], H_y [n', n], R_y [n', n'] or [B, T, n', n'])``
(``dt`` and ``u`` as passed to the estimator, ``None`` when not given).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchsvs.linalg import holds_nan
from torchsvs.models.base import StateSpaceModel


def _with_previous(
    z: Tensor, previous_used: list[int], now_used: list[int]
) -> tuple[Tensor, Tensor, Tensor]:
    """``z`` and the step before it (``[B, T, m]`` each, NaN filled with 0) and where the
    components used of either are unknown ``[B, T, 1]`` (the first step has no previous one).
    Computing on filled values and masking afterwards keeps values and gradients finite."""
    previous = torch.cat([torch.full_like(z[:, :1], float("nan")), z[:, :-1]], dim=1)
    unknown = torch.isnan(previous[..., previous_used]).any(-1, keepdim=True)
    unknown = unknown | torch.isnan(z[..., now_used]).any(-1, keepdim=True)
    return z.nan_to_num(0.0), previous.nan_to_num(0.0), unknown


class FiniteDifferenceVelocity:
    r"""Velocity from successive positions, Eq. (51), Chen et al. 2020.

    For a model with ``position_index`` and ``velocity_index`` (e.g.
    :class:`~torchsvs.models.ConstantVelocity`), the pseudo-measurement is the full state in state
    order, ``y_k = [z_{1,k}, (z_{1,k} − z_{1,k'})/Δ_{1,k}, z_{2,k}, ...]`` with ``H_y = I``, where
    ``k'`` is the last step before ``k`` at which that axis was observed and ``Δ`` the time
    between them. With ``bridge_gaps=False``, ``k' = k − 1`` only (Eq. (51) as printed: a velocity
    next to a missing position is missing). The first step has no earlier position: its velocity
    is missing, so it keeps the prior's (``torchsvs.datasets`` starts it from two-point
    differencing).

    Noise model (stated, as the paper leaves it open): with position noise ``R_k`` independent
    between steps, ``Cov(z_i, z_j) = R_{k,ij}``, ``Cov(z_i, v_j) = R_{k,ij}/Δ_j`` and
    ``Cov(v_i, v_j) = (R_{k,ij} + [k'_i = k'_j] R_{k',ij})/(Δ_i Δ_j)`` (``2R/T²`` for equal
    steps): each step's own noise, from the two positions it differences and their actual time
    gap, so a velocity across a gap of missing positions is as precise as its gap makes it. The
    correlation between successive velocities (``−R/T²``) is ignored, as the filter assumes white
    measurement noise.

    Args:
        correlated: keep the position-velocity covariance ``R/Δ`` (default); ``False`` drops it
            (a diagonal-block noise model, for ablations).
        bridge_gaps: difference against the last observed position of the axis (default), not
            only against the step before.

    A call may pass ``meas_cov`` (``[m, m]`` or per step ``[B, T, m, m]``, e.g. the adaptive
    ``R_k`` of :class:`~torchsvs.filters.AdaptiveNoise`) to stand for the model's ``R``; a
    velocity's variance then takes ``R_k`` of each of its two positions' steps.
    """

    def __init__(self, correlated: bool = True, bridge_gaps: bool = True) -> None:
        self.correlated = correlated
        self.bridge_gaps = bridge_gaps

    def __call__(
        self,
        z: Tensor,
        model: StateSpaceModel,
        dt: Tensor | None,
        u: Tensor | None = None,
        meas_cov: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        pos, vel = _positions_and_velocities(model, z.shape[-1])
        m, n = len(pos), model.state_dim
        velocity, inv, previous = self._differences(z, model, dt)
        if previous is None:
            same = torch.ones(1, 1, m, m, dtype=torch.bool)
        else:  # whether axes i, j difference against the same earlier step
            same = previous.unsqueeze(-1) == previous.unsqueeze(-2)
        R = (model.meas_cov() if meas_cov is None else meas_cov).to(z.dtype)
        cross = R * inv.unsqueeze(-2)  # Cov(z_i, v_j) = R_ij / Δ_j
        if not self.correlated:
            cross = torch.zeros_like(cross)
        earlier = _earlier_noise(R, previous)  # R_{k'} of the position each velocity differences
        vv = (R + same.to(z.dtype) * earlier) * inv.unsqueeze(-1) * inv.unsqueeze(-2)
        # Built in (positions, velocities) order, then permuted to state order at once.
        order = torch.tensor(pos + vel).argsort()  # state component -> its place in (p, v)
        y = torch.cat([z, velocity], dim=-1).index_select(-1, order)
        lead = cross.shape[:-2]
        top = torch.cat([R.expand(*lead, m, m), cross], dim=-1)
        R_y = torch.cat([top, torch.cat([cross.mT, vv], dim=-1)], dim=-2)
        R_y = R_y.index_select(-1, order).index_select(-2, order)
        if R_y.ndim == 4 and R_y.shape[:2] == (1, 1):
            R_y = R_y[0, 0]  # constant: [n, n]
        H_y = torch.eye(n, dtype=z.dtype)
        return y, H_y, R_y

    def per_axis(
        self, z: Tensor, model: StateSpaceModel, dt: Tensor | None
    ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]] | None:
        """The same measurement axis by axis, for a model whose ``R`` is diagonal (else
        ``None``): the velocities ``[B, T, m]`` (the positions are ``z``) and the noise
        ``(Var z_i, Cov(z_i, v_i), Var v_i)``, ``[m]`` or ``[B, T, m]`` each, the diagonal
        blocks of ``R_y`` (without assembling it)."""
        _positions_and_velocities(model, z.shape[-1])
        R = model.meas_cov().to(z.dtype)
        if bool((R != torch.diag_embed(R.diagonal())).any()):
            return None
        velocity, inv, _ = self._differences(z, model, dt)
        r = R.diagonal()
        inv = inv.squeeze(1).squeeze(0) if inv.shape[:2] == (1, 1) else inv
        cross = r * inv if self.correlated else torch.zeros_like(r * inv)
        return velocity, (r, cross, r * 2.0 * inv * inv)  # the diagonal of __call__'s vv

    def _differences(
        self, z: Tensor, model: StateSpaceModel, dt: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Velocities ``[B, T, m]`` (NaN where unknown), ``1/Δ`` ``[B, T, m]`` and the step each
        velocity differences against ``[B, T, m]`` (``1/Δ`` ``[1, 1, m]`` and ``None`` when every
        step has one interval)."""
        B, T, m = z.shape
        step = torch.tensor(getattr(model, "dt", 1.0), dtype=z.dtype) if dt is None else dt
        if step.ndim == 0 and not holds_nan(z):
            # No gaps, one interval: adjacent differences (the same numbers as below, in one
            # pass instead of a dozen over [B, T, m] index tensors; in place, without a
            # gradient to carry: a temporary of z's size costs as much as the pass).
            first = torch.full_like(z[:, :1], float("nan"))
            if torch.is_grad_enabled() and (z.requires_grad or step.requires_grad):
                velocity = torch.cat([first, (z[:, 1:] - z[:, :-1]) / step], dim=1)
            else:
                velocity = torch.empty_like(z)
                velocity[:, :1] = first
                torch.sub(z[:, 1:], z[:, :-1], out=velocity[:, 1:]).div_(step)
            return velocity, (1.0 / step).reshape(1, 1, 1).expand(1, 1, m), None
        observed = ~torch.isnan(z)
        index = torch.arange(T).view(1, T, 1).expand(B, T, m)
        if self.bridge_gaps:
            seen = torch.where(observed, index, torch.full_like(index, -1)).cummax(dim=1).values
            previous = torch.cat([torch.full_like(seen[:, :1], -1), seen[:, :-1]], dim=1)
        else:
            before = torch.cat([torch.zeros_like(observed[:, :1]), observed[:, :-1]], dim=1)
            previous = torch.where(before, index - 1, torch.full_like(index, -1))
        unknown = (previous < 0) | ~observed
        previous = previous.clamp_min(0)
        filled = z.nan_to_num(0.0)
        # Time since the previous observation of each axis.
        if step.ndim == 2:
            clock = torch.cumsum(step, dim=1).unsqueeze(-1).expand(B, T, m)
            elapsed = clock - clock.gather(1, previous)
        else:
            elapsed = (index - previous).to(z.dtype) * step
        elapsed = torch.where(unknown, torch.ones_like(elapsed), elapsed)
        # Computed on filled values and masked after, so gradients stay finite.
        velocity = (filled - filled.gather(1, previous)) / elapsed
        velocity = torch.where(unknown, torch.full_like(velocity, float("nan")), velocity)
        if not bool(unknown[:, 1:].any()) and step.ndim == 0:  # one interval everywhere
            return velocity, (1.0 / step).reshape(1, 1, 1).expand(1, 1, m), None
        return velocity, 1.0 / elapsed, previous


def _earlier_noise(R: Tensor, previous: Tensor | None) -> Tensor:
    """``R_{k'}``: the noise ``[m, m]`` or ``[B, T, m, m]`` of the earlier position row ``i``'s
    velocity differences against (``previous [B, T, m]``; ``None``: the step before). A
    constant ``R`` is its own."""
    if R.ndim < 4:
        return R
    B, T, m, _ = R.shape
    if previous is None:  # the step before (the first step's velocity is missing anyway)
        return torch.cat([R[:, :1], R[:, :-1]], dim=1)
    index = previous.unsqueeze(-1).expand(B, T, m, m)
    return R.gather(1, index)  # [b, t, i, j] = R[b, previous[b, t, i], i, j]


def _positions_and_velocities(model: StateSpaceModel, m: int) -> tuple[list[int], list[int]]:
    pos = getattr(model, "position_index", None)
    vel = getattr(model, "velocity_index", None)
    if pos is None or vel is None:
        raise TypeError(
            f"model: FiniteDifferenceVelocity needs position_index and velocity_index, "
            f"which {type(model).__name__} does not define"
        )
    n = model.state_dim
    if len(pos) != m or len(vel) != m or len(set(pos) | set(vel)) != n:
        raise ValueError(
            f"model: expected {m} positions and {m} velocities covering all {n} state components"
        )
    return list(pos), list(vel)


class ModulusFromAcceleration:
    r"""Artificial measurement of the EHA's bulk modulus from its measured dynamics (Sec. 5.2).

    Solving Eq. (51) (with ``x₄`` in the ``φ₁`` term) for ``x₄`` over the step ending at ``k``:

    .. math::
        y_{4,k} = \frac{z_{3,k} - (1 - T\varphi_3) z_{3,k-1}}
                       {T\,(G_E u_k - \varphi_2 z_{3,k-1} - \varphi_1 z_{2,k-1})}

    so the corrector measures the full state ``[z₁, z₂, z₃, y₄]`` with ``H = I`` (the approach of
    Eq. (47) for the ballistic coefficient). Noise model (stated): the numerator's noise has
    variance ``(1 + (1 − Tφ₃)²) R₃₃`` and the denominator is taken as exact, so
    ``Var(y₄) = (1 + (1 − Tφ₃)²) R₃₃ / D²``, independent of ``z``. Where the denominator is small
    (``|D| < min_drive · T G_E``, i.e. hardly any input drove the step) and at the first step,
    ``y₄`` is missing (NaN): the division would turn noise into huge pseudo-measurements that a
    saturated SVSF gain would follow.

    Args:
        min_drive: the smallest effective input ``|u|`` for which ``y₄`` is formed.
    """

    def __init__(self, min_drive: float = 0.2) -> None:
        self.min_drive = min_drive

    def __call__(
        self, z: Tensor, model: StateSpaceModel, dt: Tensor | None, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        for attribute in ("gain", "phi1", "phi2", "phi3"):
            if not hasattr(model, attribute):
                raise TypeError(
                    f"model: ModulusFromAcceleration needs an ElectrohydrostaticActuator, "
                    f"got {type(model).__name__}"
                )
        if u is None:
            raise ValueError("u: ModulusFromAcceleration needs the inputs u [B, T, 1]")
        m: Any = model
        T = torch.tensor(m.dt, dtype=z.dtype) if dt is None else dt.to(z.dtype)
        T = T.unsqueeze(-1) if T.ndim == 2 else T  # [B, T, 1] or 0-d
        now, previous, unknown = _with_previous(z, [1, 2], [2])
        drive = u[..., :1].to(z.dtype)  # u[:, k] drives the step into k (as in the filters)
        decay = 1.0 - T * m.phi3
        numerator = now[..., 2:3] - decay * previous[..., 2:3]
        D = T * (m.gain * drive - m.phi2 * previous[..., 2:3] - m.phi1 * previous[..., 1:2])
        skip = unknown | (D.abs() < self.min_drive * T * m.gain)  # no previous, or weak drive
        D = torch.where(skip, torch.ones_like(D), D)  # finite values (and gradients) where skipped
        modulus = torch.where(skip, torch.full_like(D, float("nan")), numerator / D)
        R = model.meas_cov().to(z.dtype)
        var = torch.where(skip, torch.ones_like(D), (1.0 + decay**2) * R[2, 2] / D.square())
        R_y = torch.diag_embed(torch.cat([R.diagonal().expand(*z.shape[:2], 3), var], dim=-1))
        y = torch.cat([z, modulus], dim=-1)
        return y, torch.eye(4, dtype=z.dtype), R_y


class BallisticCoefficientFromDrag:
    r"""Artificial ballistic-coefficient measurement, Eq. (47), Gadsden et al. 2012.

    Eq. (40) gives the speed change over a step, ``v_k − v_{k−1} = T (g − D(x_{k−1}))``; solving
    Eq. (43) for ``x₃`` with measured altitude and speed:

    .. math::
        y_{3,k} = \frac{T g \gamma\, e^{-\eta z_{1,k-1}} z_{2,k-1}^2}
                       {2\,(T g - (z_{2,k} - z_{2,k-1}))}

    so the corrector measures the full state ``[z₁, z₂, y₃]`` with ``H = I``. This is Eq. (47)
    one step later (it is "delayed one time step", as the paper says) and with the sign of the
    speed change that Eq. (40) implies: the printed ``z_{2,k+1} − z_{2,k} + Tg`` would hold for
    a speed measured upward, while Eq. (41) counts it downward.

    The denominator ``d`` is the drag's speed loss over one step, read through two speed
    measurements and one step of process noise: its noise variance is ``σ_d² = 2 R₂₂ + Q₂₂``
    (``√ ≈ 55`` m/s in Sec. 5.1) against a signal ``T D`` of 0.05 m/s at 61 km and a few m/s
    until the last seconds of the flight, so the quotient is noise for most of it (measured in
    ``experiments/spvsf_paper.py``). Steps with ``d < min_snr · σ_d`` are missing (NaN), as is the
    first step (without noise ``d = T D > 0``, so the test is one-sided); the paper initialises the
    measurement with 0 instead, which a saturated SVSF gain would follow. Where noise alone passes
    the test, ``y₃`` is a small number with a small stated variance: the first-order noise model
    ``Var(y₃) = y₃² (σ_d²/d² + 4R₂₂/z₂² + η²R₁₁)`` (correlations between steps ignored) holds
    only where the drag signal dominates the noise.

    Args:
        min_snr: the smallest ``d / σ_d`` for which ``y₃`` is formed.
    """

    def __init__(self, min_snr: float = 3.0) -> None:
        if not min_snr >= 0:
            raise ValueError(f"min_snr: expected a number >= 0, got {min_snr!r}")
        self.min_snr = min_snr

    def __call__(
        self, z: Tensor, model: StateSpaceModel, dt: Tensor | None, u: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        for attribute in ("gravity", "density", "decay"):
            if not hasattr(model, attribute):
                raise TypeError(
                    f"model: BallisticCoefficientFromDrag needs a BallisticReentry, "
                    f"got {type(model).__name__}"
                )
        m: Any = model
        T = torch.tensor(m.dt, dtype=z.dtype) if dt is None else dt.to(z.dtype)
        T = T.unsqueeze(-1) if T.ndim == 2 else T  # [B, T, 1] or 0-d
        now, previous, unknown = _with_previous(z, [0, 1], [1])
        h, v = previous[..., 0:1], previous[..., 1:2]
        d = T * m.gravity - (now[..., 1:2] - v)
        numerator = T * m.gravity * m.density * torch.exp(-m.decay * h) * v.square()
        R = model.meas_cov().to(z.dtype)
        Q = model.process_noise(dt).to(z.dtype)[..., 1, 1]  # 0-d, or [B, T]
        var_d = 2.0 * R[1, 1] + (Q.unsqueeze(-1) if Q.ndim == 2 else Q)
        # The drag only slows: d ≤ 0 is noise, so the test is one-sided.
        skip = unknown | (d < self.min_snr * var_d.sqrt()) | (v == 0)
        d, v = (torch.where(skip, torch.ones_like(x), x) for x in (d, v))  # finite where skipped
        value = numerator / (2.0 * d)
        relative = var_d / d.square() + 4.0 * R[1, 1] / v.square() + m.decay**2 * R[0, 0]
        y3 = torch.where(skip, torch.full_like(d, float("nan")), value)
        var = torch.where(skip, torch.ones_like(d), value.square() * relative)
        R_y = torch.diag_embed(torch.cat([R.diagonal().expand(*z.shape[:2], 2), var], dim=-1))
        return torch.cat([z, y3], dim=-1), torch.eye(3, dtype=z.dtype), R_y

"""The smooth variable structure filter (SVSF) with covariance."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive, UnitInterval
from torchsvs.estimator import Inputs
from torchsvs.filters import factored
from torchsvs.filters.adaptive import AdaptiveNoise, check_adaptive_noise
from torchsvs.filters.artificial import FiniteDifferenceVelocity
from torchsvs.filters.kalman import (
    GaussianFilter,
    KalmanFilter,
    Observation,
    Step,
    innovation_covariance,
)
from torchsvs.kernels import fused
from torchsvs.kernels.axes import AxisMeasurements, Sym2
from torchsvs.linalg import (
    has_orthonormal_rows,
    joseph_update,
    mask_covariance,
    masked_pinv,
    matvec,
    svsf_gain_ratio,
)
from torchsvs.models.base import StateSpaceModel

ArtificialMeasurement = Callable[
    [Tensor, StateSpaceModel, "Tensor | None", "Tensor | None"], tuple[Tensor, Tensor, Tensor]
]


def auto_artificial(model: StateSpaceModel) -> ArtificialMeasurement | None:
    """The artificial measurement ``artificial="auto"`` picks: finite-difference velocity for a
    model whose measurement is its positions and whose state adds their velocities, else none."""
    pos = getattr(model, "position_index", None)
    vel = getattr(model, "velocity_index", None)
    if pos is None or vel is None or model.meas_dim >= model.state_dim:
        return None
    if len(pos) != model.meas_dim or len(set(pos) | set(vel)) != model.state_dim:
        return None
    return FiniteDifferenceVelocity()


class SVSF(GaussianFilter):
    r"""Smooth variable structure filter with covariance, Eqs. (18)-(28), Chen et al. 2020.

    Shares the Kalman prediction (Eqs. (18), (20)) and replaces the corrector:

    .. math::
        e_{k+1|k} = z_{k+1} - H\hat x_{k+1|k} \quad\text{(Eq. (4); Eq. (21) misprints } z_k)

        K_{k+1} = H^{+}\,\mathrm{diag}\!\left(\frac{|e_{k+1|k}| + \gamma|e_{k|k}|}
                  {\max(|e_{k+1|k}|, \psi)}\right)
        \quad\text{(Eq. (23), since } \mathrm{sat}(e/\psi)/e = 1/\max(|e|,\psi))

        \hat x_{k+1|k+1} = \hat x_{k+1|k} + K_{k+1} e_{k+1|k}, \qquad
        P_{k+1|k+1} = (I - KH) P_{k+1|k} (I - KH)^T + K R K^T \quad\text{(Eq. (28), Joseph)}

        e_{k+1|k+1} = z_{k+1} - H\hat x_{k+1|k+1} \quad\text{(Eq. (24))}

    The memory ``e_{0|0}`` before the first step is zero. The gain never divides by the
    innovation, so it and its gradients are finite at ``e = 0``.

    When the state has more components than the measurement (n > m) there are two modes:

    * artificial measurements (Sec. 4.2, complex scenario, Eq. (51)): the corrector measures
      full-state pseudo-measurements with their own ``H`` and ``R``; ``psi`` then has one width
      per pseudo-measurement, in state order (``[500, 600, 500, 600]`` in the paper). The default
      ``artificial="auto"`` takes :class:`~torchsvs.filters.FiniteDifferenceVelocity` for a model
      with positions and velocities (a position-only
      :class:`~torchsvs.models.ConstantVelocity`), so the velocity is corrected too: without it
      the velocity of a recorded track stays at whatever the prior gave, for ever.
    * ``artificial=None`` (the paper's Sec. 4.1, ATC scenario; also what ``"auto"`` means for
      other models): ``H⁺`` is the Moore-Penrose pseudo-inverse, so only the measured components
      are corrected (for position-only ``H``, ``H⁺ = Hᵀ`` and the velocity is never corrected).

    Nonlinear models (Eqs. (11)-(21), Gadsden et al. 2012): the prediction is ``f(x̂)`` with the
    Jacobian ``F`` for the covariance, the innovation is ``z − h(x̂_{k+1|k})`` and ``H⁺`` is the
    pseudo-inverse of the Jacobian of ``h`` at ``x̂_{k+1|k}``; the corrector is the same.

    Missing data: a NaN component gives no correction (its column of the gain is zero, ``H⁺`` is
    that of the observed rows) and its memory ``e_{k|k}`` is carried from the previous step.

    Args:
        model: a :class:`~torchsvs.models.StateSpaceModel` (linear or nonlinear).
        psi: boundary layer widths ψ > 0 ("smoothing boundary layer"), a scalar or one per
            corrector measurement component.
        gamma: memory (convergence rate) γ in ``[0, 1)``.
        learn: hold ψ and γ as ``nn.Parameter`` s (stored as ``log ψ`` and ``logit γ``); ``False``
            makes them fixed buffers.
        artificial: ``"auto"`` (default: finite-difference velocity where the model has
            positions and velocities, else none), an artificial measurement callable (see
            :mod:`torchsvs.filters.artificial`), or ``None`` for the ``H⁺`` mode.
        adaptive_noise: an :class:`~torchsvs.filters.AdaptiveNoise`: ``R_k`` from the spread
            of the differenced recent measurements ``z`` (Eqs. (29)-(30), Bermúdez Ordoñez et
            al. 2020), or ``None`` (the model's ``R``). The gain does not read ``R``: it changes
            the covariance (Eq. (28)) and ``S``, and so what smoothers and an IMM see. An
            artificial measurement must take it as ``meas_cov`` (as
            :class:`~torchsvs.filters.FiniteDifferenceVelocity` does).
        covariance_form: how Eq. (28) is carried out: ``"joseph"`` (default, its left side),
            the factored ``"sqrt"``, ``"ud"`` or ``"svd"`` forms of the same update (the
            covariance as a factor, updated through a pre-array built with the SVSF's gain:
            :mod:`torchsvs.filters.factored`), or ``"conventional"``: the right side
            ``(I − KH)P`` as printed, which for the SVSF's gain is *not* the covariance of its
            estimate (the estimates are unchanged: the SVSF's gain does not read ``P``).

    A per-step ``psi=`` of shape ``[B, T, m]`` passed at call time replaces ψ (for an upstream
    network that drives the boundary layer).

    References:
        Habibi, "The smooth variable structure filter", Proc. IEEE 95(5), 2007.
        doi:10.1109/JPROC.2007.893255 ·
        Chen, Xu, Yan, Li, Sensors 20(6):1781, 2020. doi:10.3390/s20061781
    """

    model_type = StateSpaceModel

    def __init__(
        self,
        model: StateSpaceModel,
        psi: ArrayLike,
        gamma: float | torch.Tensor = 0.1,
        learn: bool = True,
        artificial: ArtificialMeasurement | str | None = "auto",
        adaptive_noise: AdaptiveNoise | None = None,
        covariance_form: str = "joseph",
    ) -> None:
        super().__init__(model)
        self.covariance_form = factored.check_form(covariance_form)
        if artificial == "auto":
            artificial = auto_artificial(model)
        self.adaptive_noise = check_adaptive_noise(adaptive_noise)
        self.boundary_layer = Positive(psi, "psi", learn=learn)
        self.memory = UnitInterval(gamma, "gamma", learn=learn)
        if self.boundary_layer.raw.ndim > 1:
            raise ValueError(
                "psi: expected a scalar or a vector [m], got shape "
                f"{tuple(self.boundary_layer.raw.shape)}"
            )
        if self.memory.raw.ndim != 0:
            raise ValueError(f"gamma: expected a scalar, got shape {tuple(self.memory.raw.shape)}")
        if artificial is not None and not callable(artificial):
            raise TypeError(f"artificial: expected 'auto', a callable or None, got {artificial!r}")
        if (
            adaptive_noise is not None
            and artificial is not None
            and "meas_cov" not in inspect.signature(artificial).parameters
        ):
            raise ValueError(
                f"adaptive_noise: the artificial measurement {type(artificial).__name__} takes no "
                "meas_cov to build its noise from; use FiniteDifferenceVelocity, one that takes "
                "meas_cov, or artificial=None (the H⁺ mode)"
            )
        self.artificial = artificial

    @property
    def psi(self) -> Tensor:
        """Boundary layer widths ψ (> 0)."""
        return self.boundary_layer()

    @property
    def gamma(self) -> Tensor:
        """Memory γ in [0, 1)."""
        return self.memory()

    axis_rule: str | None = "svsf"

    def takes_psi(self) -> bool:
        return True

    def axis_settings(self, inputs: Inputs) -> tuple[Tensor, Tensor]:
        """ψ as ``[2, m]`` (rows: position, velocity widths per axis) or per step
        ``[B, T, 2, m]``, and γ, for the per-axis kernel."""
        dtype = inputs.z.dtype
        widths = inputs.psi if inputs.psi is not None else self.psi.to(dtype)
        m = self.model.meas_dim
        if widths.ndim == 0:
            return widths.expand(2, m), self.gamma.to(dtype)
        if self.artificial is None:  # H⁺ mode: positions only (velocity widths unused)
            widths = torch.stack([widths, torch.ones_like(widths)], dim=-2)
        else:  # finite-difference velocity: state order p1, v1, p2, v2, ...
            widths = widths.unflatten(-1, (m, 2)).transpose(-1, -2)
        return widths, self.gamma.to(dtype)

    def measurements(
        self, inputs: Inputs, history: Any = None
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        if self.artificial is None:
            z, H, R = super().measurements(inputs, history)
        else:
            z, H, R = _artificial_measurements(
                self.artificial, self.model, history, inputs, self.adaptive_noise
            )
        self._check_widths(z.shape[-1], inputs)
        return z, H, R

    def carried_history(self, history: Any, inputs: Inputs) -> Any:
        """The raw rows an artificial measurement may still look back to: from the earliest
        step at which some track last observed some component (finite differences bridge
        gaps back to it), and at least the last row (a step's previous row); with
        ``adaptive_noise``, at least its segments' rows."""
        if self.artificial is None:
            return super().carried_history(history, inputs)
        adaptive = self.adaptive_noise
        return _rows_to_keep(history, inputs, 1 if adaptive is None else adaptive.rows_needed)

    def axis_measurements(self, inputs: Inputs) -> AxisMeasurements | None:
        """Finite-difference velocities axis by axis (``R_y`` never assembled)."""
        if not isinstance(self.artificial, FiniteDifferenceVelocity):
            return None
        parts = self.artificial.per_axis(inputs.z, self.model, inputs.dt)
        if parts is None:
            return None
        self._check_widths(self.model.state_dim, inputs)
        velocity, noise = parts
        dtype = inputs.z.dtype
        return AxisMeasurements(inputs.z, velocity, Sym2(*(x.to(dtype) for x in noise)))

    def _check_widths(self, m: int, inputs: Inputs) -> None:
        """ψ has one width per corrector measurement (``m`` of them)."""
        widths = self.boundary_layer.raw.numel()
        if self.boundary_layer.raw.ndim == 1 and widths != m:
            hint = (
                f" (the {type(self.artificial).__name__} artificial measurement: a width per "
                "state component, in state order; artificial=None is the H⁺ mode with one "
                "width per measured component)"
                if self.artificial is not None
                else ""
            )
            raise ValueError(
                f"psi: expected {m} boundary layer widths (one per corrector measurement"
                f"{hint}), got {widths}"
            )
        if inputs.psi is not None and inputs.psi.shape[-1] != m:
            raise ValueError(
                f"psi: expected a per-step override of shape [B, T, {m}], "
                f"got {tuple(inputs.psi.shape)}"
            )

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        z, mask, R = obs.z, obs.mask, obs.R
        gains: _Gains = obs.settings  # run_settings, formed once by prepare
        psi = inputs.psi[:, obs.t] if inputs.psi is not None else gains.psi
        fitted, H = obs.linearize(x_pred)  # nonlinear h: Eqs. (13)-(21), Gadsden et al. 2012
        e = z - fitted  # Eq. (4); Eq. (14) of Gadsden et al. 2012
        if mask is not None:
            e = e * mask
        H_plus = masked_pinv(H, mask, gains.orthonormal)  # zero columns where missing
        memory = carried if carried is not None else torch.zeros_like(e)
        K = H_plus * svsf_gain_ratio(e, memory, psi, gains.gamma).unsqueeze(-2)
        x = x_pred + matvec(K, e)  # Eq. (22)
        factor = obs.factor  # P_pred in a factored covariance form, else None
        if factor is None:
            P = joseph_update(P_pred, K, H, R)  # Eq. (28), left side
        else:
            factor = factor.gain_update(K, H, R)
            P = factor.full()
        S = innovation_covariance(H, P_pred @ H.mT, R)
        if mask is not None:  # H P Hᵀ + R of the observed components (see mask_measurement)
            S = mask_covariance(S, mask)
        return Step(
            x,
            P,
            e,
            K,
            post_innovation=self.memory_after(x, obs, memory),
            innovation_cov=S,
            meas_matrix=H if obs.H is None else None,
            factor=factor,
        )

    @property
    def dense_rule(self) -> str | None:  # type: ignore[override]
        return "svsf" if self.artificial is None else None

    def _dense_settings(self, dtype: torch.dtype, H: Tensor) -> tuple[float, Tensor] | None:
        gains = self.run_settings(dtype, H)
        if not gains.orthonormal or not fused.usable(gains.psi, gains.gamma):
            return None
        widths = gains.psi
        return float(gains.gamma), widths.expand(H.shape[0]) if widths.ndim == 0 else widths

    def run_settings(self, dtype: torch.dtype, H: Tensor | None) -> _Gains:
        orthonormal = None if H is None or H.ndim != 2 else has_orthonormal_rows(H)
        return _Gains(self.psi.to(dtype), self.gamma.to(dtype), orthonormal)

    def memory_after(self, x: Tensor, obs: Observation, memory: Tensor) -> Tensor:
        """The memory the next step carries: the a-posteriori innovation ``e_{k+1|k+1} = z −
        h(x̂_{k+1|k+1})`` of the estimate ``x`` (Eq. (24)), and the previous ``memory`` for a
        missing component."""
        e_post = obs.z - obs.fitted(x)
        return e_post if obs.mask is None else torch.where(obs.mask, e_post, memory)


class ArtificialKalmanFilter(KalmanFilter):
    r"""The Kalman filter on an artificial measurement: the correction of
    :class:`~torchsvs.filters.KalmanFilter` applied to the pseudo-measurements the SVSF corrects
    with (e.g. :class:`~torchsvs.filters.FiniteDifferenceVelocity`: ``y = [z_1, v_1, z_2, v_2,
    ...]`` with ``H_y = I`` and its derived ``R_y``, Eq. (51), Chen et al. 2020).

    .. math::
        S = H_y P_{k+1|k} H_y^T + R_y,\quad K = P_{k+1|k} H_y^T S^{-1},\quad
        \hat x_{k+1|k+1} = \hat x_{k+1|k} + K (y_{k+1} - H_y \hat x_{k+1|k})

    It exists so a KF and an :class:`SVSF` that measure the same thing can be the modes of one
    :class:`~torchsvs.filters.IMM` (their innovation likelihoods then compare). As a filter on
    its own it is not the optimal KF: the finite-difference velocities of successive steps
    share a position and are correlated (``−R/T²``), which the white-noise correction ignores.

    Args:
        model: a :class:`~torchsvs.models.LinearModel`.
        artificial: ``"auto"`` (finite-difference velocity for a position/velocity model, as
            for :class:`SVSF`) or an artificial measurement callable.
    """

    axis_rule = None  # the kernels' Kalman rule measures z itself
    dense_rule = None

    def __init__(
        self, model: StateSpaceModel, artificial: ArtificialMeasurement | str = "auto"
    ) -> None:
        super().__init__(model)
        if artificial == "auto":
            found = auto_artificial(model)
            if found is None:
                raise ValueError(
                    f"artificial: 'auto' finds no artificial measurement for "
                    f"{type(model).__name__} (a model with position_index and velocity_index)"
                )
            artificial = found
        if not callable(artificial):
            raise TypeError(f"artificial: expected 'auto' or a callable, got {artificial!r}")
        self.artificial = artificial

    def measurements(
        self, inputs: Inputs, history: Any = None
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        return _artificial_measurements(self.artificial, self.model, history, inputs)

    def carried_history(self, history: Any, inputs: Inputs) -> Any:
        """The raw rows the artificial measurement may still look back to (as for the SVSF)."""
        return _rows_to_keep(history, inputs)


def _artificial_measurements(
    artificial: ArtificialMeasurement,
    model: StateSpaceModel,
    history: Any,
    inputs: Inputs,
    adaptive: AdaptiveNoise | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The artificial measurement of the steps of ``inputs``, ``H`` and ``R``, formed over the
    rows kept from earlier steps and these (see :func:`_rows_to_keep`); with ``adaptive``, from
    the adaptive ``R_k`` of those rows."""
    window = _window(history, inputs)
    if adaptive is None:
        z, H, R = artificial(window.z, model, window.dt, window.u)
    else:  # the kept rows cover the segments of this call's steps (carried_history)
        R_k = adaptive.covariance(model.meas_cov().to(window.z.dtype), window.z)
        z, H, R = cast(Any, artificial)(window.z, model, window.dt, window.u, meas_cov=R_k)
    H, R = H.to(z.dtype), R.to(z.dtype)
    kept = window.z.shape[1] - inputs.steps
    return z[:, kept:], H, R[:, kept:] if R.ndim == 4 else R


def _rows_to_keep(history: Any, inputs: Inputs, at_least: int = 1) -> _Rows:
    """The raw rows an artificial measurement may still look back to: from the earliest step at
    which some track last observed some component (finite differences bridge gaps back to it),
    and at least the last ``at_least`` rows (a step's previous row)."""
    window = _window(history, inputs)
    T = window.z.shape[1]
    least = max(0, T - at_least)
    if not bool(torch.isnan(window.z[:, -1]).any()):  # every component seen last step
        return _window_rows(window, least)
    seen = ~torch.isnan(window.z)
    index = torch.arange(T).view(1, T, 1).expand_as(seen)
    last = torch.where(seen, index, torch.full_like(index, -1)).amax(dim=1)  # [B, m]
    observed = last[last >= 0]
    start = min(T - 1, int(observed.min())) if observed.numel() else T - 1
    return _window_rows(window, min(start, least))


class _Gains(NamedTuple):
    """The SVSF corrector's constants of a run."""

    psi: Tensor  #: ψ in the run's dtype (a per-step override replaces it)
    gamma: Tensor  #: γ in the run's dtype
    orthonormal: bool | None  #: whether the run's H has orthonormal rows (None: H varies)


class _Rows(NamedTuple):
    """Raw measurement rows with their intervals and inputs (``dt``: None, 0-d or ``[B, k]``)."""

    z: Tensor
    dt: Tensor | None
    u: Tensor | None


def _window(history: _Rows | None, inputs: Inputs) -> _Rows:
    """The kept rows of earlier steps followed by this call's."""
    if history is None:
        return _Rows(inputs.z, inputs.dt, inputs.u)
    B, kept = history.z.shape[:2]
    dt: Tensor | None
    if history.dt is None and inputs.dt is None:
        dt = None
    elif history.dt is None or inputs.dt is None:
        raise ValueError(
            "dt: pass it at every step or at none (the earlier steps of this state "
            f"{'had' if history.dt is not None else 'had no'} dt)"
        )
    elif history.dt.ndim == 0 and inputs.dt.ndim == 0 and bool(history.dt == inputs.dt):
        dt = inputs.dt  # one interval throughout: kept as a scalar, as a whole run has it
    else:
        dt = torch.cat([history.dt.expand(B, kept), inputs.dt.expand(B, inputs.steps)], dim=1)
    u = None if history.u is None or inputs.u is None else torch.cat([history.u, inputs.u], 1)
    return _Rows(torch.cat([history.z, inputs.z], dim=1), dt, u)


def _window_rows(window: _Rows, start: int) -> _Rows:
    dt = window.dt if window.dt is None or window.dt.ndim == 0 else window.dt[:, start:]
    u = None if window.u is None else window.u[:, start:]
    return _Rows(window.z[:, start:], dt, u)

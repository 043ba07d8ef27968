"""The smooth variable structure filter (SVSF) with covariance."""

from __future__ import annotations

import inspect
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike, Positive, UnitInterval, as_tensor
from torchsvs.estimator import Inputs
from torchsvs.filters import factored
from torchsvs.filters.adaptive import AdaptiveNoise, check_adaptive_noise
from torchsvs.filters.artificial import FiniteDifferenceVelocity
from torchsvs.filters.artificial_rows import (
    ArtificialMeasurement,
    artificial_measurements,
    auto_artificial,
    rows_to_keep,
)
from torchsvs.filters.fast_paths import NO_FAST_PATHS, FastPathFilter, FastPaths
from torchsvs.filters.gaussian import Observation, Step, innovation_covariance, kalman_correct
from torchsvs.filters.kalman import KalmanFilter
from torchsvs.kernels import build
from torchsvs.kernels.axes import AxisMeasurements
from torchsvs.kernels.blocks import Sym2
from torchsvs.linalg import (
    INFLATIONS,
    boundary_inflation,
    has_orthonormal_rows,
    joseph_update,
    mask_covariance,
    masked_pinv,
    matvec,
    svsf_gain_ratio,
)
from torchsvs.models.base import StateSpaceModel

#: How an :class:`SVSF` reads ψ: in the measurement's own units, or in standard deviations of
#: each step's own corrector-measurement noise.
PSI_UNITS = ("absolute", "noise")


class SVSF(FastPathFilter):
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
            makes them fixed buffers. A γ of exactly 0 (no memory) is fixed either way: a
            learnable γ lives in (0, 1).
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
        psi_units: ``"absolute"`` (default): ψ in the units of the corrector's measurement
            (m, m/s), as in the papers; ``"noise"``: in standard deviations of each step's own
            noise of that measurement, ``ψ_k = ψ ⊙ √diag(R_k)``, with ``R_k`` the step's own:
            for :class:`~torchsvs.filters.FiniteDifferenceVelocity` the noise of the velocity
            differenced over the step's actual interval (``√2 σ/Δ_k``, longer across missing
            positions), so one ψ (the rule of thumb's 4-5, Sec. 4.1-4.2, Chen et al. 2020) fits
            1 s and 10 s steps and irregular times alike, where one ψ in m/s fits one interval.

    A per-step ``psi=`` of shape ``[B, T, m]`` passed at call time replaces ψ (for an upstream
    network that drives the boundary layer), in the same units.

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
        psi_units: str = "absolute",
    ) -> None:
        super().__init__(model)
        self.covariance_form = factored.check_form(covariance_form)
        if psi_units not in PSI_UNITS:
            raise ValueError(f"psi_units: expected one of {PSI_UNITS}, got {psi_units!r}")
        self.psi_units = psi_units
        if artificial == "auto":
            artificial = auto_artificial(model)
        self.adaptive_noise = check_adaptive_noise(adaptive_noise)
        self.boundary_layer = Positive(psi, "psi", learn=learn)
        # No memory (γ = 0) cannot be learned in logit space: it stays fixed at 0.
        no_memory = bool((as_tensor(gamma, "gamma") == 0).all())
        self.memory = UnitInterval(gamma, "gamma", learn=learn and not no_memory)
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

    def takes_psi(self) -> bool:
        return True

    def axis_settings(self, inputs: Inputs) -> tuple[Tensor, Tensor]:
        """ψ as ``[2, m]`` (rows: position, velocity widths per axis) or per step
        ``[B, T, 2, m]``, and γ, for the per-axis kernel."""
        dtype = inputs.z.dtype
        widths = inputs.psi if inputs.psi is not None else self.psi.to(dtype)
        m = self.model.meas_dim
        if widths.ndim == 0:
            widths = widths.expand(2, m)
        elif self.artificial is None:  # H⁺ mode: positions only (velocity widths unused)
            widths = torch.stack([widths, torch.ones_like(widths)], dim=-2)
        else:  # finite-difference velocity: state order p1, v1, p2, v2, ...
            widths = widths.unflatten(-1, (m, 2)).transpose(-1, -2)
        if self.psi_units == "noise":  # each step's own noise per axis, [2, m] or [B, T, 2, m]
            widths = widths * torch.stack(self._axis_noise_std(inputs), dim=-2)
        return widths, self.gamma.to(dtype)

    def _axis_noise_std(self, inputs: Inputs) -> tuple[Tensor, Tensor]:
        """Standard deviations of the corrector's position and velocity measurement per axis
        (``[m]`` or ``[B, T, m]`` each; ones for the velocity of the ``H⁺`` mode)."""
        dtype = inputs.z.dtype
        r = self.model.meas_cov().to(dtype).diagonal()
        parts = None
        if isinstance(self.artificial, FiniteDifferenceVelocity):
            parts = self.artificial.per_axis(inputs.z, self.model, inputs.dt)
        if parts is None:
            return r.sqrt(), torch.ones_like(r)
        var_p, var_v = torch.broadcast_tensors(parts[1][0], parts[1][2])
        return var_p.sqrt(), var_v.sqrt()

    def measurements(
        self, inputs: Inputs, history: Any = None
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        if self.artificial is None:
            z, H, R = super().measurements(inputs, history)
        else:
            z, H, R = artificial_measurements(
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
        if adaptive is None:
            return rows_to_keep(history, inputs)
        # A velocity's noise reads R_k at both of its positions: the earlier one's segment too.
        needed = adaptive.rows_needed
        return rows_to_keep(history, inputs, needed, reach_back=needed)

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
        if self.psi_units == "noise":  # this step's own noise
            psi = psi * R.diagonal(dim1=-2, dim2=-1).sqrt()
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
    def paths(self) -> FastPaths:  # type: ignore[override]
        """Both kernels' ``"svsf"`` rules; the compiled dense steps in the ``H⁺`` mode only."""
        return _H_PLUS_PATHS if self.artificial is None else _ARTIFICIAL_PATHS

    def dense_settings(self, dtype: torch.dtype, H: Tensor) -> tuple[float, Tensor] | None:
        gains = self.run_settings(dtype, H)
        if not gains.orthonormal or not build.usable(gains.psi, gains.gamma):
            return None
        widths = gains.psi.expand(H.shape[0])
        if self.psi_units == "noise":  # (the dense steps run the model's constant R)
            widths = widths * self._model_noise_std(dtype)
        return float(gains.gamma), widths

    def _model_noise_std(self, dtype: torch.dtype) -> Tensor:
        return self.model.meas_cov().to(dtype).diagonal().sqrt()

    def dense_widths(self, psi: Tensor, dtype: torch.dtype) -> Tensor:
        """A per-step ψ in noise units as widths in the model's constant ``R``'s."""
        if self.psi_units == "noise":
            return psi * self._model_noise_std(dtype)
        return psi

    def run_settings(self, dtype: torch.dtype, H: Tensor | None) -> _Gains:
        orthonormal = None if H is None or H.ndim != 2 else has_orthonormal_rows(H)
        return _Gains(self.psi.to(dtype), self.gamma.to(dtype), orthonormal)

    def memory_after(self, x: Tensor, obs: Observation, memory: Tensor) -> Tensor:
        """The memory the next step carries: the a-posteriori innovation ``e_{k+1|k+1} = z −
        h(x̂_{k+1|k+1})`` of the estimate ``x`` (Eq. (24)), and the previous ``memory`` for a
        missing component."""
        e_post = obs.z - obs.fitted(x)
        return e_post if obs.mask is None else torch.where(obs.mask, e_post, memory)


class VariableBoundarySVSF(SVSF):
    r"""The SVSF with a variable boundary layer (VBL): the Kalman gain inside the layer and a
    correction that saturates towards the measurement beyond it, carried out as the Kalman gain
    of an inflated prior so that its covariance and its smoothers stay consistent.

    Inside its boundary layer the SVSF gain of Eq. (23) is ``H⁺ Ē ψ̄⁻¹`` with
    ``Ē = diag(|e_{k+1|k}| + γ|e_{k|k}|)``. Gadsden & Habibi (2013) derive the width that
    minimises the trace of the a-posteriori covariance (Eq. (28)) each step from the a-priori
    covariance and ``R``; per measured component ``i`` (the diagonal reading of
    ``ψ̄ = (Ē⁻¹ H P Hᵀ S⁻¹)⁻¹``)

    .. math::
        \psi_{VBL,i} = \bar E_i / k_i,\qquad k_i = (H P_{k+1|k} H^T S_{k+1}^{-1})_{ii},
        \qquad S_{k+1} = H P_{k+1|k} H^T + R,

    with which the gain is the Kalman gain; where the layer would grow past a limit (an error
    the model does not explain: a maneuver, a fault, too small a ``Q``) the SVSF's saturating
    correction takes over. Here the limit is ψ in standard deviations of each step's own
    innovation, a test free of units, sampling interval and target speed: the step is inside
    where every ``Ē_i ≤ ψ_i √S_ii``. Beyond it the prior is inflated, ``P̃ = λ P_{k+1|k}``, with
    the least ``λ ≥ 1`` that puts every component's innovation back on the layer's edge
    (``inflation="innovation"``, default: covariance matching, Mehra 1972),

    .. math::
        \lambda = \max\Big(1,\ \max_i \frac{\bar E_i^2/\psi_i^2 - R_{ii}}
                  {(H P_{k+1|k} H^T)_{ii}}\Big),

    or the least ``λ`` that gives every component at least Gadsden & Habibi's own gain beyond
    the limit, ``g_i = Ē_i / max(|e_i|, ψ_lim,i)`` with ``ψ_lim,i = ψ_i √S_ii / k_i``
    (``inflation="gain"``: ``λ = maxᵢ R_ii g_i / ((1 − g_i)(H P Hᵀ)_ii)``). Either way the gain
    is the Kalman gain of the inflated prior,

    .. math::
        K = \tilde P H^T (H \tilde P H^T + R)^{-1},\qquad
        P_{k+1|k+1} = (I - KH)\tilde P (I - KH)^T + K R K^T,

    which rises with the innovation from ``k_i`` at the layer's edge towards 1 (for one
    component alone, ``1 − ψ² R/Ē²`` under covariance matching): the SVSF's saturation, read as
    an adaptive Kalman filter (Spiller & Söffker 2020). Unmeasured components (velocities) move
    as the Kalman gain moves them, where ``H⁺`` would leave them alone. A component's gain is
    at most :attr:`max_gain` (a gain of 1 would take an infinite prior). The result's
    ``pred_cov`` is ``P̃``, the prior the gain is optimal for, so a smoother over this filter
    does not smooth across a step where the model failed (its gain ``P F^T P̃⁻¹`` is small
    there), where over the uninflated prior it would drag the failure into its neighbours.
    Inside the layer ``λ = 1`` and this filter *is* the Kalman filter, and :class:`SVSS` and
    the RTS smoother over it are the Kalman smoother; as ``ψ → ∞`` they equal them for any
    data. The result carries the innovations' log-likelihood under ``H P̃ Hᵀ + R``.

    The measurement is the model's own (no artificial measurement: the Kalman gain already
    corrects what is not measured). Missing components get no correction and keep their memory.

    Args:
        model: a :class:`~torchsvs.models.StateSpaceModel` (a nonlinear ``h`` is linearised at
            the prediction, as for :class:`SVSF`).
        psi: the limit ψ > 0 in innovation standard deviations, a scalar or one per measured
            component (learnable).
        gamma: memory γ in ``[0, 1)`` (learnable).
        learn, adaptive_noise: as for :class:`SVSF`.
        inflation: ``"innovation"`` (default) or ``"gain"``, the inflation beyond the limit
            (above).

    A per-step ``psi=`` of shape ``[B, T, m]`` passed at call time replaces the limit.

    References:
        Gadsden, Habibi, "A new robust filtering strategy for linear systems", J. Dyn. Sys.,
        Meas., Control 135(1):014503, 2013. doi:10.1115/1.4006628 ·
        Spiller, Söffker, "On the relation between smooth variable structure and adaptive Kalman
        filter", Front. Appl. Math. Stat. 6, 2020. doi:10.3389/fams.2020.585439 ·
        Mehra, "Approaches to adaptive filtering", IEEE Trans. Autom. Control 17(5), 1972.
    """

    #: the largest gain of a measured component: a gain of 1 would take an infinite prior
    max_gain = 0.999

    def __init__(
        self,
        model: StateSpaceModel,
        psi: ArrayLike,
        gamma: float | torch.Tensor = 0.1,
        learn: bool = True,
        adaptive_noise: AdaptiveNoise | None = None,
        inflation: str = "innovation",
    ) -> None:
        super().__init__(
            model, psi, gamma, learn=learn, artificial=None, adaptive_noise=adaptive_noise
        )
        if inflation not in INFLATIONS:
            raise ValueError(f"inflation: expected one of {INFLATIONS}, got {inflation!r}")
        self.inflation = inflation

    @property
    def paths(self) -> FastPaths:  # type: ignore[override]
        """The per-axis kernel's rule: compiled, with its reverse mode, for the default
        ``"innovation"`` inflation of as many axes as one vector of lanes holds (one λ per track
        couples its axes: :func:`~torchsvs.kernels.fused_axes.compiles`), else its tensor
        loop."""
        return FastPaths(axis=f"vbl-{self.inflation}")

    def filter_step(
        self,
        t: int,
        x: Tensor,
        P: Tensor,
        carried: Tensor | None,
        prep: Any,
        inputs: Inputs,
    ) -> tuple[Tensor, Tensor, Tensor, Step]:
        """The step of :class:`~torchsvs.filters.GaussianFilter`, recording the inflated prior
        ``P̃``."""
        x_pred, P_pred, F_t = self.predict(t, x, P, prep, inputs)
        step, inflation = self._correct(x_pred, P_pred, prep.observation(t), carried, inputs)
        return x_pred, P_pred * inflation[..., None, None], F_t, step

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        return self._correct(x_pred, P_pred, obs, carried, inputs)[0]

    def _correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> tuple[Step, Tensor]:
        """The step and its inflation ``λ [B]``."""
        gains: _Gains = obs.settings
        limit = inputs.psi[:, obs.t] if inputs.psi is not None else gains.psi
        fitted, H = obs.linearize(x_pred)
        e = obs.z - fitted
        memory = carried if carried is not None else torch.zeros_like(e)
        seen = obs.mask if obs.mask is not None else torch.ones_like(e, dtype=torch.bool)
        error = (e * seen).abs()  # (the missing components ask for nothing)
        inflation = boundary_inflation(
            error + gains.gamma * memory.abs(),
            error,
            limit,
            (H @ P_pred @ H.mT).diagonal(dim1=-2, dim2=-1),
            obs.R.diagonal(dim1=-2, dim2=-1),
            seen,
            self.inflation,
            self.max_gain,
        )
        # The Kalman correction of the inflated prior P̃ = λ P (Eq. (28), left side, on P̃).
        step = kalman_correct(x_pred, inflation[..., None, None] * P_pred, e, obs.mask, H, obs.R)
        step = step._replace(
            post_innovation=self.memory_after(step.mean, obs, memory),
            meas_matrix=H if obs.H is None else None,
        )
        return step, inflation


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

    paths = NO_FAST_PATHS  # the kernels' Kalman rule measures z itself

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
        return artificial_measurements(self.artificial, self.model, history, inputs)

    def carried_history(self, history: Any, inputs: Inputs) -> Any:
        """The raw rows the artificial measurement may still look back to (as for the SVSF)."""
        return rows_to_keep(history, inputs)


#: The fast paths of the SVSF's ``H⁺`` mode and of its artificial measurement (one each: an
#: online step reads them).
_H_PLUS_PATHS = FastPaths(axis="svsf", dense="svsf")
_ARTIFICIAL_PATHS = FastPaths(axis="svsf")


class _Gains(NamedTuple):
    """The SVSF corrector's constants of a run."""

    psi: Tensor  #: ψ in the run's dtype (a per-step override replaces it)
    gamma: Tensor  #: γ in the run's dtype
    orthonormal: bool | None  #: whether the run's H has orthonormal rows (None: H varies)

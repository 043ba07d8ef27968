r"""The separate-modeling (SM) tracker of Zhang & Zhou (2022): the :class:`~torchsvs.IMM` of the
NCV and NCA augmented mileage models (:class:`~torchsvs.models.SeparateModel`, Eqs. (13)-(16))
with the least-squares reset of the trajectory parameters in its interaction hooks.

Its cycle, per the paper's Sec. 4 and Fig. 1: initialise the augmented state from the first
three measurements by the unscented transform
(:func:`~torchsvs.filters.separate.initialisation.unscented_initialisation`, Eqs. (17)-(21));
then at every step ``k ≥ 4`` reset the trajectory parameters by least squares over the window
(:func:`~torchsvs.filters.separate.reset.reset_trajectory_parameters`, Eqs. (36)-(40); not at
the first cycle), mix (IMM interaction), filter each mode with an EKF, update the mode
probabilities and combine. The choices the paper leaves open, and why they are made as they
are: ``docs/guide/separate_modeling.md``.

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Secs. 3-4.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike
from torchsvs.estimator import check_keep, drop_batch, prepare_inputs, threads_for
from torchsvs.filters.imm import IMM, IMMResult, IMMState
from torchsvs.filters.nonlinear import ExtendedKalmanFilter, UnscentedKalmanFilter
from torchsvs.filters.separate.initialisation import INITIAL_SAMPLES, unscented_initialisation
from torchsvs.filters.separate.reset import (
    covariance_of_fit,
    fit_window_line,
    parameters_of_fit,
)
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.linalg import sum_in_order
from torchsvs.models.mileage import (
    MileageConstantAcceleration,
    MileageConstantVelocity,
    SeparateModel,
)
from torchsvs.types import FilterState

#: The mode transition matrix of the SM tracker and its Cartesian IMM baselines (the paper's
#: matrices were lost in extraction): a standard choice, 5% switching per step.
DEFAULT_TRANSITION = ((0.95, 0.05), (0.05, 0.95))


#: Where the NCV mode's ``[s, ṡ, η]`` and the NCA mode's ``[s, ṡ, s̈, η]`` sit in the
#: tracker's common state ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]`` (the
#: :class:`~torchsvs.IMM`'s ``embedding`` with the default ``mixing="unbiased"`` of
#: :class:`SeparateModelingTracker`: the NCV mode has no acceleration to mix).
MODE_EMBEDDING = ((0, 1, 3, 4, 5, 6, 7), (0, 1, 2, 3, 4, 5, 6, 7))
#: How the SM tracker mixes the acceleration the NCV mode lacks (:class:`SeparateModelingTracker`).
MIXINGS = ("unbiased", "zero")


#: What the SM tracker does to ``η``'s covariance at a reset (:class:`SeparateModelingTracker`).
RESET_COVARIANCES = ("residual", "measurement", "keep")
#: What the SM tracker does with the norm of the LS direction (:class:`SeparateModelingTracker`).
RESET_DIRECTIONS = ("rescale", "normalize", "raw")


class ResetWindow(NamedTuple):
    """What the least-squares reset keeps of earlier steps (``IMMState.aux`` of
    :class:`SeparateModelingTracker`): the latest ``k_m − 1`` measurements and their estimated
    arc lengths, oldest first.

    Attributes:
        z: ``[B, W, 2]`` measurements, NaN where missing or before the track started.
        arc_length: ``[B, W]`` their estimated arc lengths ``ŝ_{j|j}``; NaN for the newest until
            the next cycle fills it in (the estimate after the newest step is in the state).
    """

    z: Tensor
    arc_length: Tensor


class SeparateModelingResult(NamedTuple):
    """What a :class:`SeparateModelingTracker` pass produced (``B`` tracks, ``T`` steps).

    Steps ``0..2`` (the paper's ``k = 1..3``) are the unscented initialisation when the
    tracker initialised itself (``x0=None``): see :class:`SeparateModelingTracker`.

    Attributes:
        cartesian: ``[B, T, 4]`` Cartesian estimate ``[x, vx, y, vy]`` (the layout of
            :class:`~torchsvs.models.ConstantVelocity`): per mode the position
            :math:`h(\\hat x^j)` and the velocity :math:`\\hat{\\dot s}^j\\,(\\hat r_x^j,
            \\hat r_y^j)`, combined with the mode probabilities.
        mean: ``[B, T, 8]`` combined augmented state ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]``.
        cov: ``[B, T, 8, 8]`` its covariance (``None`` with ``keep="mean"``).
        mode_probs: ``[B, T, 2]`` probabilities of the NCV and NCA modes.
        imm: the :class:`~torchsvs.filters.imm.IMMResult` of the filtered steps (``z[:, 3:]``
            after a self-initialisation, else every step), per-mode results included, each in
            its mode's own state (the NCV mode's ``[s, ṡ, η]``, the NCA mode's
            ``[s, ṡ, s̈, η]``; :attr:`SeparateModelingTracker.mode_models`).
        log_likelihood: ``[B]``, the IMM's, over the filtered steps.
    """

    cartesian: Tensor
    mean: Tensor
    cov: Tensor | None
    mode_probs: Tensor
    imm: IMMResult
    log_likelihood: Tensor | None = None

    @property
    def mileage(self) -> Tensor:
        """``[B, T, 3]`` the mileage state ``[s, ṡ, s̈]`` (in units of the line's parameter:
        arc length times ``‖r‖`` when the reset keeps the raw LS direction)."""
        return self.mean[..., :3]

    @property
    def eta(self) -> Tensor:
        """``[B, T, 5]`` the trajectory parameters ``η = [x_l, r_x, y_l, r_y, s_l]``."""
        return self.mean[..., 3:]


class SeparateModelingTracker(IMM):
    r"""The separate-modeling (SM) tracker of Zhang & Zhou (2022): an NCV-NCA IMM in mileage
    coordinates on the augmented models :class:`~torchsvs.models.SeparateModel`, whose
    trajectory parameters ``η`` are reset by least squares before every interaction stage
    except the first.

    Modes: NCV (:class:`~torchsvs.models.MileageConstantVelocity`, state ``[s, ṡ, η]``) and
    NCA (:class:`~torchsvs.models.MileageConstantAcceleration`, ``[s, ṡ, s̈, η]``), both
    augmented by :math:`\eta = [x_l, r_x, y_l, r_y, s_l]`, each filtered by an
    :class:`~torchsvs.ExtendedKalmanFilter` (the paper's choice) or, with ``unscented=True``,
    an :class:`~torchsvs.UnscentedKalmanFilter`. The estimate lives in the common state
    ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]`` (:data:`MODE_EMBEDDING`), where the NCV mode's
    acceleration counts as 0 with variance 0 in the combination (the paper's Sec. 4).

    One cycle at sample ``k`` (the paper's Fig. 1):

    1. **Initialisation** (once, :meth:`initialise`): the unscented transform of the first three
       measurements (:func:`~torchsvs.filters.separate.initialisation.unscented_initialisation`,
       Eqs. (17)-(21)) gives each mode's ``x̂^a_{3|3}``, ``P^a_{3|3}`` (plus ``floor`` on the
       diagonal); the filter starts at ``k = 4``.
    2. **Reset** (:meth:`adjust_modes`, at every cycle except the first): the window's
       measurements except the newest, at the arc lengths estimated at their own steps, give
       :math:`\eta^*` by the QR least squares of
       :func:`~torchsvs.filters.separate.reset.reset_trajectory_parameters` (Eqs. (36)-(40));
       every mode's ``η`` is set to it. A window with fewer than two usable samples keeps the
       filter's ``η``.
    3. **Interaction, mode-matched filtering, mode probabilities, combination**: the
       :class:`~torchsvs.IMM`'s.

    Where the paper is silent or its equations were lost, the tracker's choices and the reasons
    for them (how the acceleration the NCV mode lacks is mixed, the reset's direction and
    covariance, the orientation of the mileage, the first three steps, the transition matrix)
    are in the guide, ``docs/guide/separate_modeling.md``.

    Called as every torchsvs estimator, ``tracker(z)`` (``z [B, T, 2]`` or ``[T, 2]``, NaN:
    missing; the first three samples of every track must be present) initialises itself from
    ``z[:, :3]`` and returns a :class:`SeparateModelingResult` of all ``T`` steps (steps
    ``0..2``: the initialisation read at the chord arc lengths of ``z_1..z_3``);
    ``tracker(z, x0, P0)`` starts instead from an augmented prior ``x0 [B, 8]``, ``P0`` one step
    before ``z[:, 0]`` (no initialisation steps; the reset window starts empty). The step
    protocol is the IMM's (``init`` or :meth:`initialise`, then ``step``/``scan``, whose
    :class:`~torchsvs.filters.imm.IMMResult` :meth:`cartesian` reads).

    Args:
        dt: sampling interval ``T`` (s); a per-step ``dt`` given to a call overrides it.
        q: standard deviation of the mileage models' process noise (m/s², Eqs. (2)-(5)), one
            for both modes or ``(q_ncv, q_nca)``.
        r: measurement noise: a variance, per-axis variances ``[2]`` or ``[2, 2]`` (m²).
        eta_std: standard deviation of the artificial process noise of ``η`` (Eq. (16)).
        window: the sliding window's length ``k_m`` ≥ 3 (the reset fits ``k_m − 1`` samples).
        transition: the ``[2, 2]`` mode transition matrix (NCV, NCA); default
            :data:`DEFAULT_TRANSITION` (the paper's was lost in extraction).
        initial_probs: the mode probabilities before ``k = 4``, ``[2]`` (the paper's
            ``[0.5, 0.5]``).
        unscented: filter each mode with a UKF instead of an EKF.
        reset: reset ``η`` by least squares (``False``: the augmented IMM alone, an ablation).
        reset_covariance: ``η``'s covariance at a reset: ``"residual"`` (default: the
            least-squares estimate's, its noise from the window's residuals pooled with ``R``),
            ``"measurement"`` (its noise ``R``) or ``"keep"`` (the filter's;
            :data:`RESET_COVARIANCES`, the guide).
        direction: the reset's direction: ``"rescale"`` (default: normalised, its norm moved
            into the mileage state), ``"normalize"`` or ``"raw"`` (the paper's text;
            :data:`RESET_DIRECTIONS`, the guide).
        mixing: how the acceleration the NCV mode lacks is mixed: ``"unbiased"`` (default: the
            NCA mode's own) or ``"zero"`` (:data:`MIXINGS`, the guide). With ``"zero"`` both
            modes' states (and their results) are ``[s, ṡ, s̈, η]``; by default the NCV mode's
            is ``[s, ṡ, η]``.
        floor: variance added to the diagonal of the initialisation's covariance and of ``η``'s
            block at a reset (> 0: both are singular).
        kappa: the initialisation's unscented ``κ``.

    References:
        Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Secs. 3-4 ·
        Blom, Bar-Shalom, IEEE Trans. Autom. Control 33(8), 1988. doi:10.1109/9.1299 ·
        Yuan, Bar-Shalom, Willett, Mozeson, Pollak, Hardiman, "A multiple IMM estimation
        approach with unbiased mixing for thrusting projectiles", IEEE Trans. Aerosp. Electron.
        Syst. 48(4), 2012 · Granström, Willett, Bar-Shalom, "Systematic approach to IMM mixing
        for unequal dimension states", IEEE Trans. Aerosp. Electron. Syst. 51(4), 2015.
    """

    def __init__(
        self,
        dt: float,
        q: float | Sequence[float] = 0.008,
        r: ArrayLike = 1.0,
        eta_std: ArrayLike = 1e-5,
        window: int = 16,
        transition: Any = DEFAULT_TRANSITION,
        initial_probs: Any = (0.5, 0.5),
        *,
        unscented: bool = False,
        reset: bool = True,
        reset_covariance: str = "residual",
        direction: str = "rescale",
        mixing: str = "unbiased",
        floor: float = 1e-6,
        kappa: float = 0.0,
    ) -> None:
        if isinstance(window, bool) or not isinstance(window, int) or window < 3:
            raise ValueError(
                f"window: expected an integer ≥ 3 (the reset fits the latest window − 1 "
                f"samples), got {window!r}"
            )
        if isinstance(q, (int, float)):
            q_ncv = q_nca = float(q)
        elif isinstance(q, Sequence) and len(q) == 2:
            q_ncv, q_nca = (float(v) for v in q)
        else:
            raise ValueError(f"q: expected a number or a pair (q_ncv, q_nca), got {q!r}")
        if reset_covariance not in RESET_COVARIANCES:
            raise ValueError(
                f"reset_covariance: expected one of {', '.join(map(repr, RESET_COVARIANCES))}, "
                f"got {reset_covariance!r}"
            )
        if direction not in RESET_DIRECTIONS:
            raise ValueError(
                f"direction: expected one of {', '.join(map(repr, RESET_DIRECTIONS))}, "
                f"got {direction!r}"
            )
        if mixing not in MIXINGS:
            raise ValueError(
                f"mixing: expected one of {', '.join(map(repr, MIXINGS))}, got {mixing!r}"
            )
        if not (isinstance(floor, (int, float)) and math.isfinite(floor) and floor > 0):
            raise ValueError(f"floor: expected a number > 0, got {floor!r}")
        zero = mixing == "zero"
        ncv = SeparateModel(MileageConstantVelocity(dt, q_ncv), eta_std, r, embed_acceleration=zero)
        nca = SeparateModel(MileageConstantAcceleration(dt, q_nca), eta_std, r)
        mode_filter = UnscentedKalmanFilter if unscented else ExtendedKalmanFilter
        super().__init__(
            [mode_filter(ncv), mode_filter(nca)],
            transition,
            initial_probs=initial_probs,
            embedding=None if zero else MODE_EMBEDDING,
        )
        self.window = window
        self.reset = bool(reset)
        self.reset_covariance = reset_covariance
        self.direction = direction
        self.mixing = mixing
        self.floor = float(floor)
        self.kappa = float(kappa)

    @property
    def mode_models(self) -> list[SeparateModel]:
        """The augmented models of the NCV and NCA modes."""
        return [f.model for f in self.mode_filters]  # type: ignore[misc]

    # --- initialisation ---

    def initialise(
        self, z: Tensor, dt: float | Tensor | None = None, mode_probs: Any = None
    ) -> IMMState:
        """The state after the first three measurements (the step protocol's start for
        ``z[:, 3:]``): each mode's unscented initialisation, the reset window holding
        ``z_1..z_3`` at their chord arc lengths (the guide's *The first three steps*).

        Args:
            z: ``[B, T ≥ 3, 2]`` (the first three are used) or one track ``[T, 2]``.
            dt: a number, per track ``[B]`` or per step ``[B, T]``; default the models'.
            mode_probs: ``[2]`` or ``[B, 2]``; default ``initial_probs``.
        """
        state, _ = self._initialise(z, dt, mode_probs)
        return state

    def _initialise(
        self, z: Tensor, dt: Any, mode_probs: Any
    ) -> tuple[IMMState, tuple[Tensor, Tensor, Tensor, Tensor]]:
        """The state after ``z_1..z_3`` and the estimates of those steps: ``(cartesian
        [B, 3, 4], mean [B, 3, n], cov [B, 3, n, n], mode probabilities [B, 3, M])``."""
        if isinstance(dt, Tensor) and dt.ndim == 0:
            dt = float(dt)
        # In float64 whatever z's dtype: the transform's covariance is singular, and a float32
        # copy of it stays positive definite only with a jitter relative to its scale.
        priors = [
            unscented_initialisation(mdl, z.double(), dt, kappa=self.kappa, floor=self.floor)
            for mdl in self.mode_models
        ]
        single = priors[0].mean.ndim == 1
        zb = z.unsqueeze(0) if single else z
        B, dtype = zb.shape[0], zb.dtype
        means = [p.mean.reshape(B, -1).to(dtype) for p in priors]
        covs = [_jittered(p.cov.reshape(B, *p.cov.shape[-2:]).to(dtype)) for p in priors]
        n = self.model.state_dim
        start = self._start(zb.new_zeros(B, n), torch.eye(n, dtype=dtype), mode_probs, single)
        modes = tuple(FilterState(x, P) for x, P in zip(means, covs, strict=True))
        # The chord arc lengths of z_1, z_2 and the initialisation's ŝ_3 (equal in both modes).
        first = zb[:, :INITIAL_SAMPLES]
        s_3 = means[0][:, 0]
        arc = torch.stack(
            [torch.zeros_like(s_3), (first[:, 1] - first[:, 0]).norm(dim=-1), s_3], dim=1
        )
        aux = self._window_with(first, arc)
        state = start._replace(modes=modes, aux=aux, single=False)
        # The estimates of k = 1..3: the initialisation read at those arc lengths.
        probs = state.log_probs.exp()
        at = [torch.cat([arc.unsqueeze(-1), x[:, None, 1:].expand(-1, 3, -1)], -1) for x in means]
        cartesian = sum_in_order(
            [
                probs[:, None, j, None] * mdl.cartesian(x)
                for j, (mdl, x) in enumerate(zip(self.mode_models, at, strict=True))
            ]
        )
        mean, cov = self.combine(
            at,
            [P.unsqueeze(1).expand(-1, 3, -1, -1) for P in covs],
            state.log_probs.unsqueeze(1).expand(-1, 3, -1),
        )
        return state._replace(single=single), (
            cartesian,
            mean,
            cov,
            probs.unsqueeze(1).expand(-1, 3, -1),
        )

    def _window_with(self, z: Tensor, arc_length: Tensor) -> ResetWindow:
        """A reset window ending with the samples ``z [B, k, 2]`` at ``arc_length [B, k]``."""
        width = self.window - 1
        B, k = arc_length.shape
        keep = min(k, width)
        zw = z.new_full((B, width, 2), float("nan"))
        sw = arc_length.new_full((B, width), float("nan"))
        zw = torch.cat([zw[:, : width - keep], z[:, k - keep :]], dim=1)
        sw = torch.cat([sw[:, : width - keep], arc_length[:, k - keep :]], dim=1)
        return ResetWindow(zw, sw)

    # --- the hooks of the IMM: the reset and its window ---

    def adjust_modes(self, state: IMMState) -> IMMState:
        """The least-squares reset of ``η`` before the interaction stage (class docstring; its
        direction and covariance: the guide), at every cycle except the first. It first records
        the arc length estimated at the last step beside that step's measurement and turns the
        mileage coordinate of a track whose estimated speed is negative (the guide's
        *Orientation*)."""
        aux = state.aux
        if aux is None or state.steps == 0:
            return state
        probs = state.log_probs.exp()
        s_hat = sum_in_order([probs[:, j] * m.mean[:, 0] for j, m in enumerate(state.modes)])
        speed = sum_in_order([probs[:, j] * m.mean[:, 1] for j, m in enumerate(state.modes)])
        arc = torch.cat([aux.arc_length[:, :-1], s_hat.unsqueeze(-1).to(aux.arc_length.dtype)], 1)
        # Orientation: (s, ṡ, s̈, r, s_l) and -(s, ṡ, s̈, r, s_l) give the same h and the same
        # models' likelihoods; keep the mileage increasing along the direction of travel.
        backwards = (speed < 0).unsqueeze(-1)
        arc = torch.where(backwards, -arc, arc)
        modes = [
            mode._replace(
                mean=torch.where(backwards, mode.mean * sign, mode.mean),
                cov=torch.where(
                    backwards.unsqueeze(-1), mode.cov * (sign.unsqueeze(-1) * sign), mode.cov
                ),
            )
            for mode, sign in zip(state.modes, self._turned(state.modes[0].mean), strict=True)
        ]
        state = state._replace(modes=tuple(modes), aux=aux._replace(arc_length=arc))
        if not self.reset:
            return state
        fit = fit_window_line(aux.z, arc)
        solved = fit.solvable.unsqueeze(-1)
        normalize = self.direction != "raw"
        eta = parameters_of_fit(fit, normalize)
        if self.reset_covariance != "keep":
            R = self.mode_models[0].meas_cov()
            residual = self.reset_covariance == "residual"
            eta_cov = covariance_of_fit(fit, aux.z, R, normalize, residual)
        if self.direction == "rescale":
            tiny = torch.finfo(arc.dtype).tiny
            rho = torch.where(fit.solvable, fit.slope.norm(dim=-1).clamp_min(tiny), 1.0)
            anchor = torch.where(fit.solvable, fit.s_l, 0.0).unsqueeze(-1)
            arc = anchor + rho.unsqueeze(-1) * (arc - anchor)
            state = state._replace(aux=aux._replace(arc_length=arc))
        adjusted = []
        for mdl, mode in zip(self.mode_models, state.modes, strict=True):
            b = mdl.base_dim
            x, P = mode.mean, mode.cov
            base, P_base = x[:, :b], P[:, :b, :b]
            if self.direction == "rescale":
                offset = torch.zeros_like(base)
                offset[:, 0] = anchor.squeeze(-1)
                base = offset + rho.unsqueeze(-1) * (base - offset)
                P_base = P_base * (rho * rho)[:, None, None]
            eta_j = torch.where(solved, eta.to(x.dtype), x[:, b:])
            x = torch.cat([base, eta_j], dim=-1)
            if self.reset_covariance == "keep":
                scale = torch.ones_like(x)
                if self.direction == "rescale":
                    scale = torch.cat([rho.unsqueeze(-1).expand(-1, b), scale[:, b:]], -1)
                P = P * scale.unsqueeze(-1) * scale.unsqueeze(-2)
            else:
                B = x.shape[0]
                eye = torch.eye(eta_cov.shape[-1], dtype=P.dtype)
                reset = torch.cat(
                    [
                        torch.cat([P_base.expand(B, b, b), P.new_zeros(B, b, 5)], -1),
                        torch.cat([P.new_zeros(B, 5, b), eta_cov + self.floor * eye], -1),
                    ],
                    dim=-2,
                )
                P = torch.where(solved.unsqueeze(-1), reset, P)
            adjusted.append(mode._replace(mean=x, cov=P))
        return state._replace(modes=tuple(adjusted))

    def _turned(self, like: Tensor) -> list[Tensor]:
        """Per mode, the signs ``[n]`` that turn the mileage coordinate: ``−1`` for ``s, ṡ, s̈,
        r_x, r_y, s_l``, ``+1`` for ``x_l, y_l``."""
        signs = []
        for mdl in self.mode_models:
            sign = torch.full((mdl.state_dim,), -1.0, dtype=like.dtype)
            sign[mdl.eta_index[0]] = sign[mdl.eta_index[2]] = 1.0
            signs.append(sign)
        return signs

    def update_aux(self, state: IMMState, z: Tensor, dt: Tensor | None, u: Tensor | None) -> Any:
        """Appends the step's measurement to the reset window (its arc length follows at the
        next cycle)."""
        aux = state.aux
        if aux is None:
            B = z.shape[0]
            aux = self._window_with(z.new_zeros(B, 0, 2), z.new_zeros(B, 0))
        B = max(aux.z.shape[0], z.shape[0])
        zw = torch.cat([aux.z[:, 1:].expand(B, -1, -1), z.expand(B, -1).unsqueeze(1)], dim=1)
        nan = aux.arc_length.new_full((B, 1), float("nan"))
        sw = torch.cat([aux.arc_length[:, 1:].expand(B, -1), nan], dim=1)
        return ResetWindow(zw, sw)

    # --- reading a result ---

    def cartesian(self, result: IMMResult) -> Tensor:
        """The Cartesian estimate ``[..., 4]`` (``[x, vx, y, vy]``) of an IMM result of this
        tracker: each mode's :meth:`~torchsvs.models.SeparateModel.cartesian`, combined with the
        mode probabilities."""
        probs = result.mode_probs
        parts = [
            mdl.cartesian(r.mean) for mdl, r in zip(self.mode_models, result.modes, strict=True)
        ]
        return sum_in_order([probs[..., j, None] * part for j, part in enumerate(parts)])

    # The IMM's call, with the prior optional and a richer result.
    @outside_dynamo
    def forward(  # type: ignore[override]
        self,
        z: Tensor,
        x0: Tensor | None = None,
        P0: Tensor | None = None,
        *,
        mode_probs: Any = None,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> SeparateModelingResult:
        """Tracks every road target: ``z [B, T, 2]`` (or ``[T, 2]``; NaN: missing), from the
        unscented initialisation of ``z[:, :3]`` (``x0 = P0 = None``, then ``T ≥ 4``) or from an
        augmented prior ``x0``, ``P0`` one step before ``z[:, 0]``; ``mode_probs``, ``dt``,
        ``keep`` as for :class:`~torchsvs.IMM`. Returns a :class:`SeparateModelingResult`."""
        self.check_psi(psi)
        check_keep(keep)
        if (x0 is None) != (P0 is None):
            raise ValueError(
                "x0, P0: give both (an augmented prior) or neither (the unscented "
                f"initialisation from z[:, :3]); got x0 {'None' if x0 is None else 'given'}, "
                f"P0 {'None' if P0 is None else 'given'}"
            )
        initialising = x0 is None
        if initialising:
            if isinstance(z, Tensor) and z.ndim in (2, 3) and z.shape[-2] <= INITIAL_SAMPLES:
                raise ValueError(
                    f"z: expected T ≥ {INITIAL_SAMPLES + 1} steps (three initialise the "
                    f"tracker), got shape {tuple(z.shape)}"
                )
            n = self.model.state_dim
            like = z.dtype if isinstance(z, Tensor) and z.is_floating_point() else torch.float64
            x0, P0 = torch.zeros(n, dtype=like), torch.eye(n, dtype=like)  # (checks only)
        inputs = prepare_inputs(self.model, z, x0, P0, u=u, dt=dt, generator=generator, keep=keep)
        with threads_for(inputs.batch, self.model.state_dim):
            if initialising:
                dt_first = inputs.dt
                state, first = self._initialise(inputs.z, dt_first, mode_probs)
                state = state._replace(single=False)
                rest = inputs.window(INITIAL_SAMPLES, inputs.steps)
            else:
                start = self._start(inputs.x0, inputs.P0, mode_probs, inputs.single)
                state, first, rest = start._replace(single=False), None, inputs
            _, imm = self._scan(state, rest)
        cartesian = self.cartesian(imm)
        mean, cov, probs = imm.mean, imm.cov, imm.mode_probs
        if first is not None:
            cartesian = torch.cat([first[0], cartesian], dim=1)
            mean = torch.cat([first[1], mean], dim=1)
            cov = torch.cat([first[2], cov], dim=1)
            probs = torch.cat([first[3], probs], dim=1)
        imm = self.trim(imm, keep)
        result = SeparateModelingResult(
            cartesian=cartesian,
            mean=mean,
            cov=None if keep == "mean" else cov,
            mode_probs=probs,
            imm=imm,
            log_likelihood=imm.log_likelihood,
        )
        return drop_batch(result) if inputs.single else result


def _jittered(P: Tensor) -> Tensor:
    """``P [B, n, n]`` plus ``64 ε`` of its largest variance on the diagonal (``ε`` of its
    dtype): a float32 copy of a covariance with tiny eigenvalues stays positive definite."""
    scale = P.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(1.0)
    eye = torch.eye(P.shape[-1], dtype=P.dtype)
    return P + (64 * torch.finfo(P.dtype).eps * scale)[:, None, None] * eye

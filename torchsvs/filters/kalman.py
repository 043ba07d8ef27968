"""The predictor-corrector loop shared by the Gaussian filters, and the Kalman filter."""

from __future__ import annotations

import threading
from dataclasses import replace
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor

from torchsvs.estimator import Inputs, SteppedEstimator, prepare_prior
from torchsvs.filters import factored
from torchsvs.filters.adaptive import AdaptiveNoise, check_adaptive_noise
from torchsvs.kernels import AXIS_KERNEL, axes, blocks, build, compiled, fused_axes, fused_dense
from torchsvs.linalg import (
    cholesky,
    gaussian_log_density,
    joseph_update,
    mask_measurement,
    matvec,
    symmetrize,
)
from torchsvs.models.base import LinearModel, StateSpaceModel
from torchsvs.models.motion import ConstantVelocity
from torchsvs.types import FilterResult, FilterState


class Step(NamedTuple):
    """What one corrector step returns, for every track: ``[B, ...]`` tensors."""

    mean: Tensor
    cov: Tensor
    innovation: Tensor
    gain: Tensor
    post_innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    log_likelihood: Tensor | None = None
    meas_matrix: Tensor | None = None  #: the (linearised) H used, when it varies per step
    #: the posterior in the filter's factored ``covariance_form`` (:mod:`.factored`), else None
    factor: Any = None


class Observation(NamedTuple):
    """What the corrector sees at step ``t``, for every track."""

    t: int
    z: Tensor  #: [B, m], 0 where missing
    mask: Tensor | None  #: [B, m], True where observed; None when nothing in the batch is missing
    H: Tensor | None  #: [m, n] or [B, m, n]: the run's H; None: the model's linearised per step
    R: Tensor  #: [m, m] or [B, m, m]
    model: StateSpaceModel
    settings: Any = None  #: the corrector's constants of the run (``run_settings``)
    #: the prediction in the filter's factored ``covariance_form`` (:mod:`.factored`), else None
    factor: Any = None

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``h(x)`` and ``H`` at ``x [B, n]``: the run's ``H`` or the model's linearisation."""
        if self.H is None:
            return self.model.linearize_h(x)
        return matvec(self.H, x), self.H

    def fitted(self, x: Tensor) -> Tensor:
        """``h(x)`` of the corrector's measurement."""
        return self.model.h(x) if self.H is None else matvec(self.H, x)


class DenseConstants(NamedTuple):
    """What a run of compiled online steps computes once (``FilterState.constants``)."""

    matrices: fused_dense.DenseMatrices  #: F, Q, H, R, contiguous, in the run's dtype
    gamma: float  #: the SVSF's γ (0 for the KF)
    widths: Tensor  #: the SVSF's ψ, [m] (zeros for the KF)
    tensors: list[Tensor]  #: the filter's and model's parameters and buffers they came from
    settings: list[str]  #: the model's plain settings (its ``dt``) they came from
    fingerprint: tuple[Any, ...]  #: :func:`_fingerprint` when they were built
    #: the compiled online steps formed so far, by (keep, leading shape, thread: each has its
    #: own scratch)
    steps: dict[tuple[Any, ...], fused_dense.OnlineStep]


def _plain_settings(model: StateSpaceModel) -> list[str]:
    return [k for k, v in vars(model).items() if isinstance(v, (bool, int, float, str))]


def _fingerprint(tensors: list[Tensor], model: StateSpaceModel, settings: list[str]) -> tuple:
    """Changes when a parameter or buffer is updated in place or given new data, a plain
    setting of the model (its ``dt``) changes, or the filter is given another model: the
    constants are then rebuilt."""
    values = model.__dict__
    return (
        id(model),
        *[(t._version, t.data_ptr()) for t in tensors],
        *[values[k] for k in settings],
    )


class Prepared(NamedTuple):
    """A run's steps as the filter sees them (:meth:`GaussianFilter.prepare`): measurements,
    their mask and the model matrices of every step, formed once; a model whose ``f`` or ``h``
    depends on the state has no run matrix and is linearised per step (``model.linearize``)."""

    z: Tensor  #: [B, T, m], 0 where missing
    observed: Tensor  #: [B, T, m], True where observed
    any_missing: bool
    H: Tensor | None  #: [m, n] or [B, T, m, n]; None: linearised per step
    R: Tensor  #: [m, m] or [B, T, m, m]
    F: Tensor | None  #: [n, n] or [B, T, n, n]; None: linearised per step
    Q: Tensor  #: [n, n] or [B, T, n, n]
    model: StateSpaceModel
    settings: Any = None  #: the corrector's constants of the run (``run_settings``)

    def observation(self, t: int) -> Observation:
        """What the corrector sees at step ``t``."""
        return Observation(
            t,
            self.z[:, t],
            self.observed[:, t] if self.any_missing else None,
            None if self.H is None else _at(self.H, t),
            _at(self.R, t),
            self.model,
            self.settings,
        )

    def window(self, start: int, stop: int) -> Prepared:
        """Steps ``start`` to ``stop - 1`` as a run of their own (views, no copies): step ``t`` of
        the window is step ``start + t`` of the run (a compiled step sees the same shapes at
        every ``start``)."""
        return self._replace(
            z=self.z[:, start:stop],
            observed=self.observed[:, start:stop],
            H=None if self.H is None else _span(self.H, start, stop),
            R=_span(self.R, start, stop),
            F=None if self.F is None else _span(self.F, start, stop),
            Q=_span(self.Q, start, stop),
        )

    def transition(self, t: int, x: Tensor, inputs: Inputs) -> tuple[Tensor, Tensor]:
        """``f(x)`` and ``F_t`` at step ``t`` from ``x [B, n]``: the run's ``F`` or the
        model's linearisation at ``x``."""
        if self.F is None:
            return self.model.linearize(x, step_interval(inputs, t), step_input(inputs, t))
        F_t = _at(self.F, t)
        return matvec(F_t, x), F_t


def _at(A: Tensor, t: int) -> Tensor:
    """Step ``t`` of a model matrix stored as ``[r, c]`` (constant) or ``[B, T, r, c]``."""
    return A[:, t] if A.ndim == 4 else A


def _span(A: Tensor, start: int, stop: int) -> Tensor:
    """Steps ``start`` to ``stop - 1`` of a model matrix stored as in :func:`_at`."""
    return A[:, start:stop] if A.ndim == 4 else A


def _stack_over_time(values: list[Tensor] | list[Tensor | None], batch: int) -> Tensor | None:
    """Stacks per-step ``[B|1, ...]`` tensors into ``[B, T, ...]``.

    Steps computed once for all tracks (a covariance while nothing track-specific has entered,
    e.g. a KF with a shared ``P0`` and no missing data) keep their batch axis of 1 and the result
    is a broadcast view over the ``B`` tracks, not ``B`` copies.
    """
    if values[0] is None:
        return None
    tensors = [v for v in values if v is not None]
    width = max(v.shape[0] for v in tensors)
    stacked = torch.stack([v.expand(width, *v.shape[1:]) for v in tensors], dim=1)
    return stacked.expand(batch, *stacked.shape[1:])


def step_interval(inputs: Inputs, t: int) -> Tensor | None:
    """The interval ending at step ``t``: ``None`` (model's own), 0-d, or per track ``[B]``."""
    dt = inputs.dt
    return dt[:, t] if dt is not None and dt.ndim == 2 else dt


def step_input(inputs: Inputs, t: int) -> Tensor | None:
    """The control input acting over step ``t``, ``[B, p]``, or ``None``."""
    return None if inputs.u is None else inputs.u[:, t]


def _as_result_matrix(A: Tensor) -> Tensor:
    """``[r, c]`` → ``[1, 1, r, c]``; ``[B, T, r, c]`` unchanged."""
    return A if A.ndim == 4 else A[None, None]


def kalman_update(
    x_pred: Tensor, P_pred: Tensor, e: Tensor, H: Tensor, R: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The Kalman correction, Eqs. (14)-(16): ``(x, P, K, S, chol(S))`` from innovation ``e``.

    ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹`` through the Cholesky factor of ``S``, Joseph-form ``P``.
    """
    PHt = P_pred @ H.mT
    S = innovation_covariance(H, PHt, R)
    L = cholesky(S)
    K = torch.cholesky_solve(PHt.mT, L).mT
    return x_pred + matvec(K, e), joseph_update(P_pred, K, H, R), K, S, L


def kalman_correct(
    x_pred: Tensor,
    P_pred: Tensor,
    e: Tensor,
    mask: Tensor | None,
    H: Tensor,
    R: Tensor,
    factor: Any = None,
) -> Step:
    """The Kalman correction with innovation ``e``; missing components are dropped.
    ``factor``: ``P_pred`` in a factored covariance form, whose update then gives the gain
    and the posterior (:mod:`.factored`)."""
    if mask is not None:
        H, R = mask_measurement(H, R, mask)
        e = e * mask
    if factor is None:
        x, P, K, S, L = kalman_update(x_pred, P_pred, e, H, R)
    else:
        S = innovation_covariance(H, P_pred @ H.mT, R)
        L = cholesky(S)
        K, factor = factor.kalman_update(H, R, S)
        x, P = x_pred + matvec(K, e), factor.full()
    observed = e.shape[-1] if mask is None else mask.sum(-1).to(e.dtype)
    loglik = gaussian_log_density(e, L, observed)
    return Step(x, P, e, K, innovation_cov=S, log_likelihood=loglik, factor=factor)


def innovation_covariance(H: Tensor, PHt: Tensor, R: Tensor) -> Tensor:
    """``S = H P Hᵀ + R`` (with ``PHt = P Hᵀ``), symmetrised: the covariance of the a-priori
    innovation that every Gaussian filter records (the NLL loss and the smoothers read it)."""
    return symmetrize(H @ PHt + R)


class GaussianFilter(SteppedEstimator[FilterResult]):
    """A filter that carries a Gaussian (mean, covariance) through predict-correct steps.

    The prediction (Eqs. (11)-(12) and (18)-(20), Chen et al. 2020) is shared; subclasses replace
    only the corrector (:meth:`correct`) and, if they measure something else than the model's
    ``z`` (artificial measurements), :meth:`measurements`; nonlinear filters replace
    :meth:`dynamics` and :meth:`predict`.
    """

    #: the kind of model the filter needs (nonlinear filters take any StateSpaceModel)
    model_type: type[StateSpaceModel] = LinearModel
    #: the adaptive ``R_k`` (:mod:`torchsvs.filters.adaptive`) of filters that take one, or None
    adaptive_noise: AdaptiveNoise | None = None
    #: how the covariance is carried and updated (:mod:`torchsvs.filters.factored`)
    covariance_form: str = "joseph"

    @property
    def kernels_apply(self) -> bool:
        """Whether the compiled and per-axis kernels can run this filter: they carry ``P`` in
        the Joseph form and take the model's constant ``R`` (no factored form, no adaptive R)."""
        return self.covariance_form == "joseph" and self.adaptive_noise is None

    def __init__(self, model: StateSpaceModel) -> None:
        super().__init__()
        if not isinstance(model, self.model_type):
            raise TypeError(
                f"model: expected a torchsvs {self.model_type.__name__}, got {type(model).__name__}"
            )
        self.model = model

    def dynamics(self, inputs: Inputs) -> tuple[Tensor | None, Tensor]:
        """``F`` and ``Q`` of the whole run, ``[n, n]`` or ``[B, T, n, n]``; ``F`` is ``None`` for a
        nonlinear model, which :meth:`predict` linearises at each estimate."""
        dtype, model = inputs.z.dtype, self.model
        Q = model.process_noise(inputs.dt).to(dtype)
        if isinstance(model, LinearModel):
            return model.transition(inputs.dt).to(dtype), Q
        return None, Q

    def predict(
        self, t: int, x: Tensor, P: Tensor, prep: Prepared, inputs: Inputs
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``x̂_{t|t-1}``, ``P_{t|t-1}`` and the (linearised) ``F_t`` used: Eqs. (11)-(12) of Chen
        et al. 2020, or for a nonlinear model ``f(x̂)`` with ``F_t = ∂f/∂x`` (Eqs. (3), (11)-(12),
        Gadsden et al. 2012)."""
        x_pred, F_t = prep.transition(t, x, inputs)
        return x_pred, symmetrize(F_t @ P @ F_t.mT + _at(prep.Q, t)), F_t

    def measurements(
        self, inputs: Inputs, history: Any = None
    ) -> tuple[Tensor, Tensor | None, Tensor]:
        """The corrector's measurements ``[B, T, m]``, ``H`` and ``R`` (``history``: see
        :meth:`carried_history`).

        ``H`` and ``R`` are ``[m, ·]`` when constant or ``[B, T, m, ·]`` per step; ``H`` is
        ``None`` for filters that linearise ``h`` per step (each step then reports its own).
        With :attr:`adaptive_noise`, ``R`` is its ``R_k`` of every step (``history``: the raw
        rows before these).
        """
        dtype, model = inputs.z.dtype, self.model
        H = model.meas_matrix().to(dtype) if isinstance(model, LinearModel) else None
        R = model.meas_cov().to(dtype)
        if self.adaptive_noise is not None:  # the one place R enters: Eqs. (29)-(30)
            R = self.adaptive_noise.covariance(R, inputs.z, history)
        return inputs.z, H, R

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        """Corrects the prediction ``x_pred [B, n]``, ``P_pred`` with the observation of step
        ``obs.t``; ``carried`` is the a-posteriori innovation of the step before, for correctors
        that carry one (the SVSF's memory; ``None`` before the first step)."""
        raise NotImplementedError

    #: the corrector's rule in the per-axis kernel (:mod:`torchsvs.kernels.axes`), or None
    axis_rule: str | None = None

    def axis_settings(self, inputs: Inputs) -> tuple[Tensor, Tensor] | None:
        """``(ψ [2, m] or [B, T, 2, m], γ)`` for the per-axis kernel's ``"svsf"`` rule."""
        return None

    # --- The step protocol: init, step, scan; forward is init and one scan. ---

    def init(self, x0: Any, P0: Any) -> FilterState:
        """The state before the first step: the prior ``x0 [B, n]``, ``P0 [B, n, n]`` or
        ``[n, n]`` (or one track: ``[n]``, ``[n, n]``), checked as :meth:`forward` checks it."""
        x0, P0, single = prepare_prior(self.model, x0, P0)
        return FilterState(x0, P0, single=single)

    state_type = FilterState

    def state_prior(self, state: FilterState) -> tuple[Tensor, Tensor]:
        return state.mean, state.cov

    def share(self, state: FilterState, inputs: Inputs) -> FilterState:
        return FilterState(inputs.x0, inputs.P0)  # as forward shares a prior of one track

    def run(self, inputs: Inputs) -> FilterResult:
        return self._scan(FilterState(inputs.x0, inputs.P0), inputs)[1]

    def _scan(self, state: FilterState, inputs: Inputs) -> tuple[FilterState, FilterResult]:
        # The per-axis kernel starts from a prior: any state without a corrector's memory or
        # earlier rows is one (a KF's chunks all run there; an SVSF's first chunk).
        fresh = state.steps == 0 or (state.post_innovation is None and state.history is None)
        by_axis = self._run_axes(inputs) if fresh else None
        factor = None
        if by_axis is not None:
            result, last, _ = by_axis
        else:
            dense = self._dense_scan(state, inputs)
            if dense is not None:
                result = dense
            else:
                form, dtype = self.covariance_form, inputs.z.dtype
                prior = factored.resume(state.factor, state.cov, dtype, form)
                result, factor = self._loop(
                    inputs, state.post_innovation, state.history, state.steps == 0, prior
                )
            post = result.post_innovation
            last = fused_axes.Last(
                result.mean[:, -1], result.cov[:, -1], None if post is None else post[:, -1]
            )
        loglik = result.log_likelihood
        if loglik is not None and state.log_likelihood is not None:
            loglik = state.log_likelihood + loglik
        after = FilterState(
            mean=last.mean,
            cov=last.cov,
            post_innovation=last.post_innovation,
            log_likelihood=loglik,
            history=self.carried_history(state.history, inputs),
            steps=state.steps + inputs.steps,
            single=state.single,
            factor=None if factor is None else factored.Carried(factor, last.cov),
        )
        return after, result

    #: the corrector's rule in the compiled dense steps
    #: (:func:`torchsvs.kernels.fused_dense.dense_run`) for linear models, or None
    dense_rule: str | None = None

    def _dense_settings(self, dtype: torch.dtype, H: Tensor) -> tuple[float, Tensor] | None:
        """``(γ, ψ [m])`` of a compiled step's corrector, or ``None`` where it cannot run."""
        return 0.0, H.new_zeros(H.shape[0])

    def _dense_constants(self, dtype: torch.dtype) -> DenseConstants | None:
        model = self.model
        assert isinstance(model, LinearModel)
        matrices = [
            A.to(dtype).contiguous()
            for A in (model.transition(), model.process_noise(), model.meas_matrix())
        ]
        matrices.append(model.meas_cov().to(dtype).contiguous())
        if not build.usable(*matrices):
            return None
        settings = self._dense_settings(dtype, matrices[2])
        if settings is None:
            return None
        gamma, widths = settings
        tensors = [*self.parameters(), *self.buffers()]
        plain = _plain_settings(model)
        return DenseConstants(
            fused_dense.DenseMatrices(matrices),
            gamma,
            widths.contiguous(),
            tensors,
            plain,
            _fingerprint(tensors, model, plain),
            {},
        )

    def _dense_ready(self, history: Any) -> bool:
        """Whether the compiled dense steps can stand for this filter's (a linear model of at
        most ``fused_dense.DENSE_MAX`` states and measurements, a corrector with a compiled rule, no
        artificial measurement's rows to carry)."""
        model = self.model
        return (
            self.dense_rule is not None
            and self.kernels_apply
            and isinstance(model, LinearModel)
            and history is None
            and model.state_dim <= fused_dense.DENSE_MAX
            and model.meas_dim <= fused_dense.DENSE_MAX
        )

    def _valid_constants(self, constants: Any, dtype: torch.dtype) -> DenseConstants | None:
        """``constants`` while they still describe the filter and its model, else new ones."""
        model = cast(StateSpaceModel, self._modules["model"])  # (Module.__getattr__: slow)
        if (
            isinstance(constants, DenseConstants)
            and constants.widths.dtype == dtype
            and constants.fingerprint == _fingerprint(constants.tensors, model, constants.settings)
        ):
            # Made without gradients; a parameter they came from may want one now.
            if torch.is_grad_enabled() and any(t.requires_grad for t in constants.tensors):
                return None
            return constants
        return self._dense_constants(dtype)

    def _dense_call(
        self,
        constants: DenseConstants,
        x: Tensor,
        P: Tensor,
        z: Tensor,
        memory: Tensor | None,
        psi: Tensor | None,
        lead: tuple[int, ...],
        keep: str,
    ) -> FilterResult | None:
        """:func:`~torchsvs.kernels.fused_dense.dense_run` from ``x [B, n]``, ``P [B|1, n, n]`` over
        ``z`` (``[B, T, m]``, or one step ``[B, m]``/``[m]``), as a result with the leading
        shape ``lead`` (its log-likelihood per step) keeping what ``keep`` keeps (and the SVSF
        memory); ``None`` where it could not run (an infinity in ``z``, ``S`` not positive
        definite)."""
        rule = self.dense_rule
        assert rule is not None
        B, n = x.shape
        m = z.shape[-1]
        widths = constants.widths if psi is None else psi.to(x.dtype).contiguous()
        if rule == "svsf" and memory is None:
            memory = x.new_zeros(B, m)
        out = fused_dense.dense_run(
            rule,
            constants.gamma,
            x.contiguous(),
            (P if P.shape[0] == B else P.expand(B, n, n)).contiguous(),
            z.contiguous(),
            x if memory is None else memory.expand(B, m).contiguous(),
            widths,
            constants.matrices,
            lead,
            keep,
        )
        if out is None:
            return None
        # The fields not kept are None (FilterResult's doc says so).
        mean, cov, x_pred, P_pred, e, K, S, loglik, e_post, seen = cast(Any, out)
        kalman = rule == "kalman"
        F: Any = None
        H: Any = None
        R: Any = None
        if keep == "all":
            F, _, H, R = constants.matrices.tensors
            if lead:  # the run's matrices, broadcast over the leading axes
                F, H, R = (A.view((1,) * len(lead) + A.shape) for A in (F, H, R))
        return FilterResult(
            mean=mean,
            cov=cov,
            pred_mean=x_pred,
            pred_cov=P_pred,
            innovation=e,
            mask=seen,
            transition=F,
            meas_matrix=H,
            meas_cov=R,
            gain=K,
            post_innovation=None if kalman else e_post,
            innovation_cov=S,
            log_likelihood=loglik if kalman else None,
        )

    def _dense_scan(self, state: FilterState, inputs: Inputs) -> FilterResult | None:
        """The steps of ``inputs`` compiled for a linear model with its own interval, without
        gradients; else ``None``."""
        if not self._dense_ready(state.history) or inputs.dt is not None or inputs.u is not None:
            return None
        if inputs.psi is not None and self.dense_rule != "svsf":
            return None
        given = (inputs.z, inputs.x0, inputs.P0, *(() if inputs.psi is None else (inputs.psi,)))
        if not build.usable(*given):  # (ψ given with a gradient: the differentiable path)
            return None
        B, T = inputs.batch, inputs.steps
        if self.dense_rule == "kalman" and B > 1 and inputs.P0.shape[0] == 1:
            # A shared prior without missing data: the general path runs one covariance
            # recursion for the whole batch (a broadcast view), less work and memory.
            if not bool(torch.isnan(inputs.z).any()):
                return None
        constants = self._valid_constants(state.constants, inputs.z.dtype)
        if constants is None:
            return None
        x0 = inputs.x0.expand(B, self.model.state_dim)
        result = self._dense_call(
            constants,
            x0,
            inputs.P0,
            inputs.z,
            state.post_innovation,
            inputs.psi,
            (B, T),
            inputs.keep,
        )
        if result is None or result.log_likelihood is None:
            return result
        return result._replace(log_likelihood=result.log_likelihood.sum(1))

    def step_shortcut(
        self, state: Any, z: Tensor, psi: Tensor | None, keep: str
    ) -> tuple[FilterState, FilterResult] | None:
        # An online step on a linear model without gradients runs compiled (the same numbers
        # up to rounding); anything else takes the one-step scan. Per call: checks, the step's
        # tensors and one library call (fused_dense.OnlineStep); filterpy's predict + update costs
        # about 20 µs, so every µs here shows.
        if not isinstance(state, FilterState) or not self.kernels_apply:
            return None
        x, single, known = state.mean, state.single, state.constants
        if torch.is_grad_enabled() and psi is not None and psi.requires_grad:
            return None
        if known is None:
            if not self._dense_ready(state.history) or not build.usable(z, x):
                return None  # (usable: CPU float32/64, no gradient, compiler available)
            m = self.model.meas_dim
        else:
            # A state an earlier compiled step made: its x is a CPU float tensor and the
            # library loaded; what may have changed is z, the mode, and whether a gradient is
            # asked for (of z or of a state a caller edited, here; of a parameter, in
            # _valid_constants).
            if not (AXIS_KERNEL["fused"] and z.is_cpu):
                return None
            if torch.is_grad_enabled() and (
                z.requires_grad or x.requires_grad or state.cov.requires_grad
            ):
                return None
            m = known.matrices.meas_dim
        if z.ndim != (1 if single else 2) or z.shape[-1] != m or z.dtype != x.dtype:
            return None
        B = 1 if single else z.shape[0]
        if x.shape[0] != B or B == 0:
            return None
        rule = self.dense_rule
        if psi is not None and (rule != "svsf" or psi.shape != z.shape):
            return None  # (the scan names what is wrong)
        constants = self._valid_constants(known, x.dtype)
        if constants is None:
            return None
        lead = () if single else (B,)
        key = (keep, lead, threading.get_ident())
        step = constants.steps.get(key)
        if step is None:
            assert rule is not None
            step = fused_dense.OnlineStep(
                rule, constants.gamma, constants.matrices, x.shape[1], lead, x.dtype, keep
            )
            constants.steps[key] = step
        P, memory = state.cov, state.post_innovation
        if P.shape[0] != B:  # a prior shared by the batch, before the first step
            P = P.expand(B, *P.shape[1:])
        if memory is None:  # the SVSF's memory before the first step (the KF reads none)
            memory = x if rule == "kalman" else x.new_zeros(B, m)
        elif memory.shape[0] != B:  # one memory shared by the batch
            memory = memory.expand(B, m).contiguous()
        widths = constants.widths if psi is None else psi.to(x.dtype).contiguous()
        total = state.log_likelihood  # (the library reads it as x's dtype, contiguous)
        total = None if total is None else total.to(x.dtype).contiguous()
        done = step(x.contiguous(), P.contiguous(), z.contiguous(), memory, widths, total)
        if done is None:
            return None  # inf in z, or S not positive definite: the scan says or copes
        out, after = done
        mean, cov, *rest = out
        if rule == "kalman":
            e_post = None
            if keep == "all":
                x_pred, P_pred, e, K, S, loglik, seen = rest
            else:
                (loglik,) = rest
        else:
            if keep == "all":
                x_pred, P_pred, e, K, S, _, e_post, seen = rest
            else:
                (e_post,) = rest
        # The state keeps the batch axis; the step's result of one track drops it.
        state_mean, state_cov, memory = (
            (mean, cov, e_post)
            if not single
            else (
                mean[None],
                cov[None],
                None if e_post is None else e_post[None],
            )
        )
        after_state = FilterState(
            state_mean, state_cov, memory, after, None, state.steps + 1, single, constants
        )
        kalman = rule == "kalman"
        if keep != "all":
            nothing: Any = None  # the fields a kept result leaves out (FilterResult's doc)
            result = FilterResult(
                mean,
                cov if keep == "moments" else nothing,
                *(nothing,) * 8,
                log_likelihood=loglik if kalman else None,
            )
            return after_state, result
        F, _, H, R = constants.matrices.tensors
        if lead:  # the run's matrices, broadcast over the batch
            F, H, R = (A.view((1,) * len(lead) + A.shape) for A in (F, H, R))
        result = FilterResult(  # (positional: FilterResult's field order)
            mean, cov, x_pred, P_pred, e, seen, F, H, R, K, e_post, S, loglik if kalman else None
        )
        return after_state, result

    def carried_history(self, history: Any, inputs: Inputs) -> Any:
        """What the next :meth:`scan` needs of these steps to form its measurements (``None``:
        nothing; the adaptive ``R``'s segments and the SVSF's artificial measurements keep raw
        rows)."""
        if self.adaptive_noise is None:
            return None
        return self.adaptive_noise.carried(history, inputs.z)

    def prepare(self, inputs: Inputs, history: Any = None) -> Prepared:
        """The measurements (:meth:`measurements`), their mask and the model matrices
        (:meth:`dynamics`) of the steps of ``inputs``, formed once for :meth:`filter_step`."""
        z, H, R = self.measurements(inputs, history)
        F, Q = self.dynamics(inputs)
        observed = ~torch.isnan(z)
        settings = self.run_settings(z.dtype, H)
        return Prepared(
            z.nan_to_num(0.0), observed, not bool(observed.all()), H, R, F, Q, self.model, settings
        )

    def run_settings(self, dtype: torch.dtype, H: Tensor | None) -> Any:
        """What the corrector computes once per run rather than at every step (its parameters
        in the run's dtype, facts about ``H``), handed to :meth:`correct` as ``obs.settings``."""
        return None

    def filter_step(
        self,
        t: int,
        x: Tensor,
        P: Tensor,
        carried: Tensor | None,
        prep: Prepared,
        inputs: Inputs,
    ) -> tuple[Tensor, Tensor, Tensor, Step]:
        """One predict-correct cycle from ``x``, ``P`` at step ``t`` of a prepared run: the
        prediction ``x̂_{t|t-1}``, ``P_{t|t-1}``, the ``F_t`` used and the corrector's step.

        In a factored ``covariance_form`` ``P`` may be the factor the step before returned
        (``Step.factor``); the prediction is made on it and handed to the corrector in
        ``Observation.factor``, and the step's own factor rides in its :class:`Step`."""
        if self.covariance_form != "joseph":
            kind = factored.FACTORS[self.covariance_form]
            prior = P if isinstance(P, kind) else kind.of(P)
            x_pred, F_t = prep.transition(t, x, inputs)
            predicted = prior.predict(F_t, _at(prep.Q, t))
            obs = prep.observation(t)._replace(factor=predicted)
            P_pred = predicted.full()
            return x_pred, P_pred, F_t, self.correct(x_pred, P_pred, obs, carried, inputs)
        x_pred, P_pred, F_t = self.predict(t, x, P, prep, inputs)
        step = self.correct(x_pred, P_pred, prep.observation(t), carried, inputs)
        return x_pred, P_pred, F_t, step

    def _loop(
        self,
        inputs: Inputs,
        carried: Tensor | None,
        history: Any,
        fresh: bool = True,
        factor: Any = None,
    ) -> tuple[FilterResult, Any]:
        """The predict-correct loop over the steps of ``inputs`` from its prior, the corrector
        carrying ``carried`` (see :meth:`correct`) in, measurements formed with ``history``;
        ``fresh``: the prior is ``init``'s (no step taken yet); ``factor``: the prior's factor
        in a factored ``covariance_form``, carried from an earlier run (else ``P0`` is
        factored). Returns the result and the last step's factor (``None``: Joseph form)."""
        prep = self.prepare(inputs, history)
        steps: list[Step] = []
        pred_means: list[Tensor] = []
        pred_covs: list[Tensor] = []
        linearised: list[Tensor] = []
        x, P = inputs.x0, inputs.P0 if factor is None else factor
        run_steps = compiled.runner(self, prep, inputs, fresh)  # filter_step, compiled or not
        while len(steps) < inputs.steps:
            for x_pred, P_pred, F_t, step in run_steps(len(steps), x, P, carried):
                if prep.F is None:
                    linearised.append(F_t)
                x, carried = step.mean, step.post_innovation
                P = step.cov if step.factor is None else step.factor
                steps.append(step)
                pred_means.append(x_pred)
                pred_covs.append(P_pred)

        def stacked(field: str) -> Tensor | None:
            return _stack_over_time([getattr(s, field) for s in steps], inputs.batch)

        def stacked_all(values: list[Tensor]) -> Tensor:
            out = _stack_over_time(values, inputs.batch)
            assert out is not None
            return out

        loglik = stacked("log_likelihood")
        result = FilterResult(
            mean=stacked_all([s.mean for s in steps]),
            cov=stacked_all([s.cov for s in steps]),
            pred_mean=stacked_all(pred_means),
            pred_cov=stacked_all(pred_covs),
            innovation=stacked_all([s.innovation for s in steps]),
            mask=prep.observed,
            transition=_as_result_matrix(prep.F) if prep.F is not None else stacked_all(linearised),
            meas_matrix=(
                stacked_all([s.meas_matrix for s in steps if s.meas_matrix is not None])
                if prep.H is None
                else _as_result_matrix(prep.H)
            ),
            meas_cov=_as_result_matrix(prep.R),
            gain=stacked_all([s.gain for s in steps]),
            post_innovation=stacked("post_innovation"),
            innovation_cov=stacked("innovation_cov"),
            log_likelihood=None if loglik is None else loglik.sum(dim=1),
        )
        return result, steps[-1].factor

    def smoother_pass(
        self, inputs: Inputs, smoothing: str | None = None, lag: int | None = 1
    ) -> tuple[FilterResult, tuple[Tensor, Tensor] | None]:
        """The pass a smoother consumes: the whole record (whatever the caller keeps), or,
        with ``smoothing`` (``"gain"``: RTS, ``"projection"``: SVSS) where the per-axis compiled
        loop runs, the smoothed mean and covariance of ``lag`` (``None``: the fixed interval)
        computed with the filter (lag 1, and other lags where less than the whole record is
        kept: :func:`axes.run_axes`) beside a record that keeps what ``inputs.keep`` keeps."""
        if smoothing is not None:
            by_axis = self._run_axes(inputs, smoothing, lag)
            if by_axis is not None:  # without the fused smoothing the record is whole
                result, _, smoothed = by_axis
                return result, smoothed
        return self.run(replace(inputs, keep="all")), None

    def _run_axes(
        self, inputs: Inputs, smoothing: str | None = None, lag: int | None = 1
    ) -> tuple[FilterResult, fused_axes.Last, tuple[Tensor, Tensor] | None] | None:
        """The pass through the per-axis kernel when the problem decouples by axis (a
        :class:`~torchsvs.models.ConstantVelocity` with diagonal ``R``, a prior without cross-axis
        covariance, a position-only or a finite-difference-velocity corrector), the state
        after its last step and the smoothed moments asked for (:func:`axes.run_axes`); else
        ``None``. Its compiled loop writes only what ``inputs.keep`` keeps."""
        model = self.model
        if not AXIS_KERNEL["enabled"] or self.axis_rule is None or not self.kernels_apply:
            return None
        if not isinstance(model, ConstantVelocity):
            return None
        m, n = model.meas_dim, model.state_dim
        dtype = inputs.z.dtype
        R = model.meas_cov().to(dtype)
        cross = ~torch.eye(m, dtype=torch.bool)
        if bool((R[cross] != 0).any()) or bool((inputs.P0[:, _cross_axis(m)] != 0).any()):
            return None
        pos, vel = model.position_index, model.velocity_index
        direct = self.axis_measurements(inputs)
        if direct is not None:
            y, with_velocity = direct, True
            H, R_c = torch.eye(n, dtype=dtype), None
        else:
            measured = self._axis_split(inputs, pos, vel)
            if measured is None:
                return None
            y, with_velocity, H, R_c = measured
        P0 = inputs.P0.expand(inputs.batch, n, n)
        prior = blocks.Sym2(P0[:, pos, pos], P0[:, pos, vel], P0[:, vel, vel])
        interval = inputs.dt if inputs.dt is not None else torch.tensor(model.dt, dtype=dtype)
        settings = self.axis_settings(inputs)
        psi, gamma = settings if settings is not None else (None, None)
        per_axis, out, last, smoothed = axes.run_axes(
            y,
            (inputs.x0[:, pos], inputs.x0[:, vel]),
            prior,
            model.q().to(dtype),
            interval.to(dtype),
            self.axis_rule,
            psi,
            gamma,
            with_velocity,
            inputs.keep,
            smoothing,
            lag,
        )
        if per_axis is None:  # only the kept moments were written
            none: dict[str, Any] = dict.fromkeys(("transition", "meas_matrix", "meas_cov"))
            return FilterResult(**out._asdict(), **none), last, smoothed
        F = model.transition(inputs.dt).to(dtype)  # Q is not part of a result
        if R_c is None:  # measured per axis: R (unmasked) from its diagonal blocks
            R_c = blocks.block_diagonal(
                blocks.full(blocks.Sym2(*torch.broadcast_tensors(*y.noise)))
            )
        return (
            FilterResult(
                **out._asdict(),
                transition=_as_result_matrix(F),
                meas_matrix=_as_result_matrix(H),
                meas_cov=_as_result_matrix(R_c),
                axes=per_axis,
            ),
            last,
            smoothed,
        )

    def axis_measurements(self, inputs: Inputs) -> axes.AxisMeasurements | None:
        """The corrector's full-state measurements built axis by axis, where a filter can
        (the SVSF's finite-difference velocities); ``None``: split :meth:`measurements`."""
        return None

    def _axis_split(
        self, inputs: Inputs, pos: list[int], vel: list[int]
    ) -> tuple[axes.AxisMeasurements, bool, Tensor, Tensor] | None:
        """:meth:`measurements` split by axis: positions only, or the full state with ``H = I``
        (and whether velocities are measured, ``H``, ``R``); ``None`` if they couple axes."""
        z, H, R_c = self.measurements(inputs)
        model = self.model
        assert H is not None and isinstance(model, ConstantVelocity)
        m, n = len(pos), model.state_dim
        if H.shape == (n, n) and bool(torch.equal(H, torch.eye(n, dtype=H.dtype))):
            if bool((R_c[..., _cross_axis(m)] != 0).any()):
                return None

            def entry(i: list[int], j: list[int]) -> Tensor:
                return R_c[..., i, j]

            noise = blocks.Sym2(entry(pos, pos), entry(pos, vel), entry(vel, vel))
            return axes.AxisMeasurements(z[..., pos], z[..., vel], noise), True, H, R_c
        if H.shape == (m, n) and bool(torch.equal(H, model.meas_matrix().to(H.dtype))):
            diagonal = R_c.diagonal(dim1=-2, dim2=-1)
            noise = blocks.Sym2(diagonal, torch.zeros_like(diagonal), torch.ones_like(diagonal))
            return (
                axes.AxisMeasurements(z, z.new_tensor(float("nan")).expand_as(z), noise),
                False,
                H,
                R_c,
            )
        return None


def _cross_axis(m: int) -> Tensor:
    """``[2m, 2m]`` True where a state covariance couples different axes (layout x, vx, y, ...)."""
    axis = torch.arange(2 * m) // 2
    return axis[:, None] != axis[None, :]


class KalmanFilter(GaussianFilter):
    r"""Batched, differentiable Kalman filter, Eqs. (11)-(16), Chen et al. 2020.

    .. math::
        S = H P_{k+1|k} H^T + R,\quad K = P_{k+1|k} H^T S^{-1},\quad
        \hat x_{k+1|k+1} = \hat x_{k+1|k} + K (z_{k+1} - H \hat x_{k+1|k}),

        P_{k+1|k+1} = (I - KH) P_{k+1|k} (I - KH)^T + K R K^T \quad\text{(Joseph form)}

    A missing component (NaN in ``z``) drops its rows of ``H`` and ``R``; an all-NaN step is a
    pure prediction. The result also carries ``S`` and the log-likelihood of the innovations.

    Args:
        model: a :class:`~torchsvs.models.LinearModel`.
        adaptive_noise: an :class:`~torchsvs.filters.AdaptiveNoise` to replace the model's ``R``
            by ``R_k`` from the spread of the differenced recent measurements (Eqs. (29)-(30),
            Bermúdez Ordoñez et al. 2020; the result's ``meas_cov`` is then ``[B, T, m, m]``),
            or ``None`` (the model's ``R``).
        covariance_form: how ``P`` is carried and updated: ``"joseph"`` (default, the form
            above), ``"conventional"`` (``P⁺ = (I − KH)P⁻``), ``"sqrt"`` (``P = SSᵀ``, QR of
            pre-arrays, Morf-Kailath update), ``"ud"`` (``P = UDUᵀ``, Thornton and Bierman) or
            ``"svd"`` (``P = UD²Uᵀ``, K-SVD, Bermúdez Ordoñez et al. 2020): the same filter in
            exact arithmetic, with different rounding (:mod:`torchsvs.filters.factored`). The
            factored forms run the general step loop (no fused or per-axis kernels); the
            result's ``cov`` is the full ``P`` and ``S`` and the log-likelihood are formed from
            the predicted ``P`` as in the Joseph form.

    References:
        Kalman, "A new approach to linear filtering and prediction problems", J. Basic Eng. 82,
        1960. doi:10.1115/1.3662552
    """

    axis_rule: str | None = "kalman"
    dense_rule: str | None = "kalman"

    def __init__(
        self,
        model: StateSpaceModel,
        adaptive_noise: AdaptiveNoise | None = None,
        covariance_form: str = "joseph",
    ) -> None:
        super().__init__(model)
        self.adaptive_noise = check_adaptive_noise(adaptive_noise)
        self.covariance_form = factored.check_form(covariance_form)

    def correct(
        self,
        x_pred: Tensor,
        P_pred: Tensor,
        obs: Observation,
        carried: Tensor | None,
        inputs: Inputs,
    ) -> Step:
        fitted, H = obs.linearize(x_pred)  # Eq. (4) of Gadsden et al. 2012 for a nonlinear h
        e = obs.z - fitted
        step = kalman_correct(x_pred, P_pred, e, obs.mask, H, obs.R, obs.factor)
        return step if obs.H is not None else step._replace(meas_matrix=H)

"""The predict-correct step every Gaussian filter shares: the Kalman correction, what a
corrector sees and returns, and :class:`GaussianFilter`'s protocol (prepare a run, predict,
correct, loop over the steps). Faster ways to run the same steps live in :mod:`.fast_paths`."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.estimator import Inputs, SteppedEstimator, prepare_prior
from torchsvs.filters import factored
from torchsvs.filters.adaptive import AdaptiveNoise
from torchsvs.kernels import compiled
from torchsvs.kernels.fused_axes import Last
from torchsvs.linalg import (
    cholesky,
    gaussian_log_density,
    joseph_update,
    mask_measurement,
    matvec,
    symmetrize,
)
from torchsvs.models.base import LinearModel, StateSpaceModel
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


def as_result_matrix(A: Tensor) -> Tensor:
    """``[r, c]`` → ``[1, 1, r, c]``; ``[B, T, r, c]`` unchanged."""
    return A if A.ndim == 4 else A[None, None]


def kalman_update(
    x_pred: Tensor, P_pred: Tensor, e: Tensor, H: Tensor, R: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The Kalman correction, Eqs. (14)-(16): ``(x, P, K, S, chol(S))`` from innovation ``e``.

    ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹`` through the Cholesky factor of ``S``, Joseph-form ``P``.

    The one Python home of this update. Its deliberate twins, written out for speed and pinned
    to this filter's general path by the kernel tests, follow any change here: the per-axis
    update (2×2 blocks, ``H = [1, 0]`` per axis) of ``torchsvs.kernels.axes._forward_step``
    (rules ``"kalman"``, ``"vbl-*"``), its C++ lane ``predict_correct`` (``Rule == 0``) in
    ``torchsvs/kernels/cpp/axis_step.h``, the dense step ``dense_track`` (``rule == 0``) in
    ``torchsvs/kernels/cpp/dense.h``, and the prior's update in the first element of
    ``torchsvs.kernels.scan.filter_scan``. Pinned by ``tests/test_kernels.py``:
    ``test_kernel_equals_general_path``, ``test_compiled_dense_runs_equal_the_general_path``,
    ``test_time_scan_on_few_long_tracks_equals_general_path``.
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
    """The Kalman correction (:func:`kalman_update`) with innovation ``e``, as a :class:`Step`
    with ``S`` and the log-likelihood; missing components are dropped. ``factor``: ``P_pred``
    in a factored covariance form, whose update then gives the gain and the posterior
    (:mod:`.factored`)."""
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
    :meth:`dynamics` and :meth:`predict`. A run goes through :meth:`filter_step` step by step
    unless :meth:`fast_pass` takes it (:class:`~torchsvs.filters.fast_paths.FastPathFilter`:
    the kernels a corrector declares).
    """

    #: the kind of model the filter needs (nonlinear filters take any StateSpaceModel)
    model_type: type[StateSpaceModel] = LinearModel
    #: the adaptive ``R_k`` (:mod:`torchsvs.filters.adaptive`) of filters that take one, or None
    adaptive_noise: AdaptiveNoise | None = None
    #: how the covariance is carried and updated (:mod:`torchsvs.filters.factored`)
    covariance_form: str = "joseph"

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
        factor = None
        fast = self.fast_pass(state, inputs)
        if fast is not None:
            result, last = fast
        else:
            form, dtype = self.covariance_form, inputs.z.dtype
            prior = factored.resume(state.factor, state.cov, dtype, form)
            result, factor = self._loop(
                inputs, state.post_innovation, state.history, state.steps == 0, prior
            )
            last = last_step(result)
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
            transition=as_result_matrix(prep.F) if prep.F is not None else stacked_all(linearised),
            meas_matrix=(
                stacked_all([s.meas_matrix for s in steps if s.meas_matrix is not None])
                if prep.H is None
                else as_result_matrix(prep.H)
            ),
            meas_cov=as_result_matrix(prep.R),
            gain=stacked_all([s.gain for s in steps]),
            post_innovation=stacked("post_innovation"),
            innovation_cov=stacked("innovation_cov"),
            log_likelihood=None if loglik is None else loglik.sum(dim=1),
        )
        return result, steps[-1].factor

    def fast_pass(self, state: FilterState, inputs: Inputs) -> tuple[FilterResult, Last] | None:
        """The steps of ``inputs`` from ``state`` run a faster way to the same numbers (the
        result and the state after its last step), or ``None``: the step loop runs them
        (:class:`~torchsvs.filters.fast_paths.FastPathFilter` declares its fast paths)."""
        return None

    def smoother_pass(
        self, inputs: Inputs, smoothing: str | None = None, lag: int | None = 1
    ) -> tuple[FilterResult, tuple[Tensor, Tensor] | None]:
        """The pass a smoother consumes: the whole record (whatever the caller keeps), and the
        smoothed mean and covariance where the filter computes them with its pass (``None``
        here; ``smoothing``, ``lag``: see
        :meth:`~torchsvs.filters.fast_paths.FastPathFilter.smoother_pass`)."""
        return self.run(replace(inputs, keep="all")), None


def last_step(result: FilterResult) -> Last:
    """The state after a pass's last step, read from its result."""
    post = result.post_innovation
    return Last(result.mean[:, -1], result.cov[:, -1], None if post is None else post[:, -1])

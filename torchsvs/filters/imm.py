"""The interacting multiple model (IMM) estimator over any torchsvs Gaussian filters."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple, cast

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.estimator import (
    Inputs,
    SteppedEstimator,
    check_keep,
    drop_batch,
    prepare_inputs,
    prepare_prior,
    threads_for,
    trim,
)
from torchsvs.filters.gaussian import (
    GaussianFilter,
    step_input,
    step_interval,
)
from torchsvs.filters.imm_embedding import Embedding, ModeSet
from torchsvs.filters.imm_runs import Runs, mode_step, prepared_runs
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.linalg import (
    cholesky,
    gaussian_log_density,
    log_divisor,
    mixture_mean,
    mixture_moments,
    sum_in_order,
)
from torchsvs.types import FilterResult, FilterState

#: The IMM's truth-free error estimate's finite-difference step (in noise standard deviations;
#: :data:`torchsvs.accuracy.PROBE_STEP` elsewhere): a probe that tips a mode switch moves its
#: estimate by far more than the step, and at 0.1 one probe's estimate of the IMM smoother's
#: error on taxiing aircraft (σ 10) spread 0.86-1.07x the true error over four seeds, at 0.3
#: 0.93-1.04x; on turning, airliner and irregular tracks (σ 50) 0.3 moved it by 0.5% or less.
IMM_PROBE_STEP = 0.3


class IMMState(NamedTuple):
    """Everything the IMM's next step needs (``imm.init``, ``imm.step``, ``imm.scan``): a carry,
    never stored on the module.

    Attributes:
        modes: each mode's filter state after the last step (its mode-conditioned mean and
            covariance in the mode's own state space, and whatever its corrector carries: the
            SVSF's memory, an artificial measurement's rows), always with the batch axis.
        log_probs: ``log μ_j``, the log mode probabilities after the last step, ``[B, M]``.
        log_likelihood: running ``Σ_t log p(z_t | z_{1:t-1})`` since ``init``, ``[B]`` (``None``
            before the first step).
        steps: steps taken since ``init``.
        single: ``init`` was given one track without the batch axis (results drop it too).
        aux: free for subclasses (what :meth:`IMM.update_aux` keeps, e.g. the recent
            measurements a least-squares reset of :meth:`IMM.adjust_modes` needs); the IMM
            itself carries it unchanged (``None``).
    """

    modes: tuple[FilterState, ...]
    log_probs: Tensor
    log_likelihood: Tensor | None = None
    steps: int = 0
    single: bool = False
    aux: Any = None


class IMMResult(NamedTuple):
    """What an IMM pass produced (``B`` tracks, ``T`` steps, ``M`` modes, common state size
    ``n``).

    A call with ``keep="moments"`` (or ``"mean"``) keeps ``mean``, ``cov`` (not with
    ``"mean"``), ``mode_probs``, the log-likelihood and each mode's result trimmed alike; the
    other fields are ``None``.

    Attributes:
        mean: combined estimate ``x̂_{t|t} = Σ_j μ_j(t) x̂^j_{t|t}`` in the common state,
            ``[B, T, n]``.
        cov: its covariance (the mixture's, with the spread of the means), ``[B, T, n, n]``.
        mode_probs: ``μ_j(t) = P(mode j at t | z_{1:t})``, ``[B, T, M]``.
        pred_mode_probs: ``c_j(t) = P(mode j at t | z_{1:t-1}) = Σ_i π_ij μ_i(t-1)``,
            ``[B, T, M]`` (the smoother reads it).
        mode_log_likelihood: ``log Λ_j(t)``, each mode-matched filter's log-likelihood of
            ``z_t`` (0 for a step without measurement), ``[B, T, M]``.
        modes: each mode's :class:`~torchsvs.types.FilterResult` in its own state space: its
            ``mean``/``cov`` the mode-conditioned ``x̂^j_{t|t}``, ``P^j_{t|t}``, its
            predictions made from the mixed initial condition ``x̂^{0j}_{t-1|t-1}``.
        log_likelihood: ``Σ_t log Σ_j c_j(t) Λ_j(t)``, ``[B]``.
    """

    mean: Tensor
    cov: Tensor
    mode_probs: Tensor
    pred_mode_probs: Tensor | None
    mode_log_likelihood: Tensor | None
    modes: tuple[FilterResult, ...]
    log_likelihood: Tensor | None = None


def check_probabilities(value: Any, shape: tuple[int, ...], name: str, want: str) -> Tensor:
    """``value`` as float64 probabilities of ``shape`` along the last axis (entries >= 0 summing
    to 1 within 1e-6, then normalised exactly); ``ValueError`` naming ``name`` otherwise."""
    if isinstance(value, Tensor):
        if not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
            raise TypeError(f"{name}: expected a real tensor, got dtype {value.dtype}")
        p = value.detach().to(torch.float64)
    else:
        try:
            p = torch.as_tensor(value, dtype=torch.float64)
        except (TypeError, ValueError) as err:
            raise TypeError(f"{name}: expected {want}, got {type(value).__name__}") from err
    if tuple(p.shape) != shape:
        raise ValueError(f"{name}: expected {want} of shape {list(shape)}, got {list(p.shape)}")
    if not bool(torch.isfinite(p).all()) or bool((p < 0).any()):
        raise ValueError(f"{name}: expected finite probabilities >= 0, got {p.tolist()}")
    total = p.sum(-1, keepdim=True)
    if bool(((total - 1).abs() > 1e-6).any()):
        raise ValueError(
            f"{name}: expected {want} whose entries sum to 1, got sums {total.flatten().tolist()}"
        )
    return p / total


def log_mode_likelihood(step: FilterResult) -> Tensor:
    """``log Λ_j``, the log-likelihood of a mode-matched filter's step ``[B]``: the step's own
    ``log_likelihood`` where it gives one (the Kalman filters), else the Gaussian log-density
    of its innovation under its innovation covariance over the observed components
    (:func:`~torchsvs.linalg.gaussian_log_density`; the SVSF). A step without measurement
    scores 0 in every mode: no information about the mode."""
    if step.log_likelihood is not None:
        return step.log_likelihood
    if step.innovation_cov is None or step.innovation is None:
        raise ValueError("filters: a mode's filter records no innovation covariance to score it")
    observed = step.mask.sum(-1).to(step.innovation.dtype)
    return gaussian_log_density(step.innovation, cholesky(step.innovation_cov), observed)


def _over_steps(results: list[FilterResult]) -> FilterResult:
    """One step's results ``[B|1, ...]`` each, stacked along a time axis 1 (log-likelihoods
    summed)."""
    fields: list[Any] = []
    for name, parts in zip(FilterResult._fields, zip(*results, strict=True), strict=True):
        if name == "axes" or parts[0] is None:
            fields.append(None)
        elif name == "log_likelihood":
            fields.append(torch.stack(torch.broadcast_tensors(*parts), 1).sum(1))
        else:
            width = max(p.shape[0] for p in parts)
            fields.append(
                torch.stack(
                    [p if p.shape[0] == width else p.expand(width, *p.shape[1:]) for p in parts],
                    dim=1,
                )
            )
    return FilterResult(*fields)


class _StepOut(NamedTuple):
    mean: Tensor
    cov: Tensor
    log_probs: Tensor
    log_pred: Tensor
    log_lik: Tensor
    modes: tuple[FilterResult, ...]
    log_likelihood: Tensor


class IMM(SteppedEstimator[IMMResult]):
    r"""Interacting multiple model estimator over torchsvs Gaussian filters (Blom & Bar-Shalom
    1988; Bar-Shalom, Li, Kirubarajan 2001, Sec. 11.6.6).

    ``M`` mode-matched filters (any :class:`~torchsvs.filters.GaussianFilter`: KF, EKF, UKF,
    SVSF, ...) run side by side; the mode follows a Markov chain with row-stochastic
    ``transition`` :math:`\pi_{ij} = P(\text{mode } j \text{ at } t \mid i \text{ at } t-1)`.
    Each step, from the mode probabilities :math:`\mu_i(t-1)` and the mode-conditioned
    estimates :math:`\hat x^i, P^i`:

    1. Interaction (mixing): :math:`c_j = \sum_i \pi_{ij}\mu_i`,
       :math:`\mu_{i|j} = \pi_{ij}\mu_i / c_j`,

       .. math::
           \hat x^{0j} = \sum_i \mu_{i|j}\,\hat x^i,\qquad
           P^{0j} = \sum_i \mu_{i|j}\big(P^i + (\hat x^i - \hat x^{0j})
               (\hat x^i - \hat x^{0j})^T\big)

    2. Mode-matched filtering: filter ``j``'s own :meth:`~GaussianFilter.step` from
       :math:`(\hat x^{0j}, P^{0j})` with ``z_t`` (its carry otherwise its own: the SVSF keeps
       its memory), giving :math:`\hat x^j, P^j` and the mode likelihood :math:`\Lambda_j`
       (:func:`log_mode_likelihood`: the step's log-likelihood, or the Gaussian density of its
       innovation; a step without measurement gives every mode :math:`\Lambda_j = 1`).
    3. Mode probabilities: :math:`\mu_j = c_j\Lambda_j / \sum_l c_l\Lambda_l`, in log space
       (``logsumexp``); the run's log-likelihood adds :math:`\log\sum_l c_l\Lambda_l`.
    4. Combination: :math:`\hat x = \sum_j \mu_j\hat x^j`,
       :math:`P = \sum_j \mu_j (P^j + (\hat x^j - \hat x)(\hat x^j - \hat x)^T)`.

    Modes of different state sizes (``embedding``): the estimate lives in a common state of
    size ``n``; ``embedding[j][k]`` is the common component of mode ``j``'s component ``k``
    (e.g. ConstantVelocity ``[x, vx, y, vy]`` inside ConstantAcceleration
    ``[x, vx, ax, y, vy, ay]``: ``[[0, 1, 3, 4], [0, 1, 2, 3, 4, 5]]``; inside
    CoordinatedTurn ``[x, vx, y, vy, ω]``: ``[[0, 1, 2, 3], [0, 1, 2, 3, 4]]``). A mode's
    missing components are padded:

    * when mixing into mode ``j``, a mode ``i`` without some of ``j``'s components lends
      mode ``j``'s own mean and variance for them, uncorrelated with its own (the unbiased
      mixing of Yuan et al. 2012; Granström et al. 2015 compare it with zero padding): a
      CV mode leaves the CA mode's acceleration, and the CT mode's turn rate, where they
      were, instead of pulling them to zero;
    * in the combined estimate a missing component is 0 with variance 0 in that mode (a CV
      mode asserts zero acceleration and turn rate), so the combined acceleration is
      :math:`\mu_{CA}\,\hat a^{CA}` with the mixture's variance.

    ``embedding=None`` (the default) is the identity, for modes of one state size.

    ``x0 [B, n]``, ``P0`` are the common-state prior (each mode starts from its components of
    it), ``mode_probs`` (``[M]`` or ``[B, M]``, default ``initial_probs``, default uniform) the
    mode probabilities one step before ``z[:, 0]``. ``psi`` overrides are not taken (a mode's
    SVSF keeps its own ψ).

    Extending the interaction stage: :meth:`interact` is the whole stage; it calls
    :meth:`adjust_modes` first, a hook that may change each mode's state before it is mixed
    (by default nothing), then :meth:`mix`. A separate-modeling tracker, for instance, resets
    the augmented part of each mode's state (its trajectory parameters) by least squares over
    a sliding window there, from the second cycle on (``state.steps``); it keeps the window's
    measurements and estimates in ``IMMState.aux`` through :meth:`update_aux`, which sees the
    state after every step and that step's ``z``, ``dt``, ``u``. The hooks run inside every
    :meth:`step` and :meth:`scan`, so chunked and whole runs stay equal.

    Args:
        filters: the mode-matched filters, one per mode (same measurement; their models may
            differ in state size when ``embedding`` says how they nest).
        transition: row-stochastic ``[M, M]`` mode transition matrix :math:`\pi`.
        initial_probs: mode probabilities before the first step, ``[M]``; default uniform.
        embedding: per mode, the common-state index of each of its components; ``None``: the
            identity (every mode has the common state).
        learn_transition: hold :math:`\pi` as an ``nn.Parameter`` of unconstrained logits
            (a softmax per row; every entry must then be > 0); else a fixed buffer.

    References:
        Blom, Bar-Shalom, "The interacting multiple model algorithm for systems with Markovian
        switching coefficients", IEEE Trans. Autom. Control 33(8), 1988. doi:10.1109/9.1299 ·
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley 2001, Sec. 11.6.6. doi:10.1002/0471221279 ·
        Yuan, Bar-Shalom, Willett, Mozeson, Pollak, Hardiman, "A multiple IMM estimation
        approach with unbiased mixing for thrusting projectiles", IEEE Trans. Aerosp. Electron.
        Syst. 48(4), 2012 ·
        Granström, Willett, Bar-Shalom, "Systematic approach to IMM mixing for unequal
        dimension states", IEEE Trans. Aerosp. Electron. Syst. 51(4), 2015.
    """

    paired_probes = True  # a Python loop over steps of small tensors
    probe_step = IMM_PROBE_STEP

    state_type = IMMState
    log_transition_matrix: Tensor
    log_initial_probs: Tensor
    transition_logits: nn.Parameter

    def __init__(
        self,
        filters: Sequence[GaussianFilter],
        transition: Any,
        *,
        initial_probs: Any = None,
        embedding: Any = None,
        learn_transition: bool = False,
    ) -> None:
        super().__init__()
        if isinstance(filters, GaussianFilter) or not isinstance(filters, Sequence):
            raise TypeError(
                "filters: expected a sequence of torchsvs Gaussian filters, got "
                f"{type(filters).__name__}"
            )
        for j, f in enumerate(filters):
            if not isinstance(f, GaussianFilter):
                raise TypeError(
                    f"filters: mode {j}: expected a torchsvs Gaussian filter (KF, EKF, UKF, "
                    f"SVSF, ...), got {type(f).__name__}"
                )
        M = len(filters)
        if M == 0:
            raise ValueError("filters: expected at least one mode-matched filter, got none")
        models = [f.model for f in filters]
        meas = {mdl.meas_dim for mdl in models}
        if len(meas) != 1:
            raise ValueError(
                f"filters: the modes measure different sizes {[mdl.meas_dim for mdl in models]}; "
                "every mode filters the same measurement"
            )
        self.filters = nn.ModuleList(filters)
        self.embedding = Embedding.of(embedding, [mdl.state_dim for mdl in models])
        inputs = {mdl.input_dim for mdl in models}
        self.model = ModeSet(
            self.embedding.size,
            meas.pop(),
            any(mdl.uses_dt for mdl in models),
            inputs.pop() if len(inputs) == 1 else 0,
        )
        Pi = check_probabilities(transition, (M, M), "transition", "a row-stochastic matrix")
        self.learn_transition = learn_transition
        if learn_transition:
            if bool((Pi <= 0).any()):
                raise ValueError(
                    "transition: a learnable transition matrix is held as logits and needs every "
                    f"entry > 0, got {Pi.tolist()}"
                )
            self.transition_logits = nn.Parameter(Pi.log())
        else:
            self.register_buffer("log_transition_matrix", Pi.log())
        p0 = (
            torch.full((M,), 1.0 / M, dtype=torch.float64)
            if initial_probs is None
            else check_probabilities(initial_probs, (M,), "initial_probs", "mode probabilities")
        )
        self.register_buffer("log_initial_probs", p0.log())

    @property
    def num_modes(self) -> int:
        """``M``, the number of modes."""
        return len(self.filters)

    @property
    def mode_filters(self) -> list[GaussianFilter]:
        """The mode-matched filters, in mode order."""
        return [cast(GaussianFilter, f) for f in self.filters]

    @property
    def transition(self) -> Tensor:
        """The mode transition matrix :math:`\\pi`, ``[M, M]`` (rows sum to 1)."""
        return self.log_transition().exp()

    def log_transition(self, dtype: torch.dtype | None = None) -> Tensor:
        """``log π``, ``[M, M]`` (``-inf`` for impossible switches), in ``dtype``."""
        if self.learn_transition:
            logits = self.transition_logits
            return torch.log_softmax(logits if dtype is None else logits.to(dtype), dim=-1)
        log_T = self.log_transition_matrix
        return log_T if dtype is None else log_T.to(dtype)

    # --- The step protocol: init, step, scan; forward is init and one scan. ---

    def init(self, x0: Any, P0: Any, mode_probs: Any = None) -> IMMState:
        """The state before the first step: the common-state prior ``x0 [B, n]``, ``P0 [B, n, n]``
        or ``[n, n]`` (or one track: ``[n]``, ``[n, n]``), checked as :meth:`forward` checks it,
        and the mode probabilities ``mode_probs`` (``[M]`` or ``[B, M]``; default
        ``initial_probs``)."""
        x0b, P0b, single = prepare_prior(self.model, x0, P0)
        return self._start(x0b, P0b, mode_probs, single)

    def _start(self, x0: Tensor, P0: Tensor, mode_probs: Any, single: bool) -> IMMState:
        log_probs = self.initial_log_probs(mode_probs, x0.shape[0], x0.dtype, single)
        modes = []
        for j, f in enumerate(self.mode_filters):
            x, P = self.embedding.project(j, x0, P0)
            modes.append(f.init(x, P[0] if P.shape[0] == 1 else P)._replace(single=False))
        return IMMState(tuple(modes), log_probs, single=single)

    def initial_log_probs(
        self, mode_probs: Any, B: int, dtype: torch.dtype, single: bool = False
    ) -> Tensor:
        """``log μ_j`` before the first step, ``[B, M]``: of ``mode_probs`` (``[M]`` or
        ``[B, M]``, checked; ``[M]`` only for ``single``) or, for ``None``, ``initial_probs``."""
        M = self.num_modes
        if mode_probs is None:
            return self.log_initial_probs.to(dtype).expand(B, M)
        rank = mode_probs.ndim if isinstance(mode_probs, Tensor) else np.ndim(mode_probs)
        shape = (M,) if single or rank == 1 else (B, M)
        want = "mode probabilities [M]" if single else "mode probabilities [M] or [B, M]"
        probs = check_probabilities(mode_probs, shape, "mode_probs", want)
        return probs.log().to(dtype).expand(B, M)

    def state_prior(self, state: IMMState) -> tuple[Tensor, Tensor]:
        b, n = state.log_probs.shape[0], self.model.state_dim
        return state.log_probs.new_zeros(b, n), state.log_probs.new_zeros(1, n, n)

    def share(self, state: IMMState, inputs: Inputs) -> IMMState:
        B = inputs.batch
        modes = tuple(m._replace(mean=m.mean.expand(B, -1)) for m in state.modes)
        return state._replace(modes=modes, log_probs=state.log_probs.expand(B, -1), single=False)

    @outside_dynamo
    def forward(
        self,
        z: Tensor,
        x0: Tensor,
        P0: Tensor,
        *,
        mode_probs: Any = None,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> IMMResult:
        """Runs the IMM over every track: ``z [B, T, m]`` (or ``[T, m]``), the common-state prior
        ``x0``, ``P0`` one step before ``z[:, 0]``, ``mode_probs`` (``[M]`` or ``[B, M]``,
        default ``initial_probs``); ``u``, ``dt``, ``generator``, ``keep`` as for every
        estimator. Returns an :class:`IMMResult`."""
        self.check_psi(psi)
        inputs = prepare_inputs(self.model, z, x0, P0, u=u, dt=dt, generator=generator, keep=keep)
        with threads_for(inputs.batch, self.model.state_dim):
            result = self.filter_pass(inputs, mode_probs)
        result = self.trim(result, keep)
        return drop_batch(result) if inputs.single else result

    def run(self, inputs: Inputs) -> IMMResult:
        return self.filter_pass(inputs)

    def filter_pass(self, inputs: Inputs, mode_probs: Any = None) -> IMMResult:
        """The whole pass over checked, batched ``inputs`` from their prior and ``mode_probs``."""
        start = self._start(inputs.x0, inputs.P0, mode_probs, inputs.single)
        return self._scan(start._replace(single=False), inputs)[1]

    @outside_dynamo
    def scan(
        self,
        state: Any,
        z: Tensor,
        *,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> tuple[IMMState, IMMResult]:
        """Runs the steps ``z [B, T, m]`` from ``state`` (see
        :meth:`~torchsvs.estimator.SteppedEstimator.scan`): a run in chunks, the state carried
        between them, equals the whole run."""
        check_keep(keep)
        after, result = super().scan(state, z, u=u, dt=dt, psi=psi, generator=generator)
        return after, self.trim(result, keep)

    @staticmethod
    def trim(result: IMMResult, keep: str) -> IMMResult:
        """``result`` keeping what ``keep`` keeps (see :class:`IMMResult`)."""
        if keep == "all":
            return result
        nothing: Any = None
        return result._replace(
            cov=result.cov if keep == "moments" else nothing,
            pred_mode_probs=None,
            mode_log_likelihood=None,
            modes=tuple(trim(r, keep) for r in result.modes),
        )

    def _scan(self, state: IMMState, inputs: Inputs) -> tuple[IMMState, IMMResult]:
        runs = self._prepared_runs(inputs)
        outs = []
        for t in range(inputs.steps):
            state, out = self._step(state, inputs, t, runs)
            outs.append(out)

        def over_time(field: str) -> Tensor:
            return torch.stack([getattr(o, field) for o in outs], dim=1)

        modes = tuple(_over_steps([o.modes[j] for o in outs]) for j in range(self.num_modes))
        nothing: Any = None
        result = IMMResult(
            mean=over_time("mean"),
            cov=nothing if inputs.keep == "mean" else over_time("cov"),
            mode_probs=over_time("log_probs").exp(),
            pred_mode_probs=over_time("log_pred").exp(),
            mode_log_likelihood=over_time("log_lik"),
            modes=modes,
            log_likelihood=sum_in_order([o.log_likelihood for o in outs]),  # as the state sums it
        )
        return state, result

    def _prepared_runs(self, inputs: Inputs) -> Runs | None:
        """Each mode's run prepared once (:func:`~torchsvs.filters.imm_runs.prepared_runs`), or
        ``None``: each step is the mode's own one-step :meth:`~GaussianFilter.step`."""
        return prepared_runs(self.mode_filters, inputs)

    def _step(
        self, state: IMMState, inputs: Inputs, t: int, runs: Runs | None = None
    ) -> tuple[IMMState, _StepOut]:
        dtype = inputs.z.dtype
        z_t, dt_t, u_t = inputs.z[:, t], step_interval(inputs, t), step_input(inputs, t)
        state, priors, log_pred = self.interact(state, self.log_transition(dtype))
        modes, results = [], []
        for j, (f, mode, (x, P)) in enumerate(
            zip(self.mode_filters, state.modes, priors, strict=True)
        ):
            prior = mode._replace(mean=x, cov=P)
            if torch.is_grad_enabled() and (x.requires_grad or P.requires_grad):
                prior = prior._replace(constants=None)  # (compiled steps run without gradients)
            if runs is None:
                after, result = f.step(prior, z_t, dt=dt_t, u=u_t, generator=inputs.generator)
            else:
                after, result = mode_step(f, prior, runs, j, inputs, t)
            modes.append(after)
            results.append(result)
        sizes = {r.innovation.shape[-1] for r in results}
        if len(sizes) > 1:
            raise ValueError(
                "filters: the modes' correctors measure different things (innovations of sizes "
                f"{[r.innovation.shape[-1] for r in results]}), so their likelihoods do not "
                "compare; give every mode the same corrector measurement (an SVSF with "
                "artificial=None measures z itself)"
            )
        log_lik = torch.stack(
            torch.broadcast_tensors(*[log_mode_likelihood(r).to(dtype) for r in results]), -1
        )
        log_joint = log_pred + log_lik
        step_log_likelihood = torch.logsumexp(log_joint, dim=-1)
        log_probs = log_joint - step_log_likelihood.unsqueeze(-1)
        if inputs.keep == "mean":  # (the combined covariance is not kept)
            nothing: Any = None
            mean, cov = self.combined_mean([m.mean for m in modes], log_probs), nothing
        else:
            mean, cov = self.combine([m.mean for m in modes], [m.cov for m in modes], log_probs)
        total = step_log_likelihood
        if state.log_likelihood is not None:
            total = state.log_likelihood + step_log_likelihood
        after = IMMState(tuple(modes), log_probs, total, state.steps + 1, state.single, state.aux)
        after = after._replace(aux=self.update_aux(after, z_t, dt_t, u_t))
        out = _StepOut(mean, cov, log_probs, log_pred, log_lik, tuple(results), step_log_likelihood)
        return after, out

    # --- The stages, each a method a subclass may override. ---

    def interact(
        self, state: IMMState, log_transition: Tensor
    ) -> tuple[IMMState, list[tuple[Tensor, Tensor]], Tensor]:
        """The interaction stage: :meth:`adjust_modes`, then :meth:`mix`. Returns the (adjusted)
        state whose modes' carries the filters continue, each mode's mixed initial condition
        ``(x̂^{0j} [B, n_j], P^{0j} [B, n_j, n_j])`` and ``log c``, the log predicted mode
        probabilities ``[B, M]``."""
        state = self.adjust_modes(state)
        priors, log_pred = self.mix(state.modes, state.log_probs, log_transition)
        return state, priors, log_pred

    def adjust_modes(self, state: IMMState) -> IMMState:
        """Hook called before each interaction stage with the state after the last step: may
        return it with each mode's filter state changed (e.g. part of an augmented state reset
        by least squares over measurements kept in ``state.aux``). By default unchanged."""
        return state

    def update_aux(self, state: IMMState, z: Tensor, dt: Tensor | None, u: Tensor | None) -> Any:
        """Hook called after each step with the state after it (each mode's new estimate, the
        mode probabilities, and ``state.aux`` as the step before left it) and the step's
        measurement ``z [B, m]`` (NaN: missing), interval (``None``, 0-d or ``[B]``) and input:
        the new ``IMMState.aux`` (e.g. a sliding window of measurements and estimated
        positions). By default ``state.aux`` unchanged."""
        return state.aux

    def mix(
        self, modes: Sequence[FilterState], log_probs: Tensor, log_transition: Tensor
    ) -> tuple[list[tuple[Tensor, Tensor]], Tensor]:
        """Mixing (interaction; Bar-Shalom et al. 2001, Sec. 11.6.6): the mixed
        initial condition of every mode and ``log c`` ``[B, M]`` (see the class docstring; a
        mode that cannot be reached, ``c_j = 0``, keeps its own state)."""
        dtype = log_probs.dtype
        M = self.num_modes
        log_joint = log_probs.unsqueeze(-1) + log_transition  # [B, i, j]: log π_ij μ_i
        log_pred = torch.logsumexp(log_joint, dim=-2)  # [B, j]: log c_j
        safe, unreachable = log_divisor(log_pred)
        weights = torch.exp(log_joint - safe.unsqueeze(-2))  # μ_{i|j}
        if bool(unreachable.any()):
            eye = torch.eye(M, dtype=dtype, device=weights.device)
            weights = torch.where(unreachable.unsqueeze(-2), eye, weights)
        B = log_probs.shape[0]
        means = [m.mean.to(dtype).expand(B, -1) for m in modes]
        covs = [m.cov.to(dtype).expand(B, -1, -1) for m in modes]
        # every mode j's mixture at once, in the common state (elementwise: the same numbers
        # as mode by mode; the components mode j lacks are dropped)
        x_lent, P_lent = self.embedding.lent(means, covs)  # [B, i, j, n], [B, i, j, n, n]
        x, P = mixture_moments(
            weights.transpose(-1, -2), x_lent.unbind(-3), P_lent.unbind(-4)
        )  # [B, j, n]...
        return self.embedding.of_modes(x, P), log_pred

    def combine(
        self, means: Sequence[Tensor], covs: Sequence[Tensor], log_probs: Tensor
    ) -> tuple[Tensor, Tensor]:
        """The combined estimate in the common state (a mode's missing components 0 with
        variance 0): ``[..., n]`` and ``[..., n, n]`` from each mode's ``[..., n_j]``,
        ``[..., n_j, n_j]`` and ``log_probs [..., M]``."""
        probs = log_probs.exp()
        lead = probs.shape[:-1]
        x = self.embedding.common_means([x.expand(*lead, -1) for x in means])
        P = self.embedding.common_covs([P.expand(*lead, -1, -1) for P in covs])
        return mixture_moments(probs, x.unbind(-2), P.unbind(-3))

    def combined_mean(self, means: Sequence[Tensor], log_probs: Tensor) -> Tensor:
        """The mean of :meth:`combine`, alone (the same numbers)."""
        probs = log_probs.exp()
        lead = probs.shape[:-1]
        x = self.embedding.common_means([x.expand(*lead, -1) for x in means])
        return mixture_mean(probs, x.unbind(-2))

"""Fixed-lag and fixed-interval smoothing of an IMM pass (Kim's approximate smoother)."""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.estimator import (
    Estimator,
    Inputs,
    check_keep,
    drop_batch,
    prepare_inputs,
    threads_for,
)
from torchsvs.filters.imm import IMM, IMM_PROBE_STEP, IMMResult
from torchsvs.filters.turn_imm import TurnIMM
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.linalg import (
    log_divisor,
    matvec,
    mixture_mean,
    mixture_moments,
    right_psd_solve,
    symmetrize,
)
from torchsvs.models.base import StateSpaceModel


class Moments(NamedTuple):
    """A mean ``[B, T, n_j]`` and covariance ``[B, T, n_j, n_j]`` (one mode's smoothed ones)."""

    mean: Tensor
    cov: Tensor


class IMMSmootherResult(NamedTuple):
    """A smoothed IMM pass and the filter pass it was computed from.

    Attributes:
        mean: combined smoothed estimate in the common state, ``[B, T, n]``: ``x̂_{t|t+L}`` for
            lag ``L``, ``x̂_{t|T}`` for the fixed interval.
        cov: its covariance, ``[B, T, n, n]``.
        mode_probs: smoothed mode probabilities ``P(mode j at t | z_{1:t+L})``, ``[B, T, M]``.
        modes: each mode's smoothed moments in its own state space (:class:`Moments`).
        filtered: the :class:`~torchsvs.filters.IMMResult` of the forward pass.
    """

    mean: Tensor
    cov: Tensor
    mode_probs: Tensor
    modes: tuple[Moments, ...]
    filtered: IMMResult


class _Moments(NamedTuple):
    """Per-mode moments and log mode probabilities at one time (any leading shape)."""

    means: list[Tensor]
    covs: list[Tensor]
    log_probs: Tensor


class _Predictions(NamedTuple):
    """Each mode's filtered estimate at ``k`` predicted by each mode's model to ``k + 1``:
    ``[j][l]`` is mode ``j``'s estimate (padded into mode ``l``'s space) through mode ``l``,
    ``[B, T-1, ...]`` for ``k = 0..T-2``."""

    mean: list[list[Tensor]]  #: x̂^{jl}_{k+1|k}, [B, T-1, n_l]
    cov: list[list[Tensor]]  #: P^{jl}_{k+1|k}, [B, T-1, n_l, n_l]
    #: the smoother gain C^{jl}_k = Cov(x^j_k, x_{k+1}) (P^{jl}_{k+1|k})⁻¹ with the cross
    #: covariance P^j_k Sᵀ Fᵀ, [B, T-1, n_j, n_l]: the same in every sweep of a fixed lag
    gain: list[list[Tensor]]


class IMMSmoother(Estimator[IMMSmootherResult]):
    r"""Fixed-lag (or fixed-interval) smoother over an :class:`~torchsvs.IMM` pass: Kim's
    approximate smoother for Markov-switching state-space models (Kim 1994), the
    backward recursion run over the window ``k .. k+L`` for each ``k``.

    From the forward IMM's mode-conditioned estimates :math:`\hat x^j_{k|k}, P^j_{k|k}`,
    mode probabilities :math:`\mu_j(k)` and predicted ones :math:`c_l(k+1)`, backwards from
    the window's end ``e`` (where smoothed = filtered) to ``k``, for every pair of modes
    ``j`` (at ``k``) and ``l`` (at ``k+1``):

    .. math::
        \hat x^{jl}_{k+1|k} = f_l(\hat x^j_{k|k}),\quad
        C^{jl}_k = P^j_{k|k} F_l^T (P^{jl}_{k+1|k})^{-1},

        \hat x^{jl}_{k|e} = \hat x^j_{k|k} + C^{jl}_k(\hat x^l_{k+1|e} - \hat x^{jl}_{k+1|k}),\quad
        P^{jl}_{k|e} = P^j_{k|k} + C^{jl}_k(P^l_{k+1|e} - P^{jl}_{k+1|k})C^{jl\,T}_k,

        q_{jl} = \frac{\mu_j(k)\,\pi_{jl}}{c_l(k+1)}\,\mu_l(k+1|e),\quad
        \mu_j(k|e) = \sum_l q_{jl},

    and the pairs are collapsed per mode with the weights :math:`q_{jl}/\mu_j(k|e)` (mean and
    spread-of-means covariance); the combined estimate mixes the modes as the IMM does. The
    predictions :math:`\hat x^{jl}_{k+1|k}, P^{jl}_{k+1|k}` and :math:`F_l` come from a
    pure-prediction :meth:`~torchsvs.filters.GaussianFilter.step` of mode ``l``'s filter (all
    of them at once, one batch), so EKF and UKF modes are linearised as they filter; a mode's
    estimate enters another mode's space padded as the IMM mixes it.

    Approximations (beyond the forward IMM's own): (i) :math:`P(s_k = j \mid s_{k+1} = l,
    z_{1:e}) \approx P(s_k = j \mid s_{k+1} = l, z_{1:k})`, and (ii) :math:`p(x_{k+1} \mid s_k
    = j, s_{k+1} = l, z_{1:e}) \approx p(x_{k+1} \mid s_{k+1} = l, z_{1:e})`, a Gaussian: the
    mode at ``k`` is assumed to tell nothing more about the future measurements than the mode
    at ``k+1`` does; (iii) each mode's smoothed density is collapsed to one Gaussian at every
    step. With one mode it is the RTS smoother, exactly.

    ``lag=L`` gives :math:`\hat x_{k|k+L}` (windows shorten at the end of the track; cost
    O(T·L·M²), vectorised over time in ``L`` sweeps); ``lag=None`` the fixed interval
    :math:`\hat x_{k|T}` (O(T·M²)).

    Long windows: the backward pass links a mode's filtered estimates by that mode's own
    dynamics, while the forward IMM re-mixes them at every step. With a nearly deterministic
    mode (a CV mode of tiny ``q``) and frequent switching, an error the mode picks up during a
    maneuver is then carried back rigidly over the whole segment before it, and the fixed
    interval can end up worse than a short lag (even than the filter). A lag of the order of a
    maneuver's duration is the safe choice; stickier transitions or a less rigid quiet mode
    make long windows pay off.

    Args:
        imm: the :class:`~torchsvs.IMM` whose pass is smoothed.
        lag: a positive integer lag, or ``None`` for the fixed interval (no default: see
            the note on long windows above).

    References:
        Kim, "Dynamic linear models with Markov-switching", J. Econometrics 60(1-2), 1994,
        pp. 1-22. doi:10.1016/0304-4076(94)90036-1 ·
        Kim, Nelson, "State-Space Models with Regime Switching", MIT Press 1999, Ch. 5 ·
        Rauch, Tung, Striebel, AIAA J. 3(8), 1965. doi:10.2514/3.3166
    """

    paired_probes = True  # the plain and probed runs in one pass (one call of a step loop)
    probe_step = IMM_PROBE_STEP

    def __init__(self, imm: IMM, lag: int | None) -> None:
        super().__init__()
        if not isinstance(imm, IMM):
            raise TypeError(f"imm: expected a torchsvs IMM, got {type(imm).__name__}")
        if lag is not None and (isinstance(lag, bool) or not isinstance(lag, int) or lag < 1):
            raise ValueError(f"lag: expected None (fixed interval) or an integer >= 1, got {lag!r}")
        self.imm = imm
        self.lag = lag

    @property
    def model(self) -> StateSpaceModel:  # type: ignore[override]
        return self.imm.model

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
    ) -> IMMSmootherResult:
        """Smooths every track; arguments as for :meth:`IMM.forward`. ``keep`` trims the
        result's filter pass (``"mean"`` also drops the smoothed covariances)."""
        self.check_psi(psi)
        inputs = prepare_inputs(self.model, z, x0, P0, u=u, dt=dt, generator=generator, keep=keep)
        with threads_for(inputs.batch, self.model.state_dim):
            result = self._pass(inputs, mode_probs)
        result = _trim(result, keep)
        return drop_batch(result) if inputs.single else result

    def run(self, inputs: Inputs) -> IMMSmootherResult:
        return self._pass(inputs, None)

    def _pass(self, inputs: Inputs, mode_probs: Any) -> IMMSmootherResult:
        """The filter pass and its smoothing (a subclass may change what they run on)."""
        return self.smooth(self.imm.filter_pass(inputs, mode_probs), inputs)

    def smooth(self, filtered: IMMResult, inputs: Inputs) -> IMMSmootherResult:
        """The smoothed pass of an IMM result (kept whole) over the checked ``inputs`` it was
        computed from (their ``dt`` and ``u`` drive the predictions)."""
        imm = self.imm
        if filtered.pred_mode_probs is None or filtered.modes[0].cov is None:
            raise ValueError("filtered: expected a whole IMM result (keep='all')")
        T = filtered.mean.shape[1]
        dtype = filtered.mean.dtype
        means = [r.mean for r in filtered.modes]
        covs = [r.cov for r in filtered.modes]
        log_mu = filtered.mode_probs.log()
        smoothed = _Moments(means, covs, log_mu)
        # The smoothed means never depend on the smoothed covariances: keep="mean" (a loss on
        # the positions, SURE's probes) skips them, about half the backward pass.
        with_cov = inputs.keep != "mean"
        if T > 1:
            log_T = imm.log_transition(dtype)
            log_c = filtered.pred_mode_probs.log()[:, 1:]  # c(k+1) for k = 0..T-2
            pred = self._predictions(means, covs, inputs)
            kept = covs if with_cov else []
            if self.lag is None:
                smoothed = self._fixed_interval(means, kept, log_mu, log_c, pred, log_T)
            else:
                smoothed = self._fixed_lag(means, kept, log_mu, log_c, pred, log_T, self.lag)
        nothing: Any = None
        if with_cov:
            mean, cov = imm.combine(smoothed.means, smoothed.covs, smoothed.log_probs)
        else:  # (the combined covariance is not kept)
            mean, cov = imm.combined_mean(smoothed.means, smoothed.log_probs), nothing
        covs_out = smoothed.covs if with_cov else [nothing] * len(smoothed.means)
        return IMMSmootherResult(
            mean,
            cov,
            smoothed.log_probs.exp(),
            tuple(Moments(x, P) for x, P in zip(smoothed.means, covs_out, strict=True)),
            filtered,
        )

    def _predictions(self, means: list[Tensor], covs: list[Tensor], inputs: Inputs) -> _Predictions:
        """Every mode's filtered estimate at ``k`` through every mode's pure-prediction step to
        ``k + 1``, all ``B·(T-1)`` of them as one batch per pair."""
        imm = self.imm
        M = imm.num_modes
        B, T = means[0].shape[:2]
        dtype = means[0].dtype
        flat = B * (T - 1)
        dt = inputs.dt
        if dt is not None and dt.ndim == 2:
            dt = dt[:, 1:].reshape(flat)
        u = None if inputs.u is None else inputs.u[:, 1:].reshape(flat, 1, -1)
        blank = torch.full((flat, 1, imm.model.meas_dim), float("nan"), dtype=dtype)
        one_dt = dt.unsqueeze(1) if dt is not None and dt.ndim == 1 else dt
        mean: list[list[Tensor]] = [[] for _ in range(M)]
        cov: list[list[Tensor]] = [[] for _ in range(M)]
        gain: list[list[Tensor]] = [[] for _ in range(M)]
        for l, f in enumerate(imm.mode_filters):
            n_l = means[l].shape[-1]
            prep = None  # (mode l's model matrices: the same for every j)
            for j in range(M):
                x_j, P_j = means[j][:, :-1], covs[j][:, :-1]
                x, P = imm.embedding.into(j, l, x_j, P_j, means[l][:, :-1], covs[l][:, :-1])
                # The filter's own prediction (no correction: nothing is measured), on inputs
                # of one step built here (not through f.init or forward: they check a prior,
                # and a float32 pass leaves some filtered covariances semi-definite by rounding)
                x0, P0 = x.reshape(flat, n_l), symmetrize(P).reshape(flat, n_l, n_l)
                one = Inputs(blank, x0, P0, one_dt, u, None, inputs.generator, False)
                prep = f.prepare(one) if prep is None else prep
                x_pred, P_pred, F = f.predict(0, x0, P0, prep, one)
                F = F.expand(flat, n_l, n_l).reshape(B, T - 1, n_l, n_l)
                mean[j].append(x_pred.reshape(B, T - 1, n_l))
                cov[j].append(P_pred.expand(flat, n_l, n_l).reshape(B, T - 1, n_l, n_l))
                cross = imm.embedding.columns(j, l, P_j) @ F.mT
                gain[j].append(right_psd_solve(cross, cov[j][-1]))
        return _Predictions(mean, cov, gain)

    def _backward(
        self,
        after: _Moments,
        means: list[Tensor],
        covs: list[Tensor],
        log_mu: Tensor,
        log_c: Tensor,
        pred: _Predictions,
        log_T: Tensor,
    ) -> _Moments:
        """One step of Kim's recursion, from the smoothed moments at ``k + 1`` (``after``) and
        the filter's at ``k``, for any leading shape; the means alone where ``covs`` is empty."""
        M = len(means)
        safe_c, impossible = log_divisor(log_c)  # c_l(k+1) = 0: mode l cannot be reached
        log_back = log_mu.unsqueeze(-1) + log_T - safe_c.unsqueeze(-2)  # P(s_k=j | s_k+1=l, z_1:k)
        log_back = torch.where(
            impossible.unsqueeze(-2), torch.full_like(log_back, -torch.inf), log_back
        )
        log_joint = log_back + after.log_probs.unsqueeze(-2)  # [.., j, l]
        log_probs = torch.logsumexp(log_joint, dim=-1)  # μ_j(k|e)
        safe, gone = log_divisor(log_probs)
        weights = torch.exp(log_joint - safe.unsqueeze(-1))  # P(s_k+1=l | s_k=j, z_1:e)
        if bool(gone.any()):  # a mode of probability 0: its estimate is its filtered one
            weights = torch.where(gone.unsqueeze(-1), torch.zeros_like(weights), weights)
        out_means, out_covs = [], []
        for j in range(M):
            xs = [
                means[j] + matvec(pred.gain[j][l], after.means[l] - pred.mean[j][l])
                for l in range(M)
            ]
            keep_filtered = gone[..., j]
            if covs:
                Ps = [
                    covs[j]
                    + pred.gain[j][l] @ (after.covs[l] - pred.cov[j][l]) @ pred.gain[j][l].mT
                    for l in range(M)
                ]
                x_s, P_s = mixture_moments(weights[..., j, :], xs, Ps)
                out_covs.append(torch.where(keep_filtered[..., None, None], covs[j], P_s))
            else:
                x_s = mixture_mean(weights[..., j, :], xs)
            out_means.append(torch.where(keep_filtered[..., None], means[j], x_s))
        return _Moments(out_means, out_covs, log_probs)

    def _fixed_interval(
        self,
        means: list[Tensor],
        covs: list[Tensor],
        log_mu: Tensor,
        log_c: Tensor,
        pred: _Predictions,
        log_T: Tensor,
    ) -> _Moments:
        T = log_mu.shape[1]
        M = len(means)
        at = _Moments([x[:, -1] for x in means], [P[:, -1] for P in covs], log_mu[:, -1])
        steps = [at]
        for k in range(T - 2, -1, -1):
            at = self._backward(
                at,
                [x[:, k] for x in means],
                [P[:, k] for P in covs],
                log_mu[:, k],
                log_c[:, k],
                _Predictions(*[[[p[:, k] for p in row] for row in part] for part in pred]),
                log_T,
            )
            steps.append(at)
        steps.reverse()
        return _Moments(
            [torch.stack([s.means[j] for s in steps], 1) for j in range(M)],
            [torch.stack([s.covs[j] for s in steps], 1) for j in range(len(covs))],
            torch.stack([s.log_probs for s in steps], 1),
        )

    def _fixed_lag(
        self,
        means: list[Tensor],
        covs: list[Tensor],
        log_mu: Tensor,
        log_c: Tensor,
        pred: _Predictions,
        log_T: Tensor,
        lag: int,
    ) -> _Moments:
        """``L`` sweeps over every target step ``k`` at once: each carries its window's
        smoothed moments from the window's end ``min(k + L, T - 1)`` down to ``k`` (the means
        alone where ``covs`` is empty)."""
        T = log_mu.shape[1]
        k = torch.arange(T)
        tau = (k + lag).clamp_max(T - 1)  # the time each target's moments are at

        def at(x: Tensor, index: Tensor) -> Tensor:
            return x[:, index]

        cur = _Moments([at(x, tau) for x in means], [at(P, tau) for P in covs], at(log_mu, tau))
        for _ in range(lag):
            active = tau > k
            if not bool(active.any()):
                break
            index = (tau - 1).clamp(0, T - 2)  # the step k' = τ - 1 each target moves to
            new = self._backward(
                cur,
                [at(x, index) for x in means],
                [at(P, index) for P in covs],
                at(log_mu, index),
                at(log_c, index),
                _Predictions(
                    [[at(p, index) for p in row] for row in pred.mean],
                    [[at(p, index) for p in row] for row in pred.cov] if covs else [],
                    [[at(p, index) for p in row] for row in pred.gain],
                ),
                log_T,
            )
            a1, a2 = active[None, :, None], active[None, :, None, None]
            cur = _Moments(
                [torch.where(a1, x, y) for x, y in zip(new.means, cur.means, strict=True)],
                [torch.where(a2, x, y) for x, y in zip(new.covs, cur.covs, strict=True)],
                torch.where(a1, new.log_probs, cur.log_probs),
            )
            tau = torch.where(active, tau - 1, tau)
        return cur


class TurnIMMSmoother(IMMSmoother):
    """Kim's fixed-lag smoother (:class:`IMMSmoother`) over a :class:`~torchsvs.TurnIMM` pass:
    the IMM(CV, CT) of ``torchsvs track --estimator imm --lag L``, called like the
    :class:`~torchsvs.TurnIMM` with the CV state's prior, its ``mean`` and ``cov`` in the CV
    state (the smoothed modes keep the CT mode's turn rate).

    Args:
        turn: the :class:`~torchsvs.TurnIMM` whose pass is smoothed.
        lag: a positive integer lag, or ``None`` for the fixed interval.
    """

    def __init__(self, turn: TurnIMM, lag: int | None) -> None:
        if not isinstance(turn, TurnIMM):
            raise TypeError(f"turn: expected a TurnIMM, got {type(turn).__name__}")
        super().__init__(turn.imm, lag)
        self.turn = turn

    @property
    def model(self) -> StateSpaceModel:  # type: ignore[override]
        return self.turn.model  # the CV state the prior and the result are in

    def _pass(self, inputs: Inputs, mode_probs: Any) -> IMMSmootherResult:
        common = self.turn.common_inputs(inputs)
        compiled = self.turn.compiled_pass(common, mode_probs, self.lag)
        if compiled is None:
            return self.turn.cv_part(super()._pass(common, mode_probs))
        smoothed = compiled.smoothed_modes  # (a smoother's lag is never 0: always there)
        assert compiled.smoothed_mean is not None and compiled.smoothed_mode_probs is not None
        assert smoothed is not None
        result = IMMSmootherResult(
            compiled.smoothed_mean,
            compiled.smoothed_cov,
            compiled.smoothed_mode_probs,
            tuple(Moments(mean, cov) for mean, cov in smoothed),
            self.turn.filtered_result(compiled),
        )
        return self.turn.cv_part(result)


def _trim(result: IMMSmootherResult, keep: str) -> IMMSmootherResult:
    check_keep(keep)
    if keep == "all":
        return result
    nothing: Any = None
    modes = (
        result.modes if keep == "moments" else tuple(Moments(m.mean, nothing) for m in result.modes)
    )
    return result._replace(
        cov=result.cov if keep == "moments" else nothing,
        modes=modes,
        filtered=IMM.trim(result.filtered, keep),
    )

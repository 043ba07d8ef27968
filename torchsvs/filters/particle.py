"""The sampling importance resampling (SIR) particle filter, with its optimal proposal and
regularisation; the SPVSF builds on it (:mod:`torchsvs.filters.spvsf`)."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache
from statistics import NormalDist
from typing import Any, Literal, NamedTuple, get_args

import torch
from torch import Tensor

from torchsvs.estimator import Inputs, SteppedEstimator, prepare_prior
from torchsvs.filters.gaussian import _at, kalman_update, step_input, step_interval
from torchsvs.filters.particle_gaussians import gaussian_draws, measurement_log_density
from torchsvs.linalg import cholesky, gaussian_log_density, mask_measurement, matvec
from torchsvs.models.base import LinearModel, StateSpaceModel, noise_factor
from torchsvs.resampling import SCHEMES, Scheme

#: Seed used when no generator is passed, so runs stay reproducible without global state.
DEFAULT_SEED = 20120601

#: The particle filter's proposals (see :class:`ParticleFilter`).
PFProposal = Literal["bootstrap", "optimal"]
PF_PROPOSALS: tuple[PFProposal, ...] = get_args(PFProposal)
#: A step is degenerate when its effective sample size falls below this share of the particles:
#: what :func:`degenerate_share` counts, and where a regularised filter redraws its particles.
DEGENERATE_SHARE = 0.1
#: False-alarm probability of the χ² test by which a regularised filter reads a measurement as
#: a maneuver its prediction does not cover (:meth:`ParticleFilter.gaussian_posterior`).
MANEUVER_ALPHA = 0.01


class ParticleResult(NamedTuple):
    """What a particle filter pass produced.

    Attributes:
        mean: weighted particle mean, ``[B, T, n]`` (Eq. (9)).
        cov: weighted particle covariance, ``[B, T, n, n]``.
        ess: effective sample size before resampling, ``[B, T]`` (Eq. (10)); the share of a
            track's steps where it fell below ``N/10`` is :func:`degenerate_share`.
        log_likelihood: ``Σ_t log`` of the mean unnormalised weight, ``[B]`` (with full
            importance weights, i.e. the bootstrap proposal or the SPVSF's
            ``proposal="particles"``, the log of an unbiased estimate of the marginal likelihood;
            for the SPVSF's other readings, a score with no such guarantee).
        particles: the last step's particles ``[B, N, n]``.
        log_weights: their normalised log-weights ``[B, N]``.
    """

    mean: Tensor
    cov: Tensor
    ess: Tensor
    log_likelihood: Tensor
    particles: Tensor
    log_weights: Tensor


class ParticleState(NamedTuple):
    """Everything a particle filter's next step needs (``est.init``, ``est.step``,
    ``est.scan``): a carry, never stored on the module.

    Attributes:
        particles: ``[B, N, n]``; log_weights: their normalised log-weights ``[B, N]``.
        log_likelihood: running sum since ``init``, ``[B]``.
        carry: what the proposal carries between steps (the SPVSF: its SVSF's estimate,
            covariance and memory), or ``None``.
        history: raw rows an artificial measurement still needs (the SPVSF), or ``None``.
        steps: steps taken since ``init``; single: ``init`` was given one track.
    """

    particles: Tensor
    log_weights: Tensor
    log_likelihood: Tensor
    carry: Any = None
    history: Any = None
    steps: int = 0
    single: bool = False


class _Moves(NamedTuple):
    """The optimal proposal's state: the model's matrices of the run and the step's proposal."""

    Q: Tensor  #: [n, n] or [B, T, n, n]
    H: Tensor | None  #: [m, n] for a linear h; None: linearised at each particle
    R: Tensor  #: [m, m]
    mu: Tensor | None = None  #: the step's proposal means [B, N, n] (a linear h)
    Sigma: Tensor | None = None  #: their shared covariance [B, 1, n, n]


class ParticleFilter(SteppedEstimator[ParticleResult]):
    r"""Sampling importance resampling (SIR) particle filter, Eqs. (5)-(10), Gadsden et al. 2012.

    Particles ``[B, N, n]`` start from ``N(x0, P0)``, move through the model with process noise
    (the bootstrap proposal, Eq. (6)), are weighted by the measurement likelihood (Eq. (7), in log
    space, over observed components only) and normalised (Eq. (8)); the estimate is the weighted
    mean (Eq. (9)). When the effective sample size (Eq. (10)) falls below
    ``resample_threshold · N`` the particles are resampled (systematic, stratified or
    multinomial, :mod:`torchsvs.resampling`) and the weights reset.

    ``proposal="optimal"`` draws each particle instead from the locally optimal proposal
    ``p(x_k | x_{k-1}^i, z_k)`` (Doucet, Godsill, Andrieu 2000, Sec. II.D: the proposal that
    minimises the variance of the weights given the past). For additive Gaussian process noise
    and a linear measurement ``z = H x + v`` it is the Kalman correction of ``N(f(xᵢ), Q)`` with
    ``z_k``: ``N(μᵢ, Σ)``, ``μᵢ = f(xᵢ) + K (z_k − H f(xᵢ))``, ``K = Q Hᵀ S⁻¹``,
    ``Σ = (I − KH) Q``, ``S = H Q Hᵀ + R``, and the incremental weight is
    ``p(z_k | x_{k-1}^i) = N(z_k; H f(xᵢ), S)``, whatever was drawn; the step's estimate then
    averages ``μᵢ`` rather than the draws (their conditional mean: Rao-Blackwell, with ``Σ``
    added to the covariance). The bootstrap weighs a cloud spread by ``Q`` with a likelihood of
    width ``R``: where ``H Q Hᵀ`` is large against ``R`` (long scan intervals, maneuvers taken as
    process noise) nearly every particle misses the measurement, the effective sample size
    collapses and a track can be lost for good; the optimal proposal moves every particle to the
    measurement and weighs only how well its past explains it. For a nonlinear ``h`` the proposal
    is that of ``h`` linearised at each particle's prediction (their Sec. II.D.2) with the full
    importance weight ``p(z | x) p(x | x_{k-1}^i) / q(x)``, so the filter stays consistent.

    ``regularize=True`` guards against the collapse a measurement far in the tail of the
    prediction causes (a maneuver the process noise does not cover, a track's start, a gap): the
    few particles the weights keep then understate the posterior's spread, the next prediction is
    too narrow, the next measurement further in its tail, and the track is lost. At every
    resampling the filter forms the Gaussian posterior of the step's prediction
    (:meth:`gaussian_posterior`: the weighted moments of ``f(x_{k-1}^i)`` plus ``Q``, widened by
    covariance matching where a χ² test reads the measurement as a maneuver, updated with ``z_k``
    in closed form). Where the resampled set's weighted covariance ``C`` falls short of that
    posterior's ``P``, each particle is moved by a draw from ``N(0, (P − C)₊)``: the
    post-regularised particle filter's kernel move after resampling (Musso, Oudjane, Le Gland
    2001), its covariance the shortfall rather than a bandwidth times ``C``, which vanishes with
    ``C``. Where the step is degenerate (``N_eff < N/10``, :data:`DEGENERATE_SHARE`), its few
    particles say little: the step's estimate is that Gaussian posterior and the particles are
    redrawn from it (the Gaussian particle filter's step, Kotecha, Djurić 2003). The filter is
    then no longer an exact particle filter of the model: it adds spread where the weights fall
    short of the Gaussian (on simulated nearly-constant-velocity tracks, where the model holds, it
    is closer to the Kalman filter than without: resampling alone impoverishes the cloud when
    ``Q`` is small), and follows maneuvers the model's ``Q`` does not cover.

    Gradients: particles are reparameterised (``x = f(x) + L_Q ε``), so parameters of the model
    receive gradients through them; resampling picks ancestors with a discrete draw and resets
    the weights, which stops the gradient through the weights there (the usual biased but
    low-variance estimator). ``soft_resampling=α`` instead draws ancestors from the mixture
    ``q = α w + (1 − α)/N`` and keeps the weights ``w/q`` (Karkus, Hsu, Lee 2018), so gradients
    also flow through the weights across resampling; ``α = 1`` is ordinary resampling.
    Randomness comes only from the ``generator=`` of the call (a fixed default seed otherwise).

    Args:
        model: any :class:`~torchsvs.models.StateSpaceModel`.
        num_particles: particles per track.
        resample_threshold: resample when ``N_eff < threshold · N`` (1 resamples every step).
        resampling: ``"systematic"``, ``"stratified"`` or ``"multinomial"``.
        soft_resampling: ``None`` (default) or the mixture weight ``α`` in ``(0, 1]``.
        proposal: ``"bootstrap"`` (default: the transition, Eq. (6)) or ``"optimal"`` (above).
        regularize: regularise the resampled particles (above; default False).

    References:
        Gordon, Salmond, Smith, "Novel approach to nonlinear/non-Gaussian Bayesian state
        estimation", IEE Proc. F 140(2), 1993 · Arulampalam, Maskell, Gordon, Clapp, IEEE TSP
        50(2), 2002 · Doucet, Godsill, Andrieu, "On sequential Monte Carlo sampling methods for
        Bayesian filtering", Statistics and Computing 10, 2000 · Musso, Oudjane, Le Gland,
        "Improving regularised particle filters", in Doucet, de Freitas, Gordon (eds.),
        Sequential Monte Carlo Methods in Practice, Springer, 2001 · Kotecha, Djurić, "Gaussian
        particle filtering", IEEE TSP 51(10), 2003.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        num_particles: int = 350,
        resample_threshold: float = 0.5,
        resampling: Scheme = "systematic",
        soft_resampling: float | None = None,
        proposal: PFProposal = "bootstrap",
        regularize: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(model, StateSpaceModel):
            raise TypeError(
                f"model: expected a torchsvs StateSpaceModel, got {type(model).__name__}"
            )
        if (
            isinstance(num_particles, bool)
            or not isinstance(num_particles, int)
            or num_particles < 2
        ):
            raise ValueError(f"num_particles: expected an integer >= 2, got {num_particles!r}")
        if not 0.0 <= resample_threshold <= 1.0:
            raise ValueError(
                f"resample_threshold: expected a value in [0, 1], got {resample_threshold!r}"
            )
        if resampling not in SCHEMES:
            raise ValueError(f"resampling: expected one of {sorted(SCHEMES)}, got {resampling!r}")
        if proposal not in PF_PROPOSALS:
            raise ValueError(f"proposal: expected one of {PF_PROPOSALS}, got {proposal!r}")
        if not isinstance(regularize, bool):
            raise TypeError(f"regularize: expected True or False, got {regularize!r}")
        self.model = model
        self.num_particles = num_particles
        self.resample_threshold = resample_threshold
        self.resampling = resampling
        if soft_resampling is not None and not 0.0 < soft_resampling <= 1.0:
            raise ValueError(
                f"soft_resampling: expected None or a value in (0, 1], got {soft_resampling!r}"
            )
        self.soft_resampling = soft_resampling
        self.proposal: str = proposal
        self.regularize = regularize

    def begin(self, inputs: Inputs, carry: Any, history: Any) -> Any:
        """The proposal's state for the steps of ``inputs`` (the bootstrap proposal: their
        ``Q``; the optimal one: ``Q``, ``H``, ``R``), from what it carried out of the steps
        before (``carry``, ``history``)."""
        model, dtype = self.model, inputs.z.dtype
        Q = model.process_noise(inputs.dt).to(dtype)
        if self.proposal == "bootstrap":
            return Q
        H = model.meas_matrix().to(dtype) if isinstance(model, LinearModel) else None
        return _Moves(Q, H, model.meas_cov().to(dtype))

    def initial_carry(self, x0: Tensor, P0: Tensor) -> Any:
        """What the proposal carries into the first step (the bootstrap proposal: nothing)."""
        return None

    def end(self, state: Any, inputs: Inputs, history: Any) -> tuple[Any, Any]:
        """What the proposal carries out of the steps of ``inputs``, and the raw rows kept."""
        return None, None

    def move(self, t: int, particles: Tensor, inputs: Inputs) -> Tensor:
        """``f(x_{t-1}^i)`` for every particle ``[B, N, n]`` (per-track ``dt`` and ``u``)."""
        B, N, n = particles.shape
        dt, u = step_interval(inputs, t), step_input(inputs, t)
        model = self.model
        if dt is not None and dt.ndim == 1 and isinstance(model, LinearModel) and u is None:
            # one F per track (not per particle), as LinearModel.f applies it
            F = model.transition(dt).to(particles.dtype).unsqueeze(1)  # [B, 1, n, n]
            return (F @ particles.unsqueeze(-1)).squeeze(-1)
        if dt is not None and dt.ndim == 1:
            dt = dt.repeat_interleave(N)
        if u is not None:
            u = u.repeat_interleave(N, dim=0)
        return self.model.f(particles.reshape(B * N, n), dt, u).reshape(B, N, n)

    def propose(
        self, t: int, particles: Tensor, state: Any, inputs: Inputs, gen: torch.Generator
    ) -> tuple[Tensor, Any, Tensor | None]:
        """Particles ``[B, N, n]`` of step ``t``, the proposal's state, and each particle's
        incremental log-weight ``[B, N]`` (``None`` where it is the likelihood of the particle,
        Eq. (7), as for this bootstrap proposal ``p(x_t | x_{t-1})``)."""
        if self.proposal == "optimal":
            return self._optimal(t, particles, state, inputs, gen)
        moved = self.move(t, particles, inputs)
        L = cholesky(_at(state, t))
        eps = torch.randn(*moved.shape, generator=gen, dtype=particles.dtype)
        return moved + eps @ L.mT, state, None

    def _optimal(
        self, t: int, particles: Tensor, moves: _Moves, inputs: Inputs, gen: torch.Generator
    ) -> tuple[Tensor, _Moves, Tensor]:
        """The optimal proposal's draws and incremental log-weights (class docstring): the
        Kalman correction of ``N(f(xᵢ), Q)`` with the step's observed components (none observed:
        the transition, weight 1)."""
        moved = self.move(t, particles, inputs)  # [B, N, n]
        B, N, n = moved.shape
        z = inputs.z[:, t]
        seen = ~torch.isnan(z)
        z = z.nan_to_num(0.0)
        Q = _at(moves.Q, t).unsqueeze(-3)  # [1|B, 1, n, n]: one Q for a track's particles
        if moves.H is None:  # h linearised at each particle's prediction
            fitted, H = self.model.linearize_h(moved.reshape(B * N, n))
            fitted, H = fitted.reshape(B, N, -1), H.reshape(B, N, -1, n).to(moved.dtype)
        else:
            fitted, H = moved @ moves.H.mT, moves.H
        H, R = mask_measurement(H, moves.R, seen.unsqueeze(1))  # [B, 1|N, m, ·]
        e = (z.unsqueeze(1) - fitted) * seen.unsqueeze(1)
        if moves.H is None:
            mu, Sigma, _, _, L_S = kalman_update(moved, Q, e, H, R)
        else:  # one gain per track: its K, Σ, S, then μᵢ = f(xᵢ) + K eᵢ for all particles
            x = moved.new_zeros(B, 1, n)
            _, Sigma, K, _, L_S = kalman_update(x, Q, e.new_zeros(B, 1, e.shape[-1]), H, R)
            mu = moved + e @ K.squeeze(1).mT
        eps = torch.randn(B, N, n, generator=gen, dtype=moved.dtype)
        factor = noise_factor(Sigma)  # [B, 1, n, n], or one per particle [B, N, n, n]
        if factor.shape[1] == 1:
            drawn = mu + eps @ factor.squeeze(1).mT
        else:
            drawn = mu + matvec(factor, eps)
        if moves.H is not None:  # log N(z; H f(xᵢ), S) over the observed components
            count = seen.sum(-1, keepdim=True).to(z.dtype)
            return drawn, moves._replace(mu=mu, Sigma=Sigma), gaussian_log_density(e, L_S, count)
        # the full weight p(z | x) p(x | f(xᵢ)) / q(x) of the linearised proposal
        log_q = gaussian_log_density(drawn - mu, cholesky(Sigma), 0.0)
        log_prior = gaussian_log_density(drawn - moved, cholesky(Q), 0.0)
        weight = self.log_likelihood(drawn, z, seen) + log_prior - log_q
        return drawn, moves._replace(mu=None, Sigma=None), weight

    def estimate_points(self, particles: Tensor, state: Any) -> tuple[Tensor, Tensor | None]:
        """The points whose weighted moments are the step's estimate, and a covariance to add:
        the particles, or with the optimal proposal and a linear ``h`` their proposal means
        ``μᵢ`` and covariance ``Σ`` (the draw's noise averaged out; the weights do not depend
        on it)."""
        if isinstance(state, _Moves) and state.mu is not None:
            return state.mu, state.Sigma
        return particles, None

    def gaussian_posterior(
        self, t: int, particles: Tensor, log_weights: Tensor, inputs: Inputs
    ) -> tuple[Tensor, Tensor]:
        """Mean ``[B, n]`` and covariance ``[B, n, n]`` (float64) of the Gaussian with the
        weighted moments of the prediction ``f(xᵢ)`` of the particles of step ``t − 1`` plus
        ``Q``, updated with the observed components of ``z_t`` (the Kalman update; ``h``
        linearised at the predicted mean where it is nonlinear).

        Where the normalised innovation squared ``ν`` of ``z_t`` against that prediction exceeds
        the ``1 − α`` quantile of ``χ²_m`` (``α`` = :data:`MANEUVER_ALPHA`, ``m`` the observed
        components), the predicted covariance is first scaled by ``ν/m`` (covariance matching:
        the prediction the measurement says the target needed; the noise-level adjustment on
        detection of Bar-Shalom, Li, Kirubarajan 2001, Ch. 11)."""
        model, f64 = self.model, torch.float64
        moved = self.move(t, particles, inputs).to(f64)
        w = log_weights.exp().to(f64)
        mean = torch.einsum("bn,bni->bi", w, moved)
        dev = moved - mean.unsqueeze(1)
        Q = model.process_noise(step_interval(inputs, t)).to(f64)
        cov = torch.einsum("bn,bni,bnj->bij", w, dev, dev) + Q
        z = inputs.z[:, t].to(f64)
        seen = ~torch.isnan(z)
        if isinstance(model, LinearModel):
            H = model.meas_matrix().to(f64)
            fitted = matvec(H, mean)
        else:
            fitted, H = model.linearize_h(mean)
            H = H.to(f64)
        H, R = mask_measurement(H, model.meas_cov().to(f64), seen)
        e = (z.nan_to_num(0.0) - fitted) * seen
        # Covariance matching on a detected maneuver: where z_t fails the χ² test against the
        # prediction, its covariance is scaled to make the normalised innovation its mean.
        L = cholesky(H @ cov @ H.mT + R)
        nis = torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False).square().sum((-2, -1))
        count = seen.sum(-1)
        gate = torch.tensor([_chi2_quantile(k, MANEUVER_ALPHA) for k in range(z.shape[-1] + 1)])
        scale = torch.where(nis > gate.to(f64)[count], nis / count.clamp_min(1), 1.0)
        x, P, _, _, _ = kalman_update(mean, cov * scale[:, None, None], e, H, R)
        return x, P

    def regularized(
        self,
        picked: Tensor,
        degenerate: Tensor,
        cov: Tensor,
        posterior: tuple[Tensor, Tensor],
        gen: torch.Generator,
    ) -> Tensor:
        """The resampled particles ``picked [B, N, n]`` regularised (class docstring): moved by
        ``N(0, (P − C)₊)``, ``C = cov`` the step's weighted covariance, or where ``degenerate``
        ``[B]``, redrawn from ``N(x, P)``, the step's :meth:`gaussian_posterior`."""
        B, N, n = picked.shape
        x, P = posterior
        with torch.no_grad():  # the kernel's width is a setting, not a path for gradients
            values, vectors = torch.linalg.eigh(P - cov.to(P.dtype))
            shortfall = vectors * values.clamp_min(0.0).sqrt().unsqueeze(-2)
        eps = torch.randn(B, N, n, generator=gen, dtype=picked.dtype)
        spread = picked + eps @ shortfall.to(picked.dtype).mT
        redrawn = x.to(picked.dtype).unsqueeze(1) + eps @ noise_factor(P).to(picked.dtype).mT
        return torch.where(degenerate[:, None, None], redrawn, spread)

    def finish_step(self, t: int, mean: Tensor, state: Any, inputs: Inputs) -> Any:
        """Hands the step's estimate back to the proposal's state."""
        return state

    def measure(self, particles: Tensor) -> Tensor:
        """``h(x_i)`` for every particle, ``[B, N, m]``."""
        B, N, n = particles.shape
        return self.model.h(particles.reshape(B * N, n)).reshape(B, N, -1)

    def log_likelihood(self, particles: Tensor, z: Tensor, mask: Tensor) -> Tensor:
        """``log p(z | x_i)`` per particle ``[B, N]`` over observed components (Eq. (7))."""
        return measurement_log_density(
            z, mask, self.measure(particles), self.model.meas_cov().to(z.dtype)
        )

    def _resample(
        self, particles: Tensor, log_w: Tensor, gen: torch.Generator
    ) -> tuple[Tensor, Tensor]:
        """Ancestors' particles and their new normalised log-weights (uniform unless soft)."""
        N = particles.shape[1]
        resample = SCHEMES[self.resampling]
        alpha = self.soft_resampling
        if alpha is None:
            index = resample(log_w.detach(), gen)
            kept = torch.full_like(log_w, -math.log(N))
        else:
            uniform = torch.full_like(log_w, math.log((1.0 - alpha) / N)) if alpha < 1 else None
            log_q = log_w if uniform is None else torch.logaddexp(log_w + math.log(alpha), uniform)
            index = resample(log_q.detach(), gen)
            ratio = (log_w - log_q).gather(1, index)
            kept = ratio - torch.logsumexp(ratio, dim=-1, keepdim=True)
        picked = particles.gather(1, index.unsqueeze(-1).expand(-1, -1, particles.shape[-1]))
        return picked, kept

    # --- The step protocol: init, step, scan; forward is init and one scan. ---

    def init(self, x0: Any, P0: Any, *, generator: torch.Generator | None = None) -> ParticleState:
        """Particles drawn from the prior ``N(x0, P0)`` (``x0 [B, n]`` or one track's ``[n]``)
        with ``generator`` (default: a fixed seed). Pass the same generator to every
        :meth:`step` or :meth:`scan` of the run: it then equals :meth:`forward` with it."""
        x0, P0, single = prepare_prior(self.model, x0, P0)
        return self._fresh(x0, P0, _generator(generator), single)

    state_type = ParticleState

    def state_prior(self, state: ParticleState) -> tuple[Tensor, Tensor]:
        # The steps start from the particles; only the batch of this "prior" is used.
        n = self.model.state_dim
        return state.particles[:, 0], torch.eye(n, dtype=state.particles.dtype).unsqueeze(0)

    def run(self, inputs: Inputs) -> ParticleResult:
        gen = _generator(inputs.generator)  # one generator for the prior draw and the steps
        return self._scan(
            self._fresh(inputs.x0, inputs.P0, gen, False), replace(inputs, generator=gen)
        )[1]

    def _fresh(self, x0: Tensor, P0: Tensor, gen: torch.Generator, single: bool) -> ParticleState:
        N = self.num_particles
        particles = gaussian_draws(x0, P0, N, gen)
        log_w = torch.full((x0.shape[0], N), -math.log(N), dtype=x0.dtype)
        zero = torch.zeros(x0.shape[0], dtype=x0.dtype)
        return ParticleState(particles, log_w, zero, self.initial_carry(x0, P0), single=single)

    def _scan(self, start: ParticleState, inputs: Inputs) -> tuple[ParticleState, ParticleResult]:
        gen = _generator(inputs.generator)
        z = inputs.z
        mask = ~torch.isnan(z)
        z_filled = z.nan_to_num(0.0)
        B, T = inputs.batch, inputs.steps
        N = self.num_particles
        particles, log_w = start.particles, start.log_weights
        state = self.begin(inputs, start.carry, start.history)
        means: list[Tensor] = []
        covs: list[Tensor] = []
        esss: list[Tensor] = []
        loglik = torch.zeros(B, dtype=z.dtype)
        for t in range(T):
            before = particles, log_w
            particles, state, log_increment = self.propose(t, particles, state, inputs, gen)
            if log_increment is None:
                log_increment = self.log_likelihood(particles, z_filled[:, t], mask[:, t])
            joint = log_w + log_increment  # Eq. (7)
            norm = torch.logsumexp(joint, dim=-1, keepdim=True)
            loglik = loglik + norm.squeeze(-1)
            log_w = joint - norm  # Eq. (8)
            w = log_w.exp()
            points, spread = self.estimate_points(particles, state)
            mean = torch.einsum("bn,bni->bi", w, points)  # Eq. (9)
            dev = points - mean.unsqueeze(1)
            cov = torch.einsum("bn,bni,bnj->bij", w, dev, dev)
            if spread is not None:
                cov = cov + spread.squeeze(-3)
            ess = 1.0 / w.square().sum(-1)  # Eq. (10)
            low = ess < self.resample_threshold * N
            posterior = None
            if self.regularize:
                degenerate = ess < DEGENERATE_SHARE * N
                low = low | degenerate
                if bool(low.any()):
                    posterior = self.gaussian_posterior(t, *before, inputs)
                    x, P = (v.to(cov.dtype) for v in posterior)
                    # a degenerate step's estimate is the Gaussian posterior's (class docstring)
                    weighted = cov
                    mean = torch.where(degenerate[:, None], x, mean)
                    cov = torch.where(degenerate[:, None, None], P, cov)
            means.append(mean)
            covs.append(cov)
            esss.append(ess)
            state = self.finish_step(t, mean, state, inputs)
            if bool(low.any()):
                picked, kept = self._resample(particles, log_w, gen)
                if posterior is not None:
                    picked = self.regularized(picked, degenerate, weighted, posterior, gen)
                particles = torch.where(low[:, None, None], picked, particles)
                log_w = torch.where(low[:, None], kept, log_w)
        carry, history = self.end(state, inputs, start.history)
        after = ParticleState(
            particles,
            log_w,
            start.log_likelihood + loglik,
            carry,
            history,
            start.steps + T,
            start.single,
        )
        result = ParticleResult(
            torch.stack(means, 1),
            torch.stack(covs, 1),
            torch.stack(esss, 1),
            loglik,
            particles,
            log_w,
        )
        return after, result


def _generator(generator: torch.Generator | None) -> torch.Generator:
    if generator is None:
        return torch.Generator().manual_seed(DEFAULT_SEED)
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator, got {type(generator).__name__}")
    return generator


def degenerate_share(
    result: ParticleResult, z: Tensor | None = None, share: float = DEGENERATE_SHARE
) -> Tensor:
    """Per track, the share of its steps whose effective sample size (``result.ess``) fell
    below ``share`` of the particles: ``[B]`` (a 0-d tensor for one track's result).

    With ``z`` (the measurements of the run, ``[B, T, m]`` or ``[T, m]``) only steps with an
    observed component count (the weights of the others do not change; padding past a track's
    end is not a step of it); a track without one gets 0. Where it is large the filter's
    particles said little: a regularised filter's estimate there is its Gaussian posterior, an
    unregularised one's rests on a handful of particles. On recorded airliners at 10 s scans
    with σ = 50 m noise the bootstrap's share is 0.4-0.8 (errors of 0.7-1.3 km), the regularised
    optimal proposal's 0.09-0.21 (errors below the Kalman filter's); a run can warn above 0.3.
    A collapse the ESS does not see, particles resampled from one ancestor with little process
    noise, shows in the estimate's distance from the measurements instead.
    """
    ess = result.ess
    if ess is None:
        raise ValueError("result: holds no ess (run with keep='all')")
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share: expected a value in (0, 1], got {share!r}")
    low = (ess < share * result.log_weights.shape[-1]).to(ess.dtype)
    if z is None:
        return low.mean(-1)
    if z.shape[:-1] != ess.shape:
        raise ValueError(
            f"z: expected the run's measurements, shape {(*tuple(ess.shape), 'm')}, got "
            f"{tuple(z.shape)}"
        )
    counted = (~torch.isnan(z)).any(-1).to(ess.dtype)
    return (low * counted).sum(-1) / counted.sum(-1).clamp_min(1.0)


@cache
def _chi2_quantile(k: int, alpha: float) -> float:
    """Upper ``alpha`` quantile of ``χ²_k`` (Wilson, Hilferty 1931: within 1% for ``k ≥ 1`` at
    ``alpha = 0.01``; 0 for ``k = 0``)."""
    if k == 0:
        return 0.0
    c = 2.0 / (9.0 * k)
    return k * (1.0 - c + NormalDist().inv_cdf(1.0 - alpha) * math.sqrt(c)) ** 3

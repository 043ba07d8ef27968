"""Particle filters: the SIR particle filter and the smooth particle variable structure filter."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike
from torchsvs.estimator import Estimator, Inputs
from torchsvs.filters.kalman import Observation, Step, _at, step_input, step_interval
from torchsvs.filters.svsf import SVSF, ArtificialMeasurement
from torchsvs.linalg import cholesky, mask_covariance
from torchsvs.models.base import StateSpaceModel
from torchsvs.resampling import SCHEMES

#: Seed used when no generator is passed, so runs stay reproducible without global state.
DEFAULT_SEED = 20120601


class ParticleResult(NamedTuple):
    """What a particle filter pass produced.

    Attributes:
        mean: weighted particle mean, ``[B, T, n]`` (Eq. (9)).
        cov: weighted particle covariance, ``[B, T, n, n]``.
        ess: effective sample size before resampling, ``[B, T]`` (Eq. (10)).
        log_likelihood: ``Σ_t log`` of the mean unnormalised weight, ``[B]`` (for the bootstrap
            proposal, an unbiased estimate of the marginal likelihood).
        particles: the last step's particles ``[B, N, n]``.
        log_weights: their normalised log-weights ``[B, N]``.
    """

    mean: Tensor
    cov: Tensor
    ess: Tensor
    log_likelihood: Tensor
    particles: Tensor
    log_weights: Tensor


def _gaussian(mean: Tensor, cov: Tensor, count: int, gen: torch.Generator) -> Tensor:
    """``count`` reparameterised draws per track from ``N(mean [B, n], cov [B|1, n, n])``."""
    L = cholesky(cov)
    eps = torch.randn(mean.shape[0], count, mean.shape[-1], generator=gen, dtype=mean.dtype)
    return mean.unsqueeze(1) + eps @ L.mT


class ParticleFilter(Estimator):
    r"""Sampling importance resampling (SIR) particle filter, Eqs. (5)-(10), Gadsden et al. 2012.

    Particles ``[B, N, n]`` start from ``N(x0, P0)``, move through the model with process noise
    (the bootstrap proposal, Eq. (6)), are weighted by the measurement likelihood (Eq. (7), in log
    space, over observed components only) and normalised (Eq. (8)); the estimate is the weighted
    mean (Eq. (9)). When the effective sample size (Eq. (10)) falls below
    ``resample_threshold · N`` the particles are resampled (systematic, stratified or
    multinomial, :mod:`torchsvs.resampling`) and the weights reset.

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

    References:
        Gordon, Salmond, Smith, "Novel approach to nonlinear/non-Gaussian Bayesian state
        estimation", IEE Proc. F 140(2), 1993 · Arulampalam, Maskell, Gordon, Clapp, IEEE TSP
        50(2), 2002.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        num_particles: int = 350,
        resample_threshold: float = 0.5,
        resampling: str = "systematic",
        soft_resampling: float | None = None,
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
        self.model = model
        self.num_particles = num_particles
        self.resample_threshold = resample_threshold
        self.resampling = resampling
        if soft_resampling is not None and not 0.0 < soft_resampling <= 1.0:
            raise ValueError(
                f"soft_resampling: expected None or a value in (0, 1], got {soft_resampling!r}"
            )
        self.soft_resampling = soft_resampling

    def begin(self, inputs: Inputs, gen: torch.Generator) -> Any:
        """Per-run state of the proposal (for the bootstrap proposal: ``Q`` of the run)."""
        return self.model.process_noise(inputs.dt).to(inputs.z.dtype)

    def propose(
        self, t: int, particles: Tensor, state: Any, inputs: Inputs, gen: torch.Generator
    ) -> tuple[Tensor, Any]:
        """Particles ``[B, N, n]`` of step ``t``: the bootstrap proposal ``p(x_t | x_{t-1})``."""
        B, N, n = particles.shape
        dt, u = step_interval(inputs, t), step_input(inputs, t)
        if dt is not None and dt.ndim == 1:
            dt = dt.repeat_interleave(N)
        if u is not None:
            u = u.repeat_interleave(N, dim=0)
        moved = self.model.f(particles.reshape(B * N, n), dt, u).reshape(B, N, n)
        L = cholesky(_at(state, t))
        eps = torch.randn(B, N, n, generator=gen, dtype=particles.dtype)
        return moved + eps @ L.mT, state

    def finish_step(self, t: int, mean: Tensor, state: Any, inputs: Inputs) -> Any:
        """Hands the step's estimate back to the proposal's state."""
        return state

    def log_likelihood(self, particles: Tensor, z: Tensor, mask: Tensor) -> Tensor:
        """``log p(z | x_i)`` per particle ``[B, N]`` over observed components (Eq. (7))."""
        B, N, n = particles.shape
        R = mask_covariance(self.model.meas_cov().to(z.dtype), mask)  # identity where missing
        predicted = self.model.h(particles.reshape(B * N, n)).reshape(B, N, -1)
        L = cholesky(R).unsqueeze(1)
        residual = ((z.unsqueeze(1) - predicted) * mask.unsqueeze(1)).unsqueeze(-1)
        white = torch.linalg.solve_triangular(L, residual, upper=False).squeeze(-1)
        log_det = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        observed = mask.sum(-1, keepdim=True).to(z.dtype)
        return -0.5 * (white.square().sum(-1) + log_det + observed * math.log(2 * math.pi))

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

    def run(self, inputs: Inputs) -> ParticleResult:
        gen = (
            inputs.generator
            if inputs.generator is not None
            else torch.Generator().manual_seed(DEFAULT_SEED)
        )
        z = inputs.z
        mask = ~torch.isnan(z)
        z_filled = z.nan_to_num(0.0)
        B, T = inputs.batch, inputs.steps
        N = self.num_particles
        particles = _gaussian(inputs.x0, inputs.P0, N, gen)
        log_w = torch.full((B, N), -math.log(N), dtype=z.dtype)
        state = self.begin(inputs, gen)
        means, covs, esss, loglik = [], [], [], torch.zeros(B, dtype=z.dtype)
        for t in range(T):
            particles, state = self.propose(t, particles, state, inputs, gen)
            log_lik = self.log_likelihood(particles, z_filled[:, t], mask[:, t])
            joint = log_w + log_lik  # Eq. (7)
            norm = torch.logsumexp(joint, dim=-1, keepdim=True)
            loglik = loglik + norm.squeeze(-1)
            log_w = joint - norm  # Eq. (8)
            w = log_w.exp()
            mean = torch.einsum("bn,bni->bi", w, particles)  # Eq. (9)
            dev = particles - mean.unsqueeze(1)
            means.append(mean)
            covs.append(torch.einsum("bn,bni,bnj->bij", w, dev, dev))
            ess = 1.0 / w.square().sum(-1)  # Eq. (10)
            esss.append(ess)
            state = self.finish_step(t, mean, state, inputs)
            low = ess < self.resample_threshold * N
            if bool(low.any()):
                picked, kept = self._resample(particles, log_w, gen)
                particles = torch.where(low[:, None, None], picked, particles)
                log_w = torch.where(low[:, None], kept, log_w)
        return ParticleResult(
            torch.stack(means, 1),
            torch.stack(covs, 1),
            torch.stack(esss, 1),
            loglik,
            particles,
            log_w,
        )


class SPVSF(ParticleFilter):
    r"""Smooth particle variable structure filter, Eqs. (23)-(35), Gadsden et al. 2012.

    An SVSF step (Eqs. (23)-(29): prediction, innovation, SVSF gain, Joseph covariance) on the
    previous estimate gives ``x̂_{k+1|k+1}``, ``P_{k+1|k+1}``; the particles are drawn from
    ``N(x̂_{k+1|k+1}, P_{k+1|k+1})`` (the proposal, Eq. (30)), weighted by the likelihood times
    their previous weight as the paper writes (Eq. (31); the transition-over-proposal factor of a
    full importance weight is omitted, as in the paper), normalised (Eq. (32)); the weighted mean
    is the estimate (Eq. (33)) and the next SVSF step starts from it, its covariance and the
    a-posteriori innovation ``z − h(x̂)`` (Eqs. (34)-(35)). The SVSF part is :class:`SVSF` itself
    (its predictor and corrector), so ψ and γ are its learnable parameters; particles are
    reparameterised draws, so ψ and γ receive gradients through them.

    Args:
        model: any :class:`~torchsvs.models.StateSpaceModel`.
        psi, gamma, learn, artificial: as for :class:`SVSF`.
        num_particles: particles per track (350 in the paper).
        resample_threshold: resample when ``N_eff < threshold · N`` (the paper's 0.8).
        resampling: ``"systematic"``, ``"stratified"`` or ``"multinomial"``.

    References:
        Gadsden, Habibi, Kirubarajan, "The Smooth Particle Variable Structure Filter", Trans.
        CSME 36(2), 2012.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        psi: ArrayLike,
        gamma: float | Tensor = 0.1,
        num_particles: int = 350,
        resample_threshold: float = 0.8,
        resampling: str = "systematic",
        learn: bool = True,
        artificial: ArtificialMeasurement | None = None,
    ) -> None:
        super().__init__(model, num_particles, resample_threshold, resampling)
        self.svsf = SVSF(model, psi=psi, gamma=gamma, learn=learn, artificial=artificial)

    class _State(NamedTuple):
        x: Tensor  # [B, n] the estimate the next SVSF step starts from
        P: Tensor  # [B|1, n, n]
        previous: Step | None  # the SVSF's last step (its memory e_{k|k})
        z: Tensor  # the SVSF's measurements [B, T, m'] (NaN filled with 0)
        mask: Tensor | None  # None when nothing is missing
        H: Tensor | None
        R: Tensor
        F: Tensor | None
        Q: Tensor

    def begin(self, inputs: Inputs, gen: torch.Generator) -> Any:
        z, H, R = self.svsf.measurements(inputs)
        F, Q = self.svsf.dynamics(inputs)
        mask = ~torch.isnan(z)
        observed = None if bool(mask.all()) else mask
        return self._State(inputs.x0, inputs.P0, None, z.nan_to_num(0.0), observed, H, R, F, Q)

    def propose(
        self, t: int, particles: Tensor, state: Any, inputs: Inputs, gen: torch.Generator
    ) -> tuple[Tensor, Any]:
        s: SPVSF._State = state
        x_pred, P_pred, _ = self.svsf.predict(t, s.x, s.P, s.F, s.Q, inputs)  # Eqs. (23)-(24)
        mask_t = None if s.mask is None else s.mask[:, t]
        H_t = None if s.H is None else _at(s.H, t)
        obs = Observation(t, s.z[:, t], mask_t, H_t, _at(s.R, t))
        step = self.svsf.correct(x_pred, P_pred, obs, s.previous, inputs)  # Eqs. (25)-(29)
        drawn = _gaussian(step.mean, step.cov, particles.shape[1], gen)  # Eq. (30)
        return drawn, s._replace(P=step.cov, previous=step)

    def finish_step(self, t: int, mean: Tensor, state: Any, inputs: Inputs) -> Any:
        s: SPVSF._State = state
        assert s.previous is not None
        # Eqs. (33)-(35): the particle mean is the estimate and its innovation the SVSF memory.
        H = None if s.H is None else _at(s.H, t)
        fitted = self.model.h(mean) if H is None else (H @ mean.unsqueeze(-1)).squeeze(-1)
        e_post = s.z[:, t] - fitted
        if s.mask is not None:
            assert s.previous.post_innovation is not None
            e_post = torch.where(s.mask[:, t], e_post, s.previous.post_innovation)
        return s._replace(x=mean, previous=s.previous._replace(post_innovation=e_post))

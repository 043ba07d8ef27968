"""The smooth particle variable structure filter (SPVSF, Gadsden et al. 2012): a particle
filter whose proposal is built from an SVSF step."""

from __future__ import annotations

from typing import Any, Literal, NamedTuple, get_args

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike
from torchsvs.estimator import Inputs
from torchsvs.filters.gaussian import Observation, Prepared, _at
from torchsvs.filters.particle import ParticleFilter
from torchsvs.filters.particle_gaussians import (
    gaussian_draws,
    log_normal,
    measurement_log_density,
)
from torchsvs.filters.svsf import SVSF, ArtificialMeasurement, VariableBoundarySVSF
from torchsvs.linalg import cholesky, joseph_update
from torchsvs.models.base import StateSpaceModel
from torchsvs.resampling import Scheme

#: The SPVSF's readings of Eqs. (30)-(31) (see :class:`SPVSF`).
Proposal = Literal["adapted", "estimate", "particles"]
PROPOSALS: tuple[Proposal, ...] = get_args(Proposal)


class SPVSF(ParticleFilter):
    r"""Smooth particle variable structure filter, Eqs. (23)-(35), Gadsden et al. 2012.

    Every step, an SVSF step (Eqs. (23)-(29): prediction, innovation, SVSF gain ``K``, Joseph
    covariance) on the previous estimate gives ``x̂_{k+1|k+1}``, ``P_{k+1|k+1}``; the SVSF's
    correction forms the particles' proposal (Eq. (30)), the particles are weighted (Eq. (31)) and
    normalised (Eq. (32)), the weighted mean is the estimate (Eq. (33)), and the next SVSF step
    starts from it, its covariance and the a-posteriori innovation ``z − h(x̂)`` (Eqs. (34)-(35)).
    The SVSF part is :class:`SVSF` itself (its predictor and corrector), so ψ and γ are its
    learnable parameters; particles are reparameterised draws, so ψ and γ receive gradients
    through them. Eqs. (30)-(31) can be read three ways (``proposal=``), measured side by side in
    ``experiments/spvsf_paper.py``:

    ``"adapted"`` (default). The paper builds the SPVSF "similar to the EPF and UPF", whose
    particles each carry their own local filter, and Eq. (31) multiplies each particle's weight
    by its previous one, so particles descend from the previous ones: each moves through the
    model, ``x̄ᵢ = f(xᵢ)``, is corrected with the step's SVSF gain (computed once, at the
    estimate), ``μᵢ = x̄ᵢ + K (z − h(x̄ᵢ))``, and is drawn from ``N(μᵢ, Σ)``,
    ``Σ = (I − KH) Q (I − KH)ᵀ + K R Kᵀ`` (Eq. (29) for one particle, whose prediction has
    covariance ``Q``). Its weight is ``w_prev · p(z | x̄ᵢ)``, ``p(z | x̄ᵢ) = N(z; h(x̄ᵢ), H Q Hᵀ +
    R)`` (``H`` the Jacobian of ``h`` at the prediction): the likelihood of the measurement under
    the particle's own prediction, before its correction, which is the weight of the "optimal"
    proposal ``p(x | x̄ᵢ, z)`` (Doucet, Godsill, Andrieu 2000) that the SVSF-corrected draw stands
    in for. A particle is judged by how well its history explains ``z``, including components the
    measurement does not see (the EHA's bulk modulus); the correction then moves it. With the
    Kalman gain in place of the SVSF's this would be the exact optimal-proposal particle filter;
    with the SVSF's gain the draw is not the distribution the weight assumes, so it is not
    consistent (on a linear-Gaussian model it stays off the KF however many particles: tested,
    within 0.35σ on average and beyond 0.5σ somewhere) and, like the SVSF, it is not held back
    by a narrow prior far from the truth.

    ``"estimate"``: Eqs. (30)-(31) as printed. The particles are drawn afresh from
    ``N(x̂_{k+1|k+1}, P_{k+1|k+1})`` around the SVSF estimate and weighted by the likelihood of
    the drawn particle times the previous weight of the particle with the same index (the
    transition-over-proposal factor of a full importance weight is omitted, as in the paper).
    The particles do not descend from the previous ones, so the weights never test a component
    the measurement does not see: there the estimate is the SVSF's plus the sampling noise of
    the particle mean.

    ``"particles"``: the draw of ``"adapted"`` with the full importance weight
    ``w_prev · p(z | x) p(x | x̄ᵢ) / q(x)``: the extended and unscented particle filters' own
    construction (van der Merwe et al. 2000) with the SVSF as the local filter. It is a
    consistent particle filter (it approaches the Kalman filter on a linear-Gaussian model as
    particles grow, tested), so it honours the prior ``P0`` as stated, narrow or not.

    With an artificial measurement, ``z``, ``h`` and ``R`` of the corrections are the SVSF's
    full-state ones, while the weights use the real measurement.

    Args:
        model: any :class:`~torchsvs.models.StateSpaceModel`.
        psi, gamma, learn, artificial, psi_units: as for :class:`SVSF`.
        variable_boundary: the SVSF part is a
            :class:`~torchsvs.filters.VariableBoundarySVSF` (the Kalman gain inside its layer,
            ψ its limit in innovation standard deviations; ``artificial`` must be ``None``).
        num_particles: particles per track (350 in the paper).
        resample_threshold: resample when ``N_eff < threshold · N`` (the paper's 0.8).
        resampling: ``"systematic"``, ``"stratified"`` or ``"multinomial"``.
        proposal: ``"adapted"``, ``"estimate"`` or ``"particles"`` (above).
        soft_resampling, regularize: as for :class:`ParticleFilter`.

    References:
        Gadsden, Habibi, Kirubarajan, "The Smooth Particle Variable Structure Filter", Trans.
        CSME 36(2), 2012 · van der Merwe, Doucet, de Freitas, Wan, "The unscented particle
        filter", NIPS 13, 2000 · Doucet, Godsill, Andrieu, "On sequential Monte Carlo
        sampling methods for Bayesian filtering", Statistics and Computing 10, 2000.
    """

    def __init__(
        self,
        model: StateSpaceModel,
        psi: ArrayLike,
        gamma: float | Tensor = 0.1,
        num_particles: int = 350,
        resample_threshold: float = 0.8,
        resampling: Scheme = "systematic",
        learn: bool = True,
        artificial: ArtificialMeasurement | str | None = "auto",
        proposal: Proposal = "adapted",
        soft_resampling: float | None = None,
        regularize: bool = False,
        variable_boundary: bool = False,
        psi_units: str = "absolute",
    ) -> None:
        super().__init__(
            model,
            num_particles,
            resample_threshold,
            resampling,
            soft_resampling,
            regularize=regularize,
        )
        if proposal not in PROPOSALS:
            raise ValueError(f"proposal: expected one of {PROPOSALS}, got {proposal!r}")
        self.proposal = proposal
        self.svsf: SVSF
        if variable_boundary:
            if artificial is not None or psi_units != "absolute":
                raise ValueError(
                    "variable_boundary: its limit is in innovation standard deviations, with the "
                    f"model's own measurement: expected artificial=None and psi_units='absolute', "
                    f"got {artificial!r} and {psi_units!r}"
                )
            self.svsf = VariableBoundarySVSF(model, psi=psi, gamma=gamma, learn=learn)
        else:
            self.svsf = SVSF(
                model, psi=psi, gamma=gamma, learn=learn, artificial=artificial, psi_units=psi_units
            )

    class _State(NamedTuple):
        x: Tensor  # [B, n] the estimate the next SVSF step starts from
        P: Tensor  # [B|1, n, n]
        post_innovation: Tensor | None  # the SVSF's memory e_{k|k} (None before the first step)
        prep: Prepared  # the SVSF's run: its measurements, mask and model matrices
        obs: Observation | None  # the SVSF's observation of the step under way

    def begin(self, inputs: Inputs, carry: Any, history: Any) -> Any:
        x, P, memory = carry
        return self._State(x, P, memory, self.svsf.prepare(inputs, history), None)

    def initial_carry(self, x0: Tensor, P0: Tensor) -> Any:
        return x0, P0, None  # the SVSF starts from the prior, without memory

    def end(self, state: Any, inputs: Inputs, history: Any) -> tuple[Any, Any]:
        s: SPVSF._State = state
        return (s.x, s.P, s.post_innovation), self.svsf.carried_history(history, inputs)

    def takes_psi(self) -> bool:
        return False  # ψ is its SVSF's parameter; a per-step override is not wired through

    def propose(
        self, t: int, particles: Tensor, state: Any, inputs: Inputs, gen: torch.Generator
    ) -> tuple[Tensor, Any, Tensor | None]:
        s: SPVSF._State = state
        # Eqs. (23)-(29): the SVSF's own step from the previous estimate.
        x_pred, _, _, step = self.svsf.filter_step(t, s.x, s.P, s.post_innovation, s.prep, inputs)
        obs = s.prep.observation(t)
        state = s._replace(P=step.cov, post_innovation=step.post_innovation, obs=obs)
        N = particles.shape[1]
        if self.proposal == "estimate":
            return gaussian_draws(step.mean, step.cov, N, gen), state, None  # Eq. (30)
        # Eq. (30) per particle: moved, corrected with the step's gain, drawn (class docstring).
        moved = self.move(t, particles, inputs)
        H_t = obs.H
        if H_t is None:  # a nonlinear h, linearised at the estimate by the SVSF step
            assert step.meas_matrix is not None
            H_t = step.meas_matrix
            e = obs.z.unsqueeze(1) - self.measure(moved)
        else:
            e = obs.z.unsqueeze(1) - moved @ H_t.mT
        if obs.mask is not None:
            e = e * obs.mask.unsqueeze(1)
        K = step.gain
        mu = moved + e @ K.mT
        Q = _at(s.prep.Q, t).to(moved.dtype)
        L_q = cholesky(joseph_update(Q, K, H_t, obs.R))  # (I − KH) Q (I − KH)ᵀ + K R Kᵀ
        drawn = mu + torch.randn(*mu.shape, generator=gen, dtype=mu.dtype) @ L_q.mT
        # The weights use the real measurement (not an artificial one).
        z = inputs.z[:, t]
        seen, z = ~torch.isnan(z), z.nan_to_num(0.0)
        if self.proposal == "particles":  # the full importance weight
            log_ratio = log_normal(drawn, moved, cholesky(Q)) - log_normal(drawn, mu, L_q)
            return drawn, state, self.log_likelihood(drawn, z, seen) + log_ratio
        # Eq. (31), "adapted": p(z | x̄ᵢ) = N(z; h(x̄ᵢ), H Q Hᵀ + R), H at the prediction: the
        # corrector's own, unless it corrects with an artificial measurement.
        H = H_t if self.svsf.artificial is None else self.model.h_jacobian(x_pred).to(moved.dtype)
        S = H @ Q @ H.mT + self.model.meas_cov().to(moved.dtype)
        return drawn, state, measurement_log_density(z, seen, self.measure(moved), S)

    def finish_step(self, t: int, mean: Tensor, state: Any, inputs: Inputs) -> Any:
        s: SPVSF._State = state
        assert s.post_innovation is not None and s.obs is not None
        # Eqs. (33)-(35): the particle mean is the estimate and its innovation the SVSF memory.
        return s._replace(
            x=mean, post_innovation=self.svsf.memory_after(mean, s.obs, s.post_innovation)
        )

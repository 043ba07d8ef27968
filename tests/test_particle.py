"""Particle filter and SPVSF: agreement with the KF, reproducibility, gradients, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, random_system
from tests.test_nonlinear import _ballistic_run


def test_many_particles_approach_the_kalman_filter():
    system = random_system(2, 1, T=12, B=2, seed=4)
    z, x0, P0 = system.tensors()
    kf = ts.KalmanFilter(system.model())(z, x0, P0)
    pf = ts.ParticleFilter(system.model(), num_particles=40000, resample_threshold=0.5)
    out = pf(z, x0, P0, generator=torch.Generator().manual_seed(0))
    std = kf.cov.diagonal(dim1=-2, dim2=-1).sqrt()
    # Monte Carlo error of a weighted mean ~ std / sqrt(N_eff): N_eff ≥ 2000 gives ≤ 0.02 std.
    assert bool((out.ess >= 2000).all())
    assert float(((out.mean - kf.mean).abs() / std).max()) < 0.1
    scale = std.unsqueeze(-1) * std.unsqueeze(-2)
    assert float(((out.cov - kf.cov).abs() / scale).max()) < 0.1
    # The marginal likelihood estimate is unbiased and concentrated for this many particles.
    assert_close(out.log_likelihood, kf.log_likelihood, atol=0.05, rtol=0)


@pytest.mark.parametrize("psi", [0.5, 3.0])
def test_spvsf_particle_proposal_is_a_consistent_particle_filter(psi):
    # With the full importance weight the SVSF-guided proposal targets the exact posterior:
    # on a linear-Gaussian model it approaches the KF as particles grow, whatever ψ is.
    system = random_system(2, 1, T=12, B=2, seed=4)
    z, x0, P0 = system.tensors()
    kf = ts.KalmanFilter(system.model())(z, x0, P0)
    spvsf = ts.SPVSF(system.model(), psi=psi, num_particles=20000, proposal="particles")
    with torch.no_grad():
        out = spvsf(z, x0, P0, generator=torch.Generator().manual_seed(0))
    std = kf.cov.diagonal(dim1=-2, dim2=-1).sqrt()
    assert bool((out.ess >= 1000).all())  # Monte Carlo error of the mean ≤ 0.03 std
    assert float(((out.mean - kf.mean).abs() / std).max()) < 0.1
    assert_close(out.log_likelihood, kf.log_likelihood, atol=0.1, rtol=0)
    # The other readings omit the transition-over-proposal factor and are not consistent: Eqs.
    # (30)-(31) as printed miss the KF by over 0.5σ on average, the default ("adapted", weighted
    # by the predictive likelihood) stays within 0.35σ on average but not everywhere.
    off = {}
    for proposal in ("estimate", "adapted"):
        with torch.no_grad():
            other = ts.SPVSF(system.model(), psi=psi, num_particles=20000, proposal=proposal)(
                z, x0, P0, generator=torch.Generator().manual_seed(0)
            )
        off[proposal] = (other.mean - kf.mean).abs() / std
    assert float(off["estimate"].mean()) > 0.5
    assert float(off["adapted"].mean()) < 0.35 < 0.5 < float(off["adapted"].max())


def test_adapted_weight_is_the_predictive_likelihood():
    # Eq. (31), default reading: a particle's incremental log-weight is
    # log N(z; H F xᵢ, H Q Hᵀ + R) over the observed components, against a NumPy evaluation.
    from torchsvs.estimator import Inputs

    system = random_system(3, 2, T=3, B=2, seed=7)
    z_np = system.z.copy()
    z_np[1, 0, 1] = np.nan  # track 1: only the first component is observed at step 0
    z, x0, P0 = torch.from_numpy(z_np), *system.tensors()[1:]
    x0 = x0.expand(2, 3).clone()
    spvsf = ts.SPVSF(system.model(), psi=2.0, num_particles=6)
    gen = torch.Generator().manual_seed(0)
    inputs = Inputs(z, x0, P0.unsqueeze(0), None, None, None, gen, False)
    particles = x0.unsqueeze(1) + torch.randn(2, 6, 3, generator=gen, dtype=z.dtype)
    state = spvsf.begin(inputs, spvsf.initial_carry(x0, P0.unsqueeze(0)), None)
    _, _, log_w = spvsf.propose(0, particles, state, inputs, gen)
    F, H, Q, R = system.F, system.H, system.Q, system.R
    S = H @ Q @ H.T + R
    expected = np.empty((2, 6))
    for b in range(2):
        seen = ~np.isnan(z_np[b, 0])
        S_b = S[np.ix_(seen, seen)]
        for i in range(6):
            r = z_np[b, 0][seen] - (H @ F @ particles[b, i].numpy())[seen]
            expected[b, i] = -0.5 * (
                r @ np.linalg.solve(S_b, r) + np.log(np.linalg.det(2 * np.pi * S_b))
            )
    assert seen.tolist() == [True, False]  # the missing component was seen as missing
    assert_close(log_w, torch.from_numpy(expected))


@pytest.mark.parametrize("kind", ["pf", "adapted", "estimate", "particles"])
def test_seeded_runs_reproduce_and_seeds_differ(kind):
    model, truth, z, x0, P0 = _ballistic_run(T=30, B=3, seed=1)
    est = (
        ts.ParticleFilter(model, 200)
        if kind == "pf"
        else ts.SPVSF(model, psi=[300.0, 100.0], num_particles=200, proposal=kind)
    )
    a = est(z, x0, P0, generator=torch.Generator().manual_seed(5))
    b = est(z, x0, P0, generator=torch.Generator().manual_seed(5))
    c = est(z, x0, P0, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a.mean, b.mean)
    assert (a.mean - c.mean).abs().max() > 0
    assert ts.metrics.accumulative_rmse(a.mean, truth)[0] < 100.0
    assert a.mean.shape == (3, 30, 3) and a.cov.shape == (3, 30, 3, 3) and a.ess.shape == (3, 30)


@pytest.mark.parametrize("proposal", ["adapted", "estimate", "particles"])
def test_spvsf_gradients_reach_psi_and_gamma(proposal):
    model, truth, z, x0, P0 = _ballistic_run(T=25, B=2, seed=2)
    spvsf = ts.SPVSF(model, psi=[300.0, 100.0], gamma=0.2, num_particles=64, proposal=proposal)
    out = spvsf(z, x0, P0, generator=torch.Generator().manual_seed(0))
    (out.mean - truth).square().mean().backward()
    for p in (spvsf.svsf.boundary_layer.raw, spvsf.svsf.memory.raw):
        assert (
            p.grad is not None and bool(torch.isfinite(p.grad).all()) and bool((p.grad != 0).any())
        )


def test_missing_measurements_are_skipped():
    model, truth, z, x0, P0 = _ballistic_run(T=20, B=2, seed=3)
    z = z.clone()
    z[:, 7] = float("nan")
    z[0, 11, 1] = float("nan")
    for est in (
        ts.ParticleFilter(model, 300),
        *(
            ts.SPVSF(model, psi=[300.0, 100.0], num_particles=300, proposal=proposal)
            for proposal in ("adapted", "estimate", "particles")
        ),
    ):
        out = est(z, x0, P0, generator=torch.Generator().manual_seed(0))
        assert bool(torch.isfinite(out.mean).all()) and bool(
            torch.isfinite(out.log_likelihood).all()
        )


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"num_particles": 1}, "^num_particles: expected an integer >= 2"),
        ({"resample_threshold": 1.5}, r"^resample_threshold: expected a value in \[0, 1\]"),
        ({"resampling": "residual"}, "^resampling: expected one of"),
    ],
)
def test_bad_particle_settings(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        ts.ParticleFilter(ts.models.BallisticReentry(), **kwargs)


def test_spvsf_paper_rmse_counts_the_initial_estimate():
    from experiments.spvsf_paper import BALLISTIC_PSI, evaluate, paper_rmse

    truth = torch.zeros(2, 3, 1, dtype=torch.float64)
    mean = torch.ones(2, 3, 1, dtype=torch.float64)
    x0, true_x0 = torch.tensor([2.0], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64)
    assert_close(
        paper_rmse(mean, truth, x0, true_x0),
        torch.tensor([((4 + 3) / 4) ** 0.5], dtype=torch.float64),
    )
    sc = ts.scenarios.ballistic_scenario(3, torch.Generator().manual_seed(0), duration=2.0)
    out = evaluate(
        sc, torch.tensor([61000.0, 3048.0, 19161.0], dtype=torch.float64), BALLISTIC_PSI, 0
    )
    assert set(out) == {"EKF", "UKF", "PF", "SVSF", "SPVSF"}
    assert all(bool(torch.isfinite(v).all()) for v in out.values())


def test_settling_time_is_the_time_the_error_stays_within_the_bound():
    from experiments.spvsf_paper import settling_time

    truth = torch.zeros(3, 5, 1, dtype=torch.float64)
    err = torch.tensor([[9.0, 0.5, 9.0, 0.5, 0.5], [0.5] * 5, [0.5, 0.5, 0.5, 0.5, 9.0]])
    times = settling_time(truth + err.unsqueeze(-1).double(), truth, 0.1, 1.0)
    # run 0 leaves the bound last at step 2 (t = 0.3 s): within from step 3 (t = 0.4 s)
    assert_close(times[:2], torch.tensor([0.4, 0.1], dtype=torch.float64))
    assert bool(torch.isinf(times[2]))


def test_soft_resampling():
    model, truth, z, x0, P0 = _ballistic_run(T=25, B=2, seed=4)

    def run(alpha):
        spvsf = ts.SPVSF(model, psi=[300.0, 100.0], num_particles=64, resample_threshold=1.0)
        spvsf.soft_resampling = alpha
        out = spvsf(z, x0, P0, generator=torch.Generator().manual_seed(0))
        (out.mean - truth).square().mean().backward()
        return out, spvsf.svsf.boundary_layer.raw.grad.clone()

    hard, g_hard = run(None)
    one, g_one = run(1.0)
    assert_close(one.mean, hard.mean)  # α = 1 is ordinary resampling
    assert_close(g_one, g_hard)
    soft, g_soft = run(0.5)
    assert bool(torch.isfinite(soft.mean).all()) and bool(torch.isfinite(g_soft).all())
    assert (soft.log_weights.exp().std(-1) > 0).all()  # weights survive resampling
    with pytest.raises(ValueError, match=r"^soft_resampling: expected None or a value in \(0, 1\]"):
        ts.ParticleFilter(model, soft_resampling=0.0)


def test_spvsf_paper_done_when_orderings_on_fewer_runs():
    # Issue 5's acceptance on 20 ballistic runs (the experiment uses 100): SPVSF altitude below
    # SVSF, UKF and EKF at the experiment's ψ, and within 10% of it with the gravity error.
    from experiments.spvsf_paper import BALLISTIC_PSI, BALLISTIC_TRUE_X0, evaluate

    true_x0 = torch.tensor(BALLISTIC_TRUE_X0, dtype=torch.float64)
    nominal = ts.scenarios.ballistic_scenario(20, torch.Generator().manual_seed(5))
    gravity = ts.scenarios.ballistic_scenario(
        20, torch.Generator().manual_seed(5), gravity_error_at=15.0
    )
    alt = {
        k: float(v[:, 0].mean()) for k, v in evaluate(nominal, true_x0, BALLISTIC_PSI, 5).items()
    }
    assert alt["SPVSF"] < min(alt["SVSF"], alt["UKF"], alt["EKF"]), alt
    with_error = evaluate(gravity, true_x0, BALLISTIC_PSI, 5)["SPVSF"][:, 0].mean()
    assert abs(float(with_error) / alt["SPVSF"] - 1) < 0.1


def test_bad_spvsf_proposal():
    with pytest.raises(ValueError, match=r"^proposal: expected one of \('adapted', 'estimate', "):
        ts.SPVSF(ts.models.BallisticReentry(), psi=[1.0, 1.0], proposal="bootstrap")


@pytest.mark.parametrize("kind", ["pf", "adapted", "estimate", "particles"])
def test_gradients_reach_learnable_q_and_r_through_particles(kind):
    # Reparameterised particles: a learnable Q, R (Cholesky factors) gets finite, nonzero
    # gradients through the particle filters, as ψ and γ do.
    system = random_system(2, 1, T=10, B=2, seed=6)
    z, x0, P0 = system.tensors()
    F, H, Q, R = (torch.from_numpy(a) for a in (system.F, system.H, system.Q, system.R))
    model = ts.models.LinearGaussian(F, H, Q, R, learn_noise=True).double()
    est = (
        ts.ParticleFilter(model, num_particles=64)
        if kind == "pf"
        else ts.SPVSF(model, psi=2.0, num_particles=64, proposal=kind)
    )
    out = est(z, x0, P0, generator=torch.Generator().manual_seed(0))
    out.mean.square().mean().backward()  # any loss of the estimate
    for p in (model.Q.raw, model.R.raw):
        assert p.grad is not None and bool(torch.isfinite(p.grad).all())
        assert bool((p.grad != 0).any())


def test_eha_modulus_claims_of_the_three_spvsf_readings():
    # The results file's EHA claims on fewer runs: the default SPVSF ("adapted") and the particle
    # proposal weigh each particle's modulus through its dynamics and do better than the SVSF;
    # Eqs. (30)-(31) as printed move the modulus only by sampling noise around the SVSF's (their
    # weights do not see it).
    from experiments.spvsf_paper import EHA_PSI, estimators, run, run_rmse, variants

    sc = ts.scenarios.eha_scenario(6, torch.Generator().manual_seed(2), changing=True, duration=1.2)
    true_x0 = torch.tensor([0.0, 0.0, 0.0, 2.1e8], dtype=torch.float64)
    rows = {name: (est, sc.P0) for name, est in estimators(sc.model, EHA_PSI).items()}
    rows |= variants(sc, EHA_PSI)
    names = ("SVSF", "SPVSF", "PF", "SPVSF, Eqs 30-31 as printed", "SPVSF, particle proposal")
    rmse = {}
    for name in names:
        est, P0 = rows[name]
        rmse[name] = float(run_rmse(run(est, sc, P0, 0), sc.truth, sc.x0, true_x0)[:, 3].mean())
    modulus = {name: rmse[name] / rmse["SVSF"] for name in names}  # relative to the SVSF's
    assert abs(modulus["SPVSF, Eqs 30-31 as printed"] - 1) < 0.01, modulus
    assert modulus["SPVSF"] < 0.995 and modulus["SPVSF, particle proposal"] < 0.995, modulus
    assert modulus["PF"] > 5, modulus

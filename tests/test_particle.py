"""Particle filter and SPVSF: agreement with the KF, reproducibility, gradients, bad input.

Monte Carlo claims are tested with a stated confidence, never against a margin tuned on one run:

* against an exact oracle (the Kalman filter of a linear-Gaussian model): each track is filtered
  ``R`` times with independent particles in one batch, and every compared entry's mean error over
  the runs must lie within ``k`` of its standard errors over the runs. ``k`` is the Student-t
  quantile (``R − 1`` degrees of freedom) of ``1e-6 / (2 E)`` for ``E`` compared entries
  (Bonferroni): an exact particle filter fails with probability at most ``1e-6``. The spread over
  runs, not ``σ/√ESS``, measures the Monte Carlo error: ``ESS`` ignores the resampling history and
  is about 1.7 times too optimistic here;
* orderings between estimators (the papers' claims): per-run paired differences on the same
  simulated runs, the claim established at one-sided 99.9% confidence (mean beyond ``k`` standard
  errors, ``k`` the t quantile of ``1e-3``), on enough runs that, at the effect measured on other
  seeds, a true ordering fails with probability below ``1e-6``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats  # installed with the dev extras (filterpy, pykalman)

import torchsvs as ts
from tests.conftest import System, assert_close, random_system
from tests.test_nonlinear import _ballistic_run

#: One-sided confidence of every ordering claim (its false-pass probability).
ORDERING_ALPHA = 1e-3
#: Probability that the joint bounds of a comparison with the KF oracle miss (for an exact filter:
#: the probability of a false failure).
ORACLE_ALPHA = 1e-6


def _over_runs(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard error over axis 1 (the runs)."""
    return x.mean(1), x.std(1) / x.shape[1] ** 0.5


def _two_sided_k(alpha: float, runs: int, count: int) -> float:
    """``k`` with ``P(|mean − μ| > k·se) ≤ alpha`` jointly for ``count`` means over ``runs`` runs
    (Student t, Bonferroni)."""
    return float(stats.t.isf(alpha / (2 * count), runs - 1))


def _one_sided_k(alpha: float, runs: int) -> float:
    """``k`` with ``P(mean − μ > k·se) ≤ alpha`` for a mean over ``runs`` runs (Student t)."""
    return float(stats.t.isf(alpha, runs - 1))


def _upper(x: torch.Tensor, alpha: float = ORDERING_ALPHA) -> float:
    """One-sided ``1 − alpha`` upper confidence bound on the mean of per-run values ``x [B]``."""
    mean, se = _over_runs(x.unsqueeze(0))
    return float(mean + _one_sided_k(alpha, x.shape[0]) * se)


def _ratio_bounds(
    x: torch.Tensor, y: torch.Tensor, alpha: float = ORDERING_ALPHA
) -> tuple[float, float]:
    """Lower and upper one-sided ``1 − alpha`` confidence bounds on ``mean(x) / mean(y)`` for
    per-run pairs ``x, y [B]`` (delta method: the standard error of ``mean(x − r·y) / mean(y)``)."""
    r = x.mean() / y.mean()
    _, se = _over_runs(((x - r * y) / y.mean()).unsqueeze(0))
    k = _one_sided_k(alpha, x.shape[0])
    return float(r - k * se), float(r + k * se)


def _replicas(est: ts.ParticleFilter, system: System, runs: int):
    """``runs`` independent runs of ``est`` on each track of ``system`` (the measurements repeated
    in one batch, one generator: every row draws its own particles) and the KF of the tracks:
    the particle means' errors in KF standard deviations ``[B, runs, T, n]``, the result, the KF."""
    z, x0, P0 = system.tensors()
    kf = ts.KalmanFilter(system.model())(z, x0, P0)
    with torch.no_grad():
        out = est(z.repeat_interleave(runs, 0), x0, P0, generator=torch.Generator().manual_seed(0))
    B, T, n = kf.mean.shape
    std = kf.cov.diagonal(dim1=-2, dim2=-1).sqrt().unsqueeze(1)
    err = (out.mean.reshape(B, runs, T, n) - kf.mean.unsqueeze(1)) / std
    return err, out, kf


def _assert_exact_filter(est: ts.ParticleFilter, system: System, runs: int) -> None:
    """``est`` against the Kalman filter on ``system`` (module docstring): the particle mean
    (``B·T·n`` entries), the weighted covariance in products of KF standard deviations (its
    ``B·T·n(n+1)/2`` distinct entries) and the marginal likelihood estimate, whose ratio to the
    KF's, ``Ẑ/Z``, is unbiased for 1 (``B`` entries): none of the ``E`` means over runs further
    from the oracle than ``k`` standard errors (``k`` for ``ORACLE_ALPHA``). The filters' own
    ``O(1/N)`` bias at 2000 particles is not detectable with 400 runs (largest ``|t|`` 2.8 of the
    122 entries, bootstrap and SVSF-guided proposals), so it leaves the bound as stated."""
    err, out, kf = _replicas(est, system, runs)
    B, _, T, n = err.shape
    std = kf.cov.diagonal(dim1=-2, dim2=-1).sqrt()
    scale = (std.unsqueeze(-1) * std.unsqueeze(-2)).unsqueeze(1)
    i, j = torch.triu_indices(n, n)
    cov_err = ((out.cov.reshape(B, runs, T, n, n) - kf.cov.unsqueeze(1)) / scale)[..., i, j]
    ratio = (out.log_likelihood.reshape(B, runs) - kf.log_likelihood.unsqueeze(1)).exp() - 1
    checks = {"mean": err, "covariance": cov_err, "likelihood ratio": ratio}
    k = _two_sided_k(ORACLE_ALPHA, runs, sum(v[:, 0].numel() for v in checks.values()))
    for what, x in checks.items():
        bias, se = _over_runs(x)
        worst = float((bias.abs() / se).max())
        assert worst < k, (
            f"{what}: a mean over {runs} runs {worst:.1f} standard errors off (k={k:.1f})"
        )


def test_many_particles_approach_the_kalman_filter():
    """The bootstrap particle filter is an exact filter against the KF oracle
    (:func:`_assert_exact_filter`, ``k = 6.9``): 50 runs of 2000 particles per track resolve
    (``k·se``, median over entries) an error of 0.05σ in the mean, 0.04σᵢσⱼ in the covariance and
    9% in the likelihood. Log-weights scaled by 0.9 (``R`` 11% too large) fail it by 10 standard
    errors, weights reset to 1 instead of 1/N at resampling (``Ẑ`` off by ``N``) by 79."""
    system = random_system(2, 1, T=12, B=2, seed=4)
    pf = ts.ParticleFilter(system.model(), num_particles=2000, resample_threshold=0.5)
    _assert_exact_filter(pf, system, runs=50)


@pytest.mark.parametrize("psi", [0.5, 3.0])
def test_spvsf_particle_proposal_is_a_consistent_particle_filter(psi):
    """With the full importance weight the SVSF-guided proposal targets the exact posterior: on a
    linear-Gaussian model it is an exact particle filter against the KF, whatever ψ is
    (:func:`_assert_exact_filter`, 50 runs of 2000 particles per track)."""
    system = random_system(2, 1, T=12, B=2, seed=4)
    spvsf = ts.SPVSF(system.model(), psi=psi, num_particles=2000, proposal="particles")
    _assert_exact_filter(spvsf, system, runs=50)


@pytest.mark.parametrize("psi", [0.5, 3.0])
def test_spvsf_other_readings_miss_the_kalman_filter(psi):
    """The other readings omit the transition-over-proposal factor and are not consistent: their
    estimate converges to something else than the KF's. Per entry (``B·T·n = 48``), the offset
    from the KF (KF σ) lies within ``b ± k·se`` of its mean ``b`` over the runs, jointly with
    probability ≥ 1 − 10⁻⁶ (Bonferroni, t quantile). On these bounds: Eqs. (30)-(31) as printed
    miss the KF by over 0.5σ on average; the default ("adapted", weighted by the predictive
    likelihood) stays within 0.35σ on average but is off by over 0.5σ somewhere. At 2000
    particles the mean offset is within 0.01σ of 20,000 particles' (printed 0.72 and 0.56σ,
    adapted 0.27 and 0.16σ at ψ = 0.5 and 3). The closest bound, the printed reading's at ψ = 3,
    needs its 100 runs: 0.52 to 0.53σ over five reseedings (0.47 with 20 runs)."""
    system = random_system(2, 1, T=12, B=2, seed=4)
    low, high = {}, {}
    for proposal, runs in (("estimate", 100), ("adapted", 50)):
        spvsf = ts.SPVSF(system.model(), psi=psi, num_particles=2000, proposal=proposal)
        err, _, _ = _replicas(spvsf, system, runs)
        offset, se = _over_runs(err)
        k = _two_sided_k(ORACLE_ALPHA, runs, offset.numel())
        low[proposal] = (offset.abs() - k * se).clamp(min=0.0)
        high[proposal] = offset.abs() + k * se
    assert float(low["estimate"].mean()) > 0.5, f"printed: {float(low['estimate'].mean()):.3f}σ"
    assert float(high["adapted"].mean()) < 0.35, f"adapted: {float(high['adapted'].mean()):.3f}σ"
    assert float(low["adapted"].max()) > 0.5, f"adapted: {float(low['adapted'].max()):.3f}σ"


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
    assert a.mean.shape == (3, 30, 3) and a.cov.shape == (3, 30, 3, 3) and a.ess.shape == (3, 30)
    # It tracks: on these tracks its altitude RMSE, averaged over 32 independent runs, is below
    # the altitude measurement's standard deviation (100 m) at one-sided 99.9% confidence.
    # Measured over 200 runs: 25 ± 4 m (pf), 78 ± 1.3 (adapted), 81 ± 0.6 (estimate), 39 ± 12
    # (particles): at least 28 standard errors of the mean of 32 below it.
    runs = 32
    with torch.no_grad():
        many = est(z.repeat(runs, 1, 1), x0, P0, generator=torch.Generator().manual_seed(0))
    err = (many.mean - truth.repeat(runs, 1, 1))[..., 0].reshape(runs, -1)
    rmse = err.square().mean(1).sqrt()
    assert _upper(rmse) < float(model.meas_cov()[0, 0]) ** 0.5, f"{float(rmse.mean()):.0f} m"


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
        paper_rmse(mean, truth, initial=(x0, true_x0)),
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
    """Issue 5's acceptance on 24 ballistic runs (the experiment uses 100), paired per run (every
    filter on the same simulated runs), each at one-sided 99.9% confidence: the SPVSF's altitude
    RMSE below the SVSF's, the UKF's and the EKF's at the experiment's ψ (upper bound of the mean
    difference below 0), and within 10% of it with the gravity error (bounds of the ratio of the
    means within 1 ± 0.1). Per-run effects measured on 100 runs of seed 0: SPVSF − SVSF −40 m,
    2.1 standard deviations of the difference (UKF, EKF: −1447 m, 235 sd); gravity error ratio
    1.0001 ± 0.00002. At 2.1 sd, 24 runs fail the SVSF ordering with probability 1e-9
    (noncentral t)."""
    from experiments.spvsf_paper import BALLISTIC_PSI, BALLISTIC_TRUE_X0, estimators, run

    true_x0 = torch.tensor(BALLISTIC_TRUE_X0, dtype=torch.float64)
    nominal = ts.scenarios.ballistic_scenario(24, torch.Generator().manual_seed(5))
    gravity = ts.scenarios.ballistic_scenario(
        24, torch.Generator().manual_seed(5), gravity_error_at=15.0
    )
    rows = estimators(nominal.model, BALLISTIC_PSI)

    def altitude(name, sc):  # per-run RMSE [B], the initial estimate counted as the paper does
        rmse = ts.metrics.run_rmse(
            run(rows[name], sc, sc.P0, 5), sc.truth, initial=(sc.x0, true_x0)
        )
        return rmse[:, 0]

    alt = {name: altitude(name, nominal) for name in ("SPVSF", "SVSF", "UKF", "EKF")}
    for other in ("SVSF", "UKF", "EKF"):
        gap = alt["SPVSF"] - alt[other]
        assert _upper(gap) < 0, f"SPVSF − {other}: {float(gap.mean()):.1f} m"
    low, high = _ratio_bounds(altitude("SPVSF", gravity), alt["SPVSF"])
    assert 0.9 < low and high < 1.1, (low, high)


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
    """The results file's EHA claims (changing modulus), paired per run over 24 runs of 0.6 s (the
    prior's modulus error and the first change, at 0.5 s), each at one-sided 99.9% confidence:
    the default SPVSF ("adapted") and the particle proposal weigh each particle's modulus through
    its dynamics and do better than the SVSF (upper bound of the mean per-run difference below 0);
    Eqs. (30)-(31) as printed move the modulus only by sampling noise around the SVSF's (their
    weights do not see it): the mean difference within ±1% of the SVSF's RMSE (both bounds), where
    the other two gain 5%; the PF, whose prior does not cover the modulus, fails (lower bound of
    its RMSE over the SVSF's above 5; measured 10.5). Per-run effects over four simulations of
    20-40 runs: SPVSF and particle proposal −5%, 1.9 to 3.4 standard deviations of the
    difference; at 1.9, 24 runs fail a true ordering with probability 1e-7 (noncentral t)."""
    from experiments.spvsf_paper import EHA_PSI, estimators, run, variants

    sc = ts.scenarios.eha_scenario(
        24, torch.Generator().manual_seed(2), changing=True, duration=0.6
    )
    true_x0 = torch.tensor([0.0, 0.0, 0.0, 2.1e8], dtype=torch.float64)
    rows = {name: (est, sc.P0) for name, est in estimators(sc.model, EHA_PSI).items()}
    rows |= variants(sc, EHA_PSI)
    names = ("SVSF", "SPVSF", "PF", "SPVSF, Eqs 30-31 as printed", "SPVSF, particle proposal")
    rmse = {}  # per-run modulus RMSE [B], the initial estimate counted as the paper does
    for name in names:
        est, P0 = rows[name]
        mean = run(est, sc, P0, 0)
        rmse[name] = ts.metrics.run_rmse(mean, sc.truth, initial=(sc.x0, true_x0))[:, 3]
    gap = {name: rmse[name] - rmse["SVSF"] for name in names}
    svsf = float(rmse["SVSF"].mean())
    for name in ("SPVSF", "SPVSF, particle proposal"):
        assert _upper(gap[name]) < 0, f"{name}: {float(gap[name].mean()) / svsf:+.2%} of the SVSF's"
    printed = gap["SPVSF, Eqs 30-31 as printed"]
    lower, upper = -_upper(-printed), _upper(printed)
    assert -0.01 < lower / svsf and upper / svsf < 0.01, (
        f"printed: {lower / svsf:+.2%}, {upper / svsf:+.2%}"
    )
    low, _ = _ratio_bounds(rmse["PF"], rmse["SVSF"])
    assert low > 5, f"PF over SVSF: {low:.1f}"

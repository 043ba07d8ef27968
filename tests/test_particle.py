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
from tests.conftest import System, assert_close, random_system, simulate_cv
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


def _replicas(est: ts.ParticleFilter, system: System | tuple, runs: int):
    """``runs`` independent runs of ``est`` on each track of ``system`` (the measurements repeated
    in one batch, one generator: every row draws its own particles) and the KF of the tracks:
    the particle means' errors in KF standard deviations ``[B, runs, T, n]``, the result, the KF.
    ``system``: a :class:`System`, or ``(model, z, x0 [B, n], P0, dt [B, T] or None)``."""
    if isinstance(system, System):
        model, (z, x0, P0), dt = system.model(), system.tensors(), None
    else:
        model, z, x0, P0, dt = system
    kf = ts.KalmanFilter(model)(z, x0, P0, dt=dt)
    many = {}
    if dt is not None:
        many["dt"] = dt.repeat_interleave(runs, 0)
    if x0.ndim == 2:
        x0 = x0.repeat_interleave(runs, 0)
    with torch.no_grad():
        out = est(
            z.repeat_interleave(runs, 0),
            x0,
            P0,
            generator=torch.Generator().manual_seed(0),
            **many,
        )
    B, T, n = kf.mean.shape
    std = kf.cov.diagonal(dim1=-2, dim2=-1).sqrt().unsqueeze(1)
    err = (out.mean.reshape(B, runs, T, n) - kf.mean.unsqueeze(1)) / std
    return err, out, kf


def _assert_exact_filter(est: ts.ParticleFilter, system: System | tuple, runs: int) -> None:
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
    adapted 0.27 and 0.16σ at ψ = 0.5 and 3). The printed reading's claim is tested at 0.4σ:
    its mean offset is 0.56σ at the closest (ψ = 3) and the confidence bound takes off k·se,
    0.03-0.04σ at 100 runs (the bound: 0.52 to 0.53σ over five reseedings), a margin of over
    0.1σ against a spread of 0.01σ; 0.5σ would leave 0.02σ."""
    system = random_system(2, 1, T=12, B=2, seed=4)
    low, high = {}, {}
    for proposal, runs in (("estimate", 100), ("adapted", 50)):
        spvsf = ts.SPVSF(system.model(), psi=psi, num_particles=2000, proposal=proposal)
        err, _, _ = _replicas(spvsf, system, runs)
        offset, se = _over_runs(err)
        k = _two_sided_k(ORACLE_ALPHA, runs, offset.numel())
        low[proposal] = (offset.abs() - k * se).clamp(min=0.0)
        high[proposal] = offset.abs() + k * se
    assert float(low["estimate"].mean()) > 0.4, f"printed: {float(low['estimate'].mean()):.3f}σ"
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


# --- The optimal proposal, regularisation and the degeneracy helper. ---


class _Opaque(ts.models.StateSpaceModel):
    """A linear model that does not say so (not a ``LinearModel``): the filters treat its ``h``
    as nonlinear and linearise it (exactly), which exercises that path against the KF."""

    uses_dt = True

    def __init__(self, inner: ts.models.ConstantVelocity) -> None:
        super().__init__()
        self.inner = inner
        self.state_dim, self.meas_dim = inner.state_dim, inner.meas_dim

    def f(self, x, dt=None, u=None):
        return self.inner.f(x, dt)

    def h(self, x):
        return self.inner.h(x)

    def h_jacobian(self, x):
        return self.inner.h_jacobian(x)

    def process_noise(self, dt=None):
        return self.inner.process_noise(dt)

    def meas_cov(self):
        return self.inner.meas_cov()


def _cv_with_gaps(seed: int = 3):
    """Two nearly-constant-velocity tracks at irregular intervals ``dt [2, 12]`` (0.5 to 10 s;
    ``Q`` up to 13 times ``R`` in position, where the bootstrap degenerates), with a missing
    step, a missing component and the second track padded with NaN after step 9:
    ``(model, z, x0, P0, dt)``."""
    gen = torch.Generator().manual_seed(seed)
    dt = 0.5 + 9.5 * torch.rand(2, 12, generator=gen, dtype=torch.float64)
    _, z = simulate_cv(dt, q=1.0, r=25.0, generator=gen, speed=3.0)
    z[0, 3] = float("nan")
    z[1, 5, 1] = float("nan")
    z[1, 10:] = float("nan")
    model = ts.models.ConstantVelocity(q=1.0, r=25.0).double()
    P0 = torch.diag(torch.tensor([100.0, 9.0, 100.0, 9.0], dtype=torch.float64))
    return model, z, torch.zeros(2, 4, dtype=torch.float64), P0, dt


def test_optimal_proposal_is_an_exact_filter_with_gaps_and_intervals():
    """The optimal proposal targets the exact posterior: against the KF oracle
    (:func:`_assert_exact_filter`, 50 runs of 2000 particles per track), on tracks with per-step
    intervals, a missing step, a missing component and padding; its weight is the closed-form
    ``N(z; H f(xᵢ), S)`` and its estimate averages the proposal means."""
    model, z, x0, P0, dt = _cv_with_gaps()
    pf = ts.ParticleFilter(model, 2000, proposal="optimal")
    _assert_exact_filter(pf, (model, z, x0, P0, dt), runs=50)


def test_linearised_optimal_proposal_is_the_closed_form_for_a_linear_h():
    """For a nonlinear ``h`` the proposal linearises it at each particle and weighs with the full
    importance weight ``p(z | x) p(x | x') / q(x)``. For an ``h`` that is linear (a model that does
    not say so), ``q`` is the optimal proposal and that weight equals ``N(z; H f(x'), S)``
    whatever was drawn: without resampling, the same particles, log-weights and likelihood as the
    closed form, draw for draw, on tracks with gaps, padding and per-step intervals."""
    model, z, x0, P0, dt = _cv_with_gaps()
    runs = {}
    for name, m in (("closed", model), ("linearised", _Opaque(model))):
        pf = ts.ParticleFilter(m, 64, resample_threshold=0.0, proposal="optimal")
        runs[name] = pf(z, x0, P0, dt=dt, generator=torch.Generator().manual_seed(1))
    closed, linearised = runs["closed"], runs["linearised"]
    assert_close(linearised.particles, closed.particles)
    assert_close(linearised.log_weights, closed.log_weights, rtol=1e-7, atol=1e-9)
    assert_close(linearised.log_likelihood, closed.log_likelihood)


def test_optimal_proposal_against_numpy():
    """One step of the optimal proposal on a random linear-Gaussian model, track 1 with only its
    first component observed: each particle's proposal mean ``f(x) + K (z − H f(x))``, its
    covariance ``(I − K H) Q`` (``K = Q Hᵀ S⁻¹``, ``S = H Q Hᵀ + R`` over the observed
    components) and the log-weight ``log N(z; H f(x), S)``, against NumPy."""
    from torchsvs.estimator import Inputs

    system = random_system(3, 2, T=3, B=2, seed=7)
    z_np = system.z.copy()
    z_np[1, 0, 1] = np.nan
    z = torch.from_numpy(z_np)
    x0 = torch.from_numpy(system.x0).expand(2, 3).clone()
    pf = ts.ParticleFilter(system.model(), num_particles=5, proposal="optimal")
    gen = torch.Generator().manual_seed(0)
    inputs = Inputs(z, x0, torch.eye(3, dtype=z.dtype)[None], None, None, None, gen, False)
    particles = x0.unsqueeze(1) + torch.randn(2, 5, 3, generator=gen, dtype=z.dtype)
    state = pf.begin(inputs, None, None)
    drawn, state, log_w = pf.propose(0, particles, state, inputs, gen)
    F, H, Q, R = system.F, system.H, system.Q, system.R
    for b in range(2):
        seen = ~np.isnan(z_np[b, 0])
        Hs = H[seen]
        S = Hs @ Q @ Hs.T + R[np.ix_(seen, seen)]
        K = Q @ Hs.T @ np.linalg.inv(S)
        assert_close(state.Sigma[b, 0], torch.from_numpy((np.eye(3) - K @ Hs) @ Q))
        for i in range(5):
            pred = F @ particles[b, i].numpy()
            r = z_np[b, 0][seen] - Hs @ pred
            assert_close(state.mu[b, i], torch.from_numpy(pred + K @ r))
            expected = -0.5 * (r @ np.linalg.solve(S, r) + np.log(np.linalg.det(2 * np.pi * S)))
            assert_close(log_w[b, i], torch.tensor(expected, dtype=torch.float64))
    assert bool(torch.isfinite(drawn).all())


def _reference_sir(model, z, x0, P0, N, threshold, gen):
    """The SIR filter of Gadsden et al. 2012, Eqs. (5)-(10), written out: draws from the prior,
    the transition with ``Q``, likelihood weights over the observed components, systematic
    resampling when ``N_eff < threshold · N``. Means ``[B, T, n]`` and ESS ``[B, T]``."""
    B, T, m = z.shape
    n = x0.shape[-1]
    Q, R, H = model.process_noise(), model.meas_cov(), model.meas_matrix()
    x = (
        x0[:, None]
        + torch.randn(B, N, n, generator=gen, dtype=z.dtype) @ torch.linalg.cholesky(P0).mT
    )
    log_w = torch.full((B, N), -np.log(N), dtype=z.dtype)
    means, esss = [], []
    for t in range(T):
        moved = model.f(x.reshape(B * N, n)).reshape(B, N, n)
        eps = torch.randn(B, N, n, generator=gen, dtype=z.dtype)
        x = moved + eps @ torch.linalg.cholesky(Q).mT
        for b in range(B):
            seen = ~torch.isnan(z[b, t])
            if seen.any():
                r = z[b, t, seen] - x[b] @ H[seen].mT
                S = R[seen][:, seen]
                log_w[b] += -0.5 * (r @ torch.linalg.inv(S) * r).sum(-1)
        log_w = log_w - torch.logsumexp(log_w, -1, keepdim=True)
        w = log_w.exp()
        means.append(torch.einsum("bn,bni->bi", w, x))
        ess = 1.0 / w.square().sum(-1)
        esss.append(ess)
        low = ess < threshold * N
        if low.any():
            u = torch.rand(B, 1, generator=gen, dtype=z.dtype)
            cdf = torch.cumsum(w, -1)
            cdf = cdf / cdf[:, -1:]
            index = torch.searchsorted(cdf, (torch.arange(N) + u) / N, right=True).clamp(max=N - 1)
            picked = x.gather(1, index.unsqueeze(-1).expand(-1, -1, n))
            x = torch.where(low[:, None, None], picked, x)
            log_w = torch.where(low[:, None], -np.log(N), log_w)
    return torch.stack(means, 1), torch.stack(esss, 1)


def test_bootstrap_is_the_plain_sir_filter():
    """The default proposal is the bootstrap SIR filter the paper reproductions use, unchanged by
    the optimal proposal and the regularisation: the same numbers as the filter written out
    (:func:`_reference_sir`, the same draws from one seed), with a missing step and component."""
    system = random_system(3, 2, T=15, B=3, seed=2)
    z, x0, P0 = system.tensors()
    z = z.clone()
    z[0, 4] = float("nan")
    z[2, 6, 0] = float("nan")
    x0 = x0.expand(3, 3)
    pf = ts.ParticleFilter(system.model(), num_particles=40, resample_threshold=0.8)
    out = pf(z, x0, P0, generator=torch.Generator().manual_seed(11))
    mean, ess = _reference_sir(
        system.model(),
        z,
        x0,
        torch.from_numpy(system.P0),
        40,
        0.8,
        torch.Generator().manual_seed(11),
    )
    assert_close(out.mean, mean)
    assert_close(out.ess, ess)


@pytest.mark.parametrize("proposal", ["bootstrap", "optimal"])
def test_ess_is_that_of_the_normalised_weights(proposal):
    """``ess`` is ``1 / Σ wᵢ²`` of the step's normalised weights before resampling (Eq. (10)):
    without resampling, the last step's equals that of the final log-weights; every ESS lies in
    ``[1, N]``; at a step without a measurement the weights do not change, so its ESS is that of
    the step before (or ``N`` after a resampling)."""
    model, z, x0, P0, dt = _cv_with_gaps()
    kept = ts.ParticleFilter(model, 50, resample_threshold=0.0, proposal=proposal)
    out = kept(z, x0, P0, dt=dt, generator=torch.Generator().manual_seed(0))
    assert_close(out.ess[:, -1], 1.0 / out.log_weights.exp().square().sum(-1))
    assert bool((out.ess >= 1.0 - 1e-9).all()) and bool((out.ess <= 50.0 + 1e-9).all())
    pf = ts.ParticleFilter(model, 50, proposal=proposal)
    out = pf(z, x0, P0, dt=dt, generator=torch.Generator().manual_seed(0))
    before = out.ess[0, 2]
    assert_close(out.ess[0, 3], before if before >= 25 else torch.tensor(50.0, dtype=before.dtype))


def test_degenerate_share():
    """The share of a track's measured steps whose ESS fell below ``N/10``: counted by hand on a
    result with a missing step and padding (neither counts), over all steps without ``z``, for
    one track's result, and bad input named."""
    from torchsvs.filters.particle import ParticleResult, degenerate_share

    N = 20
    ess = torch.tensor([[1.0, 19.0, 1.9, 2.0, 5.0], [20.0, 1.0, 1.0, 3.0, 3.0]])
    z = torch.zeros(2, 5, 2)
    z[0, 2] = float("nan")  # ESS 1.9 < 2 at a step without a measurement: not counted
    z[1, 3:] = float("nan")  # padding
    result = ParticleResult(ess, ess, ess, ess, torch.zeros(2, N, 4), torch.zeros(2, N))
    assert_close(degenerate_share(result, z), torch.tensor([1 / 4, 2 / 3]))
    assert_close(degenerate_share(result), torch.tensor([2 / 5, 2 / 5]))
    assert_close(degenerate_share(result, z, share=0.2), torch.tensor([2 / 4, 2 / 3]))
    assert_close(degenerate_share(result, z, share=0.3), torch.tensor([3 / 4, 2 / 3]))
    single = ParticleResult(ess[0], ess[0], ess[0], ess[0], torch.zeros(N, 4), torch.zeros(N))
    assert_close(degenerate_share(single, z[0]), torch.tensor(1 / 4))
    none = torch.full((1, 5, 2), float("nan"))
    assert_close(degenerate_share(result._replace(ess=ess[:1]), none), torch.tensor([0.0]))
    with pytest.raises(ValueError, match="^share: expected a value in"):
        degenerate_share(result, z, share=0.0)
    with pytest.raises(ValueError, match="^z: expected the run's measurements"):
        degenerate_share(result, z[:, :4])
    with pytest.raises(ValueError, match="^result: holds no ess"):
        degenerate_share(result._replace(ess=None))


def test_gaussian_posterior_against_numpy():
    """The regularisation's Gaussian posterior: the weighted moments of the particles' prediction
    plus ``Q``, Kalman-updated with the observed components, against NumPy; a measurement beyond
    the χ² gate (``α = 0.01``; 2 components: 9.21) first scales the predicted covariance by
    ``ν/m``, one within it leaves it as it is."""
    from torchsvs.estimator import Inputs

    system = random_system(3, 2, T=1, B=2, seed=5)
    model = system.model()
    gen = torch.Generator().manual_seed(1)
    particles = torch.randn(2, 30, 3, generator=gen, dtype=torch.float64)
    log_w = torch.log_softmax(torch.randn(2, 30, generator=gen, dtype=torch.float64), -1)
    F, H, Q, R = system.F, system.H, system.Q, system.R
    moved = particles.numpy() @ F.T
    w = log_w.exp().numpy()
    m = np.einsum("bn,bni->bi", w, moved)
    d = moved - m[:, None]
    C = np.einsum("bn,bni,bnj->bij", w, d, d) + Q
    S = H @ C @ H.T + R
    near = H @ m[0] + np.linalg.cholesky(S[0]) @ np.array([0.5, -0.3])  # ν = 0.34
    far = H @ m[1] + np.linalg.cholesky(S[1]) @ np.array([3.0, 2.0])  # ν = 13 > 9.21
    z = torch.from_numpy(np.stack([near, far]))[:, None]
    pf = ts.ParticleFilter(model, 30, proposal="optimal", regularize=True)
    inputs = Inputs(
        z, particles[:, 0], torch.eye(3, dtype=z.dtype)[None], None, None, None, gen, False
    )
    x, P = pf.gaussian_posterior(0, particles, log_w, inputs)
    for b, scale in ((0, 1.0), (1, 13.0 / 2)):
        Cb = scale * C[b]
        Sb = H @ Cb @ H.T + R
        K = Cb @ H.T @ np.linalg.inv(Sb)
        assert_close(x[b], torch.from_numpy(m[b] + K @ (z[b, 0].numpy() - H @ m[b])))
        assert_close(P[b], torch.from_numpy(Cb - K @ Sb @ K.T))


def test_regularized_particles_cover_the_gaussian_posterior():
    """After resampling, a regularised set whose weighted covariance ``C`` falls short of the
    Gaussian posterior ``N(x, P)`` gets ``N(0, (P − C)₊)`` added (track 0, ``C = 0``: one
    ancestor; mean the ancestor, covariance ``P``); a degenerate step's set (track 1) is redrawn
    from ``N(x, P)``. Sample means and covariances of 20,000 particles within
    ``k`` of their standard errors (``k`` for a joint false failure of ``1e-6``)."""
    from torchsvs.estimator import Inputs

    system = random_system(3, 2, T=1, B=2, seed=6)
    model, (z, _, _) = system.model(), system.tensors()
    gen = torch.Generator().manual_seed(2)
    N = 20_000
    before = (
        torch.randn(2, N, 3, generator=gen, dtype=torch.float64),
        torch.full((2, N), -np.log(N), dtype=torch.float64),
    )
    inputs = Inputs(
        z[:2, :1], before[0][:, 0], torch.eye(3, dtype=z.dtype)[None], None, None, None, gen, False
    )
    pf = ts.ParticleFilter(model, N, proposal="optimal", regularize=True)
    x, P = pf.gaussian_posterior(0, *before, inputs)
    ancestor = torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64).expand(2, 3)
    picked = ancestor.unsqueeze(1).expand(2, N, 3).clone()
    degenerate = torch.tensor([False, True])
    out = pf.regularized(picked, degenerate, torch.zeros(2, 3, 3, dtype=torch.float64), (x, P), gen)
    centre = torch.stack([ancestor[0], x[1]])  # track 0 moved around its ancestor, 1 redrawn
    k = _two_sided_k(ORACLE_ALPHA, N, 2 * 9)
    for b in range(2):
        mean, cov = out[b].mean(0), torch.cov(out[b].T)
        se_mean = (P[b].diagonal() / N).sqrt()
        se_cov = ((P[b].diagonal()[:, None] * P[b].diagonal()[None] + P[b] ** 2) / N).sqrt()
        assert bool(((mean - centre[b]).abs() < k * se_mean).all()), (b, mean, centre[b])
        assert bool(((cov - P[b]).abs() < k * se_cov).all()), (b, cov, P[b])


def test_degenerate_step_estimate_is_the_gaussian_posterior():
    """Regularised, a degenerate step (``N_eff < N/10``: here a measurement 12 predicted standard
    deviations off on one track) reports the Gaussian posterior of its prediction
    (:meth:`~torchsvs.ParticleFilter.gaussian_posterior` of the particles before it), a step that
    is not (the other track) its weighted particles' moments, as without regularisation."""
    system = random_system(2, 1, T=1, B=2, seed=4)
    model, (z, x0, P0) = system.model(), system.tensors()
    x0 = x0.expand(2, 2)
    S = ts.KalmanFilter(model)(z, x0, P0).innovation_cov[0, 0, 0, 0]
    z = z.clone()
    z[0, 0] += 12.0 * float(S) ** 0.5
    results = {}
    for regularize in (False, True):
        pf = ts.ParticleFilter(model, 200, proposal="optimal", regularize=regularize)
        gen = torch.Generator().manual_seed(0)
        start = pf.init(x0, P0, generator=gen)
        _, results[regularize] = pf.scan(start, z, generator=gen)
    out = results[True]
    assert float(out.ess[0, 0]) < 20 <= float(out.ess[1, 0])
    from torchsvs.estimator import prepare_inputs

    inputs = prepare_inputs(model, z, x0, P0)
    x, P = pf.gaussian_posterior(0, start.particles, start.log_weights, inputs)
    assert_close(out.mean[0, 0], x[0])
    assert_close(out.cov[0, 0], P[0])
    assert_close(out.mean[1], results[False].mean[1])
    assert_close(out.cov[1], results[False].cov[1])


def test_regularized_filter_follows_maneuvers_its_q_misses():
    """The ATC scenario of Chen et al. 2020 (Sec. 4.1: 3°/s and 1°/s turns between straight legs,
    T = 1 s) measured with σ = 50 m, filtered as ``torchsvs track`` would: a nearly-constant-
    velocity model with the measurement noise and ``q`` read off the data (``q`` 2.6, from the
    straight legs, misses the turns: the KF's normalised innovation reaches 20 in them). Over the
    first 200 s (the 3°/s turn and 45 s after it) the optimal proposal alone collapses in the turn
    and loses the track (position RMSE 1060-1250 m on four runs, against 71 m for the raw
    measurements); regularised, it follows (42-46 m; the KF 66 m). Claimed over the 4 runs at
    one-sided 99.9% confidence (t quantile, 3 degrees of freedom): the regularised filter's mean
    RMSE below the raw measurements', the unregularised one's above."""
    from torchsvs.datasets import estimate_noise

    sc = ts.scenarios.atc_scenario(4, torch.Generator().manual_seed(3))
    truth = sc.truth[:, :200]
    gen = torch.Generator().manual_seed(4)
    z = truth[..., [0, 2]] + 50.0 * torch.randn(
        4, truth.shape[1], 2, generator=gen, dtype=torch.float64
    )
    dt = torch.ones(z.shape[:2], dtype=torch.float64)
    noise = estimate_noise(z, dt)
    model = ts.models.ConstantVelocity(q=noise.q, r=noise.meas_var.tolist()).double()
    prior = ts.datasets.two_point_prior(z, dt, noise.meas_var)

    def rmse(est):
        with torch.no_grad():
            out = est(z, prior.x0, prior.P0, dt=dt, generator=torch.Generator().manual_seed(0))
        return (out.mean - truth)[..., [0, 2]].square().sum(-1).mean(-1).sqrt()

    raw = float((z - truth[..., [0, 2]]).square().sum(-1).mean().sqrt())
    lost = rmse(ts.ParticleFilter(model, 350, proposal="optimal"))
    kept = rmse(ts.ParticleFilter(model, 350, proposal="optimal", regularize=True))
    assert _upper(kept) < raw, f"regularised: {float(kept.mean()):.0f} m, raw {raw:.0f} m"
    assert -_upper(-lost) > raw, f"unregularised: {float(lost.mean()):.0f} m, raw {raw:.0f} m"


def test_bad_pf_proposal_and_regularize():
    model = ts.models.BallisticReentry()
    with pytest.raises(ValueError, match=r"^proposal: expected one of \('bootstrap', 'optimal'\)"):
        ts.ParticleFilter(model, proposal="adapted")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^regularize: expected True or False"):
        ts.ParticleFilter(model, regularize=0.5)  # type: ignore[arg-type]


def test_track_runs_the_regularised_optimal_filter(tmp_path):
    """``torchsvs track --estimator pf`` builds the optimal proposal, regularised, with 350
    particles, and on maneuvering tracks (two runs of the ATC scenario's first 200 s with
    σ = 50 m noise, the measurement noise and ``q`` read off the file, float32) its position
    RMSE is below the raw measurements' (42 m against 72 m; the bootstrap it replaced: over a
    kilometre, see :func:`test_regularized_filter_follows_maneuvers_its_q_misses`)."""
    import pandas as pd

    from torchsvs.recipes import Settings, make_estimator, make_model
    from torchsvs.tracking import track_file

    settings = Settings(estimator="pf", meas_var=[2500.0, 2500.0], q=1.0)
    pf = make_estimator(settings, make_model(settings))
    assert isinstance(pf, ts.ParticleFilter)
    assert (pf.proposal, pf.regularize, pf.num_particles) == ("optimal", True, 350)
    truth = ts.scenarios.atc_scenario(2, torch.Generator().manual_seed(3)).truth[:, :200]
    gen = torch.Generator().manual_seed(4)
    noise = 50.0 * torch.randn(2, 200, 2, generator=gen, dtype=torch.float64).numpy()
    z = truth[..., [0, 2]].numpy() + noise
    rows = pd.DataFrame(
        {
            "track_id": np.repeat(["a", "b"], 200),
            "time": np.tile(np.arange(200.0), 2),
            "x": z[..., 0].ravel(),
            "y": z[..., 1].ravel(),
        }
    )
    source, target = tmp_path / "in.csv", tmp_path / "out.csv"
    rows.to_csv(source, index=False)
    track_file(source, target, Settings(estimator="pf"), progress=False)
    out = pd.read_csv(target).sort_values(["track_id", "time"])
    error = out[["x", "y"]].to_numpy() - truth[..., [0, 2]].reshape(-1, 2).numpy()
    rmse = float(np.sqrt((error**2).sum(-1).mean()))
    raw = float(np.sqrt((noise**2).sum(-1).mean()))
    assert rmse < raw, f"pf {rmse:.0f} m, raw {raw:.0f} m"

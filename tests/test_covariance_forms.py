"""The covariance forms of the KF, EKF and SVSF (``covariance_form=``, torchsvs.filters.factored):
the Joseph filter's numbers on well-conditioned problems (gaps, per-track priors), the K-SVD
filter of a NumPy reference written from Bermúdez Ordoñez et al. 2020, runs in chunks, the
smoothers on top, gradients, and the ill-conditioned example (Grewal & Andrews; the paper's
Example 1) where the conventional form breaks and the factored forms do not."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, random_system
from tests.reference import ksvd_numpy as ref
from torchsvs.filters import factored
from torchsvs.kernels import compiled, compiled_steps, eager_loops, general_path

FACTORED = ("sqrt", "ud", "svd")
FORMS = ("conventional", *FACTORED)
#: Per-step fields every form must reproduce (the SVSF records no log-likelihood).
FIELDS = ("mean", "cov", "pred_mean", "pred_cov", "innovation", "gain", "innovation_cov")
TOL = {"atol": 1e-9, "rtol": 1e-9}
CHUNK_TOL = {"atol": 1e-12, "rtol": 1e-12}


def _with_gaps(z: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """``z`` with about 15 % of its components missing, a step without any measurement and a
    gap on one component of the first track."""
    gen = torch.Generator().manual_seed(seed)
    z = z.clone()
    z[torch.rand(z.shape, generator=gen) < 0.15] = float("nan")
    z[:, 5] = float("nan")
    z[0, 9:13, -1] = float("nan")
    return z


def _per_track_priors(x0: torch.Tensor, P0: torch.Tensor, B: int) -> tuple[torch.Tensor, ...]:
    """Distinct priors per track: ``P0`` scaled by 1, 1.5, 2, ... and shifted means."""
    scale = 1.0 + 0.5 * torch.arange(B, dtype=P0.dtype)
    x = x0 + 0.1 * torch.arange(B, dtype=x0.dtype)[:, None]
    return x, scale[:, None, None] * P0


def _linear_problem(n: int = 4, m: int = 2, seed: int = 3):
    """A random linear system with a full R (the UD form decorrelates it), gaps, per-track
    priors."""
    system = random_system(n, m, T=30, B=3, seed=seed)
    z, x0, P0 = system.tensors()
    x0, P0 = _per_track_priors(x0, P0, z.shape[0])
    return system.model(), _with_gaps(z), x0, P0


def _turn_problem(B: int = 3, T: int = 30):
    """The coordinated-turn model (nonlinear f, rank-3 Q) simulated, with gaps and per-track
    priors."""
    model = ts.models.CoordinatedTurn(dt=1.0, q=0.5, q_turn=1e-3, r=[4.0, 2.0]).double()
    x0 = torch.tensor([0.0, 10.0, 0.0, 5.0, 0.05], dtype=torch.float64)
    _, z = model.simulate(x0.expand(B, 5), T, generator=torch.Generator().manual_seed(1))
    P0 = torch.diag(torch.tensor([25.0, 4.0, 25.0, 4.0, 1e-3], dtype=torch.float64))
    x0b, P0b = _per_track_priors(x0, P0, B)
    return model, _with_gaps(z), x0b, P0b


def _cv_problem(B: int = 3, T: int = 30, r=(4.0, 2.0)):
    model = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=list(r)).double()
    x0 = torch.tensor([0.0, 3.0, 0.0, -2.0], dtype=torch.float64)
    _, z = model.simulate(x0.expand(B, 4), T, generator=torch.Generator().manual_seed(2))
    P0 = torch.diag(torch.tensor([9.0, 2.0, 9.0, 2.0], dtype=torch.float64))
    x0b, P0b = _per_track_priors(x0, P0, B)
    return model, _with_gaps(z), x0b, P0b


def _filters(kind: str, form: str, model) -> ts.filters.GaussianFilter:
    if kind in ("KF", "KF on CV"):
        return ts.KalmanFilter(model, covariance_form=form)
    if kind == "EKF":
        return ts.ExtendedKalmanFilter(model, covariance_form=form)
    if kind == "SVSF H+":
        psi = torch.linspace(0.8, 2.5, model.meas_dim, dtype=torch.float64)
        return ts.SVSF(model, psi=psi, gamma=0.3, artificial=None, covariance_form=form)
    if kind == "SVSF FD":  # finite-difference velocities: R per step and track
        psi = [3.0, 2.0, 4.0, 1.5]
        return ts.SVSF(model, psi=psi, gamma=0.2, covariance_form=form)
    if kind == "SVSF on CT":
        return ts.SVSF(model, psi=[6.0, 4.0], gamma=0.2, covariance_form=form)
    raise KeyError(kind)


PROBLEMS = {
    "KF": _linear_problem,
    "KF on CV": _cv_problem,
    "EKF": _turn_problem,
    "SVSF H+": _linear_problem,
    "SVSF FD": _cv_problem,
    "SVSF on CT": _turn_problem,
}


def _run(kind: str, form: str):
    model, z, x0, P0 = PROBLEMS[kind]()
    est = _filters(kind, form, model).double()
    with torch.no_grad():
        return est(z, x0, P0), est, (z, x0, P0)


def _compare(got, want, fields=FIELDS, tol=TOL):
    for key in fields:
        a, b = getattr(got, key), getattr(want, key)
        assert_close(a, b.expand_as(a), msg=key, **tol)


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("kind", ["KF", "KF on CV", "EKF"])
def test_kalman_forms_equal_the_joseph_filter(kind, form):
    got, _, (z, _, P0) = _run(kind, form)
    want, _, _ = _run(kind, "joseph")
    _compare(got, want, FIELDS + ("log_likelihood",))
    assert bool(torch.isnan(z).any()) and not torch.equal(P0[0], P0[1])


@pytest.mark.parametrize("form", FACTORED)
@pytest.mark.parametrize("kind", ["SVSF H+", "SVSF FD", "SVSF on CT"])
def test_svsf_factored_forms_equal_the_joseph_svsf(kind, form):
    got, _, _ = _run(kind, form)
    want, _, _ = _run(kind, "joseph")
    _compare(got, want, FIELDS + ("post_innovation",))


@pytest.mark.parametrize("kind", ["SVSF H+", "SVSF FD"])
def test_conventional_svsf_is_the_printed_short_form(kind):
    """Eq. (28)'s right side, ``(I − KH)P``: the estimates are the SVSF's (its gain does not read
    P), the covariance is the short-form recursion (rebuilt here from the run's own gains),
    which is not the Joseph covariance for the SVSF's gain."""
    got, _, (z, _, P0) = _run(kind, "conventional")
    want, _, _ = _run(kind, "joseph")
    _compare(got, want, ("mean", "pred_mean", "innovation", "gain", "post_innovation"))
    F, H = got.transition[0, 0].numpy(), got.meas_matrix.numpy()
    Q = PROBLEMS[kind]()[0].process_noise().detach().numpy()
    B, T = z.shape[:2]
    for b in range(B):
        P = P0[b].numpy()
        for t in range(T):
            Hb = H[b, t] if H.shape[0] > 1 else H[0, 0]
            K = got.gain[b, t].numpy()
            P = (np.eye(P.shape[0]) - K @ Hb) @ (F @ P @ F.T + Q)
            assert_close(got.cov[b, t], P, msg=f"track {b}, step {t}")
    assert (got.cov - want.cov).abs().max() > 1e-3


@pytest.mark.parametrize("missing", [False, True], ids=["complete", "gaps"])
def test_svd_form_is_the_ksvd_filter_of_the_reference(missing):
    system = random_system(4, 3, T=25, B=3, seed=7)
    z, x0, P0 = system.tensors()
    if missing:
        z = _with_gaps(z)
    est = ts.KalmanFilter(system.model(), covariance_form="svd").double()
    with torch.no_grad():
        got = est(z, x0, P0)
    for b in range(z.shape[0]):
        want = ref.ksvd_filter(z[b].numpy(), *system[4:6], *system[:4])
        for key in ("mean", "cov", "pred_mean", "pred_cov", "gain"):
            assert_close(getattr(got, key)[b], want[key], msg=f"{key}, track {b}")


def _chunked(est, state, z, size):
    parts = []
    for start in range(0, z.shape[1], size):
        state, part = est.scan(state, z[:, start : start + size])
        parts.append(part)
    return state, parts


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("kind", ["KF", "EKF", "SVSF FD"])
def test_chunked_and_online_runs_equal_the_whole_run(kind, form):
    whole, est, (z, x0, P0) = _run(kind, form)
    with torch.no_grad():
        for size in (1, 7):
            state, parts = _chunked(est, est.init(x0, P0), z, size)
            assert isinstance(state.factor, factored.Carried)
            assert isinstance(state.factor.factor, factored.FACTORS[form])
            for key in ("mean", "cov", "gain", "innovation_cov"):
                got = torch.cat([getattr(p, key) for p in parts], dim=1)
                assert_close(got, getattr(whole, key).expand_as(got), msg=key, **CHUNK_TOL)
        state = est.init(x0, P0)
        for t in range(z.shape[1]):
            state, out = est.step(state, z[:, t])
            assert_close(out.cov, whole.cov[:, t], msg=f"step {t}", **CHUNK_TOL)
            assert_close(out.mean, whole.mean[:, t], msg=f"step {t}", **CHUNK_TOL)
        assert state.constants is None  # no compiled online step was taken


@pytest.mark.parametrize("form", FACTORED)
def test_per_step_intervals_psi_and_one_track(form):
    """Per-step ``dt`` (``F`` and ``Q`` per track and step), a per-step ψ, and one track without
    the batch axis run online."""
    model, z, x0, P0 = _cv_problem()
    gen = torch.Generator().manual_seed(6)
    dt = torch.rand(z.shape[:2], generator=gen, dtype=torch.float64) + 0.5
    psi = torch.rand(*z.shape[:2], 4, generator=gen, dtype=torch.float64) * 3 + 1
    for make, kw in (
        (lambda f: ts.KalmanFilter(model, covariance_form=f), {}),
        (lambda f: _filters("SVSF FD", f, model), {"psi": psi}),
    ):
        with torch.no_grad():
            got, want = make(form)(z, x0, P0, dt=dt, **kw), make("joseph")(z, x0, P0, dt=dt, **kw)
        _compare(got, want, ("mean", "cov", "gain"))
    kf = ts.KalmanFilter(model, covariance_form=form)
    with torch.no_grad():
        whole = kf(z[1], x0[1], P0[1])
        state = kf.init(x0[1], P0[1])
        for t in range(z.shape[1]):
            state, out = kf.step(state, z[1, t])
            assert out.mean.shape == (4,) and out.cov.shape == (4, 4)
            assert_close(out.cov, whole.cov[t], **CHUNK_TOL)


def test_a_replaced_covariance_is_factored_anew():
    """An IMM mixes its modes' covariances into their states (``_replace(cov=...)``): the
    carried factor no longer stands for the covariance and must not be used."""
    model, z, x0, P0 = _cv_problem()
    modes = [ts.models.ConstantVelocity(dt=1.0, q=q, r=[4.0, 2.0]).double() for q in (0.1, 2.0)]
    Pi = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64)
    with torch.no_grad():
        results = {
            form: ts.IMM([ts.KalmanFilter(m, covariance_form=form) for m in modes], Pi)(z, x0, P0)
            for form in ("joseph", "sqrt", "svd")
        }
    for form in ("sqrt", "svd"):
        assert_close(results[form].mean, results["joseph"].mean, **TOL)
        assert_close(results[form].cov, results["joseph"].cov, **TOL)


@pytest.mark.parametrize("form", FACTORED)
def test_smoothers_over_the_forms_equal_those_over_joseph(form):
    model, z, x0, P0 = _cv_problem()
    lin, zl, x0l, P0l = _linear_problem()
    cases = [
        (lambda f: ts.RTSSmoother(ts.KalmanFilter(model, covariance_form=f)), (z, x0, P0)),
        (lambda f: ts.RTSSmoother(ts.KalmanFilter(lin, covariance_form=f), lag=2), (zl, x0l, P0l)),
        (lambda f: ts.SVSS(_filters("SVSF H+", f, lin), lag=None), (zl, x0l, P0l)),
        (lambda f: ts.SVSS(_filters("SVSF FD", f, model), lag=1), (z, x0, P0)),
    ]
    for make, args in cases:
        with torch.no_grad():
            got, want = make(form).double()(*args), make("joseph").double()(*args)
        assert_close(got.mean, want.mean, **TOL)
        assert_close(got.cov, want.cov, **TOL)


def test_factored_forms_take_no_fast_path():
    """The Joseph KF on a CV model runs the per-axis kernel (and compiled dense steps); the
    factored forms decline every fast path, compiled steps included."""
    model, z, x0, P0 = _cv_problem()
    with torch.no_grad():
        assert ts.KalmanFilter(model).double()(z, x0, P0).axes is not None
        before = compiled.STATS["compiles"]
        with compiled_steps():
            for form in FORMS:
                est = ts.KalmanFilter(model, covariance_form=form).double()
                assert est(z, x0, P0).axes is None
                assert est.step(est.init(x0, P0), z[:, 0])[0].constants is None
        assert compiled.STATS["compiles"] == before


def test_joseph_is_the_default_and_unchanged():
    model, z, x0, P0 = _cv_problem()
    for make in (
        lambda **kw: ts.KalmanFilter(model, **kw),
        lambda **kw: ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], **kw),
    ):
        default, joseph = make().double(), make(covariance_form="joseph").double()
        assert default.covariance_form == "joseph"
        with torch.no_grad():
            a, b = default(z, x0, P0), joseph(z, x0, P0)
        for key in ("mean", "cov", "gain"):
            assert torch.equal(getattr(a, key), getattr(b, key)), key


@pytest.mark.parametrize("bad", ["cholesky", "Joseph", "", None, 3])
def test_an_unknown_covariance_form_names_the_argument(bad):
    model = ts.models.ConstantVelocity()
    for make in (
        lambda: ts.KalmanFilter(model, covariance_form=bad),
        lambda: ts.ExtendedKalmanFilter(model, covariance_form=bad),
        lambda: ts.SVSF(model, psi=800.0, covariance_form=bad),
    ):
        with pytest.raises(ValueError, match="covariance_form: expected one of 'joseph', "):
            make()


def _gradients(form: str, kind: str, r, gaps: bool = True) -> dict[str, torch.Tensor]:
    """Gradients of a loss of means, variances and the log-likelihood with respect to ``z``
    and every parameter (by name)."""
    model = ts.models.ConstantVelocity(dt=1.0, q=0.5, r=list(r), learn_noise=True).double()
    x0 = torch.tensor([0.0, 3.0, 0.0, -2.0], dtype=torch.float64)
    _, z = model.simulate(x0.expand(2, 4), 12, generator=torch.Generator().manual_seed(4))
    z = (_with_gaps(z) if gaps else z).detach().requires_grad_(True)
    # A shared prior: with equal variances and no gaps the axes stay identical.
    P0 = torch.diag(torch.tensor([9.0, 2.0, 9.0, 2.0], dtype=torch.float64))
    if kind == "KF":
        est: torch.nn.Module = ts.KalmanFilter(model, covariance_form=form)
    else:
        est = ts.SVSF(model, psi=[3.0, 2.0, 4.0, 1.5], gamma=0.2, covariance_form=form)
    # Joseph on the general loop, as the factored forms run (the per-axis kernel treats a
    # diagonal R per axis and gives no gradient to its off-diagonal factor entries).
    with general_path(), eager_loops():
        out = est.double()(z, x0, P0)
    loss = out.mean.square().mean() + out.cov.diagonal(dim1=-2, dim2=-1).mean()
    if out.log_likelihood is not None:
        loss = loss - out.log_likelihood.sum()
    names, params = zip(
        *[(k, p) for k, p in est.named_parameters() if p.requires_grad], strict=True
    )
    # (the conventional SVSF's covariance, (I − KH)P, does not read R)
    grads = torch.autograd.grad(loss, [z, *params], allow_unused=True)
    return {k: g for k, g in zip(("z", *names), grads, strict=True) if g is not None}


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("kind", ["KF", "SVSF"])
def test_gradients_are_finite_and_the_joseph_filters(form, kind):
    """Per-axis variances that differ (no coinciding singular values): every gradient is the
    Joseph filter's."""
    got, want = _gradients(form, kind, (4.0, 2.0)), _gradients("joseph", kind, (4.0, 2.0))
    assert len(got) >= 3 and all(bool(torch.isfinite(g).all()) for g in got.values())
    if not (form == "conventional" and kind == "SVSF"):
        for name, g in got.items():
            assert_close(g, want[name], atol=1e-8, rtol=1e-6, msg=name)


def test_svd_gradients_where_singular_values_coincide():
    """Identical axes give every singular value twice: torch.linalg.svd's own backward is not
    finite there, the guarded one is, and for the shared process noise ``q`` (which keeps the
    axes identical) and the measurements it is exact."""
    got = _gradients("svd", "KF", (4.0, 4.0), gaps=False)
    want = _gradients("joseph", "KF", (4.0, 4.0), gaps=False)
    assert all(bool(torch.isfinite(g).all()) for g in got.values())
    shared = [name for name in got if name == "z" or ".q." in name or name.endswith(".q")]
    assert len(shared) == 2, list(got)
    for name in shared:
        assert_close(got[name], want[name], atol=1e-8, rtol=1e-6, msg=name)


def test_right_svd_backward_matches_finite_differences():
    """The guarded backward of ``right_svd`` is the SVD's (distinct singular values), checked
    on functions of its outputs that do not depend on the singular vectors' signs."""
    gen = torch.Generator().manual_seed(0)
    M = torch.randn(7, 4, generator=gen, dtype=torch.float64, requires_grad=True)

    def root(M):
        V, s = factored.right_svd(M)
        return (V * s) @ V.mT, (V * s.square()) @ V.mT

    assert torch.autograd.gradcheck(root, (M,))
    assert torch.autograd.gradcheck(lambda M: factored.right_svd(M)[1], (M,))


# --- The ill-conditioned example: Grewal & Andrews, Example 1 of Bermúdez Ordoñez et al. ---


def _delta_example(delta: float, dtype: torch.dtype, form: str):
    """One measurement update from ``P0 = I₃`` with ``H = [[1, 1, 1], [1, 1, 1 + δ]]`` and
    ``R = δ² I₂`` (the prediction before it: ``F = I``, ``Q = 10⁻³⁰ I``, below the rounding of
    ``P``): the filter's posterior covariance, its factor, and the problem's float64 matrices."""
    H = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0 + delta]], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    R = delta**2 * torch.eye(2, dtype=torch.float64)
    model = ts.models.LinearGaussian(eye, H, 1e-30 * eye, R).to(dtype)
    est = ts.KalmanFilter(model, covariance_form=form)
    z = torch.zeros(1, 1, 2, dtype=dtype)
    with torch.no_grad():
        state, out = est.scan(
            est.init(torch.zeros(1, 3, dtype=dtype), torch.eye(3, dtype=dtype)), z
        )
    matrices = [m.detach().double().numpy() for m in (model.meas_matrix(), model.meas_cov())]
    prior = (torch.eye(3, dtype=dtype) + model.process_noise()).double().numpy()
    return out.cov[0, 0].double(), state.factor, (prior, *matrices)


def _factor_is_positive_definite(carried) -> bool:
    f = carried.factor
    if isinstance(f, factored.Cholesky):
        pivots = f.S.diagonal(dim1=-2, dim2=-1)
    elif isinstance(f, (factored.UD, factored.SVD)):
        pivots = f.d
    else:
        return bool(torch.linalg.cholesky_ex(f.P).info == 0)
    return bool(torch.isfinite(pivots).all() and (pivots > 0).all())


DELTAS = [1e-9, 1e-10, 1e-11, 1e-12]


def test_ill_conditioned_update_breaks_the_conventional_form_only():
    """Below δ ≈ √eps, ``HPHᵀ + R`` is singular in float64: the conventional ``P = (I − KH)P``
    loses the second measurement (an error of 1/6: an eigenvalue 0.75 stays near 1), is not
    symmetric, and at some δ indefinite. The square-root, UD and SVD forms keep a positive
    definite factor and an error of the order eps/δ (the conditioning of their pre-arrays),
    against the exact posterior computed in rational arithmetic from the same float64 inputs."""
    eps = torch.finfo(torch.float64).eps
    indefinite = []
    for delta in DELTAS:
        exact = None
        for form in ("conventional", *FACTORED):
            P, carried, (prior, H, R) = _delta_example(delta, torch.float64, form)
            if exact is None:
                exact = torch.from_numpy(ref.exact_information_update(prior, H, R))
            error = (P - exact).abs().max().item()
            if form == "conventional":
                assert error > 0.1 and bool((P != P.mT).any()), (delta, error)
                indefinite.append(bool(torch.linalg.eigvalsh(0.5 * (P + P.mT)).min() < 0))
            else:
                assert _factor_is_positive_definite(carried), (form, delta)
                assert error < 10 * eps / delta, (form, delta, error)
    assert any(indefinite), indefinite


@pytest.mark.parametrize("form", ["sqrt", "ud", "svd"])
def test_factored_forms_use_the_adaptive_noise_of_every_step(form):
    """Adaptive R (Eqs. 29-30) changes R at every step: a factored form must update with that
    R_k, not the model's, so it agrees with the Joseph form under the same adaptive R (and both
    differ from the model's fixed R)."""
    from torchsvs.filters import AdaptiveNoise

    g = torch.Generator().manual_seed(3)
    model = ts.models.ConstantVelocity(ndim=2, q=1.0, r=4.0)
    z = torch.randn(3, 60, 2, generator=g, dtype=torch.float64).cumsum(1) * 3
    z[0, 5, 1] = float("nan")
    x0, P0 = torch.zeros(3, 4, dtype=torch.float64), 10 * torch.eye(4, dtype=torch.float64)
    for make in (
        lambda **kw: ts.KalmanFilter(model, **kw),
        lambda **kw: ts.SVSF(model, psi=[50.0, 20.0, 50.0, 20.0], gamma=0.1, **kw),
    ):
        joseph = make(adaptive_noise=AdaptiveNoise(window=10)).double()(z, x0, P0)
        factored = make(adaptive_noise=AdaptiveNoise(window=10), covariance_form=form).double()
        out = factored(z, x0, P0)
        fixed = make(covariance_form=form).double()(z, x0, P0)
        torch.testing.assert_close(out.mean, joseph.mean, rtol=0, atol=1e-9)
        torch.testing.assert_close(out.cov, joseph.cov, rtol=0, atol=1e-9)
        assert (fixed.cov - out.cov).abs().max() > 1e-3

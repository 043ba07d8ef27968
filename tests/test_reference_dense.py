"""Checks of the brute-force exact smoother error covariance in ``tests/reference/svs_numpy.py``.

``ref.dense_smoother_covariance`` writes every filter / smoother error as an explicit linear
map of the noise vector ``xi = (x~_init, w_0.., v_0..)`` and returns ``M Cov(xi) M^T``. These
tests check the map itself (Joseph P's, Kalman/RTS optimality, Monte Carlo), so that it can be
trusted as an oracle for a fast recursion.
"""

import numpy as np
import pytest

from tests.reference import svs_numpy as ref


def random_system(n, m, T, seed):
    """Seeded random stable linear-Gaussian system with simulated measurements ``z [T, m]``."""
    rng = np.random.default_rng(seed)
    F = np.eye(n) + 0.25 * rng.standard_normal((n, n))
    F /= max(1.0, np.max(np.abs(np.linalg.eigvals(F))) / 0.97)
    H = rng.standard_normal((m, n))
    A = rng.standard_normal((n, n))
    Q = 0.1 * (A @ A.T) / n + 0.05 * np.eye(n)
    B = rng.standard_normal((m, m))
    R = 0.5 * (B @ B.T) / m + 0.2 * np.eye(m)
    P0 = np.eye(n) + 0.1 * np.ones((n, n))
    x0 = rng.standard_normal(n)
    x = x0 + np.linalg.cholesky(P0) @ rng.standard_normal(n)
    Lq, Lr = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    z = np.zeros((T, m))
    for t in range(T):
        x = F @ x + Lq @ rng.standard_normal(n)
        z[t] = H @ x + Lr @ rng.standard_normal(m)
    return z, x0, P0, F, H, Q, R


def with_missing(z):
    z = z.copy()
    z[2, 0] = np.nan
    z[5, :] = np.nan  # one all-missing step
    z[7, -1] = np.nan
    z[10, 0] = np.nan
    return z


def svsf_setup(z, x0, P0, F, H, Q, R, gamma=0.3):
    """psi near the innovation scale (median |e| of a KF run) so that the saturation switches."""
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    obs = kf["observed"]
    psi = np.array([np.median(np.abs(kf["innovation"][obs[:, i], i])) for i in range(z.shape[1])])
    res = ref.svsf(z, x0, P0, F, H, Q, R, psi, gamma)
    K = ref.svsf_gains(z, x0, P0, F, H, Q, R, psi, gamma)
    return res, K, psi


def assert_rel(actual, expected, rtol, msg=""):
    scale = np.max(np.abs(expected))
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * scale, err_msg=msg)


def assert_sym_psd(C, msg=""):
    for k, Ck in enumerate(C):
        scale = np.max(np.abs(Ck))
        np.testing.assert_allclose(Ck, Ck.T, rtol=0, atol=1e-12 * scale, err_msg=f"{msg} k={k}")
        ev = np.linalg.eigvalsh(0.5 * (Ck + Ck.T))
        assert ev.min() >= -1e-12 * scale, f"{msg} k={k}: min eigenvalue {ev.min():.3e}"


SYSTEMS = [(4, 2, 15, 0), (3, 3, 12, 1)]


# --------------------------------------------------------------------------------------------
# gain helpers reproduce the reference filters
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("missing", [False, True])
def test_gain_helpers_reproduce_updates(missing):
    z, x0, P0, F, H, Q, R = random_system(4, 2, 15, 0)
    if missing:
        z = with_missing(z)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    Kk = ref.kalman_gains(z, x0, P0, F, H, Q, R)
    sv, Ks, psi = svsf_setup(z, x0, P0, F, H, Q, R)
    for res, K in ((kf, Kk), (sv, Ks)):
        obs = res["observed"]
        # zero columns for missing components, zero gain for an all-missing step
        assert np.all(K.transpose(0, 2, 1)[~obs] == 0.0)
        upd = np.einsum("tnm,tm->tn", K, res["innovation"])
        assert_rel(upd, res["mean"] - res["pred_mean"], 1e-12)
    if missing:
        assert np.all(Kk[5] == 0.0) and np.all(Ks[5] == 0.0)
    # the SVSF gain is not the Kalman gain (sanity of the setup)
    assert np.max(np.abs(Ks - Kk)) > 1e-2


# --------------------------------------------------------------------------------------------
# 1. Kalman gains: the dense covariance is the classical (windowed) RTS covariance
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("system", SYSTEMS)
@pytest.mark.parametrize("kind", ["rts", "svss"])
def test_kalman_gains_equal_rts(system, kind):
    z, x0, P0, F, H, Q, R = random_system(*system)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    K = ref.kalman_gains(z, x0, P0, F, H, Q, R)
    obs = kf["observed"]
    for lag in (None, 1, 2):
        d = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=lag, kind=kind)
        assert_rel(d["cov"], ref.rts_window(kf, F, lag=lag)["cov"], 1e-8, f"lag={lag}")
        assert_rel(d["filter_cov"], kf["cov"], 1e-9)
        assert_rel(d["pred_cov"], kf["pred_cov"], 1e-9)
    d0 = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=0, kind=kind)
    assert_rel(d0["cov"], kf["cov"], 1e-9)


# --------------------------------------------------------------------------------------------
# 2. SVSF gains: symmetric PSD, dense filter covariance = Joseph = reference svsf "cov"
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("system", SYSTEMS)
def test_svsf_gains_psd_and_joseph(system):
    z, x0, P0, F, H, Q, R = random_system(*system)
    sv, K, psi = svsf_setup(z, x0, P0, F, H, Q, R)
    e = np.abs(sv["innovation"])
    assert np.any(e > psi) and np.any(e < psi), "saturation should switch"
    obs = sv["observed"]
    for kind in ("svss", "rts"):
        for lag in (1, 2, 3, None):
            d = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=lag, kind=kind)
            assert_sym_psd(d["cov"], f"{kind} lag={lag}")
            assert_rel(d["filter_cov"], d["P_post"], 1e-10)
            assert_rel(d["pred_cov"], d["P_pred"], 1e-10)
            assert_rel(d["filter_cov"], sv["cov"], 1e-10)
            assert_rel(d["pred_cov"], sv["pred_cov"], 1e-10)
        # lag 0: the smoother is the filter
        d0 = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=0, kind=kind)
        assert_rel(d0["cov"], sv["cov"], 1e-10)
    # the suboptimal gains make a difference: svss and rts (lag None) are not the same
    ds = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, kind="svss")["cov"]
    dr = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, kind="rts")["cov"]
    assert np.max(np.abs(ds - dr)) > 1e-6 * np.max(np.abs(dr))


@pytest.mark.parametrize("system", SYSTEMS)
@pytest.mark.parametrize("missing", [False, True])
def test_svsf_gains_rts_kind_equals_rts_window(system, missing):
    """For ANY fixed gains the RTS covariance recursion (Eq. 17 with the Joseph P's) is exact:
    eps_k = (x~_{k|k} - A_k x~_{k+1|k}) + A_k eps_{k+1}, the two terms are uncorrelated since
    A_k P_{k+1|k} = P_{k|k} F^T. So kind="rts" must equal rts_window over the SVSF (SVSTPS),
    while kind="svss" is NOT P_{k|k} - sum M S M^T (that covariance assumes optimal gains)."""
    z, x0, P0, F, H, Q, R = random_system(*system)
    if missing:
        z = with_missing(z)
    sv, K, psi = svsf_setup(z, x0, P0, F, H, Q, R)
    obs = sv["observed"]
    for lag in (None, 0, 1, 2, 3):
        d = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=lag, kind="rts")
        assert_rel(d["cov"], ref.rts_window(sv, F, lag=lag)["cov"], 1e-8, f"lag={lag}")
    d = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=2, kind="svss")
    claimed = ref.smooth_direct(sv, F, H, R, lag=2)["cov"]
    assert np.max(np.abs(d["cov"] - claimed)) > 1e-3 * np.max(np.abs(claimed))


# --------------------------------------------------------------------------------------------
# 3. Monte Carlo: simulate truth, data and the fixed-gain filter + smoother directly
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["svss", "rts"])
def test_monte_carlo_matches_dense(kind):
    z, x0, P0, F, H, Q, R = random_system(4, 2, 15, 0)
    z = with_missing(z)
    sv, K, psi = svsf_setup(z, x0, P0, F, H, Q, R)
    obs = sv["observed"]
    T, m = obs.shape
    n = F.shape[0]
    lag = 2
    d = ref.dense_smoother_covariance(F, H, Q, R, P0, K, obs, lag=lag, kind=kind)

    # smoother gains written inline from the reference svsf's (Joseph) covariances
    Pf, Pp = sv["cov"], sv["pred_cov"]
    C = [Pf[i] @ F.T @ np.linalg.inv(Pp[i + 1]) for i in range(T - 1)]
    G = np.zeros((T, n, m))
    for N in range(T):
        idx = np.flatnonzero(obs[N])
        if kind == "rts":
            G[N] = K[N]
        elif idx.size:
            Ho = H[idx]
            S = Ho @ Pp[N] @ Ho.T + R[np.ix_(idx, idx)]
            G[N][:, idx] = Pp[N] @ Ho.T @ np.linalg.inv(S)

    # draws: truth x, data y (missing -> not used), estimator with the fixed gains
    Nd = 20000
    rng = np.random.default_rng(12345)
    Lp, Lq, Lr = (np.linalg.cholesky(A) for A in (P0, Q, R))
    x = x0 + rng.standard_normal((Nd, n)) @ Lp.T  # truth one step before z[0]
    xhat = np.broadcast_to(x0, (Nd, n)).copy()
    err_rec = x - xhat  # error recursion run alongside
    truth, xf, innov, err_f = [], [], [], []
    for t in range(T):
        w = rng.standard_normal((Nd, n)) @ Lq.T
        v = rng.standard_normal((Nd, m)) @ Lr.T
        x = x @ F.T + w
        y = x @ H.T + v
        xp = xhat @ F.T
        e = np.where(obs[t], y - xp @ H.T, 0.0)
        xhat = xp + e @ K[t].T
        err_p = err_rec @ F.T + w
        e_rec = err_p @ (obs[t][:, None] * H).T + np.where(obs[t], v, 0.0)
        err_rec = err_p - e_rec @ K[t].T
        truth.append(x)
        xf.append(xhat)
        innov.append(e)
        err_f.append(err_rec)
        np.testing.assert_allclose(e, e_rec, atol=1e-9)
    for t in range(T):
        np.testing.assert_allclose(truth[t] - xf[t], err_f[t], atol=1e-9)

    worst = 0.0
    for k in range(T):
        xs = xf[k].copy()
        prod = np.eye(n)
        for j in range(1, min(lag, T - 1 - k) + 1):
            prod = prod @ C[k + j - 1]
            xs = xs + innov[k + j] @ (prod @ G[k + j]).T
        eps = truth[k] - xs
        S_mc = eps.T @ eps / Nd  # the errors have mean zero
        rel = np.linalg.norm(S_mc - d["cov"][k]) / np.linalg.norm(d["cov"][k])
        worst = max(worst, rel)
        # filter error too
        ef = err_f[k]
        relf = np.linalg.norm(ef.T @ ef / Nd - d["filter_cov"][k]) / np.linalg.norm(
            d["filter_cov"][k]
        )
        worst = max(worst, relf)
    assert worst < 0.05, f"worst relative Frobenius error {worst:.3f}"


# --------------------------------------------------------------------------------------------
# 4. missing data (partially missing steps and one all-NaN step)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("system", SYSTEMS)
def test_missing_data(system):
    z, x0, P0, F, H, Q, R = random_system(*system)
    z = with_missing(z)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    Kk = ref.kalman_gains(z, x0, P0, F, H, Q, R)
    sv, Ks, psi = svsf_setup(z, x0, P0, F, H, Q, R)
    obs = kf["observed"]
    assert not obs[5].any()
    for kind in ("svss", "rts"):
        for lag in (None, 1, 2, 3):
            d = ref.dense_smoother_covariance(F, H, Q, R, P0, Kk, obs, lag=lag, kind=kind)
            assert_sym_psd(d["cov"], f"KF {kind} lag={lag}")
            if lag != 3:
                assert_rel(d["cov"], ref.rts_window(kf, F, lag=lag)["cov"], 1e-8)
            assert_rel(d["filter_cov"], kf["cov"], 1e-9)
            s = ref.dense_smoother_covariance(F, H, Q, R, P0, Ks, obs, lag=lag, kind=kind)
            assert_sym_psd(s["cov"], f"SVSF {kind} lag={lag}")
            assert_rel(s["filter_cov"], sv["cov"], 1e-10)
            assert_rel(s["filter_cov"], s["P_post"], 1e-10)
    # gains in missing columns are ignored (they multiply zeros)
    Kj = Ks.copy()
    Kj[2][:, 0] = 7.0
    Kj[5] = 3.0
    a = ref.dense_smoother_covariance(F, H, Q, R, P0, Ks, obs, lag=2)
    b = ref.dense_smoother_covariance(F, H, Q, R, P0, Kj, obs, lag=2)
    np.testing.assert_array_equal(a["cov"], b["cov"])

"""Self-checks of the float64 NumPy oracle ``tests/reference/svs_numpy.py`` (Chen et al. 2020).

The oracle is checked against itself and against independent formulations (an inline
classical RTS, a dense batch Gaussian conditioning, an inline SVSF written with the closed form
``sat(e/psi)/e = 1/max(|e|, psi)``, Eq. (A21)), so that a mistake in it is likely to show up.
"""

import numpy as np
import pytest

from tests.reference import svs_numpy as ref

RTOL = 1e-9
ATOL = 1e-9


def cv_model(T=20, seed=0, q=0.5, r=4.0):
    """Constant-velocity model of Eqs. (43)-(48) with position measurements, Eq. (45)."""
    rng = np.random.default_rng(seed)
    dt = 1.0
    F = np.array([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]], dtype=np.float64)
    qb = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = q * np.kron(np.eye(2), qb)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = r * np.eye(2)
    L = np.linalg.cholesky(Q)
    x = np.array([0.0, 1.0, 0.0, -0.5])
    xs = np.zeros((T, 4))
    for t in range(T):
        x = F @ x + L @ rng.standard_normal(4)
        xs[t] = x
    z = xs @ H.T + np.sqrt(r) * rng.standard_normal((T, 2))
    x0 = np.array([0.5, 0.8, -0.3, -0.3])
    P0 = np.diag([4.0, 1.0, 4.0, 1.0])
    return z, x0, P0, F, H, Q, R


def generic_model(T=15, seed=1):
    """A non-structured model: dense F, H (3 x 4), correlated R; exercises non-commuting C_i."""
    rng = np.random.default_rng(seed)
    n, m = 4, 3
    F = np.eye(n) + 0.2 * rng.standard_normal((n, n))
    F /= max(1.0, np.max(np.abs(np.linalg.eigvals(F))) / 0.98)
    H = rng.standard_normal((m, n))
    A = rng.standard_normal((n, n))
    Q = 0.1 * (A @ A.T) + 0.05 * np.eye(n)
    B = rng.standard_normal((m, m))
    R = 0.3 * (B @ B.T) + 0.2 * np.eye(m)
    x = rng.standard_normal(n)
    xs = np.zeros((T, n))
    for t in range(T):
        x = F @ x + np.linalg.cholesky(Q) @ rng.standard_normal(n)
        xs[t] = x
    z = xs @ H.T + (np.linalg.cholesky(R) @ rng.standard_normal((m, T))).T
    x0 = np.zeros(n)
    P0 = np.eye(n)
    return z, x0, P0, F, H, Q, R


def with_missing(z):
    z = z.copy()
    z[3, 1] = np.nan
    z[5, :] = np.nan
    z[8, 0] = np.nan
    z[9, :] = np.nan
    return z


def classical_rts(kf, F, Q):
    """Independent textbook RTS pass; predictions recomputed from F, Q (not taken from kf)."""
    xf, Pf = kf["mean"], kf["cov"]
    T = xf.shape[0]
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(T - 2, -1, -1):
        xp = F @ xf[k]
        Pp = F @ Pf[k] @ F.T + Q
        G = Pf[k] @ F.T @ np.linalg.inv(Pp)
        xs[k] = xf[k] + G @ (xs[k + 1] - xp)
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp) @ G.T
    return xs, Ps


def batch_posterior(z, x0, P0, F, H, Q, R):
    """Dense Gaussian conditioning of [x_{-1}, x_0, ..., x_{T-1}] on z (NaN = not observed).

    Returns mean [T, n] and cov [T, n, n] of x_0..x_{T-1} given all of z.
    """
    T = z.shape[0]
    n = x0.shape[0]
    D = (T + 1) * n
    Lam = np.zeros((D, D))
    eta = np.zeros(D)

    def blk(i):
        return slice(i * n, (i + 1) * n)

    P0i = np.linalg.inv(P0)
    Lam[blk(0), blk(0)] += P0i
    eta[blk(0)] += P0i @ x0
    Qi = np.linalg.inv(Q)
    for t in range(T):
        A = np.zeros((n, D))
        A[:, blk(t)] = -F
        A[:, blk(t + 1)] = np.eye(n)
        Lam += A.T @ Qi @ A
        idx = np.flatnonzero(~np.isnan(z[t]))
        if idx.size:
            Ho = H[idx]
            Roi = np.linalg.inv(R[np.ix_(idx, idx)])
            Lam[blk(t + 1), blk(t + 1)] += Ho.T @ Roi @ Ho
            eta[blk(t + 1)] += Ho.T @ Roi @ z[t, idx]
    cov = np.linalg.inv(Lam)
    mean = cov @ eta
    means = np.stack([mean[blk(t + 1)] for t in range(T)])
    covs = np.stack([cov[blk(t + 1), blk(t + 1)] for t in range(T)])
    return means, covs


def inline_svsf(z, x0, P0, F, H, Q, R, psi, gamma):
    """Independent SVSF (no missing data): correction by Eq. (5), gain by the closed form."""
    T, m = z.shape
    n = x0.shape[0]
    Hp = np.linalg.pinv(H)
    x, P = x0.copy(), P0.copy()
    e_mem = np.zeros(m)
    means, covs = [], []
    for t in range(T):
        xp = F @ x
        Pp = F @ P @ F.T + Q
        e = z[t] - H @ xp
        x = xp + Hp @ ((np.abs(e) + gamma * np.abs(e_mem)) * np.clip(e / psi, -1, 1))  # Eq. (5)
        K = Hp @ np.diag((np.abs(e) + gamma * np.abs(e_mem)) / np.maximum(np.abs(e), psi))
        IKH = np.eye(n) - K @ H
        P = IKH @ Pp @ IKH.T + K @ R @ K.T
        e_mem = z[t] - H @ x
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


# --------------------------------------------------------------------------------------------
# (a) smoothers on a Kalman filter
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("missing", [False, True])
def test_kf_direct_full_equals_rts_and_classical(missing):
    z, x0, P0, F, H, Q, R = cv_model()
    if missing:
        z = with_missing(z)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    d = ref.smooth_direct(kf, F, H, R, lag=None)
    r = ref.rts_window(kf, F, lag=None)
    xs, Ps = classical_rts(kf, F, Q)
    np.testing.assert_allclose(d["mean"], r["mean"], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(d["cov"], r["cov"], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(d["mean"], xs, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(d["cov"], Ps, rtol=RTOL, atol=ATOL)
    # the "rts" increment (unrolled Eq. 17) is the same thing on a KF
    u = ref.smooth_direct(kf, F, H, R, lag=None, increment="rts")
    np.testing.assert_allclose(u["mean"], d["mean"], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(u["cov"], d["cov"], rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("lag", [0, 1, 2, 3])
def test_kf_direct_fixed_lag_equals_rts_window(lag):
    z, x0, P0, F, H, Q, R = generic_model()
    z = with_missing(z)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    d = ref.smooth_direct(kf, F, H, R, lag=lag)
    r = ref.rts_window(kf, F, lag=lag)
    np.testing.assert_allclose(d["mean"], r["mean"], rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(d["cov"], r["cov"], rtol=RTOL, atol=ATOL)
    if lag == 0:
        np.testing.assert_array_equal(d["mean"], kf["mean"])
        np.testing.assert_array_equal(r["mean"], kf["mean"])


def test_kf_and_smoothers_match_batch_conditioning():
    z, x0, P0, F, H, Q, R = generic_model(T=12)
    z = with_missing(z)
    T = z.shape[0]
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    # full interval
    bm, bP = batch_posterior(z, x0, P0, F, H, Q, R)
    d = ref.smooth_direct(kf, F, H, R)
    np.testing.assert_allclose(d["mean"], bm, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(d["cov"], bP, rtol=1e-8, atol=1e-8)
    # filter (x_{t|t}) and fixed lag 2 (x_{k|k+2}) from truncated data
    d2 = ref.smooth_direct(kf, F, H, R, lag=2)
    for t in range(T):
        bm_t, bP_t = batch_posterior(z[: t + 1], x0, P0, F, H, Q, R)
        np.testing.assert_allclose(kf["mean"][t], bm_t[t], rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(kf["cov"][t], bP_t[t], rtol=1e-8, atol=1e-8)
        end = min(t + 2, T - 1)
        bm_l, bP_l = batch_posterior(z[: end + 1], x0, P0, F, H, Q, R)
        np.testing.assert_allclose(d2["mean"][t], bm_l[t], rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(d2["cov"][t], bP_l[t], rtol=1e-8, atol=1e-8)


def test_kf_missing_component_equals_reduced_model():
    z, x0, P0, F, H, Q, R = cv_model()
    zn = z.copy()
    zn[:, 1] = np.nan
    a = ref.kalman_filter(zn, x0, P0, F, H, Q, R)
    b = ref.kalman_filter(z[:, :1], x0, P0, F, H[:1], Q, R[:1, :1])
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a["innovation"][:, :1], b["innovation"], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(a["innovation"][:, 1], 0.0)
    np.testing.assert_array_equal(a["post_innovation"][:, 1], 0.0)


# --------------------------------------------------------------------------------------------
# (b) SVSF limits and gain
# --------------------------------------------------------------------------------------------


def square_model(T=15, seed=2):
    rng = np.random.default_rng(seed)
    F = np.array([[1.0, 0.3], [-0.2, 0.9]])
    H = np.array([[1.0, 0.5], [0.2, 1.3]])  # square, invertible
    Q = np.array([[0.2, 0.05], [0.05, 0.1]])
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    z = rng.standard_normal((T, 2)) * 3.0
    return z, np.array([0.3, -0.2]), np.eye(2), F, H, Q, R


def test_svsf_huge_psi_gives_almost_no_correction():
    z, x0, P0, F, H, Q, R = square_model()
    sv = ref.svsf(z, x0, P0, F, H, Q, R, psi=[1e12, 1e12], gamma=0.0)
    # linear region of sat: K = H^{-1} diag(|e|)/psi ~ 0
    np.testing.assert_allclose(sv["mean"], sv["pred_mean"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sv["cov"], sv["pred_cov"], rtol=1e-9, atol=1e-9)
    kf = ref.kalman_filter(z, x0, P0, F, H, Q, R)
    assert np.max(np.abs(kf["mean"] - sv["mean"])) > 1e-2  # not the KF


def test_svsf_tiny_psi_identity_h_is_full_correction():
    z, x0, P0, F, _, Q, R = square_model()
    H = np.eye(2)
    sv = ref.svsf(z, x0, P0, F, H, Q, R, psi=[1e-12, 1e-12], gamma=0.0)
    np.testing.assert_allclose(sv["mean"], z, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(sv["post_innovation"], 0.0, rtol=0, atol=1e-13)
    # saturated gain with gamma = 0 is K = diag(|e|/|e|) = I: posterior covariance is R
    np.testing.assert_allclose(sv["cov"], np.broadcast_to(R, sv["cov"].shape), atol=1e-12)


@pytest.mark.parametrize("gamma", [0.0, 0.1, 0.7])
def test_svsf_matches_inline_closed_form(gamma):
    z, x0, P0, F, H, Q, R = generic_model()
    psi = np.array([0.5, 1.5, 3.0])
    sv = ref.svsf(z, x0, P0, F, H, Q, R, psi, gamma)
    m_, P_ = inline_svsf(z, x0, P0, F, H, Q, R, psi, gamma)
    np.testing.assert_allclose(sv["mean"], m_, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sv["cov"], P_, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(sv["post_innovation"], z - sv["mean"] @ H.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sv["innovation"], z - sv["pred_mean"] @ H.T, rtol=1e-12, atol=1e-12)


def test_svsf_gain_zero_innovation_limit():
    Hp = np.array([[1.0, 0.0], [0.5, 2.0], [0.0, 1.0]])
    e = np.array([0.0, 3.0])
    e_mem = np.array([2.0, 1.0])
    psi = np.array([4.0, 1.0])
    gamma = 0.25
    K = ref.svsf_gain(Hp, e, e_mem, psi, gamma)  # warnings are errors under pytest config
    expected = Hp @ np.diag([gamma * 2.0 / 4.0, (3.0 + gamma * 1.0) / 3.0])
    np.testing.assert_allclose(K, expected, rtol=1e-15, atol=0)
    # a filter step with an exactly zero innovation: finite, no correction
    z = np.array([[1.5, -2.0]])
    sv = ref.svsf(z, z[0], np.eye(2), np.eye(2), np.eye(2), 0.1 * np.eye(2), np.eye(2), psi, 0.5)
    np.testing.assert_array_equal(sv["innovation"], 0.0)
    np.testing.assert_array_equal(sv["mean"], z)
    np.testing.assert_array_equal(sv["cov"][0], sv["pred_cov"][0])


def test_svsf_atc_velocity_never_corrected_and_h_pinv():
    z, x0, P0, F, H, Q, R = cv_model()
    psi = np.array([8.0, 8.0])
    sv = ref.svsf(z, x0, P0, F, H, Q, R, psi, 0.1)
    np.testing.assert_array_equal(sv["mean"][:, [1, 3]], sv["pred_mean"][:, [1, 3]])
    sv2 = ref.svsf(z, x0, P0, F, H, Q, R, psi, 0.1, h_pinv=H.T)  # H^+ = H^T here
    for key in ("mean", "cov"):
        np.testing.assert_allclose(sv2[key], sv[key], rtol=1e-13, atol=1e-13)


# --------------------------------------------------------------------------------------------
# (c) missing data in the SVSF
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", [cv_model, generic_model])
def test_svsf_missing_component_equals_reduced_model(model):
    z, x0, P0, F, H, Q, R = model()
    psi = np.array([3.0, 5.0, 7.0])[: H.shape[0]]
    zn = z.copy()
    zn[:, 1] = np.nan
    a = ref.svsf(zn, x0, P0, F, H, Q, R, psi, 0.2)
    keep = [i for i in range(H.shape[0]) if i != 1]
    b = ref.svsf(z[:, keep], x0, P0, F, H[keep], Q, R[np.ix_(keep, keep)], psi[keep], 0.2)
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a["innovation"][:, keep], b["innovation"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        a["post_innovation"][:, keep], b["post_innovation"], rtol=1e-12, atol=1e-12
    )
    np.testing.assert_array_equal(a["innovation"][:, 1], 0.0)
    np.testing.assert_array_equal(a["post_innovation"][:, 1], 0.0)
    # the smoother skips the missing component the same way
    for lag in (1, 2):
        da = ref.smooth_direct(a, F, H, R, lag=lag)
        db = ref.smooth_direct(b, F, H[keep], R[np.ix_(keep, keep)], lag=lag)
        np.testing.assert_allclose(da["mean"], db["mean"], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(da["cov"], db["cov"], rtol=1e-10, atol=1e-10)


def test_svsf_missing_rows_carry_memory_and_predict():
    z, x0, P0, F, H, Q, R = cv_model()
    z = with_missing(z)
    sv = ref.svsf(z, x0, P0, F, H, Q, R, np.array([8.0, 8.0]), 0.1)
    for t in (5, 9):  # all-NaN rows: pure prediction, memory carried
        np.testing.assert_array_equal(sv["mean"][t], sv["pred_mean"][t])
        np.testing.assert_array_equal(sv["cov"][t], sv["pred_cov"][t])
        np.testing.assert_array_equal(sv["innovation"][t], 0.0)
        np.testing.assert_array_equal(sv["post_innovation"][t], sv["post_innovation"][t - 1])
    assert sv["post_innovation"][3, 1] == sv["post_innovation"][2, 1]
    assert sv["innovation"][3, 1] == 0.0
    assert np.all(np.isfinite(sv["mean"]))


# --------------------------------------------------------------------------------------------
# SVSS over an SVSF
# --------------------------------------------------------------------------------------------


def test_svss_lag1_on_svsf_matches_eq_a21():
    z, x0, P0, F, H, Q, R = generic_model()
    sv = ref.svsf(z, x0, P0, F, H, Q, R, np.array([0.5, 1.5, 3.0]), 0.1)
    d = ref.smooth_direct(sv, F, H, R, lag=1)
    T = z.shape[0]
    for k in range(T - 1):
        Pf = sv["cov"][k]
        S = H @ sv["pred_cov"][k + 1] @ H.T + R
        G = Pf @ F.T @ H.T @ np.linalg.inv(S)  # Eq. (A16)/(A21)
        np.testing.assert_allclose(
            d["mean"][k], sv["mean"][k] + G @ sv["innovation"][k + 1], rtol=1e-9, atol=1e-9
        )
        np.testing.assert_allclose(d["cov"][k], Pf - G @ S @ G.T, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(d["mean"][T - 1], sv["mean"][T - 1])


@pytest.mark.parametrize("lag", [1, 2, 4, None])
def test_unrolled_rts_equals_rts_window_on_svsf(lag):
    z, x0, P0, F, H, Q, R = generic_model(T=12)
    sv = ref.svsf(z, x0, P0, F, H, Q, R, np.array([0.5, 1.5, 3.0]), 0.1)
    u = ref.smooth_direct(sv, F, H, R, lag=lag, increment="rts")
    r = ref.rts_window(sv, F, lag=lag)
    np.testing.assert_allclose(u["mean"], r["mean"], rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(u["cov"], r["cov"], rtol=1e-8, atol=1e-9)
    # and SVSS differs from SVSTPS over an SVSF (non-optimal gain)
    s = ref.smooth_direct(sv, F, H, R, lag=lag)
    assert np.max(np.abs(s["mean"] - u["mean"])) > 1e-6


def test_rts_window_full_equals_long_lag():
    z, x0, P0, F, H, Q, R = cv_model(T=10)
    sv = ref.svsf(z, x0, P0, F, H, Q, R, np.array([8.0, 8.0]), 0.1)
    a = ref.rts_window(sv, F, lag=None)
    b = ref.rts_window(sv, F, lag=100)
    np.testing.assert_allclose(a["mean"], b["mean"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a["cov"], b["cov"], rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Eq. (51)
# --------------------------------------------------------------------------------------------


def test_finite_difference_velocity():
    z = np.array([[0.0, 10.0], [2.0, 9.0], [np.nan, 7.0], [8.0, 4.0], [9.0, np.nan]])
    y = ref.finite_difference_velocity(z, dt=2.0)
    expected = np.array(
        [
            [0.0, np.nan, 10.0, np.nan],
            [2.0, 1.0, 9.0, -0.5],
            [np.nan, np.nan, 7.0, -1.0],
            [8.0, np.nan, 4.0, -1.5],
            [9.0, 0.5, np.nan, np.nan],
        ]
    )
    np.testing.assert_array_equal(y, expected)

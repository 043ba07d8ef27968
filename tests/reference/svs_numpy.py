"""Float64 NumPy reference ("oracle") for the torchsvs filters and smoothers.

Written only from the paper

    Chen, Xu, Yan, Li, "A Novel Smooth Variable Structure Smoother for Robust Estimation",
    Sensors 20(6):1781, 2020 (``/work/shared/papers/svss-chen-2020.md``)

and the reading notes in ``/work/shared/papers/README.md``. Single track (no batch), plain
Python loops over time, written for clarity, not speed. Nothing here is meant to be fast.

Conventions (shared by every function)
--------------------------------------
* ``z`` is ``[T, m]``; a NaN entry is a missing measurement component.
* ``x0 [n]``, ``P0 [n, n]`` is the prior ONE STEP BEFORE ``z[0]``. Step ``t = 0..T-1`` first
  predicts from the previous posterior (``x_{t|t-1} = F x_{t-1|t-1}``,
  ``P_{t|t-1} = F P F^T + Q``) and then updates with ``z[t]``.
* ``F [n, n]``, ``H [m, n]``, ``Q [n, n]``, ``R [m, m]`` are constant.
* The filters return a dict of arrays:

  ``mean [T, n]``            x_{t|t}
  ``cov [T, n, n]``          P_{t|t}
  ``pred_mean [T, n]``       x_{t|t-1}
  ``pred_cov [T, n, n]``     P_{t|t-1}
  ``innovation [T, m]``      a-priori e_{t|t-1} = z_t - H x_{t|t-1}, 0.0 where z is NaN
  ``post_innovation [T, m]`` e_{t|t} = z_t - H x_{t|t}; where z is NaN the previous step's
                             value of that component is carried (0.0 before the first step)
  ``observed [T, m]``        (extra key, bool) ~isnan(z); lets ``smooth_direct`` tell a
                             missing component from an innovation that is exactly 0.

Readings of the paper decided here (see the README's reading notes)
-------------------------------------------------------------------
* Eq. (21) prints ``z_k - H x_{k+1|k}``; the innovation used is ``z_{k+1} - H x_{k+1|k}``
  (Eq. (4); only this reproduces Tables 1-2).
* The SVSF posterior covariance is the Joseph form, the LEFT side of Eq. (28); the right side
  ``(I - K H) P`` equals it only for the optimal (Kalman) gain.
* Eq. (23) has a removable singularity at e = 0: ``sat(e/psi)/e -> 1/psi``. It is evaluated
  literally (saturation, then division by e) with ``np.where`` so that nothing is ever divided
  by zero; mathematically ``sat(e/psi)/e = 1/max(|e|, psi)``.
* The "•" in Eq. (23) is read as: the diagonal matrix whose entries are
  ``(|e_{k+1|k}| + gamma |e_{k|k}|) * sat(e_{k+1|k}/psi)`` (elementwise), so that
  ``K e_{k+1|k} = H^+ [(|e_{k+1|k}| + gamma |e_{k|k}|) * sat(e_{k+1|k}/psi)]``, i.e. Eq. (5).
* ``P_{k|k+1}`` / ``x_{N-1}`` in the printed smoother are read as ``P_{k+1|k}`` /
  ``x_{N|N-1}`` (README note).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "kalman_filter",
    "svsf",
    "smooth_direct",
    "rts_window",
    "finite_difference_velocity",
    "sat",
    "svsf_gain",
]


# ----------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------


def sat(x):
    """Saturation function, Eq. (6), elementwise: clip ``x`` to [-1, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x >= 1.0, 1.0, np.where(x <= -1.0, -1.0, x))


def _right_solve(A, B):
    """Return ``A @ inv(B)`` without forming the inverse (solves ``X B = A``)."""
    return np.linalg.solve(B.T, A.T).T


def _f64(a, ndim, name):
    a = np.array(a, dtype=np.float64)  # copy: the caller's arrays are never modified
    if a.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {a.shape}")
    return a


def _check_model(z, x0, P0, F, H, Q, R):
    z = _f64(z, 2, "z")
    x0 = _f64(x0, 1, "x0")
    P0 = _f64(P0, 2, "P0")
    F = _f64(F, 2, "F")
    H = _f64(H, 2, "H")
    Q = _f64(Q, 2, "Q")
    R = _f64(R, 2, "R")
    n = x0.shape[0]
    m = H.shape[0]
    if z.shape[1] != m:
        raise ValueError(f"z has {z.shape[1]} components but H has {m} rows")
    if P0.shape != (n, n) or F.shape != (n, n) or Q.shape != (n, n):
        raise ValueError("P0, F and Q must be [n, n]")
    if H.shape != (m, n) or R.shape != (m, m):
        raise ValueError("H must be [m, n] and R must be [m, m]")
    return z, x0, P0, F, H, Q, R


def _run_filter(z, x0, P0, F, H, Q, R, gain):
    """Shared predictor-corrector loop of Eqs. (11)-(16) and (18)-(28).

    ``gain(t, idx, x_pred, P_pred, e_obs, e_mem_obs) -> K [n, len(idx)]`` returns the gain for
    the observed components ``idx`` at step ``t``; ``e_obs`` is the a-priori innovation of those
    components and ``e_mem_obs`` their (carried) posterior innovation of the previous step.
    The update is then ``x = x_pred + K e`` (Eq. 16 top / Eq. 22) and the Joseph covariance
    ``(I - K H_o) P_pred (I - K H_o)^T + K R_oo K^T`` (Eq. 16 bottom / Eq. 28 left side), with
    ``H_o`` the observed rows of H and ``R_oo`` the observed sub-block of R.
    """
    T, m = z.shape
    n = x0.shape[0]
    eye = np.eye(n)

    out_mean = np.zeros((T, n))
    out_cov = np.zeros((T, n, n))
    out_pmean = np.zeros((T, n))
    out_pcov = np.zeros((T, n, n))
    out_innov = np.zeros((T, m))
    out_post = np.zeros((T, m))
    observed = ~np.isnan(z)

    x = x0.copy()
    P = P0.copy()
    e_post_prev = np.zeros(m)  # e_{k|k} before the first step is 0

    for t in range(T):
        # prediction, Eqs. (11)-(12) / (18), (20)
        x_pred = F @ x
        P_pred = F @ P @ F.T + Q

        idx = np.flatnonzero(observed[t])
        innov = np.zeros(m)
        if idx.size == 0:
            # nothing observed: pure prediction
            x = x_pred.copy()
            P = P_pred.copy()
        else:
            H_o = H[idx, :]
            R_oo = R[np.ix_(idx, idx)]
            e = z[t, idx] - H_o @ x_pred  # Eqs. (4), (13), (21) with z_{k+1}
            K = gain(t, idx, x_pred, P_pred, e, e_post_prev[idx])
            x = x_pred + K @ e  # Eq. (16) top / Eq. (22)
            I_KH = eye - K @ H_o
            P = I_KH @ P_pred @ I_KH.T + K @ R_oo @ K.T  # Eq. (16) bottom / Eq. (28) left
            innov[idx] = e

        # posterior innovation, Eqs. (9)-(10) / (24); carry missing components
        e_post = e_post_prev.copy()
        if idx.size:
            e_post[idx] = z[t, idx] - H[idx, :] @ x

        out_mean[t] = x
        out_cov[t] = P
        out_pmean[t] = x_pred
        out_pcov[t] = P_pred
        out_innov[t] = innov
        out_post[t] = e_post
        e_post_prev = e_post

    return {
        "mean": out_mean,
        "cov": out_cov,
        "pred_mean": out_pmean,
        "pred_cov": out_pcov,
        "innovation": out_innov,
        "post_innovation": out_post,
        "observed": observed,
    }


# ----------------------------------------------------------------------------------------------
# 1. Kalman filter
# ----------------------------------------------------------------------------------------------


def kalman_filter(z, x0, P0, F, H, Q, R):
    """Kalman filter, Eqs. (11)-(16) of Chen et al. 2020, Joseph-form covariance.

    Prediction Eqs. (11)-(12); innovation covariance Eq. (14) ``S = H P H^T + R``; gain
    Eq. (15) ``K = P H^T S^{-1}``; update Eq. (16) with the Joseph form
    ``(I - K H) P (I - K H)^T + K R K^T``.

    Missing components (NaN in ``z[t]``): only the observed rows of H and the observed
    sub-block of R enter Eqs. (13)-(16). An all-NaN row is a pure prediction (posterior =
    prediction). See the module docstring for the input/output conventions.
    """
    z, x0, P0, F, H, Q, R = _check_model(z, x0, P0, F, H, Q, R)

    def gain(t, idx, x_pred, P_pred, e, e_mem):
        H_o = H[idx, :]
        R_oo = R[np.ix_(idx, idx)]
        S = H_o @ P_pred @ H_o.T + R_oo  # Eq. (14)
        return _right_solve(P_pred @ H_o.T, S)  # Eq. (15)

    return _run_filter(z, x0, P0, F, H, Q, R, gain)


# ----------------------------------------------------------------------------------------------
# 2. SVSF with covariance
# ----------------------------------------------------------------------------------------------


def svsf_gain(H_pinv, e, e_mem, psi, gamma):
    """SVSF gain matrix, Eq. (23) of Chen et al. 2020 (with the saturation of Eqs. (6)-(7)).

    ``K = H^+ diag(|e_{k+1|k}| + gamma |e_{k|k}|) diag(sat(e_{k+1|k}/psi)) diag(e_{k+1|k})^{-1}``

    ``H_pinv [n, m_o]``, ``e``, ``e_mem``, ``psi`` are ``[m_o]``. Evaluated literally: saturate,
    then divide by e; the removable singularity at ``e == 0`` is replaced by its limit
    ``sat(e/psi)/e -> 1/psi`` via ``np.where``, so no division by zero is ever performed.
    Returns ``K [n, m_o]``; ``K @ e`` is the correction of Eq. (5).
    """
    e = np.asarray(e, dtype=np.float64)
    e_mem = np.asarray(e_mem, dtype=np.float64)
    psi = np.asarray(psi, dtype=np.float64)
    s = sat(e / psi)  # Eq. (6), with psi^{-1} of Eq. (7)
    nonzero = e != 0.0
    e_safe = np.where(nonzero, e, 1.0)
    sat_over_e = np.where(nonzero, s / e_safe, 1.0 / psi)  # sat(e/psi) * diag(e)^{-1}
    d = (np.abs(e) + gamma * np.abs(e_mem)) * sat_over_e
    return H_pinv @ np.diag(d)


def svsf(z, x0, P0, F, H, Q, R, psi, gamma, h_pinv=None):
    """Smooth variable structure filter with covariance, Eqs. (18)-(28) of Chen et al. 2020.

    * prediction: Eq. (20) ``x_{k+1|k} = F x_{k|k}``, Eq. (18) ``P_{k+1|k} = F P F^T + Q``;
    * innovation: Eq. (21) read as ``e_{k+1|k} = z_{k+1} - H x_{k+1|k}`` (Eq. (4));
    * gain: Eq. (23), see :func:`svsf_gain`; ``psi [m]`` boundary-layer widths, ``gamma``
      scalar memory (0 <= gamma < 1), ``H^+`` the Moore-Penrose pseudo-inverse of H
      (``np.linalg.pinv``) unless ``h_pinv [n, m]`` is given;
    * update: Eq. (22) ``x_{k+1|k+1} = x_{k+1|k} + K e_{k+1|k}``;
    * posterior covariance: Joseph form, Eq. (28) LEFT side,
      ``(I - K H) P_{k+1|k} (I - K H)^T + K R K^T``;
    * posterior innovation: Eq. (24) ``e_{k+1|k+1} = z_{k+1} - H x_{k+1|k+1}``, used as the
      memory ``e_{k|k}`` of the next step (zeros before the first step).

    Missing components (NaN in ``z[t]``): H^+ is the pseudo-inverse of the observed rows of H
    only and only the observed components of e (and of the memory) enter the gain, so a
    missing component gives no correction; ``K`` is ``[n, m_obs]`` and the Joseph form uses
    the observed rows of H and the observed sub-block of R. ``h_pinv`` (if given) is used only
    at fully observed steps; at a partially observed step ``pinv(H[obs])`` is computed. An
    all-NaN row is a pure prediction. The memory of a missing component is carried.
    """
    z, x0, P0, F, H, Q, R = _check_model(z, x0, P0, F, H, Q, R)
    m, n = H.shape
    psi = np.array(psi, dtype=np.float64).reshape(-1)
    if psi.shape != (m,):
        raise ValueError(f"psi must have shape [{m}], got {psi.shape}")
    if np.any(psi <= 0):
        raise ValueError("psi must be positive")
    gamma = float(gamma)
    H_pinv_full = np.linalg.pinv(H) if h_pinv is None else _f64(h_pinv, 2, "h_pinv")
    if H_pinv_full.shape != (n, m):
        raise ValueError(f"h_pinv must be [{n}, {m}]")

    def gain(t, idx, x_pred, P_pred, e, e_mem):
        if idx.size == m:
            Hp = H_pinv_full
        else:
            Hp = np.linalg.pinv(H[idx, :])  # pseudo-inverse of the observed rows only
        return svsf_gain(Hp, e, e_mem, psi[idx], gamma)

    return _run_filter(z, x0, P0, F, H, Q, R, gain)


# ----------------------------------------------------------------------------------------------
# 3. smoothers
# ----------------------------------------------------------------------------------------------


def _window_end(k, T, lag):
    if lag is None:
        return T - 1
    lag = int(lag)
    if lag < 0:
        raise ValueError("lag must be >= 0 or None")
    return min(k + lag, T - 1)


def smooth_direct(res, F, H, R, lag=None, increment="svss", observed=None):
    """Direct (slow, O(T^3) for lag=None) evaluation of the SVSS, Eq. (42) / Eq. (A35).

    For every k, start from ``x_{k|k}``, ``P_{k|k}`` and for ``N = k+1, ..., min(k+lag, T-1)``
    (``lag=None``: up to T-1) add

        x_{k|N} = x_{k|N-1} + M e_N,   M = (prod_{i=k}^{N-1} C_i) B_N          (Eq. 42, A33-A35)
        C_i = P_{i|i} F^T P_{i+1|i}^{-1},  B_N = P_{N|N-1} H^T S_N^{-1},
        S_N = H P_{N|N-1} H^T + R                                             (Eq. 39, A25)
        P_{k|N} = P_{k|N-1} - M S_N M^T

    with ``e_N = res["innovation"][N]`` (= z_N - H x_{N|N-1}) and the product taken with i
    increasing from left to right. The product matrix is built literally for every (k, N).
    Missing components at N: only the observed rows of H, the observed sub-block of R and the
    observed entries of e_N enter; N is skipped if nothing was observed (the C_i product still
    runs through it). The mask is ``observed`` if given, else ``res["observed"]`` if present,
    else everything is taken as observed.

    ``increment``:
      * ``"svss"`` (default): the SVSS increment above, Eq. (42).
      * ``"rts"``: the increment ``(prod C_i) (x_{N|N} - x_{N|N-1})`` with covariance increment
        ``(prod C_i) (P_{N|N} - P_{N|N-1}) (prod C_i)^T`` -- the RTS recursion Eq. (17)
        (SVSTPS over an SVSF) unrolled; it equals :func:`rts_window` for any filter and equals
        ``"svss"`` for a Kalman filter (where ``x_{N|N} - x_{N|N-1} = B_N e_N``).

    Returns ``{"mean": [T, n], "cov": [T, n, n]}``.
    """
    if increment not in ("svss", "rts"):
        raise ValueError(f"unknown increment {increment!r}")
    F = np.asarray(F, dtype=np.float64)
    H = np.asarray(H, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    mean = np.asarray(res["mean"], dtype=np.float64)
    cov = np.asarray(res["cov"], dtype=np.float64)
    pmean = np.asarray(res["pred_mean"], dtype=np.float64)
    pcov = np.asarray(res["pred_cov"], dtype=np.float64)
    innov = np.asarray(res["innovation"], dtype=np.float64)
    T, n = mean.shape
    m = H.shape[0]
    if observed is None:
        observed = res.get("observed")
    if observed is None:
        observed = np.ones((T, m), dtype=bool)
    observed = np.asarray(observed, dtype=bool)

    # C_i = P_{i|i} F^T P_{i+1|i}^{-1}, i = 0..T-2
    C = [_right_solve(cov[i] @ F.T, pcov[i + 1]) for i in range(T - 1)]

    out_mean = np.zeros((T, n))
    out_cov = np.zeros((T, n, n))
    for k in range(T):
        x = mean[k].copy()
        P = cov[k].copy()
        for N in range(k + 1, _window_end(k, T, lag) + 1):
            prod = np.eye(n)
            for i in range(k, N):  # prod_{i=k}^{N-1} C_i, i increasing left to right
                prod = prod @ C[i]
            if increment == "svss":
                idx = np.flatnonzero(observed[N])
                if idx.size == 0:
                    continue
                H_o = H[idx, :]
                R_oo = R[np.ix_(idx, idx)]
                e_N = innov[N, idx]
                S_N = H_o @ pcov[N] @ H_o.T + R_oo
                B_N = _right_solve(pcov[N] @ H_o.T, S_N)
                M = prod @ B_N
                x = x + M @ e_N
                P = P - M @ S_N @ M.T
            else:  # "rts"
                x = x + prod @ (mean[N] - pmean[N])
                P = P + prod @ (cov[N] - pcov[N]) @ prod.T
        out_mean[k] = x
        out_cov[k] = P
    return {"mean": out_mean, "cov": out_cov}


def rts_window(res, F, lag=None):
    """Rauch-Tung-Striebel smoother, Eq. (17) of Chen et al. 2020, applied literally per window.

    For each k the backward recursion of Eq. (17)

        A_j = P_{j|j} F^T P_{j+1|j}^{-1}
        x_{j|N} = x_{j|j} + A_j (x_{j+1|N} - x_{j+1|j})
        P_{j|N} = P_{j|j} + A_j (P_{j+1|N} - P_{j+1|j}) A_j^T

    runs over the window ``j = N-1, ..., k`` with ``N = min(k+lag, T-1)``, starting from the
    filtered ``x_{N|N}``, ``P_{N|N}`` (``res["mean"][N]``, ``res["cov"][N]``) and using the
    filter's ``pred_mean`` / ``pred_cov``. ``lag=None`` is the full fixed interval (one
    backward pass). Over an SVSF this is the SVSTPS; over a Kalman filter with ``lag=None`` it
    is the classical RTS smoother (KS). Returns ``{"mean": [T, n], "cov": [T, n, n]}``.
    """
    F = np.asarray(F, dtype=np.float64)
    mean = np.asarray(res["mean"], dtype=np.float64)
    cov = np.asarray(res["cov"], dtype=np.float64)
    pmean = np.asarray(res["pred_mean"], dtype=np.float64)
    pcov = np.asarray(res["pred_cov"], dtype=np.float64)
    T, n = mean.shape

    def backward(k, N):
        """Eq. (17) from j = N-1 down to k; returns (x_{k|N}, P_{k|N})."""
        x_s = mean[N].copy()
        P_s = cov[N].copy()
        for j in range(N - 1, k - 1, -1):
            A = _right_solve(cov[j] @ F.T, pcov[j + 1])
            x_s = mean[j] + A @ (x_s - pmean[j + 1])
            P_s = cov[j] + A @ (P_s - pcov[j + 1]) @ A.T
        return x_s, P_s

    out_mean = np.zeros((T, n))
    out_cov = np.zeros((T, n, n))
    if lag is None:
        # one backward pass over the whole interval
        x_s = mean[T - 1].copy()
        P_s = cov[T - 1].copy()
        out_mean[T - 1] = x_s
        out_cov[T - 1] = P_s
        for j in range(T - 2, -1, -1):
            A = _right_solve(cov[j] @ F.T, pcov[j + 1])
            x_s = mean[j] + A @ (x_s - pmean[j + 1])
            P_s = cov[j] + A @ (P_s - pcov[j + 1]) @ A.T
            out_mean[j] = x_s
            out_cov[j] = P_s
    else:
        for k in range(T):
            out_mean[k], out_cov[k] = backward(k, _window_end(k, T, lag))
    return {"mean": out_mean, "cov": out_cov}


# ----------------------------------------------------------------------------------------------
# 4. artificial velocity measurement
# ----------------------------------------------------------------------------------------------


def finite_difference_velocity(z, dt, bridge_gaps=False):
    """Artificial velocity measurement, Eq. (51) of Chen et al. 2020.

    ``z [T, 2]`` = (x, y) positions; returns ``y [T, 4]`` =
    ``[z1_k, (z1_k - z1_{k-1})/dt, z2_k, (z2_k - z2_{k-1})/dt]``.
    The velocity is NaN at k = 0 (no previous measurement) and, per axis, wherever the current
    or the previous position of that axis is NaN. With ``bridge_gaps`` the difference is taken
    against the last earlier step at which the axis was observed, over the time between them.
    Positions are copied as-is (NaN stays NaN).
    """
    z = _f64(z, 2, "z")
    if z.shape[1] != 2:
        raise ValueError("z must be [T, 2]")
    dt = float(dt)
    T = z.shape[0]
    y = np.full((T, 4), np.nan)
    y[:, 0] = z[:, 0]
    y[:, 2] = z[:, 1]
    for k in range(1, T):
        for axis, col in ((0, 1), (1, 3)):
            cur = z[k, axis]
            if np.isnan(cur):
                continue
            j = k - 1
            if bridge_gaps:
                while j >= 0 and np.isnan(z[j, axis]):
                    j -= 1
            if j >= 0 and not np.isnan(z[j, axis]):
                y[k, col] = (cur - z[j, axis]) / ((k - j) * dt)
    return y


def finite_difference_noise(z, dt, R, bridge_gaps=True):
    """Per-step noise covariance ``[T, 4, 4]`` of :func:`finite_difference_velocity`'s ``y``.

    With ``v_i = (z_i,k - z_i,j_i)/Δ_i`` and white position noise ``R``: ``Cov(z_i, z_j) = R_ij``,
    ``Cov(z_i, v_j) = R_ij/Δ_j``, ``Cov(v_i, v_j) = R_ij (1 + [j_i = j_j]) / (Δ_i Δ_j)``.
    Entries of a missing velocity are whatever a unit interval gives (they are masked).
    """
    z = _f64(z, 2, "z")
    T = z.shape[0]
    out = np.zeros((T, 4, 4))
    pos, vel = (0, 2), (1, 3)
    for k in range(T):
        last, span = [], []
        for axis in (0, 1):
            j = k - 1
            if bridge_gaps:
                while j >= 0 and np.isnan(z[j, axis]):
                    j -= 1
            known = j >= 0 and not np.isnan(z[j, axis]) and not np.isnan(z[k, axis])
            last.append(j if known else -1)
            span.append((k - j) * dt if known else 1.0)
        for a in (0, 1):
            for b in (0, 1):
                r = R[a, b]
                out[k, pos[a], pos[b]] = r
                out[k, pos[a], vel[b]] = r / span[b]
                out[k, vel[a], pos[b]] = r / span[a]
                same = 1.0 + float(last[a] == last[b])
                out[k, vel[a], vel[b]] = r * same / (span[a] * span[b])
    return out


# ----------------------------------------------------------------------------------------------
# self-check
# ----------------------------------------------------------------------------------------------


def _demo_model(T=25, seed=0):
    rng = np.random.default_rng(seed)
    dt = 1.0
    F = np.array([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]], dtype=np.float64)
    q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = 0.5 * np.kron(np.eye(2), q)  # Eq. (48) shape
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])  # Eq. (45)
    R = 4.0 * np.eye(2)
    x_true = np.zeros((T, 4))
    x = np.array([0.0, 1.0, 0.0, -0.5])
    L = np.linalg.cholesky(Q)
    for t in range(T):
        x = F @ x + L @ rng.standard_normal(4)
        x_true[t] = x
    z = x_true @ H.T + 2.0 * rng.standard_normal((T, 2))
    x0 = np.array([0.0, 0.8, 0.0, -0.3])
    P0 = np.diag([4.0, 1.0, 4.0, 1.0])
    return z, x0, P0, F, H, Q, R


if __name__ == "__main__":
    z, x0, P0, F, H, Q, R = _demo_model()

    kf = kalman_filter(z, x0, P0, F, H, Q, R)
    d_full = smooth_direct(kf, F, H, R)
    r_full = rts_window(kf, F)
    err = np.max(np.abs(d_full["mean"] - r_full["mean"]))
    err_P = np.max(np.abs(d_full["cov"] - r_full["cov"]))
    print(f"KF: direct SVSS (lag=None) vs RTS: mean {err:.2e}, cov {err_P:.2e}")
    assert err < 1e-9 and err_P < 1e-9

    d1 = smooth_direct(kf, F, H, R, lag=1)
    r1 = rts_window(kf, F, lag=1)
    err1 = np.max(np.abs(d1["mean"] - r1["mean"]))
    print(f"KF: direct SVSS (lag=1) vs RTS window: mean {err1:.2e}")
    assert err1 < 1e-9

    Fi = np.eye(2)
    Hi = np.eye(2)
    res = svsf(z, np.zeros(2), np.eye(2), Fi, Hi, np.eye(2), np.eye(2), [1e-12, 1e-12], 0.0)
    err_z = np.max(np.abs(res["mean"] - z))
    print(f"SVSF H=I, psi->0, gamma=0: |posterior - z| max {err_z:.2e}")
    assert err_z < 1e-12

    sv = svsf(z, x0, P0, F, H, Q, R, [8.0, 8.0], 0.1)
    d_rts = smooth_direct(sv, F, H, R, lag=3, increment="rts")
    r_rts = rts_window(sv, F, lag=3)
    err_rts = np.max(np.abs(d_rts["mean"] - r_rts["mean"]))
    print(f"SVSF: unrolled RTS (lag=3) vs RTS window: mean {err_rts:.2e}")
    assert err_rts < 1e-9
    print("self-check OK")


# ----------------------------------------------------------------------------------------------
# 5. exact error covariance of a fixed-gain filter + linear smoother, by a dense linear map
# ----------------------------------------------------------------------------------------------
#
# Everything below is brute force on purpose: the estimation errors are written as explicit
# matrices acting on the stacked noise vector
#
#     xi = (x~_init, w_0, ..., w_{T-1}, v_0, ..., v_{T-1}),   dim D = n + T n + T m,
#     Cov(xi) = blockdiag(P0, Q, ..., Q, R, ..., R)
#
# (errors are truth minus estimate). Nothing here is a recursion for covariances except the
# Joseph-form P's that the smoother gains C_i, B_N are built from (as a filter would).

__all__ += [
    "kalman_gains",
    "svsf_gains",
    "noise_covariance",
    "dense_smoother_covariance",
]


def _gains_from_result(res, gain_fn):
    """Rebuild the full ``[T, n, m]`` gains of a reference filter run.

    ``gain_fn(t, idx, res) -> K_o [n, len(idx)]``; columns of missing components are 0 and an
    all-missing step has ``K_t = 0``.
    """
    observed = np.asarray(res["observed"], dtype=bool)
    T, m = observed.shape
    n = res["mean"].shape[1]
    K = np.zeros((T, n, m))
    for t in range(T):
        idx = np.flatnonzero(observed[t])
        if idx.size:
            K[t][:, idx] = gain_fn(t, idx, res)
    return K


def kalman_gains(z, x0, P0, F, H, Q, R):
    """Gains ``K_t [T, n, m]`` used by :func:`kalman_filter` on the same inputs.

    Recomputed from the returned ``pred_cov`` exactly as the filter does (Eqs. (14)-(15) on the
    observed rows of H / sub-block of R), so ``mean[t] - pred_mean[t] == K_t @ innovation[t]``.
    Columns of missing components are zero; an all-NaN step has ``K_t = 0``.
    """
    z, x0, P0, F, H, Q, R = _check_model(z, x0, P0, F, H, Q, R)
    res = kalman_filter(z, x0, P0, F, H, Q, R)

    def gain_fn(t, idx, res):
        H_o = H[idx, :]
        R_oo = R[np.ix_(idx, idx)]
        P_pred = res["pred_cov"][t]
        S = H_o @ P_pred @ H_o.T + R_oo
        return _right_solve(P_pred @ H_o.T, S)

    return _gains_from_result(res, gain_fn)


def svsf_gains(z, x0, P0, F, H, Q, R, psi, gamma, h_pinv=None):
    """Gains ``K_t [T, n, m]`` used by :func:`svsf` on the same inputs.

    Recomputed from the dict :func:`svsf` returns, with its conventions: the a-priori innovation
    ``innovation[t]`` (observed components), the memory ``e_{k|k}`` = ``post_innovation[t-1]``
    (zeros for ``t = 0``; carried values for missing components, which never enter since only
    observed components are used), ``H^+`` = ``h_pinv`` / ``pinv(H)`` at a fully observed step
    and ``pinv(H[observed])`` otherwise, then :func:`svsf_gain`. Columns of missing components
    are zero; an all-NaN step has ``K_t = 0``. ``mean[t] - pred_mean[t] == K_t @ innovation[t]``.
    """
    z, x0, P0, F, H, Q, R = _check_model(z, x0, P0, F, H, Q, R)
    m, n = H.shape
    res = svsf(z, x0, P0, F, H, Q, R, psi, gamma, h_pinv=h_pinv)
    psi = np.array(psi, dtype=np.float64).reshape(-1)
    gamma = float(gamma)
    H_pinv_full = np.linalg.pinv(H) if h_pinv is None else _f64(h_pinv, 2, "h_pinv")
    innov = res["innovation"]
    post = res["post_innovation"]

    def gain_fn(t, idx, res):
        Hp = H_pinv_full if idx.size == m else np.linalg.pinv(H[idx, :])
        e_mem = post[t - 1, idx] if t > 0 else np.zeros(idx.size)
        return svsf_gain(Hp, innov[t, idx], e_mem, psi[idx], gamma)

    return _gains_from_result(res, gain_fn)


def noise_covariance(P0, Q, R, T):
    """Dense ``Cov(xi) = blockdiag(P0, Q x T, R x T)`` of ``xi = (x~_init, w_0.., v_0..)``."""
    P0 = np.asarray(P0, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    n, m = Q.shape[0], R.shape[0]
    D = n + T * n + T * m
    S = np.zeros((D, D))
    S[:n, :n] = P0
    for t in range(T):
        a = n + t * n
        S[a : a + n, a : a + n] = Q
        b = n + T * n + t * m
        S[b : b + m, b : b + m] = R
    return S


def dense_smoother_covariance(F, H, Q, R, P0, gains, observed=None, lag=None, kind="svss"):
    """EXACT error covariance of a fixed-gain filter followed by a linear (SVSS / RTS) smoother.

    Brute force: every error is an explicit ``[n, D]`` (or ``[m, D]``) matrix acting on
    ``xi = (x~_init ~ N(0, P0), w_0..w_{T-1} ~ N(0, Q), v_0..v_{T-1} ~ N(0, R))``
    (``D = n + T n + T m``, see :func:`noise_covariance`); a covariance is ``M Cov(xi) M^T``.

    Filter errors (truth minus estimate), with ``O_t = diag(observed[t])``, ``H_t = O_t H``:

        x~_{t|t-1} = F x~_{t-1|t-1} + w_t          (x~_{-1|-1} = x~_init)
        e_t        = H_t x~_{t|t-1} + O_t v_t       (innovation; 0 in missing components)
        x~_{t|t}   = x~_{t|t-1} - K_t e_t

    with the GIVEN gains ``gains [T, n, m]`` (columns of missing components are ignored: they
    multiply zeros; they are zeroed here). Joseph-form covariances of that filter:

        P_{t|t-1} = F P_{t-1|t-1} F^T + Q,
        P_{t|t}   = (I - K_t H_t) P_{t|t-1} (I - K_t H_t)^T + K_t R_t K_t^T,  R_t = O_t R O_t.

    Smoother: ``x^s_k = x_{k|k} + sum_{j=1}^{L_k} (C_k C_{k+1} ... C_{k+j-1}) G_{k+j} e_{k+j}``,
    ``L_k = min(lag, T-1-k)`` (``lag=None``: ``T-1-k``), ``C_i = P_{i|i} F^T P_{i+1|i}^{-1}``
    built from the JOSEPH P's above, and

      * ``kind="svss"``: ``G_N = B_N = P_{N|N-1} H_o^T S_oo^{-1}`` in the observed columns (0
        elsewhere), ``S_oo = H_o P_{N|N-1} H_o^T + R_oo`` (observed rows / sub-block);
        ``G_N = 0`` at an all-missing step;
      * ``kind="rts"``: ``G_N = K_N`` (the RTS recursion Eq. (17) unrolled).

    So ``eps^s_k = x~_{k|k} - sum_j (prod C) G_{k+j} e_{k+j}``, linear in xi.

    Returns a dict:
      ``cov [T, n, n]``        exact Cov(eps^s_k) = M_k Cov(xi) M_k^T (not symmetrised)
      ``filter_cov [T, n, n]`` Cov(x~_{t|t}) from the dense map
      ``pred_cov [T, n, n]``   Cov(x~_{t|t-1}) from the dense map
      ``P_post``, ``P_pred``   ``[T, n, n]`` from the Joseph recursion
      ``map [T, n, D]``        the smoother error maps M_k
      ``noise_cov [D, D]``     Cov(xi)
    """
    if kind not in ("svss", "rts"):
        raise ValueError(f"unknown kind {kind!r}")
    F = _f64(F, 2, "F")
    H = _f64(H, 2, "H")
    Q = _f64(Q, 2, "Q")
    R = _f64(R, 2, "R")
    P0 = _f64(P0, 2, "P0")
    K = _f64(gains, 3, "gains")
    T = K.shape[0]
    m, n = H.shape
    if K.shape != (T, n, m):
        raise ValueError(f"gains must be [T, {n}, {m}], got {K.shape}")
    if observed is None:
        observed = np.ones((T, m), dtype=bool)
    observed = np.asarray(observed, dtype=bool)
    if observed.shape != (T, m):
        raise ValueError(f"observed must be [{T}, {m}], got {observed.shape}")
    K = K * observed[:, None, :].astype(np.float64)  # missing columns never act
    eye = np.eye(n)
    D = n + T * n + T * m

    def w_cols(t):
        return slice(n + t * n, n + (t + 1) * n)

    def v_cols(t):
        return slice(n + T * n + t * m, n + T * n + (t + 1) * m)

    Sigma = noise_covariance(P0, Q, R, T)

    # ---- dense error maps of the filter
    A_pred = np.zeros((T, n, D))  # x~_{t|t-1}
    A_post = np.zeros((T, n, D))  # x~_{t|t}
    E = np.zeros((T, m, D))  # e_t
    prev = np.zeros((n, D))
    prev[:, :n] = eye  # x~_{-1|-1} = x~_init
    for t in range(T):
        O = np.diag(observed[t].astype(np.float64))
        a = F @ prev
        a[:, w_cols(t)] += eye
        e = O @ H @ a
        e[:, v_cols(t)] += O
        A_pred[t] = a
        E[t] = e
        A_post[t] = a - K[t] @ e
        prev = A_post[t]

    # ---- Joseph recursion with the same gains
    P_pred = np.zeros((T, n, n))
    P_post = np.zeros((T, n, n))
    P = P0.copy()
    for t in range(T):
        O = np.diag(observed[t].astype(np.float64))
        Pp = F @ P @ F.T + Q
        H_t = O @ H
        R_t = O @ R @ O
        I_KH = eye - K[t] @ H_t
        P = I_KH @ Pp @ I_KH.T + K[t] @ R_t @ K[t].T
        P_pred[t] = Pp
        P_post[t] = P

    # ---- smoother gains
    C = [_right_solve(P_post[i] @ F.T, P_pred[i + 1]) for i in range(T - 1)]
    G = np.zeros((T, n, m))
    for N in range(T):
        if kind == "rts":
            G[N] = K[N]
            continue
        idx = np.flatnonzero(observed[N])
        if idx.size == 0:
            continue
        H_o = H[idx, :]
        S_oo = H_o @ P_pred[N] @ H_o.T + R[np.ix_(idx, idx)]
        G[N][:, idx] = _right_solve(P_pred[N] @ H_o.T, S_oo)

    # ---- smoother error maps
    M = np.zeros((T, n, D))
    for k in range(T):
        L = (T - 1 - k) if lag is None else min(int(lag), T - 1 - k)
        if L < 0:
            raise ValueError("lag must be >= 0 or None")
        Mk = A_post[k].copy()
        prod = eye.copy()
        for j in range(1, L + 1):
            prod = prod @ C[k + j - 1]  # C_k C_{k+1} ... C_{k+j-1}
            Mk = Mk - prod @ G[k + j] @ E[k + j]
        M[k] = Mk

    def covs(maps):
        return np.stack([Mt @ Sigma @ Mt.T for Mt in maps])

    return {
        "cov": covs(M),
        "filter_cov": covs(A_post),
        "pred_cov": covs(A_pred),
        "P_post": P_post,
        "P_pred": P_pred,
        "map": M,
        "noise_cov": Sigma,
    }

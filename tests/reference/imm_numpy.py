"""Float64 NumPy reference ("oracle") for the IMM over linear Kalman modes of different sizes.

Written from the algorithm's statement, not from the torchsvs implementation:

    Blom, Bar-Shalom, IEEE Trans. Autom. Control 33(8), 1988; Bar-Shalom, Li, Kirubarajan,
    "Estimation with Applications to Tracking and Navigation", 2001, Sec. 11.6.6 (the IMM
    cycle: interaction, mode-matched filtering, mode probability update, combination), and
    Yuan et al., IEEE Trans. AES 48(4), 2012 (unbiased mixing of unequal states: a mode that
    lacks some of the receiving mode's components lends the receiving mode's own estimate of
    them, uncorrelated).

Conventions: one track, plain loops, no batch. ``z [T, m]`` with NaN for a missing component;
``x0 [N]``, ``P0 [N, N]`` the common-state prior one step before ``z[0]``; ``modes`` a list of
dicts with ``F``, ``Q``, ``H``, ``R`` in the mode's own state, ``index`` the common-state
position of each of its components. The combined estimate counts a component a mode lacks as 0
with variance 0 in that mode. The Kalman update drops the missing rows of ``z``, ``H``, ``R``
and uses the textbook covariance ``(I - K H) P``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["imm"]


def _kalman(x, P, F, Q, H, R, z):
    x_pred = F @ x
    P_pred = F @ P @ F.T + Q
    seen = ~np.isnan(z)
    if not seen.any():
        return x_pred, P_pred, 0.0
    H, R, z = H[seen], R[np.ix_(seen, seen)], z[seen]
    e = z - H @ x_pred
    S = H @ P_pred @ H.T + R
    K = P_pred @ H.T @ np.linalg.inv(S)
    x_new = x_pred + K @ e
    P_new = (np.eye(len(x)) - K @ H) @ P_pred
    P_new = 0.5 * (P_new + P_new.T)
    sign, logdet = np.linalg.slogdet(2 * np.pi * S)
    assert sign > 0
    loglik = -0.5 * (e @ np.linalg.solve(S, e) + logdet)
    return x_new, P_new, loglik


def imm(z, x0, P0, modes, transition, mu0):
    """The IMM over ``z``: ``mean [T, N]``, ``cov [T, N, N]``, ``mu [T, M]`` and per mode the
    filtered ``means[j] [T, n_j]``, ``covs[j]``, and the run's log-likelihood."""
    M = len(modes)
    N = len(x0)
    Pi = np.asarray(transition, dtype=float)
    mu = np.asarray(mu0, dtype=float)
    xs = [x0[np.array(md["index"])] for md in modes]
    Ps = [P0[np.ix_(md["index"], md["index"])] for md in modes]
    out = {
        "mean": [],
        "cov": [],
        "mu": [],
        "means": [[] for _ in modes],
        "covs": [[] for _ in modes],
    }
    total = 0.0
    for zt in z:
        # Interaction.
        c = np.array([sum(Pi[i, j] * mu[i] for i in range(M)) for j in range(M)])
        mixed = []
        for j, md_j in enumerate(modes):
            idx_j = md_j["index"]
            lent_x, lent_P = [], []
            for i, md_i in enumerate(modes):
                idx_i = list(md_i["index"])
                x = np.empty(len(idx_j))
                P = np.zeros((len(idx_j), len(idx_j)))
                for a, ka in enumerate(idx_j):
                    x[a] = xs[i][idx_i.index(ka)] if ka in idx_i else xs[j][a]
                    for b, kb in enumerate(idx_j):
                        if ka in idx_i and kb in idx_i:
                            P[a, b] = Ps[i][idx_i.index(ka), idx_i.index(kb)]
                        elif ka not in idx_i and kb not in idx_i:
                            P[a, b] = Ps[j][a, b]
                lent_x.append(x)
                lent_P.append(P)
            w = [Pi[i, j] * mu[i] / c[j] for i in range(M)]
            x0j = sum(w[i] * lent_x[i] for i in range(M))
            P0j = sum(
                w[i] * (lent_P[i] + np.outer(lent_x[i] - x0j, lent_x[i] - x0j)) for i in range(M)
            )
            mixed.append((x0j, P0j))
        # Mode-matched filtering.
        logliks = np.empty(M)
        for j, md in enumerate(modes):
            xs[j], Ps[j], logliks[j] = _kalman(*mixed[j], md["F"], md["Q"], md["H"], md["R"], zt)
        # Mode probabilities.
        weights = c * np.exp(logliks - logliks.max())
        total += np.log(weights.sum()) + logliks.max()
        mu = weights / weights.sum()
        # Combination in the common state.
        X = np.zeros((M, N))
        PP = np.zeros((M, N, N))
        for j, md in enumerate(modes):
            X[j, md["index"]] = xs[j]
            PP[j][np.ix_(md["index"], md["index"])] = Ps[j]
        x = sum(mu[j] * X[j] for j in range(M))
        P = sum(mu[j] * (PP[j] + np.outer(X[j] - x, X[j] - x)) for j in range(M))
        out["mean"].append(x)
        out["cov"].append(P)
        out["mu"].append(mu.copy())
        for j in range(M):
            out["means"][j].append(xs[j])
            out["covs"][j].append(Ps[j])
    result = {k: np.array(v) for k, v in out.items() if k in ("mean", "cov", "mu")}
    result["means"] = [np.array(v) for v in out["means"]]
    result["covs"] = [np.array(v) for v in out["covs"]]
    result["log_likelihood"] = total
    return result

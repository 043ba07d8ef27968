// The dense linear-Gaussian filters' predict-correct step (part of fused.cpp): the online
// `step` of a KF or the SVSF's H⁺ mode, and whole runs of models the per-axis kernel does not
// cover (torchsvs/kernels/fused_dense.py).
#pragma once

#include "lanes.h"

namespace {

// Largest state or measurement size of the dense steps.
constexpr int64_t kMax = 16;

// One predict-correct step of a dense linear-Gaussian filter for one track:
// GaussianFilter.predict, then KalmanFilter.correct (rule 0) or SVSF.correct with an H of
// orthonormal rows, whose H⁺ is Hᵀ (rule 1). n, m ≤ kMax; every array contiguous.
// A deliberate twin of the tensor path's Kalman update (torchsvs.filters.gaussian's
// kalman_update: S, its Cholesky factor, K by two triangular solves, Joseph-form P) and of the
// SVSF's correction; tests/test_kernels.py holds them to 1e-10 in float64
// (test_compiled_online_steps_equal_the_tensor_steps, test_compiled_dense_runs_equal_the_general_path).
// Given x [n], P [n, n], z [m] (NaN: missing), the SVSF's memory and psi [m], and
// F [n, n], Q [n, n], H [m, n], R [m, m]; writes x, P, x_pred, P_pred, e [m], K [n, m],
// S [m, m], *loglik, e_post [m], observed [m]. Returns 0, or 1 when a Cholesky factor failed
// (the caller then takes the tensor path, whose factorisation adds jitter).

// C = A B (r × k times k × c), or A Bᵀ with B stored c × k; row-major, summed in k order.
template <typename R>
inline void product(const R* A, const R* B, R* C, int64_t r, int64_t k, int64_t c, bool bt) {
    for (int64_t i = 0; i < r; ++i)
        for (int64_t j = 0; j < c; ++j) {
            R a = 0;
            for (int64_t l = 0; l < k; ++l) a += A[i * k + l] * (bt ? B[j * k + l] : B[l * c + j]);
            C[i * c + j] = a;
        }
}

// out = (A + Aᵀ) / 2 for an n × n A (symmetrize in linalg.py).
template <typename R>
inline void symmetrized(const R* A, R* out, int64_t n) {
    for (int64_t i = 0; i < n; ++i)
        for (int64_t j = 0; j < n; ++j) out[i * n + j] = R(0.5) * (A[i * n + j] + A[j * n + i]);
}

// y = L⁻¹ b for a lower-triangular m × m L.
template <typename R>
inline void forward_solve(const R* L, const R* b, R* y, int64_t m) {
    for (int64_t i = 0; i < m; ++i) {
        R a = b[i];
        for (int64_t k = 0; k < i; ++k) a -= L[i * m + k] * y[k];
        y[i] = a / L[i * m + i];
    }
}

template <typename R>
int dense_track(int64_t n, int64_t m, int rule, R gamma, const R* x, const R* Pb, const R* z,
                const R* mem, const R* psi, const R* F, const R* Q, const R* H, const R* Rm,
                R* xb, R* Pb1, R* x1, R* P1, R* e, R* K, R* S, R* ll, R* epost, bool* so) {
    const R log2pi = static_cast<R>(1.8378770664093453);
    R FP[kMax * kMax], A[kMax * kMax], AP[kMax * kMax], Hm[kMax * kMax], Rmk[kMax * kMax];
    R PHt[kMax * kMax], L[kMax * kMax], KR[kMax * kMax];
    bool seen[kMax];
    // Prediction: x̂ = F x, P = sym(F P Fᵀ + Q) (Eqs. (11)-(12)).
    product(F, x, x1, n, n, 1, false);
    product(F, Pb, FP, n, n, n, false);
    product(FP, F, A, n, n, n, true);
    for (int64_t i = 0; i < n * n; ++i) A[i] += Q[i];
    symmetrized(A, P1, n);
    // Innovation over the observed components; masked H and R (mask_measurement).
    int observed = 0;
    for (int64_t i = 0; i < m; ++i) {
        seen[i] = !std::isnan(z[i]);
        so[i] = seen[i];
        observed += seen[i];
        R acc = 0;
        for (int64_t k = 0; k < n; ++k) acc += H[i * n + k] * x1[k];
        e[i] = seen[i] ? z[i] - acc : R(0);
        for (int64_t k = 0; k < n; ++k) Hm[i * n + k] = seen[i] ? H[i * n + k] : R(0);
    }
    for (int64_t i = 0; i < m; ++i)
        for (int64_t j = 0; j < m; ++j)
            Rmk[i * m + j] = (seen[i] && seen[j]) ? Rm[i * m + j] : (i == j ? R(1) : R(0));
    // S = sym(H P Hᵀ + R) of the observed components, identity elsewhere.
    product(P1, Hm, PHt, n, n, m, true);
    product(Hm, PHt, A, m, n, m, false);
    for (int64_t i = 0; i < m * m; ++i) A[i] += Rmk[i];
    symmetrized(A, S, m);
    if (rule == 0) {
        // Kalman gain K = P Hᵀ S⁻¹ through L = chol(S) (kalman_update).
        for (int64_t i = 0; i < m; ++i)
            for (int64_t j = 0; j <= i; ++j) {
                R a = S[i * m + j];
                for (int64_t k = 0; k < j; ++k) a -= L[i * m + k] * L[j * m + k];
                if (i == j) {
                    if (!(a > 0)) return 1;
                    L[i * m + i] = std::sqrt(a);
                } else {
                    L[i * m + j] = a / L[j * m + j];
                }
            }
        for (int64_t r = 0; r < n; ++r) {  // row r of K: solve S kᵀ = (P Hᵀ)[r]ᵀ
            R y[kMax];
            forward_solve(L, PHt + r * m, y, m);
            for (int64_t i = m - 1; i >= 0; --i) {
                R a = y[i];
                for (int64_t k = i + 1; k < m; ++k) a -= L[k * m + i] * K[r * m + k];
                K[r * m + i] = a / L[i * m + i];
            }
        }
        // log N(e; 0, S) over the observed components (gaussian_log_density).
        R white = 0, logdet = 0, y[kMax];
        forward_solve(L, e, y, m);
        for (int64_t i = 0; i < m; ++i) {
            white += y[i] * y[i];
            logdet += std::log(L[i * m + i]);
        }
        *ll = R(-0.5) * (white + R(2) * logdet + R(observed) * log2pi);
    } else {
        // SVSF gain K = Hᵀ D diag((|e| + γ|e_post|) / max(|e|, ψ)) (Eq. (23)).
        for (int64_t j = 0; j < m; ++j) {
            R ratio = gain_ratio(e[j], mem[j], psi[j], gamma);
            for (int64_t r = 0; r < n; ++r) K[r * m + j] = Hm[j * n + r] * ratio;
        }
    }
    // x = x̂ + K e; P = sym((I − K H) P (I − K H)ᵀ + K R Kᵀ) (Joseph form). The KF's Joseph
    // form uses the masked H and R, the SVSF's the full ones (equal: K has zero columns where
    // missing).
    product(K, e, xb, n, m, 1, false);
    for (int64_t i = 0; i < n; ++i) xb[i] += x1[i];
    product(K, rule == 0 ? Hm : H, A, n, m, n, false);
    for (int64_t i = 0; i < n; ++i)
        for (int64_t j = 0; j < n; ++j) A[i * n + j] = (i == j ? R(1) : R(0)) - A[i * n + j];
    product(A, P1, AP, n, n, n, false);
    product(AP, A, FP, n, n, n, true);
    product(K, rule == 0 ? Rmk : Rm, KR, n, m, m, false);
    product(KR, K, PHt, n, m, n, true);  // PHt is free again: K R Kᵀ
    for (int64_t i = 0; i < n * n; ++i) FP[i] += PHt[i];
    symmetrized(FP, Pb1, n);
    if (rule == 1) {  // the memory: e_post = z − H x̂ (Eq. (24)), carried where missing
        product(H, xb, epost, m, n, 1, false);
        for (int64_t i = 0; i < m; ++i) epost[i] = seen[i] ? z[i] - epost[i] : mem[i];
    }
    return 0;
}

// dense_track over T steps of B tracks (T = 1: an online `step` call; T > 1: a whole run of a
// dense model, offline). in: x0 [B, n], P0 [B, n, n], z [B, T, m], memory0 [B, m] (SVSF),
// psi [B, T, m] or [m] (psi_track, psi_step: element strides). consts: F, Q, H, R.
// outs (10): x, P, x_pred, P_pred [B, T, ...], e [B, T, m], K [B, T, n, m], S [B, T, m, m],
// loglik [B, T], e_post [B, T, m], observed [B, T, m] (bool).
// total_out (may be null): [B], total_in [B] (null: 0) plus each track's log-likelihoods, added
// in step order (what a state's running total adds, without a tensor op per online step).
// Returns 0; 1 when a Cholesky factor failed; 2 when z holds an infinity (the caller's tensor
// path reports it).
template <typename R>
int dense_run(int64_t B, int64_t T, int64_t n, int64_t m, int rule, R gamma, const R* X,
              const R* P, const R* Z, const R* M, const R* W, int64_t psi_track,
              int64_t psi_step, const void* const* consts, void* const* outs,
              const R* total_in, R* total_out) {
    const R* F = static_cast<const R*>(consts[0]);
    const R* Q = static_cast<const R*>(consts[1]);
    const R* H = static_cast<const R*>(consts[2]);
    const R* Rm = static_cast<const R*>(consts[3]);
    R* xo = static_cast<R*>(outs[0]);
    R* Po = static_cast<R*>(outs[1]);
    R* xp = static_cast<R*>(outs[2]);
    R* Pp = static_cast<R*>(outs[3]);
    R* eo = static_cast<R*>(outs[4]);
    R* Ko = static_cast<R*>(outs[5]);
    R* So = static_cast<R*>(outs[6]);
    R* ll = static_cast<R*>(outs[7]);
    R* ep = static_cast<R*>(outs[8]);
    bool* so = static_cast<bool*>(outs[9]);
    for (int64_t i = 0; i < B * T * m; ++i)
        if (std::isinf(Z[i])) return 2;
    for (int64_t b = 0; b < B; ++b) {
        const R* x = X + b * n;
        const R* Pb = P + b * n * n;
        const R* mem = M + b * m;
        for (int64_t t = 0; t < T; ++t) {
            int64_t k = b * T + t;
            int failed = dense_track<R>(
                n, m, rule, gamma, x, Pb, Z + k * m, mem, W + b * psi_track + t * psi_step, F, Q,
                H, Rm, xo + k * n, Po + k * n * n, xp + k * n, Pp + k * n * n, eo + k * m,
                Ko + k * n * m, So + k * m * m, ll + k, ep + k * m, so + k * m);
            if (failed) return failed;
            x = xo + k * n;
            Pb = Po + k * n * n;
            if (rule == 1) mem = ep + k * m;
        }
        if (total_out != nullptr) {
            R total = total_in != nullptr ? total_in[b] : R(0);
            for (int64_t t = 0; t < T; ++t) total += ll[b * T + t];
            total_out[b] = total;
        }
    }
    return 0;
}

// The C entry points' casts, once for both dtypes.
template <typename R>
int dense_entry(int64_t B, int64_t T, int64_t n, int64_t m, int rule, double gamma, const void* x,
                const void* P, const void* z, const void* memory, const void* psi,
                int64_t psi_track, int64_t psi_step, const void* const* consts,
                void* const* outs, const void* total_in, void* total_out) {
    return dense_run<R>(B, T, n, m, rule, static_cast<R>(gamma), static_cast<const R*>(x),
                        static_cast<const R*>(P), static_cast<const R*>(z),
                        static_cast<const R*>(memory), static_cast<const R*>(psi), psi_track,
                        psi_step, consts, outs, static_cast<const R*>(total_in),
                        static_cast<R*>(total_out));
}

// One online step of dense_run with its arguments in two arrays, filled once per run of steps
// but for the step's own pointers (a call from Python pays for every argument it passes):
// sizes: B, n, m, rule, psi_track; a: x, P, z, memory, psi, F, Q, H, R, the 10 outs,
// total_in, total_out.
template <typename R>
int dense_step(const int64_t* sizes, double gamma, void* const* a) {
    return dense_entry<R>(sizes[0], 1, sizes[1], sizes[2], static_cast<int>(sizes[3]), gamma,
                          a[0], a[1], a[2], a[3], a[4], sizes[4], 0, a + 5, a + 9, a[19], a[20]);
}

}  // namespace

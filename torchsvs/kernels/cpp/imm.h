// The IMM of torchsvs track, compiled (part of fused.cpp): a Kalman filter on a nearly-constant-
// velocity mode and an extended Kalman filter on a coordinated turn with unknown turn rate,
// mixed by the IMM, then Kim's fixed-lag (or fixed-interval) smoother; tracks in vectors of
// lanes (a register of float64 tracks steps together: lanes.h), blocks of them on threads
// (torchsvs/kernels/fused_imm.py calls it).
//
// A deliberate twin of the tensor path, formula by formula: TurnIMM and IMM
// (filters/turn_imm.py, filters/imm.py: mix, the modes' steps, combine), the models' f,
// Jacobian and Q (models/motion.py ConstantVelocity and CoordinatedTurn, models/turn.py
// CoordinatedTurn3D), kalman_update (filters/gaussian.py) and IMMSmoother (smoothers/imm.py:
// _predictions, _backward, _fixed_lag, _fixed_interval). Those are the formulas' homes, with
// the references (Blom & Bar-Shalom 1988; Bar-Shalom, Li, Kirubarajan 2001, Secs. 11.6.6 and
// 11.7; Kim 1994); tests/test_fused_imm.py holds both to 1e-9 in float64.
//
// Everything lives in the common state of size N = 2D + 1 (D position axes; the layout
// [x, vx, y, vy(, z, vz)], then the turn rate ω): the CV mode is its first V = 2D components,
// the CT mode all of them (TurnIMM's embedding [[0, ..., 2D-1], [0, ..., 2D]]). A lane's
// conditions (a missing measurement, a small turn angle, a mode of probability 0) are masks
// that pick per lane, so each lane gets the numbers it gets alone.
#pragma once

#include <atomic>
#include <cmath>
#include <limits>
#include <vector>

#include "lanes.h"

namespace {
namespace imm {

// A vector of lanes, one track each: lanes.h's Wide<double>, one of the machine's registers (8
// float64 with AVX-512, 4 with AVX, 2 with SSE2).
typedef Wide<double>::type X;
constexpr int kW = LaneBlock<double>::kWidth;
typedef decltype(X{} < X{}) Mask;

constexpr double kLog2Pi = 1.8378770664093453;
constexpr double kNegInf = -std::numeric_limits<double>::infinity();

inline X all(double c) { return splat<X>(c); }
// f applied lane by lane (the library functions have no vector forms here).
template <typename F>
inline X each(X x, F f) {
    X out{};
    for (int w = 0; w < kW; ++w) out[w] = f(x[w]);
    return out;
}
inline X sqrt_of(X x) {  // (correctly rounded either way: the same numbers)
#if defined(__AVX512F__)
    static_assert(sizeof(X) == sizeof(__m512d), "one AVX-512 register of lanes");
    return reinterpret_cast<X>(_mm512_sqrt_pd(reinterpret_cast<__m512d>(x)));
#elif defined(__AVX__)
    static_assert(sizeof(X) == sizeof(__m256d), "one AVX register of lanes");
    return reinterpret_cast<X>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(x)));
#else
    return each(x, [](double v) { return std::sqrt(v); });
#endif
}
typedef int64_t Bits __attribute__((vector_size(sizeof(X))));  // a lane's bits
// The lanes of y where x lies in [lo, hi], else f(x) (the library function: the rare lanes
// a polynomial below does not cover, NaN and infinities among them).
template <typename F>
inline X covered(X x, X y, double lo, double hi, F f) {
    const Mask outside = !((x >= all(lo)) & (x <= all(hi)));
    for (int w = 0; w < kW; ++w)
        if (outside[w]) y[w] = f(x[w]);
    return y;
}
// exp and log on whole vectors (the library's are lane by lane, most of this loop's time):
// exp by x = n ln 2 + r, |r| <= ln 2 / 2, Taylor to r¹³ and 2ⁿ in the exponent bits; log by
// x = m 2ᵉ, m in [√½, √2), and 2 atanh((m − 1)/(m + 1)) to the 23rd power. Within 1 and 3 units
// in the last place of the library's (checked on 16 M draws): the IMM's sums move by far less
// than the tests' 1e-9.
inline X exp_of(X x) {
    const X shift = all(6755399441055744.0);  // 1.5 · 2⁵²: adding it rounds to an integer
    const X n = (x * all(1.4426950408889634) + shift) - shift;
    const X r = (x - n * all(0.6931471803691238)) - n * all(1.9082149292705877e-10);
    constexpr double kTaylor[] = {1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0,
                                  1.0 / 362880.0,    1.0 / 40320.0,    1.0 / 5040.0,
                                  1.0 / 720.0,       1.0 / 120.0,      1.0 / 24.0,
                                  1.0 / 6.0,         0.5,              1.0,
                                  1.0};
    X p = all(1.0 / 6227020800.0);
    for (double c : kTaylor) p = p * r + all(c);
    const Bits exponent = __builtin_convertvector(n, Bits) + 1023;
    const X power = reinterpret_cast<X>(exponent << 52);  // 2ⁿ
    return covered(x, p * power, -708.0, 709.0, [](double v) { return std::exp(v); });
}
inline X log_of(X x) {
    const Bits bits = reinterpret_cast<Bits>(x);
    Bits e = ((bits >> 52) & 0x7ff) - 1023;
    X m = reinterpret_cast<X>((bits & 0x000fffffffffffffLL) | 0x3ff0000000000000LL);  // [1, 2)
    const Mask high = m > all(1.4142135623730951);
    m = high ? m * all(0.5) : m;
    e = high ? e + 1 : e;
    const X u = (m - all(1.0)) / (m + all(1.0)), u2 = u * u;
    constexpr double kAtanh[] = {1.0 / 21, 1.0 / 19, 1.0 / 17, 1.0 / 15, 1.0 / 13, 1.0 / 11,
                                 1.0 / 9,  1.0 / 7,  1.0 / 5,  1.0 / 3,  1.0};
    X p = all(1.0 / 23);
    for (double c : kAtanh) p = p * u2 + all(c);
    const X ef = __builtin_convertvector(e, X);
    const X y = ef * all(0.6931471803691238) + (ef * all(1.9082149292705877e-10) + all(2.0) * u * p);
    return covered(x, y, 2.2250738585072014e-308, 1.7976931348623157e308,
                   [](double v) { return std::log(v); });
}
inline X sin_of(X x) { return each(x, [](double v) { return std::sin(v); }); }
inline X cos_of(X x) { return each(x, [](double v) { return std::cos(v); }); }
inline bool every(Mask m) {
    for (int w = 0; w < kW; ++w)
        if (!m[w]) return false;
    return true;
}

// C = A B (r × k times k × c), summed in k order; with `transposed`, C = A Bᵀ for B stored
// c × k (mul_t).
template <int r, int k, int c, bool transposed = false>
inline void mul(const X* A, const X* B, X* C) {
    for (int i = 0; i < r; ++i)
        for (int j = 0; j < c; ++j) {
            X a{};
            for (int l = 0; l < k; ++l) a += A[i * k + l] * B[transposed ? j * k + l : l * c + j];
            C[i * c + j] = a;
        }
}
template <int r, int k, int c>
inline void mul_t(const X* A, const X* B, X* C) {
    mul<r, k, c, true>(A, B, C);
}

// Where the models' transitions can be nonzero, row by row (column indices in order): the
// constant velocity's per-axis [[1, T], [0, 1]] and the coordinated turn's Jacobian
// (CoordinatedTurn, with CoordinatedTurn3D's vertical axis and ω last). Products through a
// pattern skip the terms that are always zero, which add nothing: the same sums in the same
// order as the dense products, a fraction of the work.
template <int D, bool Turn>
struct Pattern {
    static constexpr int n = Turn ? 2 * D + 1 : 2 * D;
    int count[n], col[n][4];
    constexpr Pattern() : count(), col() {
        for (int a = 0; a < D; ++a) {  // the constant velocity's axes
            count[2 * a] = 2, col[2 * a][0] = 2 * a, col[2 * a][1] = 2 * a + 1;
            count[2 * a + 1] = 1, col[2 * a + 1][0] = 2 * a + 1;
        }
        if (Turn) {  // the plane's rows, each with ω's column last
            const int w = n - 1;
            const int rows[4][4] = {{0, 1, 3, w}, {1, 3, w, 0}, {1, 2, 3, w}, {1, 3, w, 0}};
            const int counts[4] = {4, 3, 4, 3};
            for (int r = 0; r < 4; ++r) {
                count[r] = counts[r];
                for (int l = 0; l < 4; ++l) col[r][l] = rows[r][l];
            }
            count[w] = 1, col[w][0] = w;
        }
    }
};
// out = F Y (Y n × k) and out = Y Fᵀ (Y k × n) for F of pattern P.
template <typename P, int k>
inline void pattern_times(const X* F, const X* Y, X* out) {
    constexpr P p{};
    constexpr int n = P::n;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < k; ++j) {
            X a{};
            for (int l = 0; l < p.count[i]; ++l) a += F[i * n + p.col[i][l]] * Y[p.col[i][l] * k + j];
            out[i * k + j] = a;
        }
}
template <typename P, int k>
inline void pattern_times_t(const X* Y, const X* F, X* out) {
    constexpr P p{};
    constexpr int n = P::n;
    for (int i = 0; i < k; ++i)
        for (int j = 0; j < n; ++j) {
            X a{};
            for (int l = 0; l < p.count[j]; ++l) a += Y[i * n + p.col[j][l]] * F[j * n + p.col[j][l]];
            out[i * n + j] = a;
        }
}

// (A + Aᵀ) / 2 in place (symmetrize).
template <int n>
inline void symmetrize(X* A) {
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < i; ++j) {
            X v = all(0.5) * (A[i * n + j] + A[j * n + i]);
            A[i * n + j] = A[j * n + i] = v;
        }
}
// Lower Cholesky factor L and the reciprocals of its diagonal (multiplications instead of
// divisions in the solves: a triangular solve is a chain of them); `ok` loses the lanes whose
// matrix is not positive definite (the caller then takes the tensor path, whose factorisation
// adds jitter).
template <int n>
inline void cholesky(const X* S, X* L, X* inv, Mask& ok) {
    for (int i = 0; i < n; ++i)
        for (int j = 0; j <= i; ++j) {
            X a = S[i * n + j];
            for (int k = 0; k < j; ++k) a -= L[i * n + k] * L[j * n + k];
            if (i == j) {
                ok &= a > X{};
                L[i * n + i] = sqrt_of(a);
                inv[i] = all(1.0) / L[i * n + i];
            } else {
                L[i * n + j] = a * inv[j];
            }
        }
}
// y = L⁻¹ b, then (with both) x = L⁻ᵀ y: S⁻¹ b for S = L Lᵀ.
template <int n>
inline void lower_solve(const X* L, const X* inv, const X* b, X* y) {
    for (int i = 0; i < n; ++i) {
        X a = b[i];
        for (int k = 0; k < i; ++k) a -= L[i * n + k] * y[k];
        y[i] = a * inv[i];
    }
}
template <int n>
inline void chol_solve(const X* L, const X* inv, const X* b, X* x) {
    X y[n];
    lower_solve<n>(L, inv, b, y);
    for (int i = n - 1; i >= 0; --i) {
        X a = y[i];
        for (int k = i + 1; k < n; ++k) a -= L[k * n + i] * x[k];
        x[i] = a * inv[i];
    }
}
// G = A S⁻¹ for A r × n and symmetric positive definite S (right_psd_solve): row by row.
template <int r, int n>
inline void right_solve(const X* A, const X* S, X* G, Mask& ok) {
    X L[n * n], inv[n];
    cholesky<n>(S, L, inv, ok);
    for (int i = 0; i < r; ++i) chol_solve<n>(L, inv, A + i * n, G + i * n);
}
// log(exp(a) + exp(b)) as torch.logsumexp takes it (max + log Σ exp(x − max); −inf when both
// are), and the normalised weights exp(a − lse), exp(b − lse) from the same exponential (one
// of the two terms is exp(0)); where both are −inf the caller picks its own weights.
inline X logsumexp2(X a, X b, X* w = nullptr) {
    const Mask first = a >= b;
    const X m = first ? a : b, one = all(1.0);
    const X e = exp_of(first ? b - m : a - m), s = one + e;
    if (w != nullptr) w[0] = (first ? one : e) / s, w[1] = (first ? e : one) / s;
    return m == all(kNegInf) ? m : log_of(s) + m;
}
// log p as the tensor path reads a probability back (log of exp): −inf where exp underflows.
inline X read_back(X log_p) { return log_p < all(-745.1332191019412) ? all(kNegInf) : log_p; }

// turn_coefficients (models/motion.py): s, c, s', c' of a = ωT, the series below |a| < 1e-2,
// the closed forms on a denominator that is 1 there; sin a and cos a given.
inline void turn_coefficients(X a, X sin, X cos, X& s, X& c, X& ds, X& dc) {
    const Mask small = (a < X{} ? -a : a) < all(1e-2);
    const X a2 = a * a, one = all(1.0), safe = small ? one : a;
    const X half = sin_of(safe / all(2.0));
    const X versine = all(2.0) * half * half;  // 1 − cos a without cancellation
    s = small ? one - a2 / all(6.0) * (one - a2 / all(20.0) * (one - a2 / all(42.0))) : sin / safe;
    c = small ? a / all(2.0) * (one - a2 / all(12.0) * (one - a2 / all(30.0) * (one - a2 / all(56.0))))
              : versine / safe;
    ds = small ? -a / all(3.0) * (one - a2 / all(10.0) * (one - a2 / all(28.0) * (one - a2 / all(54.0))))
               : (safe * cos - sin) / (safe * safe);
    dc = small ? all(0.5) * (one - a2 / all(4.0) * (one - a2 / all(18.0) * (one - a2 / all(40.0))))
               : (safe * sin - versine) / (safe * safe);
}

// The model constants: CV's spectral density q, the CT mode's horizontal acceleration variance
// and turn-rate noise, R (D × D), log π (2 × 2).
template <int D>
struct Constants {
    double q, turn_q, turn_rate_q, R[D * D], log_pi[4];
};

// One mode's prediction x̂ = f(x), P = sym(F P Fᵀ + Q) over interval T, with the F used.
// Mode 0: ConstantVelocity (2D states); mode 1: CoordinatedTurn (D = 2) or CoordinatedTurn3D.
template <int D>
inline void predict_cv(const Constants<D>& k, X T, const X* x, const X* P, X* xp, X* Pp, X* F) {
    constexpr int n = 2 * D;
    using Cv = Pattern<D, false>;
    X Q[n * n] = {};
    const X q = all(k.q), q11 = T * T * T / all(3.0), q12 = T * T / all(2.0), q22 = T;
    for (int i = 0; i < n * n; ++i) F[i] = X{};
    for (int a = 0; a < D; ++a) {
        const int p = 2 * a, v = p + 1;
        F[p * n + p] = F[v * n + v] = all(1.0), F[p * n + v] = T;
        Q[p * n + p] = q * q11, Q[p * n + v] = Q[v * n + p] = q * q12, Q[v * n + v] = q * q22;
    }
    pattern_times<Cv, 1>(F, x, xp);
    X FP[n * n];
    pattern_times<Cv, n>(F, P, FP);
    pattern_times_t<Cv, n>(FP, F, Pp);
    for (int i = 0; i < n * n; ++i) Pp[i] += Q[i];
    symmetrize<n>(Pp);
}

// The terms of a turn over interval T at turn rate ω (CoordinatedTurn._turn): a = ωT, cos a,
// sin a and turn_coefficients of a.
struct Turn {
    X T, a, cos, sin, s, c, ds, dc;
    Turn(X T_, X omega) : T(T_), a(omega * T_), cos(cos_of(a)), sin(sin_of(a)) {
        turn_coefficients(a, sin, cos, s, c, ds, dc);
    }
};

template <int D>
inline void predict_ct(const Constants<D>& k, const Turn& turn, const X* x, const X* P, X* xp,
                       X* Pp, X* F) {
    constexpr int n = 2 * D + 1, w = n - 1;  // ω last
    using Ct = Pattern<D, true>;
    const X px = x[0], vx = x[1], py = x[2], vy = x[3], omega = x[w];
    const X T = turn.T, cos = turn.cos, sin = turn.sin, s = turn.s, c = turn.c, ds = turn.ds,
            dc = turn.dc;
    xp[0] = px + T * (s * vx - c * vy);
    xp[1] = cos * vx - sin * vy;
    xp[2] = py + T * (c * vx + s * vy);
    xp[3] = sin * vx + cos * vy;
    xp[w] = omega;
    const X one = all(1.0);
    for (int i = 0; i < n * n; ++i) F[i] = X{};
    F[0 * n + 0] = one, F[0 * n + 1] = T * s, F[0 * n + 3] = -T * c;
    F[0 * n + w] = T * T * (ds * vx - dc * vy);
    F[1 * n + 1] = cos, F[1 * n + 3] = -sin, F[1 * n + w] = -T * (sin * vx + cos * vy);
    F[2 * n + 1] = T * c, F[2 * n + 2] = one, F[2 * n + 3] = T * s;
    F[2 * n + w] = T * T * (dc * vx + ds * vy);
    F[3 * n + 1] = sin, F[3 * n + 3] = cos, F[3 * n + w] = T * (cos * vx - sin * vy);
    F[w * n + w] = one;
    X Q[n * n] = {};
    // Γ diag(q, q, q_ω) Γᵀ (CoordinatedTurn.process_noise)
    const X h = T * T / all(2.0), tq = all(k.turn_q);
    for (int p = 0; p < 4; p += 2) {
        Q[p * n + p] = h * tq * h, Q[p * n + p + 1] = Q[(p + 1) * n + p] = h * tq * T;
        Q[(p + 1) * n + p + 1] = T * tq * T;
    }
    Q[w * n + w] = T * all(k.turn_rate_q) * T;
    if (D == 3) {  // the vertical axis: one axis of the CV model (CoordinatedTurn3D)
        const X q = all(k.q);
        xp[4] = x[4] + T * x[5], xp[5] = x[5];
        F[4 * n + 4] = F[5 * n + 5] = one, F[4 * n + 5] = T;
        Q[4 * n + 4] = q * (T * T * T / all(3.0)), Q[4 * n + 5] = Q[5 * n + 4] = q * (T * T / all(2.0));
        Q[5 * n + 5] = q * T;
    }
    X FP[n * n];
    pattern_times<Ct, n>(F, P, FP);
    pattern_times_t<Ct, n>(FP, F, Pp);
    for (int i = 0; i < n * n; ++i) Pp[i] += Q[i];
    symmetrize<n>(Pp);
}

// The Kalman correction of a prediction with the positions z [D] (NaN: missing), H the
// position selection (kalman_correct: masked H and R, S, its Cholesky factor, K, Joseph P,
// the log-likelihood over the observed components).
template <int D, int n>
inline void correct(const Constants<D>& k, const X* z, const X* xp, const X* Pp, X* x, X* P,
                    X& loglik, Mask& ok) {
    constexpr int m = D;
    const X one = all(1.0), zero{};
    Mask seen[m];
    X observed{}, e[m], H[m * n] = {}, Rm[m * m];
    for (int i = 0; i < m; ++i) {
        seen[i] = z[i] == z[i];
        observed += seen[i] ? one : zero;
        e[i] = seen[i] ? z[i] - xp[2 * i] : zero;
        H[i * n + 2 * i] = seen[i] ? one : zero;
    }
    for (int i = 0; i < m; ++i)
        for (int j = 0; j < m; ++j)
            Rm[i * m + j] = (seen[i] & seen[j]) ? all(k.R[i * m + j]) : (i == j ? one : zero);
    X PHt[n * m], S[m * m], L[m * m], inv[m], K[n * m];
    mul_t<n, n, m>(Pp, H, PHt);
    mul<m, n, m>(H, PHt, S);
    for (int i = 0; i < m * m; ++i) S[i] += Rm[i];
    symmetrize<m>(S);
    cholesky<m>(S, L, inv, ok);
    for (int r = 0; r < n; ++r) chol_solve<m>(L, inv, PHt + r * m, K + r * m);
    X Ke[n];
    mul<n, m, 1>(K, e, Ke);
    for (int i = 0; i < n; ++i) x[i] = xp[i] + Ke[i];
    X A[n * n], AP[n * n], KR[n * m], KRK[n * n];
    mul<n, m, n>(K, H, A);
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) A[i * n + j] = (i == j ? one : zero) - A[i * n + j];
    mul<n, n, n>(A, Pp, AP);
    mul_t<n, n, n>(AP, A, P);
    mul<n, m, m>(K, Rm, KR);
    mul_t<n, m, n>(KR, K, KRK);
    for (int i = 0; i < n * n; ++i) P[i] += KRK[i];
    symmetrize<n>(P);
    X y[m], white{}, logdet{};
    lower_solve<m>(L, inv, e, y);
    for (int i = 0; i < m; ++i) white += y[i] * y[i];
    for (int i = 0; i < m; ++i) logdet += log_of(L[i * m + i]);
    loglik = all(-0.5) * (white + all(2.0) * logdet + observed * all(kLog2Pi));
}

// Σ_k w_k N(x_k, P_k) moment-matched (mixture_moments): x = Σ w x_k, P = sym(Σ w (P_k + d dᵀ));
// the mean alone without P.
template <int n>
inline void mixture(const X* w, const X* const* xs, const X* const* Ps, X* x, X* P) {
    for (int i = 0; i < n; ++i) x[i] = w[0] * xs[0][i] + w[1] * xs[1][i];
    if (P == nullptr) return;
    X d0[n], d1[n];
    for (int i = 0; i < n; ++i) d0[i] = xs[0][i] - x[i], d1[i] = xs[1][i] - x[i];
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j)
            P[i * n + j] = w[0] * (Ps[0][i * n + j] + d0[i] * d0[j]) +
                           w[1] * (Ps[1][i * n + j] + d1[i] * d1[j]);
    symmetrize<n>(P);
}

// Each mode's moments, in its own state, and the log mode probabilities: what the filter
// keeps of every step (with log c(t), both as the tensor path reads them back) and the
// smoother carries.
template <int D>
struct Moments {
    static constexpr int N = 2 * D + 1, V = 2 * D;
    X cv_x[V], cv_P[V * V], ct_x[N], ct_P[N * N], log_p[2], log_c[2];
};

// Mode j's moments in mode l's space (Embedding.into; the component ω the CV mode lacks lent
// by the CT mode, uncorrelated), written to x [n_l], P [n_l²].
template <int D>
inline void into(int j, int l, const Moments<D>& f, X* x, X* P) {
    constexpr int N = 2 * D + 1, V = 2 * D;
    if (j == 0 && l == 1) {
        for (int a = 0; a < N; ++a) {
            x[a] = a < V ? f.cv_x[a] : f.ct_x[V];
            for (int b = 0; b < N; ++b)
                P[a * N + b] = (a < V && b < V)     ? f.cv_P[a * V + b]
                               : (a == V && b == V) ? f.ct_P[V * N + V]
                                                    : X{};
        }
    } else if (j == 1 && l == 0) {
        for (int a = 0; a < V; ++a) {
            x[a] = f.ct_x[a];
            for (int b = 0; b < V; ++b) P[a * V + b] = f.ct_P[a * N + b];
        }
    } else if (j == 0) {
        for (int a = 0; a < V; ++a) x[a] = f.cv_x[a];
        for (int a = 0; a < V * V; ++a) P[a] = f.cv_P[a];
    } else {
        for (int a = 0; a < N; ++a) x[a] = f.ct_x[a];
        for (int a = 0; a < N * N; ++a) P[a] = f.ct_P[a];
    }
}

// Kim's backward quantities of one step k → k + 1 for every pair (j at k, l at k + 1):
// x̂^{jl}_{k+1|k}, P^{jl}_{k+1|k} and the gain C^{jl}_k (IMMSmoother._predictions), in the
// largest sizes; pair index 2j + l.
template <int D>
struct Pairs {
    static constexpr int N = 2 * D + 1;
    X x[4][N], P[4][N * N], C[4][N * N];
};

template <int D>
inline void pairs_of(const Constants<D>& k, X T, const Moments<D>& f, Pairs<D>& out, Mask& ok) {
    constexpr int N = 2 * D + 1, V = 2 * D;
    const Turn turn(T, f.ct_x[V]);  // both modes enter the turn with the CT mode's ω (into)
    for (int j = 0; j < 2; ++j)
        for (int l = 0; l < 2; ++l) {
            const int p = 2 * j + l;
            X x[N], P[N * N], F[N * N], cross[N * N];
            into<D>(j, l, f, x, P);
            const X* Pj = j == 0 ? f.cv_P : f.ct_P;
            if (l == 0) {
                symmetrize<V>(P);
                predict_cv<D>(k, T, x, P, out.x[p], out.P[p], F);
            } else {
                symmetrize<N>(P);
                predict_ct<D>(k, turn, x, P, out.x[p], out.P[p], F);
            }
            // cross = columns(j, l, P_j) Fᵀ: P_j's columns at mode l's components (zero for ω
            // where mode j is the CV mode), then the gain C = cross P_pred⁻¹.
            if (j == 0 && l == 1) {
                X cols[V * N];
                for (int a = 0; a < V; ++a)
                    for (int b = 0; b < N; ++b) cols[a * N + b] = b < V ? Pj[a * V + b] : X{};
                pattern_times_t<Pattern<D, true>, V>(cols, F, cross);
                right_solve<V, N>(cross, out.P[p], out.C[p], ok);
            } else if (j == 1 && l == 0) {
                X cols[N * V];
                for (int a = 0; a < N; ++a)
                    for (int b = 0; b < V; ++b) cols[a * V + b] = Pj[a * N + b];
                pattern_times_t<Pattern<D, false>, N>(cols, F, cross);
                right_solve<N, V>(cross, out.P[p], out.C[p], ok);
            } else if (j == 0) {
                pattern_times_t<Pattern<D, false>, V>(Pj, F, cross);
                right_solve<V, V>(cross, out.P[p], out.C[p], ok);
            } else {
                pattern_times_t<Pattern<D, true>, N>(Pj, F, cross);
                right_solve<N, N>(cross, out.P[p], out.C[p], ok);
            }
        }
}

// Mode j's pair (j, l) term: x_j + C (x^l_s − x̂^{jl}), P_j + C (P^l_s − P^{jl}) Cᵀ (the
// covariance only with P).
template <int nj, int nl>
inline void pair_term(const X* xj, const X* Pj, const X* C, const X* xp, const X* Pp,
                      const X* xl, const X* Pl, X* x, X* P) {
    X d[nl], Cd[nj];
    for (int a = 0; a < nl; ++a) d[a] = xl[a] - xp[a];
    mul<nj, nl, 1>(C, d, Cd);
    for (int a = 0; a < nj; ++a) x[a] = xj[a] + Cd[a];
    if (P == nullptr) return;
    X dP[nl * nl], CdP[nj * nl], CdPC[nj * nj];
    for (int a = 0; a < nl * nl; ++a) dP[a] = Pl[a] - Pp[a];
    mul<nj, nl, nl>(C, dP, CdP);
    mul_t<nj, nl, nj>(CdP, C, CdPC);
    for (int a = 0; a < nj * nj; ++a) P[a] = Pj[a] + CdPC[a];
}

// Mode j's smoothed moments from its two pair terms (the weights P(s_k+1 = l | s_k = j,
// z_1:e)), or its filtered ones where its smoothed probability is 0 (`gone`).
template <int nj, int nl0, int nl1>
inline void collapse(const X* xj, const X* Pj, const X* w, Mask gone, const X* C0, const X* x0,
                     const X* P0, const X* xl0, const X* Pl0, const X* C1, const X* x1,
                     const X* P1, const X* xl1, const X* Pl1, bool cov, X* x, X* P) {
    X xs[2][nj], Ps[2][nj * nj];
    pair_term<nj, nl0>(xj, Pj, C0, x0, P0, xl0, Pl0, xs[0], cov ? Ps[0] : nullptr);
    pair_term<nj, nl1>(xj, Pj, C1, x1, P1, xl1, Pl1, xs[1], cov ? Ps[1] : nullptr);
    const X* xp[2] = {xs[0], xs[1]};
    const X* Pp[2] = {Ps[0], Ps[1]};
    mixture<nj>(w, xp, Pp, x, cov ? P : nullptr);
    for (int a = 0; a < nj; ++a) x[a] = gone ? xj[a] : x[a];
    if (cov)
        for (int a = 0; a < nj * nj; ++a) P[a] = gone ? Pj[a] : P[a];
}

// One step of Kim's recursion (IMMSmoother._backward): from the smoothed moments at k + 1
// (`after`) and the filter's at k (`f`, its log c the one at k + 1: `log_c`), with the pairs
// of step k; the means alone without `cov`.
template <int D>
inline void backward(const Constants<D>& k, const Moments<D>& after, const Moments<D>& f,
                     const X* log_c, const Pairs<D>& pr, bool cov, Moments<D>& out) {
    constexpr int N = 2 * D + 1, V = 2 * D;
    const X neg_inf = all(kNegInf);
    X log_joint[2][2], weights[2][2] = {};
    for (int j = 0; j < 2; ++j)
        for (int l = 0; l < 2; ++l) {
            const Mask impossible = log_c[l] == neg_inf;  // mode l cannot be reached
            const X back = impossible ? neg_inf : f.log_p[j] + all(k.log_pi[2 * j + l]) - log_c[l];
            log_joint[j][l] = back + after.log_p[l];
        }
    Mask gone[2];
    for (int j = 0; j < 2; ++j) {
        out.log_p[j] = logsumexp2(log_joint[j][0], log_joint[j][1], weights[j]);
        gone[j] = out.log_p[j] == neg_inf;  // probability 0: the filtered estimate stays
    }
    collapse<V, V, N>(f.cv_x, f.cv_P, weights[0], gone[0], pr.C[0], pr.x[0], pr.P[0], after.cv_x,
                      after.cv_P, pr.C[1], pr.x[1], pr.P[1], after.ct_x, after.ct_P, cov, out.cv_x,
                      out.cv_P);
    collapse<N, V, N>(f.ct_x, f.ct_P, weights[1], gone[1], pr.C[2], pr.x[2], pr.P[2], after.cv_x,
                      after.cv_P, pr.C[3], pr.x[3], pr.P[3], after.ct_x, after.ct_P, cov, out.ct_x,
                      out.ct_P);
}

// The combined estimate (IMM.combine): each mode in the common state (the CV mode's ω 0 with
// variance 0), mixed by the mode probabilities w; the mean alone without P.
template <int D>
inline void combine(const Moments<D>& s, const X* w, X* x, X* P) {
    constexpr int N = 2 * D + 1, V = 2 * D;
    X x0[N], P0[N * N];
    for (int a = 0; a < N; ++a) {
        x0[a] = a < V ? s.cv_x[a] : X{};
        if (P != nullptr)
            for (int b = 0; b < N; ++b) P0[a * N + b] = (a < V && b < V) ? s.cv_P[a * V + b] : X{};
    }
    const X* xs[2] = {x0, s.ct_x};
    const X* Ps[2] = {P0, s.ct_P};
    mixture<N>(w, xs, Ps, x, P);
}

// The outputs (null: not wanted), each contiguous with leading [B, T] (loglik [B], mode_loglik
// [B, 2]): the filter pass's combined mean and covariance, mode probabilities, each mode's mean
// and covariance, the log-likelihoods; the smoother's the same (null smean: filter only).
struct Outputs {
    double *fmean, *fcov, *fprob, *fmode_x[2], *fmode_P[2], *loglik, *mode_loglik;
    double *smean, *scov, *sprob, *smode_x[2], *smode_P[2];
};

// A block of lanes: each lane's track (a short last block repeats its last track) and how many
// are real: lanes.h's LaneBlock of tracks with one "axis" each.
struct Lanes : LaneBlock<double> {
    Lanes(int64_t first, int64_t B) : LaneBlock<double>(first, B, 1) {}
    // Writes `size` values of every real lane at step t of a [B, T, size] output.
    void put(double* out, int64_t T, int64_t t, const X* from, int size) const {
        if (out == nullptr) return;
        for (int w = 0; w < count; ++w) {
            double* at = out + (b[w] * T + t) * size;
            for (int i = 0; i < size; ++i) at[i] = from[i][w];
        }
    }
};

// The filter forward over a block of lanes, then the smoother backward. lag: −1 the fixed
// interval, 0 no smoothing, L > 0 the fixed lag. `ok` loses the lanes where a Cholesky factor
// failed.
template <int D>
void block(const Constants<D>& k, const Lanes& lanes, int64_t T, int64_t lag, bool cov,
           const double* x0, const double* P0, const double* z, const double* dt,
           int64_t dt_track, int64_t dt_step, const double* log_p0, const Outputs& o,
           std::vector<Moments<D>>& filt, std::vector<Pairs<D>>& pairs, Mask& ok) {
    constexpr int N = 2 * D + 1, V = 2 * D;
    // What the smoother reads of the filter pass and the pairs: the fixed interval's sweep every
    // step's moments (its pairs made as it goes), the fixed lag a ring of its window's steps,
    // made as the filter goes (the window's data stay in cache), the filter alone nothing.
    const bool smooth = o.smean != nullptr, sweep = smooth && (lag < 0 || lag >= T - 1);
    const int64_t ring = !smooth ? 1 : sweep ? T : lag + 1;
    filt.resize(ring);
    pairs.resize(sweep || !smooth ? 1 : ring);
    auto filtered = [&filt, ring](int64_t t) -> Moments<D>& { return filt[t % ring]; };
    auto pair = [&pairs, ring](int64_t t) -> Pairs<D>& { return pairs[t % ring]; };
    auto gather = [&lanes](const double* base, int64_t stride, int64_t offset) {
        X v;
        for (int w = 0; w < kW; ++w) v[w] = base[lanes.b[w] * stride + offset];
        return v;
    };
    auto interval = [&](int64_t t) { return gather(dt, dt_track, t * dt_step); };
    Moments<D> cur;  // the filter's state: each mode's estimate, log μ
    for (int a = 0; a < V; ++a) {  // each mode starts from its components of the prior
        cur.cv_x[a] = gather(x0, N, a);
        for (int c = 0; c < V; ++c) cur.cv_P[a * V + c] = gather(P0, N * N, a * N + c);
    }
    for (int a = 0; a < N; ++a) cur.ct_x[a] = gather(x0, N, a);
    for (int a = 0; a < N * N; ++a) cur.ct_P[a] = gather(P0, N * N, a);
    auto emit = [&](int64_t t, const Moments<D>& s) {
        X xc[N], Pc[N * N];
        const X prob[2] = {exp_of(s.log_p[0]), exp_of(s.log_p[1])};
        combine<D>(s, prob, xc, cov && o.scov != nullptr ? Pc : nullptr);
        lanes.put(o.smean, T, t, xc, N);
        if (cov) lanes.put(o.scov, T, t, Pc, N * N);
        lanes.put(o.sprob, T, t, prob, 2);
        lanes.put(o.smode_x[0], T, t, s.cv_x, V);
        lanes.put(o.smode_x[1], T, t, s.ct_x, N);
        if (cov) {
            lanes.put(o.smode_P[0], T, t, s.cv_P, V * V);
            lanes.put(o.smode_P[1], T, t, s.ct_P, N * N);
        }
    };
    Moments<D> window[2];  // a fixed-lag window's moments, alternately (no copies)
    auto smooth_target = [&](int64_t t, int64_t end) {  // x̂_{t|end}: the window end → t
        const Moments<D>* at = &filtered(end);
        for (int64_t s = end - 1; s >= t; --s) {
            Moments<D>& into_ = window[(end - 1 - s) % 2];
            backward<D>(k, *at, filtered(s), filtered(s + 1).log_c, pair(s), cov, into_);
            at = &into_;
        }
        emit(t, *at);
    };
    X lp[2] = {gather(log_p0, 2, 0), gather(log_p0, 2, 1)};
    X total{}, mode_total[2] = {};
    const X neg_inf = all(kNegInf), one = all(1.0);
    for (int64_t t = 0; t < T; ++t) {
        const X Tt = interval(t);
        // Mixing (IMM.mix): c_j, μ_{i|j}, each mode's mixed prior.
        X log_joint[2][2], lc[2], w[2][2] = {};
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 2; ++j) log_joint[i][j] = lp[i] + all(k.log_pi[2 * i + j]);
        for (int j = 0; j < 2; ++j) {
            X wj[2] = {};
            lc[j] = logsumexp2(log_joint[0][j], log_joint[1][j], wj);
            const Mask unreachable = lc[j] == neg_inf;  // mode j keeps its own state
            for (int i = 0; i < 2; ++i) w[i][j] = unreachable ? (i == j ? one : X{}) : wj[i];
        }
        X mx0[V], mP0[V * V], mx1[N], mP1[N * N];
        {  // into the CV mode: the CT mode's first 2D components
            X ct_xv[V], ct_Pv[V * V];
            for (int a = 0; a < V; ++a) {
                ct_xv[a] = cur.ct_x[a];
                for (int c = 0; c < V; ++c) ct_Pv[a * V + c] = cur.ct_P[a * N + c];
            }
            const X ww[2] = {w[0][0], w[1][0]};
            const X* xs[2] = {cur.cv_x, ct_xv};
            const X* Ps[2] = {cur.cv_P, ct_Pv};
            mixture<V>(ww, xs, Ps, mx0, mP0);
        }
        {  // into the CT mode: the CV mode lends ω from the CT mode (unbiased mixing)
            X cv_xn[N], cv_Pn[N * N];
            into<D>(0, 1, cur, cv_xn, cv_Pn);
            const X ww[2] = {w[0][1], w[1][1]};
            const X* xs[2] = {cv_xn, cur.ct_x};
            const X* Ps[2] = {cv_Pn, cur.ct_P};
            mixture<N>(ww, xs, Ps, mx1, mP1);
        }
        // The modes' own predict-correct steps.
        X xp0[V], Pp0[V * V], F0[V * V], xp1[N], Pp1[N * N], F1[N * N], ll[2], zt[D];
        predict_cv<D>(k, Tt, mx0, mP0, xp0, Pp0, F0);
        predict_ct<D>(k, Turn(Tt, mx1[N - 1]), mx1, mP1, xp1, Pp1, F1);
        for (int i = 0; i < D; ++i) zt[i] = gather(z, T * D, t * D + i);
        correct<D, V>(k, zt, xp0, Pp0, cur.cv_x, cur.cv_P, ll[0], ok);
        correct<D, N>(k, zt, xp1, Pp1, cur.ct_x, cur.ct_P, ll[1], ok);
        // Mode probabilities μ_j = c_j Λ_j / Σ, in log space.
        const X lj[2] = {lc[0] + ll[0], lc[1] + ll[1]};
        X prob[2] = {};
        const X step = logsumexp2(lj[0], lj[1], prob);
        lp[0] = lj[0] - step, lp[1] = lj[1] - step;
        total += step;
        mode_total[0] += ll[0], mode_total[1] += ll[1];
        X xc[N], Pc[N * N];
        combine<D>(cur, prob, xc, o.fcov != nullptr ? Pc : nullptr);
        lanes.put(o.fmean, T, t, xc, N);
        lanes.put(o.fcov, T, t, Pc, N * N);
        lanes.put(o.fprob, T, t, prob, 2);
        lanes.put(o.fmode_x[0], T, t, cur.cv_x, V);
        lanes.put(o.fmode_x[1], T, t, cur.ct_x, N);
        lanes.put(o.fmode_P[0], T, t, cur.cv_P, V * V);
        lanes.put(o.fmode_P[1], T, t, cur.ct_P, N * N);
        for (int j = 0; j < 2; ++j) cur.log_p[j] = read_back(lp[j]), cur.log_c[j] = read_back(lc[j]);
        filtered(t) = cur;
        if (smooth && !sweep) {  // the fixed lag: step t − 1's pairs, then target t − L's window
            if (t >= 1) pairs_of<D>(k, Tt, filtered(t - 1), pair(t - 1), ok);
            if (t >= lag) smooth_target(t - lag, t);
        }
    }
    for (int w = 0; w < lanes.count; ++w) {
        if (o.loglik != nullptr) o.loglik[lanes.b[w]] = total[w];
        if (o.mode_loglik != nullptr)
            for (int j = 0; j < 2; ++j) o.mode_loglik[2 * lanes.b[w] + j] = mode_total[j][w];
    }
    if (!smooth) return;
    if (!sweep) {  // the last L targets' windows end at T − 1
        for (int64_t t = T - lag; t < T; ++t) smooth_target(t, T - 1);
        return;
    }
    // The fixed interval: one sweep from the end (every window ends at T − 1), each step's
    // pairs made as it is reached.
    Moments<D> next;
    cur = filt[T - 1];
    emit(T - 1, cur);
    for (int64_t t = T - 2; t >= 0; --t) {
        pairs_of<D>(k, interval(t + 1), filt[t], pairs[0], ok);
        backward<D>(k, cur, filt[t], filt[t + 1].log_c, pairs[0], cov, next);
        cur = next;
        emit(t, cur);
    }
}

// Every track, in blocks of lanes on threads. in: x0 [B, N], P0 [B, N, N], z [B, T, D], dt
// (element strides dt_track, dt_step; 0 for one interval), log p0 [B, 2]. Returns 0; 1 when a
// Cholesky factor failed (the caller then takes the tensor path); 2 when z holds an infinity.
template <int D>
int run(int64_t B, int64_t T, int64_t lag, bool cov, int threads, const Constants<D>& k,
        const double* x0, const double* P0, const double* z, const double* dt, int64_t dt_track,
        int64_t dt_step, const double* log_p0, const Outputs& o) {
    for (int64_t i = 0; i < B * T * D; ++i)
        if (std::isinf(z[i])) return 2;
    const int64_t blocks = (B + kW - 1) / kW;
    std::atomic<int> failed{0};
    over_tracks(blocks, threads, [&](int64_t first, int64_t last) {
        std::vector<Moments<D>> filt;
        std::vector<Pairs<D>> pairs;
        for (int64_t i = first; i < last && !failed.load(std::memory_order_relaxed); ++i) {
            const Lanes lanes(i * kW, B);
            Mask ok = X{} == X{};
            block<D>(k, lanes, T, lag, cov, x0, P0, z, dt, dt_track, dt_step, log_p0, o, filt,
                     pairs, ok);
            if (!every(ok)) failed.store(1);
        }
    });
    return failed.load();
}

}  // namespace imm

// The C entry point's unpacking: params q, turn_q, turn_rate_q, log π [4], R [D²];
// in: x0, P0, z, dt, log p0; out: the 16 pointers of imm::Outputs in order.
template <int D>
int turn_imm_of(int64_t B, int64_t T, int64_t lag, int cov, int threads, const double* params,
                const void* const* in, int64_t dt_track, int64_t dt_step, void* const* out) {
    auto d = [out](int i) { return static_cast<double*>(out[i]); };
    const imm::Outputs outputs{d(0),  d(1),  d(2),  {d(3), d(4)},   {d(5), d(6)},   d(7), d(8),
                               d(9),  d(10), d(11), {d(12), d(13)}, {d(14), d(15)}};
    imm::Constants<D> k;
    k.q = params[0], k.turn_q = params[1], k.turn_rate_q = params[2];
    for (int i = 0; i < 4; ++i) k.log_pi[i] = params[3 + i];
    for (int i = 0; i < D * D; ++i) k.R[i] = params[7 + i];
    auto p = [in](int i) { return static_cast<const double*>(in[i]); };
    return imm::run<D>(B, T, lag, cov != 0, threads, k, p(0), p(1), p(2), p(3), dt_track,
                       dt_step, p(4), outputs);
}

}  // namespace

// The sequential time loops of the per-axis kernel (torchsvs/kernels/axes.py) as compiled C++.
//
// Each (track, axis) pair is an independent chain of two-state steps; its state stays in
// registers and every step costs a few dozen flops instead of a few dozen tensor operations.
// The formulas are those of axes.py, transcribed line by line (the Python functions named in
// the comments are their home and the differentiable path); tests hold both to 1e-9.
//
// Every array argument is a pointer and three element strides (track, step, axis) into a
// [B, T, m] view, so broadcast inputs (stride 0) need no copies. Outputs are contiguous.
// Built and loaded by torchsvs/kernels/fused.py (g++ -O3, ctypes).

#include <cmath>
#include <cstdint>
#include <vector>

namespace {

template <typename R>
struct View {
    const R* data;
    int64_t sb, st, sm;
    R at(int64_t b, int64_t t, int64_t j) const { return data[b * sb + t * st + j * sm]; }
};

template <typename R>
View<R> view(const void* const* ptrs, const int64_t* strides, int i) {
    return View<R>{static_cast<const R*>(ptrs[i]), strides[3 * i], strides[3 * i + 1],
                   strides[3 * i + 2]};
}

// svsf_gain_ratio (torchsvs/linalg.py): (|e| + γ|e_post|) / max(|e|, ψ), Eq. (23).
template <typename R>
inline R gain_ratio(R e, R memory, R width, R gamma) {
    R magnitude = std::fabs(e);
    return (magnitude + gamma * std::fabs(memory)) / (magnitude > width ? magnitude : width);
}

// axes._forward_step over all steps. rule 0: Kalman (position-only), 1: SVSF.
// Inputs (13): T, Qa, Qb, Qc, fp, fv, yp, yv, rp, rpv, rvv, wp, wv.
// Prior (5, [B, m] views as [B, 1, m]): p, v, a, b, c.
// Outputs (17, [B, T, m]): p, v, a, b, c, p_pred, a1, b1, c1, ep, ev, ka, kb, kc, kd, mp, mv.
template <typename R>
void forward(int64_t B, int64_t T, int64_t m, int rule, R gamma, const void* const* in,
             const int64_t* in_strides, const void* const* prior, const int64_t* prior_strides,
             void* const* out) {
    View<R> Ts = view<R>(in, in_strides, 0), Qa = view<R>(in, in_strides, 1),
            Qb = view<R>(in, in_strides, 2), Qc = view<R>(in, in_strides, 3),
            Fp = view<R>(in, in_strides, 4), Fv = view<R>(in, in_strides, 5),
            Yp = view<R>(in, in_strides, 6), Yv = view<R>(in, in_strides, 7),
            Rp = view<R>(in, in_strides, 8), Rpv = view<R>(in, in_strides, 9),
            Rvv = view<R>(in, in_strides, 10), Wp = view<R>(in, in_strides, 11),
            Wv = view<R>(in, in_strides, 12);
    R* o[17];
    for (int i = 0; i < 17; ++i) o[i] = static_cast<R*>(out[i]);
    // Steps outermost and the independent (track, axis) chains inside: the processor overlaps
    // the chains' dependent arithmetic (each step waits on the one before, within a chain).
    const int64_t chains = B * m;
    std::vector<R> state(7 * chains);
    R *P = state.data(), *V = P + chains, *A = V + chains, *Bc = A + chains, *Cc = Bc + chains,
      *MP = Cc + chains, *MV = MP + chains;
    for (int64_t bi = 0; bi < B; ++bi) {
        for (int64_t j = 0; j < m; ++j) {
            int64_t i = bi * m + j;
            P[i] = view<R>(prior, prior_strides, 0).at(bi, 0, j);
            V[i] = view<R>(prior, prior_strides, 1).at(bi, 0, j);
            A[i] = view<R>(prior, prior_strides, 2).at(bi, 0, j);
            Bc[i] = view<R>(prior, prior_strides, 3).at(bi, 0, j);
            Cc[i] = view<R>(prior, prior_strides, 4).at(bi, 0, j);
            MP[i] = MV[i] = 0;
        }
    }
    for (int64_t t = 0; t < T; ++t) {
        for (int64_t bi = 0; bi < B; ++bi) {
            for (int64_t j = 0; j < m; ++j) {
                int64_t i = bi * m + j;
                R p = P[i], v = V[i], a = A[i], b = Bc[i], c = Cc[i];
                R memory_p = MP[i], memory_v = MV[i];
                R dt = Ts.at(bi, t, j), fp = Fp.at(bi, t, j), fv = Fv.at(bi, t, j);
                R yp = Yp.at(bi, t, j), yv = Yv.at(bi, t, j), rp = Rp.at(bi, t, j);
                // Prediction, Eqs. (11)-(12): F P Fᵀ + Q with F = [[1, T], [0, 1]].
                R p_pred = p + dt * v, v_pred = v;
                R bT = b + dt * c;
                R a1 = a + dt * (b + bT) + Qa.at(bi, t, j);
                R b1 = bT + Qb.at(bi, t, j);
                R c1 = c + Qc.at(bi, t, j);
                R ep = (yp - p_pred) * fp;
                R ev = 0, ka, kb = 0, kc, kd;
                if (rule == 0) {
                    R S = a1 * fp + rp;
                    R kp = a1 * fp / S, kv_p = b1 * fp / S;
                    R one_k = 1 - kp;
                    a = one_k * one_k * a1 + kp * kp * rp;
                    b = one_k * (b1 - kv_p * a1) + kp * kv_p * rp;
                    c = c1 - 2 * kv_p * b1 + kv_p * kv_p * (a1 + rp);
                    p = p_pred + kp * ep;
                    v = v_pred + kv_p * ep;
                    ka = kp, kc = kv_p, kd = 0;
                } else {
                    ev = (yv - v_pred) * fv;
                    R kp = gain_ratio(ep, memory_p, Wp.at(bi, t, j), gamma) * fp;
                    R kv = gain_ratio(ev, memory_v, Wv.at(bi, t, j), gamma) * fv;
                    R one_p = 1 - kp, one_v = 1 - kv;
                    a = one_p * one_p * a1 + kp * kp * rp;
                    b = one_p * one_v * b1 + kp * kv * Rpv.at(bi, t, j);
                    c = one_v * one_v * c1 + kv * kv * Rvv.at(bi, t, j);
                    p = p_pred + kp * ep;
                    v = v_pred + kv * ev;
                    // Eq. (24): the a-posteriori innovation, carried where missing.
                    if (fp > 0) memory_p = yp - p;
                    if (fv > 0) memory_v = yv - v;
                    ka = kp, kc = 0, kd = kv;
                }
                P[i] = p, V[i] = v, A[i] = a, Bc[i] = b, Cc[i] = c, MP[i] = memory_p;
                MV[i] = memory_v;
                int64_t k = (bi * T + t) * m + j;
                R values[17] = {p,  v,  a,  b,  c,  p_pred, a1,       b1,      c1,
                                ep, ev, ka, kb, kc, kd,     memory_p, memory_v};
                for (int n = 0; n < 17; ++n) o[n][k] = values[n];
            }
        }
    }
}

// axes._rts_interval: x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k}),
// Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ, C_k = P_k Fᵀ P_{k+1|k}⁻¹ (Eq. (17)).
// Inputs (11): p, v, a, b, c (filtered), p_pred, v_pred, a1, b1, c1 (predicted), T.
// Outputs (5, [B, T, m]): p, v, a, b, c (smoothed).
template <typename R>
void rts_interval(int64_t B, int64_t T, int64_t m, const void* const* in,
                  const int64_t* in_strides, void* const* out) {
    View<R> P = view<R>(in, in_strides, 0), V = view<R>(in, in_strides, 1),
            A = view<R>(in, in_strides, 2), Bc = view<R>(in, in_strides, 3),
            Cc = view<R>(in, in_strides, 4), Pp = view<R>(in, in_strides, 5),
            Vp = view<R>(in, in_strides, 6), A1 = view<R>(in, in_strides, 7),
            B1 = view<R>(in, in_strides, 8), C1 = view<R>(in, in_strides, 9),
            Ts = view<R>(in, in_strides, 10);
    R* o[5];
    for (int i = 0; i < 5; ++i) o[i] = static_cast<R*>(out[i]);
    for (int64_t bi = 0; bi < B; ++bi) {
        for (int64_t j = 0; j < m; ++j) {
            int64_t last = (bi * T + T - 1) * m + j;
            R ps = P.at(bi, T - 1, j), vs = V.at(bi, T - 1, j);
            R sa = A.at(bi, T - 1, j), sb = Bc.at(bi, T - 1, j), sc = Cc.at(bi, T - 1, j);
            R values[5] = {ps, vs, sa, sb, sc};
            for (int i = 0; i < 5; ++i) o[i][last] = values[i];
            for (int64_t k = T - 2; k >= 0; --k) {
                R dt = Ts.at(bi, k + 1, j);
                R a = A.at(bi, k, j), b = Bc.at(bi, k, j), c = Cc.at(bi, k, j);
                R pa = A1.at(bi, k + 1, j), pb = B1.at(bi, k + 1, j), pc = C1.at(bi, k + 1, j);
                // C = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]] (axes.inverse, axes.mm).
                R det = pa * pc - pb * pb;
                R ia = pc / det, ib = -pb / det, ic = pa / det;
                R xa = a + dt * b, xb = b, xc = b + dt * c, xd = c;
                R ca = xa * ia + xb * ib, cb = xa * ib + xb * ic;
                R cc = xc * ia + xd * ib, cd = xc * ib + xd * ic;
                R dp = ps - Pp.at(bi, k + 1, j), dv = vs - Vp.at(bi, k + 1, j);
                ps = P.at(bi, k, j) + (ca * dp + cb * dv);
                vs = V.at(bi, k, j) + (cc * dp + cd * dv);
                // axes.sandwich(C, Pˢ − Pp): C D Cᵀ, symmetrised.
                R da = sa - pa, db = sb - pb, dd = sc - pc;
                R ma = ca * da + cb * db, mb = ca * db + cb * dd;
                R mc = cc * da + cd * db, md = cc * db + cd * dd;
                R ea = ma * ca + mb * cb, eb = ma * cc + mb * cd;
                R ec = mc * ca + md * cb, ed = mc * cc + md * cd;
                sa = a + ea;
                sb = b + 0.5 * (eb + ec);
                sc = c + ed;
                int64_t idx = (bi * T + k) * m + j;
                R now[5] = {ps, vs, sa, sb, sc};
                for (int i = 0; i < 5; ++i) o[i][idx] = now[i];
            }
        }
    }
}

template <typename R>
struct M2 {
    R a, b, c, d;
};

template <typename R>
inline M2<R> mul(const M2<R>& X, const M2<R>& Y) {
    return {X.a * Y.a + X.b * Y.c, X.a * Y.b + X.b * Y.d, X.c * Y.a + X.d * Y.c,
            X.c * Y.b + X.d * Y.d};
}

template <typename R>
inline M2<R> tr(const M2<R>& X) {
    return {X.a, X.c, X.b, X.d};
}

template <typename R>
inline M2<R> plus(const M2<R>& X, const M2<R>& Y) {
    return {X.a + Y.a, X.b + Y.b, X.c + Y.c, X.d + Y.d};
}

template <typename R>
inline M2<R> neg(const M2<R>& X) {
    return {-X.a, -X.b, -X.c, -X.d};
}

// axes.full(axes.inverse(S)) of a symmetric block given as (a, b, -, d).
template <typename R>
inline M2<R> inverse(R a, R b, R d) {
    R det = a * d - b * b;
    return {d / det, -b / det, -b / det, a / det};
}

// axes.backward_terms at one step: C, d, ΓHF, ΓSΓᵀ, ΓX, AF (22 values, in that order) of the
// backward recursion at index k+1, from the filter's moments (P at k; the rest at k+1).
// Γ = K (RTS) or, with `projection`, P Hᵀ S⁻¹ (SVSS, Eq. (42)).
template <typename R>
inline void terms_at(R* w, bool projection, R a, R b, R c, R a1, R b1, R c1, const M2<R>& K,
                     R rp, R rpv, R rvv, R fp, R fv, R dt, R ep, R ev) {
    M2<R> Pp{a1, b1, b1, c1}, P{a, b, b, c}, R_{rp, rpv, rpv, rvv};
    M2<R> H{fp, 0, 0, fv}, F{1, dt, 0, 1};
    M2<R> PHt = mul(Pp, H);
    M2<R> S = plus(mul(H, PHt), R_);
    M2<R> Gamma = projection ? mul(PHt, inverse(S.a, S.b, S.d)) : K;
    M2<R> A{1 - K.a, -K.b, -K.c, 1 - K.d};
    M2<R> X = plus(mul(tr(PHt), tr(A)), neg(mul(R_, tr(K))));
    M2<R> C = tr(mul(inverse(Pp.a, Pp.b, Pp.d), mul(F, P)));
    M2<R> GHF = mul(mul(Gamma, H), F), GSG = mul(mul(Gamma, S), tr(Gamma));
    M2<R> GX = mul(Gamma, X), AF = mul(A, F);
    R d0 = Gamma.a * ep + Gamma.b * ev, d1 = Gamma.c * ep + Gamma.d * ev;
    const M2<R>* blocks[5] = {&C, &GHF, &GSG, &GX, &AF};
    int n = 0;
    for (int i = 0; i < 5; ++i) {
        w[n++] = blocks[i]->a, w[n++] = blocks[i]->b, w[n++] = blocks[i]->c;
        w[n++] = blocks[i]->d;
        if (i == 0) w[n++] = d0, w[n++] = d1;
    }
}

template <typename R>
struct Backward {
    R g0, g1;
    M2<R> G, Z;
};

// axes._recurse at a step whose 22 terms are `w` (C, d, ΓHF, ΓSΓᵀ, ΓX, AF in order):
// g_k = C (d + g), G_k = C (ΓHF + G AF), Z_k = C (ΓSΓᵀ + X + Xᵀ + Z) Cᵀ with X = ΓX Gᵀ.
template <typename R>
inline Backward<R> recurse(const R* w, const Backward<R>& s) {
    M2<R> C{w[0], w[1], w[2], w[3]}, GHF{w[6], w[7], w[8], w[9]};
    M2<R> GSG{w[10], w[11], w[12], w[13]}, GX{w[14], w[15], w[16], w[17]};
    M2<R> AF{w[18], w[19], w[20], w[21]};
    M2<R> cross = mul(GX, tr(s.G));
    R d0 = w[4] + s.g0, d1 = w[5] + s.g1;
    Backward<R> out;
    out.g0 = C.a * d0 + C.b * d1;
    out.g1 = C.c * d0 + C.d * d1;
    out.G = mul(C, plus(GHF, mul(s.G, AF)));
    M2<R> inner = plus(plus(plus(GSG, cross), tr(cross)), s.Z);
    out.Z = mul(mul(C, inner), tr(C));
    return out;
}

// axes.smooth_axes: the backward recursion from zero at the end (fixed interval) or, with a
// lag L < T-1, L applications from zero at step k+L for each k (the fixed-lag form), then
// axes._smoothed: x̂ˢ_k = x̂_k + g_k, Pˢ_k = P_k − P_k G_kᵀ − G_k P_k + Z_k (symmetrised; the
// last step as filtered).
// Inputs (20, [B, T, m]): the filter's cov a, b, c; pred_cov a, b, c; gain a, b, c, d;
// noise (masked) pp, pv, vv; observed p, v (0/1); T; innovation p, v; mean p, v.
// Outputs (5, [B, T, m]): smoothed p, v, a, b, c.
template <typename R>
void backward(int64_t B, int64_t T, int64_t m, int64_t lag, int projection, const void* const* in,
              const int64_t* in_strides, void* const* out) {
    View<R> v[20];
    for (int i = 0; i < 20; ++i) v[i] = view<R>(in, in_strides, i);
    R* o[5];
    for (int i = 0; i < 5; ++i) o[i] = static_cast<R*>(out[i]);
    const Backward<R> zero{0, 0, {0, 0, 0, 0}, {0, 0, 0, 0}};
    const int64_t n = T - 1;  // steps with a successor
    // One chain's terms, step by step (contiguous for the sweeps), and its results.
    std::vector<R> terms(22 * (n > 0 ? n : 1));
    std::vector<Backward<R>> result(n + 1, zero);  // result[n]: zero beyond the end
    for (int64_t bi = 0; bi < B; ++bi) {
        for (int64_t j = 0; j < m; ++j) {
            auto at = [&](int i, int64_t t) { return v[i].at(bi, t, j); };
            for (int64_t k = 0; k < n; ++k) {
                int64_t t = k + 1;
                M2<R> K{at(6, t), at(7, t), at(8, t), at(9, t)};
                terms_at(&terms[22 * k], projection != 0, at(0, k), at(1, k), at(2, k), at(3, t),
                         at(4, t), at(5, t), K, at(10, t), at(11, t), at(12, t), at(13, t),
                         at(14, t), at(15, t), at(16, t), at(17, t));
            }
            if (lag >= n) {
                for (int64_t k = n - 1; k >= 0; --k)
                    result[k] = recurse(&terms[22 * k], result[k + 1]);
            } else {
                // `lag` sweeps, each applying one step to the previous sweep's value at k+1
                // (read before it is overwritten, going forward).
                for (int64_t k = 0; k < n; ++k) result[k] = zero;
                for (int64_t sweep = 0; sweep < lag; ++sweep)
                    for (int64_t k = 0; k < n; ++k)
                        result[k] = recurse(&terms[22 * k], result[k + 1]);
            }
            for (int64_t k = 0; k <= n; ++k) {
                R a = at(0, k), b = at(1, k), c = at(2, k);
                R now[5] = {at(18, k), at(19, k), a, b, c};
                if (k < n) {  // axes._smoothed
                    const Backward<R>& s = result[k];
                    M2<R> P{a, b, b, c};
                    M2<R> PGt = mul(P, tr(s.G));
                    M2<R> cov = plus(plus(plus(P, neg(PGt)), neg(tr(PGt))), s.Z);
                    now[0] += s.g0, now[1] += s.g1;
                    now[2] = cov.a, now[3] = 0.5 * (cov.b + cov.c), now[4] = cov.d;
                }
                int64_t idx = (bi * T + k) * m + j;
                for (int i = 0; i < 5; ++i) o[i][idx] = now[i];
            }
        }
    }
}

// One predict-correct step of a dense linear-Gaussian filter for one track:
// GaussianFilter.predict, then KalmanFilter.correct (rule 0) or SVSF.correct with an H of
// orthonormal rows, whose H⁺ is Hᵀ (rule 1). n, m ≤ kMax; every array contiguous.
// Given x [n], P [n, n], z [m] (NaN: missing), the SVSF's memory and psi [m], and
// F [n, n], Q [n, n], H [m, n], R [m, m]; writes x, P, x_pred, P_pred, e [m], K [n, m],
// S [m, m], *loglik, e_post [m], observed [m]. Returns 0, or 1 when a Cholesky factor failed
// (the caller then takes the tensor path, whose factorisation adds jitter).
constexpr int64_t kMax = 16;

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
// Returns 0; 1 when a Cholesky factor failed; 2 when z holds an infinity (the caller's tensor
// path reports it).
template <typename R>
int dense_run(int64_t B, int64_t T, int64_t n, int64_t m, int rule, R gamma, const R* X,
              const R* P, const R* Z, const R* M, const R* W, int64_t psi_track,
              int64_t psi_step, const void* const* consts, void* const* outs) {
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
    }
    return 0;
}

// The C entry points' casts, once for both dtypes.
template <typename R>
int dense_entry(int64_t B, int64_t T, int64_t n, int64_t m, int rule, double gamma, const void* x,
                const void* P, const void* z, const void* memory, const void* psi,
                int64_t psi_track, int64_t psi_step, const void* const* consts,
                void* const* outs) {
    return dense_run<R>(B, T, n, m, rule, static_cast<R>(gamma), static_cast<const R*>(x),
                        static_cast<const R*>(P), static_cast<const R*>(z),
                        static_cast<const R*>(memory), static_cast<const R*>(psi), psi_track,
                        psi_step, consts, outs);
}

}  // namespace

extern "C" {

void forward_f32(int64_t B, int64_t T, int64_t m, int rule, double gamma, const void* const* in,
                 const int64_t* s, const void* const* prior, const int64_t* ps, void* const* out) {
    forward<float>(B, T, m, rule, static_cast<float>(gamma), in, s, prior, ps, out);
}

void forward_f64(int64_t B, int64_t T, int64_t m, int rule, double gamma, const void* const* in,
                 const int64_t* s, const void* const* prior, const int64_t* ps, void* const* out) {
    forward<double>(B, T, m, rule, gamma, in, s, prior, ps, out);
}

void rts_interval_f32(int64_t B, int64_t T, int64_t m, const void* const* in, const int64_t* s,
                      void* const* out) {
    rts_interval<float>(B, T, m, in, s, out);
}

void rts_interval_f64(int64_t B, int64_t T, int64_t m, const void* const* in, const int64_t* s,
                      void* const* out) {
    rts_interval<double>(B, T, m, in, s, out);
}

void backward_f32(int64_t B, int64_t T, int64_t m, int64_t lag, int projection,
                  const void* const* in, const int64_t* s, void* const* out) {
    backward<float>(B, T, m, lag, projection, in, s, out);
}

void backward_f64(int64_t B, int64_t T, int64_t m, int64_t lag, int projection,
                  const void* const* in, const int64_t* s, void* const* out) {
    backward<double>(B, T, m, lag, projection, in, s, out);
}

int dense_run_f32(int64_t B, int64_t T, int64_t n, int64_t m, int rule, double gamma,
                  const void* x, const void* P, const void* z, const void* memory, const void* psi,
                  int64_t psi_track, int64_t psi_step, const void* const* consts, void* o0,
                  void* o1, void* o2, void* o3, void* o4, void* o5, void* o6, void* o7, void* o8,
                  void* o9) {
    void* const outs[10] = {o0, o1, o2, o3, o4, o5, o6, o7, o8, o9};
    return dense_entry<float>(B, T, n, m, rule, gamma, x, P, z, memory, psi, psi_track, psi_step,
                              consts, outs);
}

int dense_run_f64(int64_t B, int64_t T, int64_t n, int64_t m, int rule, double gamma,
                  const void* x, const void* P, const void* z, const void* memory, const void* psi,
                  int64_t psi_track, int64_t psi_step, const void* const* consts, void* o0,
                  void* o1, void* o2, void* o3, void* o4, void* o5, void* o6, void* o7, void* o8,
                  void* o9) {
    void* const outs[10] = {o0, o1, o2, o3, o4, o5, o6, o7, o8, o9};
    return dense_entry<double>(B, T, n, m, rule, gamma, x, P, z, memory, psi, psi_track,
                               psi_step, consts, outs);
}

}  // extern "C"

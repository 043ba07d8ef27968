// The per-axis kernel's backward recursions (part of fused.cpp): the general recursion's terms
// and steps (twins of torchsvs/kernels/axes_smoother.py's backward_terms, _recurse, _smoothed),
// the one-step-lag smoother the forward loop runs as it steps, the RTS's own fixed-interval loop
// (twin of axes_smoother._rts_interval) and the general recursion over a whole record
// (twin of axes_smoother.smooth_axes). tests/test_kernels.py holds each to the tensor loops to
// 1e-10 in float64.
#pragma once

#include "axis_step.h"

namespace {

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

// blocks.full(blocks.inverse(S)) of a symmetric block given as (a, b, -, d).
template <typename R>
inline M2<R> inverse(R a, R b, R d) {
    R det = a * d - b * b;
    return {d / det, -b / det, -b / det, a / det};
}

// What axes_smoother.backward_terms reads at index k (the step k and its successor t = k + 1): P at k;
// the prediction, gain, noise (masked: an identity on missing components, as
// blocks.masked_noise), masks, interval and innovation at t.
template <typename R>
struct TermArgs {
    R a, b, c, a1, b1, c1;
    M2<R> K;
    R rp, rpv, rvv, fp, fv, dt, ep, ev;
};

// TermArgs from a lane's values, the noise unmasked: masked here (an identity on missing
// components, as blocks.masked_noise).
template <typename R>
inline TermArgs<R> masked_args(R a, R b, R c, R a1, R b1, R c1, const M2<R>& K, R rp, R rpv,
                               R rvv, R fp, R fv, R dt, R ep, R ev) {
    return {a, b, c, a1, b1, c1, K, rp * fp + (1 - fp), rpv * fp * fv, rvv * fv + (1 - fv),
            fp, fv, dt, ep, ev};
}

// TermArgs at index k from a lane's 20 inputs, `at(i, step)` in backward's input order.
template <typename R, typename At>
inline TermArgs<R> term_args(const At& at, int64_t k) {
    const int64_t t = k + 1;
    return masked_args<R>(at(0, k), at(1, k), at(2, k), at(3, t), at(4, t), at(5, t),
                          {at(6, t), at(7, t), at(8, t), at(9, t)}, at(10, t), at(11, t),
                          at(12, t), at(13, t), at(14, t), at(15, t), at(16, t), at(17, t));
}

// axes_smoother.backward_terms at one index, with its intermediates (the reverse mode reads them):
// C, d, ΓHF, ΓSΓᵀ, ΓX, AF of the backward recursion at index k+1, from the filter's moments.
// Γ = K (RTS) or, with `projection`, P Hᵀ S⁻¹ (SVSS, Eq. (42)).
template <typename R>
struct Terms {
    M2<R> Pp, P, R_, H, F, PHt, S, Sinv, Gamma, A, X, Ppinv, FP, HF;
    M2<R> C, GHF, GSG, GX, AF;
    R d0, d1;
};

template <typename R>
__attribute__((always_inline)) inline Terms<R> terms(bool projection, const TermArgs<R>& x) {
    Terms<R> t;
    t.Pp = {x.a1, x.b1, x.b1, x.c1}, t.P = {x.a, x.b, x.b, x.c};
    t.R_ = {x.rp, x.rpv, x.rpv, x.rvv};
    const R zero{}, one = zero + 1;  // scalars, or vectors of lanes (Wide)
    t.H = {x.fp, zero, zero, x.fv}, t.F = {one, x.dt, zero, one};
    t.PHt = mul(t.Pp, t.H);
    t.S = plus(mul(t.H, t.PHt), t.R_);
    t.Sinv = inverse(t.S.a, t.S.b, t.S.d);
    // Γ entry by entry: a whole-block copy here keeps the lanes' loop from vectorising.
    const M2<R> projected = mul(t.PHt, t.Sinv);
    t.Gamma.a = projection ? projected.a : x.K.a, t.Gamma.b = projection ? projected.b : x.K.b;
    t.Gamma.c = projection ? projected.c : x.K.c, t.Gamma.d = projection ? projected.d : x.K.d;
    t.A = {1 - x.K.a, -x.K.b, -x.K.c, 1 - x.K.d};
    t.X = plus(mul(tr(t.PHt), tr(t.A)), neg(mul(t.R_, tr(x.K))));
    t.Ppinv = inverse(t.Pp.a, t.Pp.b, t.Pp.d);
    t.FP = mul(t.F, t.P), t.HF = mul(t.H, t.F);
    t.C = tr(mul(t.Ppinv, t.FP));
    t.GHF = mul(t.Gamma, t.HF), t.GSG = mul(mul(t.Gamma, t.S), tr(t.Gamma));
    t.GX = mul(t.Gamma, t.X), t.AF = mul(t.A, t.F);
    t.d0 = t.Gamma.a * x.ep + t.Gamma.b * x.ev, t.d1 = t.Gamma.c * x.ep + t.Gamma.d * x.ev;
    return t;
}

// The 22 values the recursion reads at an index (C, d, ΓHF, ΓSΓᵀ, ΓX, AF in order).
template <typename R>
__attribute__((always_inline)) inline void terms_at(R* w, bool projection, const TermArgs<R>& x) {
    const Terms<R> t = terms(projection, x);
    const M2<R>* blocks[5] = {&t.C, &t.GHF, &t.GSG, &t.GX, &t.AF};
    int n = 0;
    for (int i = 0; i < 5; ++i) {
        w[n++] = blocks[i]->a, w[n++] = blocks[i]->b, w[n++] = blocks[i]->c;
        w[n++] = blocks[i]->d;
        if (i == 0) w[n++] = t.d0, w[n++] = t.d1;
    }
}

template <typename R>
struct Backward {
    R g0, g1;
    M2<R> G, Z;
};

// axes_smoother._recurse at a step whose 22 terms are `w` (C, d, ΓHF, ΓSΓᵀ, ΓX, AF in order):
// g_k = C (d + g), G_k = C (ΓHF + G AF), Z_k = C (ΓSΓᵀ + X + Xᵀ + Z) Cᵀ with X = ΓX Gᵀ.
template <typename R>
__attribute__((always_inline)) inline Backward<R> recurse(const R* w, const Backward<R>& s) {
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

// axes_smoother._smoothed at one step of a lane: `now` holds its filtered moments (p, v, a, b, c) and
// becomes x̂ˢ = x̂ + g, Pˢ = P − P Gᵀ − G P + Z (symmetrised).
template <typename R>
__attribute__((always_inline)) inline void smoothed(R* now, const Backward<R>& s) {
    M2<R> P{now[2], now[3], now[3], now[4]};
    M2<R> PGt = mul(P, tr(s.G));
    M2<R> cov = plus(plus(plus(P, neg(PGt)), neg(tr(PGt))), s.Z);
    now[0] += s.g0, now[1] += s.g1;
    now[2] = cov.a, now[3] = 0.5 * (cov.b + cov.c), now[4] = cov.d;
}

// The one-step-lag smoother at k = t − 1 for `lanes` lanes, as step t completes: `backward`'s
// recursion from zero over one step (lane_recursion with lag 1) and its smoothed moments, from
// the step's inputs `g` and results `r`. `moments` holds each lane's filtered moments at k
// (p, v, a, b, c) and becomes the smoothed ones. (Projection is a template argument: a branch
// in the loop would keep it from vectorising.)
template <typename R, bool Projection>
inline void smooth_lanes(int64_t lanes, const R (*g)[kLanes], const R (*r)[kLanes],
                         R (*moments)[kLanes]) {
    const Backward<R> zero{0, 0, {0, 0, 0, 0}, {0, 0, 0, 0}};
    for (int64_t l = 0; l < lanes; ++l) {
        R now[5] = {moments[0][l], moments[1][l], moments[2][l], moments[3][l], moments[4][l]};
        const TermArgs<R> x = masked_args<R>(
            now[2], now[3], now[4], r[kA1][l], r[kB1][l], r[kC1][l],
            {r[kKa][l], R(0), r[kKc][l], r[kKd][l]}, g[kRp][l], g[kRpv][l], g[kRvv][l],
            r[kSeenP][l], r[kSeenV][l], g[kT][l], r[kEp][l], r[kEv][l]);
        R w[22];
        terms_at(w, Projection, x);
        smoothed(now, recurse(w, zero));
        for (int q = 0; q < 5; ++q) moments[q][l] = now[q];
    }
}

// One step back of axes_smoother._rts_interval: x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k}),
// Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ, C_k = P_k Fᵀ P_{k+1|k}⁻¹ (Eq. (17)): the
// smoothed (ps, vs, [[sa, sb], [sb, sc]]) at k + 1 in, at k out, from the filtered moments at
// k (p, v, a, b, c), the prediction into k + 1 (pp, vp, pa, pb, pc) and its interval dt.
// X: a lane's scalar or a vector of lanes.
// Its gain C = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]] (blocks.inverse, blocks.matmul), from
// the filtered covariance at k and the predicted one at k + 1.
template <typename X>
inline M2<X> rts_gain(X a, X b, X c, X pa, X pb, X pc, X dt) {
    X det = pa * pc - pb * pb;
    X ia = pc / det, ib = -pb / det, ic = pa / det;
    X xa = a + dt * b, xb = b, xc = b + dt * c, xd = c;
    return {xa * ia + xb * ib, xa * ib + xb * ic, xc * ia + xd * ib, xc * ib + xd * ic};
}

template <typename X>
inline void rts_back(X& ps, X& vs, X& sa, X& sb, X& sc, X p, X v, X a, X b, X c, X pp, X vp,
                     X pa, X pb, X pc, X dt) {
    const M2<X> C = rts_gain(a, b, c, pa, pb, pc, dt);
    const X ca = C.a, cb = C.b, cc = C.c, cd = C.d;
    X dp = ps - pp, dv = vs - vp;
    ps = p + (ca * dp + cb * dv);
    vs = v + (cc * dp + cd * dv);
    // blocks.sandwich(C, Pˢ − Pp): C D Cᵀ, symmetrised.
    X da = sa - pa, db = sb - pb, dd = sc - pc;
    X ma = ca * da + cb * db, mb = ca * db + cb * dd;
    X mc = cc * da + cd * db, md = cc * db + cd * dd;
    X ea = ma * ca + mb * cb, eb = ma * cc + mb * cd;
    X ec = mc * ca + md * cb, ed = mc * cc + md * cd;
    sa = a + ea;
    sb = b + splat<X>(0.5) * (eb + ec);
    sc = c + ed;
}

// axes_smoother._rts_interval over the filter's written record (rts_back at each step).
// Inputs (11): p, v, a, b, c (filtered), p_pred, v_pred, a1, b1, c1 (predicted), T.
// Outputs: the smoothed mean [B, T, 2m] and covariance [B, T, 2m, 2m] in the general layout.
template <typename R>
void rts_interval(int64_t B, int64_t T, int64_t m, int threads, const void* const* in,
                  const int64_t* in_strides, R* mean_out, R* cov_out) {
    View<R> P = view<R>(in, in_strides, 0), V = view<R>(in, in_strides, 1),
            A = view<R>(in, in_strides, 2), Bc = view<R>(in, in_strides, 3),
            Cc = view<R>(in, in_strides, 4), Pp = view<R>(in, in_strides, 5),
            Vp = view<R>(in, in_strides, 6), A1 = view<R>(in, in_strides, 7),
            B1 = view<R>(in, in_strides, 8), C1 = view<R>(in, in_strides, 9),
            Ts = view<R>(in, in_strides, 10);
    const int64_t n = 2 * m;
    auto write = [&](int64_t bi, int64_t k, int64_t j, R ps, R vs, R sa, R sb, R sc) {
        int64_t idx = bi * T + k;
        write_axis(mean_out + idx * n, cov_out + idx * n * n, n, j, ps, vs, sa, sb, sc);
    };
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        for (int64_t bi = first; bi < last; ++bi) {
            for (int64_t j = 0; j < m; ++j) {
                R ps = P.at(bi, T - 1, j), vs = V.at(bi, T - 1, j);
                R sa = A.at(bi, T - 1, j), sb = Bc.at(bi, T - 1, j), sc = Cc.at(bi, T - 1, j);
                write(bi, T - 1, j, ps, vs, sa, sb, sc);
                for (int64_t k = T - 2; k >= 0; --k) {
                    rts_back(ps, vs, sa, sb, sc, P.at(bi, k, j), V.at(bi, k, j), A.at(bi, k, j),
                             Bc.at(bi, k, j), Cc.at(bi, k, j), Pp.at(bi, k + 1, j),
                             Vp.at(bi, k + 1, j), A1.at(bi, k + 1, j), B1.at(bi, k + 1, j),
                             C1.at(bi, k + 1, j), Ts.at(bi, k + 1, j));
                    write(bi, k, j, ps, vs, sa, sb, sc);
                }
            }
        }
    });
}

// How many sweeps of `lane_recursion` a run of n steps with a successor takes: one from the
// end (fixed interval, lag ≥ n) or `lag` from zero.
inline int64_t sweeps_of(int64_t n, int64_t lag) { return lag >= n ? 1 : lag; }

// The backward recursion of a lane over its terms (n indices), every state kept (the reverse
// mode reads them): `states` holds (sweeps_of(n, lag) + 1) rows of n + 1, all zero to begin
// with. Fixed interval (lag ≥ n): row 0, from zero at the end, states[k] = recurse(k,
// states[k + 1]). Fixed lag: row s (s = 1..lag) applies one step to row s − 1 at every
// index, states[s][k] = recurse(k, states[s − 1][k + 1]): after `lag` rows, the sum of `lag`
// terms from zero at k + lag. Returns the results' row; its entry at n stays zero.
template <typename R>
inline const Backward<R>* lane_recursion(const R* terms, int64_t n, int64_t lag,
                                         std::vector<Backward<R>>& states) {
    if (lag >= n) {
        for (int64_t k = n - 1; k >= 0; --k) states[k] = recurse(&terms[22 * k], states[k + 1]);
        return states.data();
    }
    for (int64_t s = 1; s <= lag; ++s)
        for (int64_t k = 0; k < n; ++k)
            states[s * (n + 1) + k] = recurse(&terms[22 * k], states[(s - 1) * (n + 1) + k + 1]);
    return &states[lag * (n + 1)];
}

// Whether a position is at step t or after it (`later[t]` > 0), t = 0..n, from the observed
// position flags `at(13, t)`: the steps after a track's last position learn nothing.
template <typename R, typename At>
inline void positions_ahead(const At& at, int64_t n, std::vector<R>& later) {
    later.resize(n + 1);
    later[n] = at(13, n);
    for (int64_t t = n - 1; t >= 0; --t)
        later[t] = at(13, t) > later[t + 1] ? at(13, t) : later[t + 1];
}

// A lane's terms (written to `terms`, n indices) and recursion (in `states`, see
// lane_recursion), from its 20 inputs `at(i, step)`; returns the results' row.
template <typename R, typename At>
inline const Backward<R>* lane_backward(const At& at, int64_t n, int64_t lag, bool projection,
                                        std::vector<R>& terms, std::vector<Backward<R>>& states) {
    for (int64_t k = 0; k < n; ++k) terms_at(&terms[22 * k], projection, term_args<R>(at, k));
    // C_k is 0 where no position follows step k (a padded batch's shorter tracks): the terms
    // from there on are 0, and C_k multiplies only them; but a covariance predicted over many
    // empty steps can lose its definiteness to rounding (an SVSF's, near rank 1, at a tiny q)
    // and make C_k NaN, which NaN * 0 carried into every estimate of the track.
    static thread_local std::vector<R> later;
    positions_ahead(at, n, later);
    const R zero{};
    for (int64_t k = 0; k < n; ++k)
        for (int i = 0; i < 4; ++i)
            terms[22 * k + i] = later[k + 1] > zero ? terms[22 * k + i] : zero;
    return lane_recursion(terms.data(), n, lag, states);
}

// axes_smoother.smooth_axes: the backward recursion from zero at the end (fixed interval) or, with a
// lag L < T-1, L applications from zero at step k+L for each k (the fixed-lag form), then
// axes_smoother._smoothed: x̂ˢ_k = x̂_k + g_k, Pˢ_k = P_k − P_k G_kᵀ − G_k P_k + Z_k (symmetrised; the
// last step as filtered).
// Inputs (20, [B, T, m]): the filter's cov a, b, c; pred_cov a, b, c; gain a, b, c, d;
// noise (unmasked) pp, pv, vv; observed p, v (0/1); T; innovation p, v; mean p, v.
// Outputs: the smoothed mean [B, T, 2m] and covariance [B, T, 2m, 2m] in the general layout.
template <typename R>
void backward(int64_t B, int64_t T, int64_t m, int64_t lag, int projection, int threads,
              const void* const* in, const int64_t* in_strides, R* mean_out, R* cov_out) {
    using V = typename Wide<R>::type;
    View<R> v[20];
    for (int i = 0; i < 20; ++i) v[i] = view<R>(in, in_strides, i);
    const int64_t n = T - 1;  // steps with a successor
    const int64_t width = 2 * m;
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        // A block of lanes' terms, step by step (contiguous for the sweeps), and its states.
        std::vector<V> terms(22 * (n > 0 ? n : 1));
        std::vector<Backward<V>> states((sweeps_of(n, lag) + 1) * (n + 1), Backward<V>{});
        for (int64_t l = first * m; l < last * m; l += LaneBlock<R>::kWidth) {
            const LaneBlock<R> lanes(l, last * m, m);
            auto at = [&](int i, int64_t t) { return lanes.at(v[i], t); };
            const Backward<V>* result =
                lane_backward<V>(at, n, lag, projection != 0, terms, states);
            for (int64_t k = 0; k <= n; ++k) {
                V now[5] = {at(18, k), at(19, k), at(0, k), at(1, k), at(2, k)};
                if (k < n) smoothed(now, result[k]);  // the last step as filtered
                for (int w = 0; w < lanes.count; ++w) {
                    const int64_t idx = lanes.b[w] * T + k;
                    write_axis(mean_out + idx * width, cov_out + idx * width * width, width,
                               lanes.j[w], now[0][w], now[1][w], now[2][w], now[3][w], now[4][w]);
                }
            }
        }
    });
}

}  // namespace

// Hand-written reverse modes of the per-axis loops, for training (part of fused.cpp): of the
// smoother's general recursion (backward_adjoint; torchsvs/kernels/axes_smoother.py's
// _CompiledSmoother) and of the forward loop (adjoint; torchsvs/kernels/axes.py's
// _CompiledAxes). Their references are torch's autograd through the tensor loops:
// tests/test_kernels.py compares the gradients to 1e-10 in float64 and runs gradcheck.
#pragma once

#include "axis_filter.h"

namespace {

// Reverse mode of `backward`, for training (torchsvs.kernels.axes._CompiledSmoother): each
// lane recomputes its terms and recursion, then runs their adjoints backwards (every matrix
// product, inverse and transpose reversed: for Y = A B, dA = dY Bᵀ and dB = Aᵀ dY; for
// Y = A⁻¹, dA = −Yᵀ dY Yᵀ).

// The adjoint of inverse(a, b, d) = Y given dY, added to a symmetric block's (a, b, d) (b
// stands for both off-diagonal entries).
template <typename R>
inline void inverse_adjoint(const M2<R>& Y, const M2<R>& dY, R& da, R& db, R& dd) {
    M2<R> E = neg(mul(mul(tr(Y), dY), tr(Y)));
    da += E.a, db += E.b + E.c, dd += E.d;
}

// The adjoint of a symmetric block [[a, b], [b, c]] built from (a, b, c).
template <typename R>
inline void symmetric_adjoint(const M2<R>& dX, R& da, R& db, R& dc) {
    da += dX.a, db += dX.b + dX.c, dc += dX.d;
}

// terms_at's adjoint: from dw (the adjoints of its 22 values) those of its inputs, as a
// TermArgs of adjoints (dR: of the masked noise).
template <typename R>
inline TermArgs<R> terms_adjoint(const R* dw, bool projection, const TermArgs<R>& x) {
    const Terms<R> t = terms(projection, x);
    TermArgs<R> d{};
    M2<R> dC{dw[0], dw[1], dw[2], dw[3]}, dGHF{dw[6], dw[7], dw[8], dw[9]};
    M2<R> dGSG{dw[10], dw[11], dw[12], dw[13]}, dGX{dw[14], dw[15], dw[16], dw[17]};
    M2<R> dAF{dw[18], dw[19], dw[20], dw[21]};
    const R dd0 = dw[4], dd1 = dw[5];
    // AF = A F
    M2<R> dA = mul(dAF, tr(t.F)), dF = mul(tr(t.A), dAF);
    // ΓX = Γ X
    M2<R> dGamma = mul(dGX, tr(t.X)), dX = mul(tr(t.Gamma), dGX);
    // ΓSΓᵀ
    dGamma = plus(dGamma, plus(mul(mul(dGSG, t.Gamma), tr(t.S)), mul(mul(tr(dGSG), t.Gamma), t.S)));
    M2<R> dS = mul(mul(tr(t.Gamma), dGSG), t.Gamma);
    // ΓHF = Γ (H F)
    dGamma = plus(dGamma, mul(dGHF, tr(t.HF)));
    dF = plus(dF, mul(tr(t.H), mul(tr(t.Gamma), dGHF)));
    // d = Γ e
    dGamma.a += dd0 * x.ep, dGamma.b += dd0 * x.ev, dGamma.c += dd1 * x.ep, dGamma.d += dd1 * x.ev;
    d.ep = t.Gamma.a * dd0 + t.Gamma.c * dd1, d.ev = t.Gamma.b * dd0 + t.Gamma.d * dd1;
    // C = (Pp⁻¹ F P)ᵀ
    M2<R> dM = tr(dC);
    M2<R> dFP = mul(tr(t.Ppinv), dM);
    dF = plus(dF, mul(dFP, tr(t.P)));
    M2<R> dP = mul(tr(t.F), dFP);
    inverse_adjoint(t.Ppinv, mul(dM, tr(t.FP)), d.a1, d.b1, d.c1);
    // X = PHtᵀ Aᵀ − R Kᵀ
    M2<R> dPHt = mul(tr(t.A), tr(dX));
    dA = plus(dA, mul(tr(dX), tr(t.PHt)));
    M2<R> dR = neg(mul(dX, x.K));
    d.K = plus(neg(mul(tr(dX), t.R_)), neg(dA));  // and A = I − K
    if (projection) {  // Γ = PHt S⁻¹
        dPHt = plus(dPHt, mul(dGamma, tr(t.Sinv)));
        inverse_adjoint(t.Sinv, mul(tr(t.PHt), dGamma), dS.a, dS.b, dS.d);
    } else {
        d.K = plus(d.K, dGamma);
    }
    // S = H PHt + R, PHt = Pp H
    dPHt = plus(dPHt, mul(tr(t.H), dS));
    dR = plus(dR, dS);
    M2<R> dPp = mul(dPHt, tr(t.H));
    symmetric_adjoint(dP, d.a, d.b, d.c);
    symmetric_adjoint(dPp, d.a1, d.b1, d.c1);
    symmetric_adjoint(dR, d.rp, d.rpv, d.rvv);
    d.dt = dF.b;
    return d;
}

// recurse's adjoint: from the adjoint of its result (dout) adds those of its terms to dw and
// of its input state s to ds.
template <typename R>
inline void recurse_adjoint(const R* w, const Backward<R>& s, const Backward<R>& dout, R* dw,
                            Backward<R>& ds) {
    M2<R> C{w[0], w[1], w[2], w[3]}, GHF{w[6], w[7], w[8], w[9]};
    M2<R> GSG{w[10], w[11], w[12], w[13]}, GX{w[14], w[15], w[16], w[17]};
    M2<R> AF{w[18], w[19], w[20], w[21]};
    M2<R> cross = mul(GX, tr(s.G));
    R d0 = w[4] + s.g0, d1 = w[5] + s.g1;
    M2<R> U = plus(GHF, mul(s.G, AF));
    M2<R> inner = plus(plus(plus(GSG, cross), tr(cross)), s.Z);
    // g = C (d + g)
    M2<R> dC{dout.g0 * d0, dout.g0 * d1, dout.g1 * d0, dout.g1 * d1};
    R dd0 = C.a * dout.g0 + C.c * dout.g1, dd1 = C.b * dout.g0 + C.d * dout.g1;
    dw[4] += dd0, dw[5] += dd1, ds.g0 += dd0, ds.g1 += dd1;
    // G = C (ΓHF + G AF)
    dC = plus(dC, mul(dout.G, tr(U)));
    M2<R> dU = mul(tr(C), dout.G);
    ds.G = plus(ds.G, mul(dU, tr(AF)));
    M2<R> dAF = mul(tr(s.G), dU);
    // Z = C inner Cᵀ, inner = ΓSΓᵀ + X + Xᵀ + Z with X = ΓX Gᵀ
    dC = plus(dC, plus(mul(mul(dout.Z, C), tr(inner)), mul(mul(tr(dout.Z), C), inner)));
    M2<R> dinner = mul(mul(tr(C), dout.Z), C);
    ds.Z = plus(ds.Z, dinner);
    M2<R> dcross = plus(dinner, tr(dinner));
    M2<R> dGX = mul(dcross, s.G);
    ds.G = plus(ds.G, mul(tr(dcross), GX));
    const M2<R>* blocks[5] = {&dC, &dU, &dinner, &dGX, &dAF};  // dΓHF = dU, dΓSΓᵀ = dinner
    const int offsets[5] = {0, 6, 10, 14, 18};
    for (int i = 0; i < 5; ++i) {
        R* o = dw + offsets[i];
        o[0] += blocks[i]->a, o[1] += blocks[i]->b, o[2] += blocks[i]->c, o[3] += blocks[i]->d;
    }
}

// The buffers of a vector of lanes' smoother pass and its reverse mode (n indices, `lag` as
// backward takes it), reused from vector to vector.
template <typename V>
struct SmootherBuffers {
    std::vector<V> terms, dterms, acc;
    std::vector<Backward<V>> states, dres, dprev;
    SmootherBuffers(int64_t T, int64_t lag)
        : terms(22 * std::max<int64_t>(T - 1, 1)),
          dterms(terms.size()),
          acc(20 * T),
          states((sweeps_of(T - 1, lag) + 1) * T, Backward<V>{}),
          dres(T, Backward<V>{}),
          dprev(T, Backward<V>{}) {}
};

// backward's reverse mode for a vector of lanes: from their 20 inputs `at(i, step)` and the
// gradients of the smoothed mean and covariance (general layout, [B, T, 2m] and
// [B, T, 2m, 2m]; null: zero), the inputs' adjoints in `buffers.acc` (input by input over the
// steps, acc[i * T + t]; the masked noise's onto the unmasked, none for the masks).
template <typename R, typename At>
void lane_backward_adjoint(const LaneBlock<R>& lanes, const At& at, int64_t T, int64_t m,
                           int64_t lag, bool projection, const R* g_mean, const R* g_cov,
                           SmootherBuffers<typename Wide<R>::type>& buffers) {
    using V = typename Wide<R>::type;
    const Backward<V> zero{};
    const int64_t n = T - 1, width = 2 * m;
    auto& [terms, dterms, acc, states, dres, dprev] = buffers;
    const Backward<V>* result = lane_backward<V>(at, n, lag, projection, terms, states);
    auto add = [&acc, T](int input, int64_t step, V value) { acc[input * T + step] += value; };
    std::fill(acc.begin(), acc.end(), V{});
    std::fill(dterms.begin(), dterms.end(), V{});
    // The smoothed moments' adjoints (axes_smoother._smoothed).
    for (int64_t k = 0; k <= n; ++k) {
        V dps{}, dvs{}, dsa{}, dsb{}, dsc{};
        for (int w = 0; w < lanes.kWidth; ++w) {  // the lanes' output gradients
            const int64_t idx = lanes.b[w] * T + k;
            const int64_t p = 2 * lanes.j[w], q = p + 1;
            if (g_mean) dps[w] = g_mean[idx * width + p], dvs[w] = g_mean[idx * width + q];
            if (!g_cov) continue;
            const R* gc = g_cov + idx * width * width;
            dsa[w] = gc[p * width + p], dsc[w] = gc[q * width + q];
            dsb[w] = gc[p * width + q] + gc[q * width + p];
        }
        add(18, k, dps), add(19, k, dvs);
        if (k == n) {  // as filtered
            add(0, k, dsa), add(1, k, dsb), add(2, k, dsc);
            continue;
        }
        const Backward<V>& s = result[k];
        M2<V> P{at(0, k), at(1, k), at(1, k), at(2, k)};
        M2<V> dY{dsa, R(0.5) * dsb, R(0.5) * dsb, dsc};
        // Y = P − P Gᵀ − G P + Z
        M2<V> dPGt = neg(plus(dY, tr(dY)));
        M2<V> dP = plus(dY, mul(dPGt, s.G));
        Backward<V>& dr = dres[k];
        dr = zero;
        dr.g0 = dps, dr.g1 = dvs;
        dr.G = mul(tr(dPGt), P);
        dr.Z = dY;
        V da{}, db{}, dc{};
        symmetric_adjoint(dP, da, db, dc);
        add(0, k, da), add(1, k, db), add(2, k, dc);
    }
    dres[n] = zero;
    // The recursion's adjoint, in lane_recursion's layout of states.
    if (lag >= n) {
        for (int64_t k = 0; k < n; ++k)  // dres[k] is complete once k − 1 is done
            recurse_adjoint(&terms[22 * k], states[k + 1], dres[k], &dterms[22 * k], dres[k + 1]);
    } else {
        for (int64_t s = lag; s >= 1; --s) {
            std::fill(dprev.begin(), dprev.end(), zero);
            for (int64_t k = 0; k < n; ++k)
                recurse_adjoint(&terms[22 * k], states[(s - 1) * (n + 1) + k + 1], dres[k],
                                &dterms[22 * k], dprev[k + 1]);
            std::swap(dres, dprev);
        }
    }
    // The terms' adjoints, onto the inputs (the masked noise's onto the unmasked); none where
    // no position follows step k (lane_backward's C_k = 0: the terms there are 0 whatever the
    // inputs, whose intermediates may not be finite).
    std::vector<V> later;
    positions_ahead(at, n, later);
    for (int64_t k = 0; k < n; ++k) {
        const int64_t t = k + 1;
        const TermArgs<V> x = term_args<V>(at, k);
        TermArgs<V> d = terms_adjoint(&dterms[22 * k], projection, x);
        const V none{};
        const auto follows = later[k + 1] > none;
        for (V* f : {&d.a, &d.b, &d.c, &d.a1, &d.b1, &d.c1, &d.K.a, &d.K.b, &d.K.c, &d.K.d,
                     &d.rp, &d.rpv, &d.rvv, &d.dt, &d.ep, &d.ev})
            *f = follows ? *f : none;
        add(0, k, d.a), add(1, k, d.b), add(2, k, d.c);
        add(3, t, d.a1), add(4, t, d.b1), add(5, t, d.c1);
        add(6, t, d.K.a), add(7, t, d.K.b), add(8, t, d.K.c), add(9, t, d.K.d);
        add(10, t, d.rp * x.fp), add(11, t, d.rpv * x.fp * x.fv);
        add(12, t, d.rvv * x.fv);
        add(15, t, d.dt), add(16, t, d.ep), add(17, t, d.ev);
    }
}

// backward's gradients: given those of its outputs (mean [B, T, 2m], cov [B, T, 2m, 2m];
// null: zero), writes those of its 20 inputs (contiguous [B, T, m]; null: not wanted; the
// observed masks get none).
template <typename R>
void backward_adjoint(int64_t B, int64_t T, int64_t m, int64_t lag, int projection,
                      int threads, const void* const* in, const int64_t* in_strides,
                      const R* g_mean, const R* g_cov, R* const* dgiven) {
    using V = typename Wide<R>::type;
    View<R> v[20];
    for (int i = 0; i < 20; ++i) v[i] = view<R>(in, in_strides, i);
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        SmootherBuffers<V> buffers(T, lag);
        for (int64_t l = first * m; l < last * m; l += LaneBlock<R>::kWidth) {
            const LaneBlock<R> lanes(l, last * m, m);
            auto at = [&](int i, int64_t t) { return lanes.at(v[i], t); };
            lane_backward_adjoint(lanes, at, T, m, lag, projection != 0, g_mean, g_cov, buffers);
            for (int i = 0; i < 20; ++i)
                if (dgiven[i])
                    for (int w = 0; w < lanes.count; ++w)
                        for (int64_t t = 0; t < T; ++t)
                            dgiven[i][(lanes.b[w] * T + t) * m + lanes.j[w]] =
                                buffers.acc[i * T + t][w];
        }
    });
}

// Reverse mode of the forward loop, for training (torchsvs.kernels.axes._CompiledAxes).

// Adjoints of what a step records besides the state (from the outputs' gradients).
template <typename X>
struct Recorded {
    X p_pred, v_pred, a1, b1, c1, ep, ev, kp, kc, kv, Sp, Spv, Sv, ll;
};

// gain_ratio's adjoint: adds dk's contributions to those of e, the memory, ψ and γ.
template <typename X>
inline void gain_ratio_adjoint(X e, X memory, X width, X gamma, X dk, X& de, X& dmemory,
                               X& dwidth, X& dgamma) {
    const X zero{};
    X magnitude = magnitude_of(e), held = magnitude_of(memory);
    const auto saturated = magnitude > width;
    X den = saturated ? magnitude : width, num = magnitude + gamma * held;
    X sign_e = sign_of(e), sign_m = sign_of(memory);
    X over = num / (den * den);
    de += dk * (sign_e / den - (saturated ? over * sign_e : zero));
    dmemory += dk * gamma * sign_m / den;
    dwidth += saturated ? zero : -dk * over;
    dgamma += dk * held / den;
}

// predict_correct's adjoint: from the adjoints of the state after the step (dn) and of its
// records (o), those of the state before (returned), of the step's inputs (dg, Given's
// order, overwritten) and of γ (added to dgamma). Branch-free, as predict_correct. Rule 2:
// `share` maps each lane's part of dλ to the adjoint of what it wanted (track_inflation_adjoint
// over the lanes' vector), the other rules never call it.
template <typename X, int Rule, typename Share>
inline State<X> step_adjoint(const State<X>& x, const X* g, X gamma, const Step<X>& s,
                             const State<X>& dn, const Recorded<X>& o, X* dg, X& dgamma,
                             const Share& share) {
    const X zero{};
    const X dt = g[kT];
    const auto seen_p = s.fp > zero, seen_v = s.fv > zero;
    State<X> d{zero, zero, zero, zero, zero, zero, zero};
    X drp = zero, drpv = zero, drvv = zero, dyp = zero, dyv = zero;
    X da1 = o.a1, db1 = o.b1, dc1 = o.c1, dep = o.ep, dev = o.ev;
    X dpp = o.p_pred, dvp = o.v_pred, dkp = o.kp, dkc = o.kc, dkv = o.kv, dSp = o.Sp;
    for (int q = 0; q < kGiven; ++q) dg[q] = zero;
    if (Rule != 1) {
        const X kp = s.kp, kvp = s.kc, one_k = 1 - kp;
        X dp = dn.p;
        d.mem_p = dn.mem_p, d.mem_v = dn.mem_v;
        if (Rule == 2) {  // mem' = y − p' where observed, else mem
            const X held = seen_p ? dn.mem_p : zero;
            dyp += held, dp -= held, d.mem_p -= held;
        }
        // p' = p_pred + kp ep, v' = v_pred + kvp ep
        dpp += dp, dvp += dn.v;
        dkp += dp * s.ep, dkc += dn.v * s.ep, dep += dp * kp + dn.v * kvp;
        // c' = c1 − 2 kvp b1 + kvp² (a1 + rp)
        dc1 += dn.c, db1 -= 2 * kvp * dn.c, da1 += kvp * kvp * dn.c, drp += kvp * kvp * dn.c;
        dkc += dn.c * (2 * kvp * (s.a1 + s.rp) - 2 * s.b1);
        // b' = (1 − kp)(b1 − kvp a1) + kp kvp rp
        X done = dn.b * (s.b1 - kvp * s.a1);
        db1 += one_k * dn.b, da1 -= one_k * kvp * dn.b;
        dkc += dn.b * (kp * s.rp - one_k * s.a1), dkp += dn.b * kvp * s.rp;
        drp += dn.b * kp * kvp;
        // a' = (1 − kp)² a1 + kp² rp
        done += 2 * one_k * s.a1 * dn.a, da1 += one_k * one_k * dn.a;
        dkp += 2 * kp * s.rp * dn.a, drp += kp * kp * dn.a;
        dkp -= done;
        // kp = a1 fp / Sp, kvp = b1 fp / Sp
        da1 += s.fp / s.Sp * dkp, db1 += s.fp / s.Sp * dkc;
        dSp -= (s.a1 * dkp + s.b1 * dkc) * s.fp / (s.Sp * s.Sp);
        // ll = −(ep²/Sp + log Sp)/2 + const
        dep -= o.ll * s.ep / s.Sp;
        dSp += splat<X>(0.5) * o.ll * (s.ep * s.ep / (s.Sp * s.Sp) - 1 / s.Sp);
    } else {
        const X kp = s.kp, kv = s.kv, one_p = 1 - kp, one_v = 1 - kv;
        X dp = dn.p, dv = dn.v;
        // mem' = y − x' where observed, else mem
        const X held_p = seen_p ? dn.mem_p : zero, held_v = seen_v ? dn.mem_v : zero;
        dyp += held_p, dp -= held_p, d.mem_p += dn.mem_p - held_p;
        dyv += held_v, dv -= held_v, d.mem_v += dn.mem_v - held_v;
        // p' = p_pred + kp ep, v' = v_pred + kv ev
        dpp += dp, dkp += dp * s.ep, dep += dp * kp;
        dvp += dv, dkv += dv * s.ev, dev += dv * kv;
        // c' = (1 − kv)² c1 + kv² rvv
        X done_v = 2 * one_v * s.c1 * dn.c;
        dc1 += one_v * one_v * dn.c, dkv += 2 * kv * s.rvv * dn.c, drvv += kv * kv * dn.c;
        // b' = (1 − kp)(1 − kv) b1 + kp kv rpv
        X done_p = one_v * s.b1 * dn.b;
        done_v += one_p * s.b1 * dn.b, db1 += one_p * one_v * dn.b;
        dkp += kv * s.rpv * dn.b, dkv += kp * s.rpv * dn.b, drpv += kp * kv * dn.b;
        // a' = (1 − kp)² a1 + kp² rp
        done_p += 2 * one_p * s.a1 * dn.a, da1 += one_p * one_p * dn.a;
        dkp += 2 * kp * s.rp * dn.a, drp += kp * kp * dn.a;
        dkp -= done_p, dkv -= done_v;
        // k = gain_ratio(e, mem, ψ, γ) where observed (else 0), Eq. (23)
        gain_ratio_adjoint(s.ep, x.mem_p, g[kWp], gamma, seen_p ? dkp : zero, dep, d.mem_p,
                           dg[kWp], dgamma);
        gain_ratio_adjoint(s.ev, x.mem_v, g[kWv], gamma, seen_v ? dkv : zero, dev, d.mem_v,
                           dg[kWv], dgamma);
        // Spv = b1 fp fv + rpv, Sv = c1 fv + rvv
        db1 += s.fp * s.fv * o.Spv, drpv += o.Spv, dc1 += s.fv * o.Sv, drvv += o.Sv;
        // ev = yv − v_pred where observed
        const X seen_dev = seen_v ? dev : zero;
        dyv += seen_dev, dvp -= seen_dev;
    }
    // Sp = a1 fp + rp
    da1 += s.fp * dSp, drp += dSp;
    if (Rule == 2) {  // (a1, b1, c1) = λ (a1r, b1r, c1r), λ the track's (track_inflation)
        const X dwanted = share(s.a1r * da1 + s.b1r * db1 + s.c1r * dc1);
        da1 = s.inflation * da1, db1 = s.inflation * db1, dc1 = s.inflation * dc1;
        wanted_inflation_adjoint(x, g, gamma, s, dwanted, da1, dep, drp, d.mem_p, dg[kWp],
                                 dgamma);
    }
    // ep = yp − p_pred where observed
    const X seen_dep = seen_p ? dep : zero;
    dyp += seen_dep, dpp -= seen_dep;
    // The masked noise: the inputs count where observed only.
    dg[kRp] = seen_p ? drp : zero;
    dg[kRpv] = (seen_p & seen_v) ? drpv : zero;
    dg[kRvv] = seen_v ? drvv : zero;
    dg[kYp] = dyp, dg[kYv] = dyv;
    // c1 = c + Qc, b1 = bT + Qb, a1 = a + T (b + bT) + Qa, bT = b + T c
    dg[kQa] = da1, dg[kQb] = db1, dg[kQc] = dc1;
    X dbT = db1 + dt * da1;
    d.a += da1, d.b += dt * da1 + dbT, d.c += dc1 + dt * dbT;
    // p_pred = p + T v, v_pred = v
    d.p += dpp, d.v += dt * dpp + dvp;
    dg[kT] = (x.b + s.bT) * da1 + x.c * dbT + x.v * dpp;
    return d;
}

// smooth_lanes' adjoint at k = t − 1 for a lane (or a vector of lanes): from the adjoints ds
// of its smoothed moments (p, v, a, b, c; b: both off-diagonal entries' summed), adds those of
// the filtered moments before step t to dx, of step t's records to o, and returns those of its
// masked noise (onto the unmasked inputs) and interval in Given's slots kT, kRp, kRpv, kRvv.
template <typename X>
struct SmoothedInputs {
    X dt, rp, rpv, rvv;
};
template <typename X>
inline SmoothedInputs<X> smooth_adjoint(bool projection, const State<X>& x, const X* g,
                                        const Step<X>& s, const X* ds, State<X>& dx,
                                        Recorded<X>& o) {
    const X zero{};
    const TermArgs<X> args = masked_args<X>(x.a, x.b, x.c, s.a1, s.b1, s.c1,
                                            {s.kp, zero, s.kc, s.kv}, g[kRp], g[kRpv], g[kRvv],
                                            s.fp, s.fv, g[kT], s.ep, s.ev);
    X w[22];
    terms_at(w, projection, args);
    const Backward<X> none{zero, zero, {zero, zero, zero, zero}, {zero, zero, zero, zero}};
    const Backward<X> r = recurse(w, none);
    // x̂ˢ = x̂ + g, Pˢ = P − P Gᵀ − G P + Z, symmetrised (`smoothed`).
    const M2<X> P{x.a, x.b, x.b, x.c};
    const X half = splat<X>(0.5) * ds[3];
    const M2<X> dY{ds[2], half, half, ds[4]};
    const M2<X> dPGt = neg(plus(dY, tr(dY)));
    const M2<X> dP = plus(dY, mul(dPGt, r.G));
    const Backward<X> dr{ds[0], ds[1], mul(tr(dPGt), P), dY};
    dx.p += ds[0], dx.v += ds[1];
    symmetric_adjoint(dP, dx.a, dx.b, dx.c);
    X dw[22];
    for (X& v : dw) v = zero;
    Backward<X> dnone = none;
    recurse_adjoint(w, none, dr, dw, dnone);
    const TermArgs<X> d = terms_adjoint(dw, projection, args);
    dx.a += d.a, dx.b += d.b, dx.c += d.c;
    o.a1 += d.a1, o.b1 += d.b1, o.c1 += d.c1;
    o.kp += d.K.a, o.kc += d.K.c, o.kv += d.K.d;  // K.b is 0, not a record
    o.ep += d.ep, o.ev += d.ev;
    return {d.dt, d.rp * s.fp, d.rpv * s.fp * s.fv, d.rvv * s.fv};
}

// The forward loop's gradients. `grads`: the gradients of forward's outputs (null: zero) in
// Layout's order: mean, cov, pred_mean, pred_cov, innovation, gain, S, post, loglik, then the
// state after the last step (mean [B, n], cov [B, n, n], post [B, m_z]) and the smoothed mean
// and cov (with `smoothing`: 1 RTS, 2 SVSS; `lag` 0: the one-step-lag smoothing of
// `forward`, else filter_smoother's recursion with that lag, as `backward` takes it). Writes
// the inputs' gradients: `dgiven` 11 contiguous [B, T, m] arrays, or [B, 1, m] summed over the steps for
// an input constant in time (null: not wanted), `dprior` 5 [B, m] (p, v, a, b, c), and
// `dgamma` [B, m] (per lane, summed by the caller).
//
// Vectors of W lanes (Wide) go back in time together, G of them side by side (independent
// chains keep the processor busy): each recomputes its forward states, then runs the adjoint
// of predict_correct (and of smooth_lanes) backwards in time, every assignment reversed. The
// derivatives follow torch's conventions where the step is not smooth (d|x|/dx = 0 at 0;
// max(|e|, ψ) differentiates in |e| only when |e| > ψ). The block's recomputed states stay in
// a core's L2 (half a MiB): long tracks take fewer vectors at a time.
template <typename R, int Rule>
void adjoint(int64_t B, int64_t T, int64_t m, int velocity, R gamma, int smoothing, int64_t lag,
             int threads, const void* const* in, const int64_t* in_strides,
             const void* const* prior, const int64_t* prior_strides, const R* const* grads,
             R* const* dgiven, R* const* dprior, R* dgamma) {
    using V = typename Wide<R>::type;
    using Lanes = LaneBlock<R>;
    constexpr int W = Lanes::kWidth;
    View<R> given[kGiven], start[5];
    for (int q = 0; q < kGiven; ++q) given[q] = view<R>(in, in_strides, q);
    for (int q = 0; q < 5; ++q) start[q] = view<R>(prior, prior_strides, q);
    const int64_t n = 2 * m, mz = velocity ? n : m;
    const R *g_mean = grads[0], *g_cov = grads[1], *g_pm = grads[2], *g_pc = grads[3];
    const R *g_e = grads[4], *g_K = grads[5], *g_S = grads[6], *g_post = grads[7];
    const R *g_ll = grads[8], *g_last_mean = grads[9], *g_last_cov = grads[10];
    const R *g_last_post = grads[11], *g_smooth_mean = grads[12], *g_smooth_cov = grads[13];
    const bool projection = smoothing == 2, general = smoothing && lag > 0;
    const bool in_loop = smoothing && !general;  // the one-step-lag smoothing of `forward`
    const V gam = splat<V>(gamma);
    const int64_t fits = (int64_t(1) << 19) / ((T + 1) * int64_t(sizeof(State<V>)));
    const int64_t per = lanes_per_vector<R>(m, Rule == 2);
    // Rule 2's λ of a vector's tracks (track_inflation) from the state before a step.
    auto inflation_of = [&gam](const Lanes& at, const State<V>& x, const V* g) {
        return Rule == 2 ? track_inflation(at, wanted_inflation<V>(x, g, gam)) : splat<V>(1.0);
    };
    // The general recursion's buffers hold a vector's whole record: one vector at a time.
    const int64_t G =
        general ? 1 : std::max<int64_t>(1, std::min<int64_t>(kAdjointVectors, fits));
    // Per lane: a mean's (p, v) entries, a covariance's (a, b, c) entries (b: both
    // off-diagonal entries summed), the gradients' values at a record.
    auto mean_at = [](const R* grad, int64_t size, int64_t at, int64_t i) {
        return grad ? grad[at * size + i] : R(0);
    };
    auto sym_at = [n](const R* grad, int64_t at, int64_t p, int64_t v, R& a, R& b, R& c) {
        if (!grad) return;
        const R* x = grad + at * n * n;
        a += x[p * n + p], b += x[p * n + v] + x[v * n + p], c += x[v * n + v];
    };
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        const int64_t end = last * m;
        std::vector<State<V>> states((T + 1) * G);  // [t][vector]
        std::vector<Lanes> lanes;
        std::vector<LaneInputs<R>> inputs;
        std::vector<State<V>> dx(G);
        std::vector<V> summed(G * kGiven), dgam(G);
        std::vector<V> rec(general ? 20 * T : 0);
        SmootherBuffers<V> buffers(general ? T : 1, general ? lag : 1);
        const std::vector<V>& acc = buffers.acc;
        for (int64_t l0 = first * m; l0 < end; l0 += G * per) {
            lanes.clear(), inputs.clear();
            for (int64_t l = l0; l < end && l < l0 + G * per; l += per) {
                lanes.emplace_back(l, end, m, per);
                inputs.emplace_back(lanes.back(), given);
            }
            const int64_t count = static_cast<int64_t>(lanes.size());
            const V zero{};
            if (general) {  // the record, and the recursion's adjoints of its entries (acc)
                filter_record<R, Rule>(lanes[0], given, start, T, gam, states.data(), rec.data());
                auto at = [&](int i, int64_t t) { return rec[i * T + t]; };
                lane_backward_adjoint(lanes[0], at, T, m, lag, projection, g_smooth_mean,
                                      g_smooth_cov, buffers);
            } else {  // the states, the vectors side by side
                for (int64_t v = 0; v < count; ++v)
                    states[v] = {lanes[v].at(start[0], 0), lanes[v].at(start[1], 0),
                                 lanes[v].at(start[2], 0), lanes[v].at(start[3], 0),
                                 lanes[v].at(start[4], 0), zero, zero};
                for (int64_t t = 0; t < T; ++t)
                    for (int64_t v = 0; v < count; ++v) {
                        V g[kGiven];
                        inputs[v].at(t, g);
                        const State<V>& x = states[t * G + v];
                        states[(t + 1) * G + v] =
                            predict_correct<V, Rule>(x, g, gam, inflation_of(lanes[v], x, g))
                                .next;
                    }
            }
            // The state after the last step: its own gradient and, smoothing in the loop, that
            // of the last smoothed step (the last filtered one; the recursion's is in acc).
            for (int64_t v = 0; v < count; ++v) {
                State<V>& d = dx[v];
                d = {zero, zero, zero, zero, zero, zero, zero};
                for (int w = 0; w < W; ++w) {
                    const int64_t bi = lanes[v].b[w], j = lanes[v].j[w], p = 2 * j, q = p + 1;
                    const int64_t end_step = bi * T + T - 1;
                    R mp = mean_at(g_last_mean, n, bi, p), mv = mean_at(g_last_mean, n, bi, q);
                    R a = 0, b = 0, c = 0;
                    sym_at(g_last_cov, bi, p, q, a, b, c);
                    if (in_loop) {
                        mp += mean_at(g_smooth_mean, n, end_step, p);
                        mv += mean_at(g_smooth_mean, n, end_step, q);
                        sym_at(g_smooth_cov, end_step, p, q, a, b, c);
                    }
                    d.p[w] = mp, d.v[w] = mv, d.a[w] = a, d.b[w] = b, d.c[w] = c;
                    if (g_last_post) {
                        d.mem_p[w] = g_last_post[bi * mz + (velocity ? p : j)];
                        d.mem_v[w] = velocity ? g_last_post[bi * mz + q] : R(0);
                    }
                }
            }
            std::fill_n(summed.begin(), count * kGiven, zero);
            std::fill_n(dgam.begin(), count, zero);
            for (int64_t t = T - 1; t >= 0; --t)
                for (int64_t v = 0; v < count; ++v) {
                    const Lanes& at = lanes[v];
                    V g[kGiven], dg[kGiven];
                    inputs[v].at(t, g);
                    const State<V>& before = states[t * G + v];
                    const V wanted = Rule == 2 ? wanted_inflation<V>(before, g, gam) : zero;
                    const V inflation = Rule == 2 ? track_inflation(at, wanted) : splat<V>(1.0);
                    const Step<V> s = predict_correct<V, Rule>(before, g, gam, inflation);
                    // The outputs' gradients at this step, read from the general layout.
                    State<V>& d = dx[v];
                    Recorded<V> o{};
                    V ds[5] = {zero, zero, zero, zero, zero};  // smoothed k = t − 1
                    for (int w = 0; w < W; ++w) {
                        const int64_t bi = at.b[w], j = at.j[w], rec = bi * T + t;
                        const int64_t p = 2 * j, q = p + 1;
                        R a = 0, b = 0, c = 0;
                        d.p[w] += mean_at(g_mean, n, rec, p), d.v[w] += mean_at(g_mean, n, rec, q);
                        sym_at(g_cov, rec, p, q, a, b, c);
                        d.a[w] += a, d.b[w] += b, d.c[w] += c;
                        o.p_pred[w] = mean_at(g_pm, n, rec, p);
                        o.v_pred[w] = mean_at(g_pm, n, rec, q);
                        a = b = c = 0;
                        sym_at(g_pc, rec, p, q, a, b, c);
                        o.a1[w] = a, o.b1[w] = b, o.c1[w] = c;
                        o.ll[w] = g_ll ? g_ll[bi] : R(0);
                        if (velocity) {
                            o.ep[w] = mean_at(g_e, mz, rec, p), o.ev[w] = mean_at(g_e, mz, rec, q);
                            if (g_K) {
                                const R* K = g_K + rec * n * n;
                                o.kp[w] = K[p * n + p], o.kc[w] = K[q * n + p];
                                o.kv[w] = K[q * n + q];
                            }
                            if (g_S) {
                                const R* S = g_S + rec * n * n;
                                o.Sp[w] = S[p * n + p], o.Sv[w] = S[q * n + q];
                                o.Spv[w] = S[p * n + q] + S[q * n + p];
                            }
                            d.mem_p[w] += mean_at(g_post, mz, rec, p);
                            d.mem_v[w] += mean_at(g_post, mz, rec, q);
                        } else {
                            o.ep[w] = mean_at(g_e, mz, rec, j);
                            if (g_K) {
                                const R* K = g_K + rec * n * m;
                                o.kp[w] = K[p * m + j], o.kc[w] = K[q * m + j];
                            }
                            o.Sp[w] = g_S ? g_S[rec * m * m + j * m + j] : R(0);
                            d.mem_p[w] += mean_at(g_post, mz, rec, j);
                        }
                        if (in_loop && t > 0) {
                            ds[0][w] = mean_at(g_smooth_mean, n, rec - 1, p);
                            ds[1][w] = mean_at(g_smooth_mean, n, rec - 1, q);
                            a = b = c = 0;
                            sym_at(g_smooth_cov, rec - 1, p, q, a, b, c);
                            ds[2][w] = a, ds[3][w] = b, ds[4][w] = c;
                        }
                    }
                    State<V> dsmooth{zero, zero, zero, zero, zero, zero, zero};
                    SmoothedInputs<V> extra{zero, zero, zero, zero};
                    if (in_loop && t > 0)
                        extra = smooth_adjoint(projection, before, g, s, ds, dsmooth, o);
                    if (general) {  // the record's entries at t, read by the recursion
                        auto entry = [&acc, T, t](int i) { return acc[i * T + t]; };
                        d.a += entry(0), d.b += entry(1), d.c += entry(2);
                        d.p += entry(18), d.v += entry(19);
                        o.a1 += entry(3), o.b1 += entry(4), o.c1 += entry(5);
                        o.kp += entry(6), o.kc += entry(8), o.kv += entry(9);  // K.b is 0
                        o.ep += entry(16), o.ev += entry(17);
                        extra = {entry(15), entry(10), entry(11), entry(12)};  // unmasked noise
                    }
                    auto share = [&at, &wanted](V dlam) {
                        return track_inflation_adjoint(at, wanted, dlam);
                    };
                    d = step_adjoint<V, Rule>(before, g, gam, s, d, o, dg, dgam[v], share);
                    d.p += dsmooth.p, d.v += dsmooth.v;
                    d.a += dsmooth.a, d.b += dsmooth.b, d.c += dsmooth.c;
                    dg[kT] += extra.dt, dg[kRp] += extra.rp;
                    dg[kRpv] += extra.rpv, dg[kRvv] += extra.rvv;
                    // An input constant in time (Q, R of a fixed interval) gets its gradient
                    // summed here, [B, 1, m]: no [B, T, m] buffer to write and sum afterwards.
                    for (int q = 0; q < kGiven; ++q) {
                        if (!dgiven[q]) continue;
                        if (given[q].st == 0) {
                            summed[v * kGiven + q] += dg[q];
                            continue;
                        }
                        for (int w = 0; w < at.count; ++w)
                            dgiven[q][(at.b[w] * T + t) * m + at.j[w]] = dg[q][w];
                    }
                }
            for (int64_t v = 0; v < count; ++v)
                for (int w = 0; w < lanes[v].count; ++w) {
                    const int64_t lane = lanes[v].b[w] * m + lanes[v].j[w];
                    for (int q = 0; q < kGiven; ++q)
                        if (dgiven[q] && given[q].st == 0)
                            dgiven[q][lane] = summed[v * kGiven + q][w];
                    const State<V>& d = dx[v];
                    const V prior_adjoint[5] = {d.p, d.v, d.a, d.b, d.c};
                    for (int q = 0; q < 5; ++q)
                        if (dprior[q]) dprior[q][lane] = prior_adjoint[q][w];
                    dgamma[lane] = dgam[v][w];
                }
        }
    });
}

template <typename R>
void adjoint_entry(int64_t B, int64_t T, int64_t m, int rule, int velocity, double gamma,
                   int smoothing, int64_t lag, int threads, const void* const* in, const int64_t* s,
                   const void* const* prior, const int64_t* ps, void* const* grads,
                   void* const* dgiven, void* const* dprior, void* dgamma) {
    auto g = reinterpret_cast<const R* const*>(grads);
    auto dg = reinterpret_cast<R* const*>(dgiven);
    auto dp = reinterpret_cast<R* const*>(dprior);
    R gm = static_cast<R>(gamma);
    R* dgm = static_cast<R*>(dgamma);
    if (rule == 0)
        adjoint<R, 0>(B, T, m, velocity, gm, smoothing, lag, threads, in, s, prior, ps, g, dg, dp,
                      dgm);
    else if (rule == 1)
        adjoint<R, 1>(B, T, m, velocity, gm, smoothing, lag, threads, in, s, prior, ps, g, dg, dp,
                      dgm);
    else
        adjoint<R, 2>(B, T, m, velocity, gm, smoothing, lag, threads, in, s, prior, ps, g, dg, dp,
                      dgm);
}

}  // namespace

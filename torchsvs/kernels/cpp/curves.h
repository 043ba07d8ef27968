// The nearly-constant-velocity Kalman smoother's SURE curves and positions (part of fused.cpp):
// torchsvs/kernels/curves.py's loop. Per lane (a track's axis), for each of K values of q:
// the Kalman filter, position-only (axis_step.h's predict_correct, Rule 0), then the fixed-
// interval RTS recursion (axis_smoother.h's rts_back; without `smooth`, the filter's moments
// stand), from the lane's prior. What it writes:
//   risk [K, B, m]  Σ over the counted steps of (z − x̂ˢ)² − r + 2 Pˢ_pp: the exact SURE of
//                   the smoother's positions (torchsvs/fitting/noise.py's _sure_of), per lane;
//   mean [B, T, 2m] the means (general layout) and var [B, T, m] the positions' variances,
//                   of the one q (K = 1);
//   first_two [B, m, 2]  with them, the derivative of the position estimate at each axis's
//                   first and second observation by the measurement there, through the
//                   two-point prior too (whose mean moves with both: its tangent by each is
//                   given), NaN where there is no such observation: the divergence that the
//                   position variance over r gives everywhere else (accuracy.exact_divergence).
//                   Each is a tangent run of the means (unit measurement there, the prior's
//                   tangent) with the pass's own gains;
//   sums [B, C, m, 3]  with first_two, SURE's sums over each track's chunks of `chunk` steps
//                   (C of them) of its observed components: (z − x̂)², the divergence (the
//                   position variance over r, the tangents' at the first two observations) and
//                   the count (accuracy.exact_risk_terms' sums, without a pass over [B, T, m]);
//   student [B, T, m]  of the one q, the studentized squared residual (z − x̂ˢ)² / (r (1 − h)),
//                   h = Pˢ_pp / r (floored at 1e-12 below 1), NaN where z is missing or h is
//                   above max_leverage: fitting/outliers.py's outlier_distances per axis, without
//                   writing the means;
//   step_risk [B, T]  with first_two (and K = 1), each step's SURE: its observed components'
//                   (z − x̂)² − r + 2 r ∂x̂/∂z summed (the divergence as the sums'), 0 where none
//                   is observed: what fitting/q_windows.py weighs each pass by, step by step,
//                   without passes of its own over [B, T, m]. A track's axes are lanes of one
//                   thread, its first axis's before the others', so the first writes, the others
//                   add.
// Nothing else is written: a curve of K values costs K passes over registers and the lane's
// own record of T steps, not K full results in memory.
#pragma once

#include "axis_smoother.h"

namespace {

// Inputs, each a [B, T, m] view: 0 z, 1 the interval, 2 the weight of a step in the risk (1
// counted, 0 not), 3-7 the prior p, v, a, b, c (stride 0 in time), 8 r (per axis), 9 q (its
// step stride the factor's); with first_two, 10-13 the prior mean's tangents (p, v) by the
// first and by the second observation (stride 0 in time).
template <typename R>
void kalman_curves(int64_t B, int64_t T, int64_t m, int64_t K, int smooth, int threads,
                   const void* const* in, const int64_t* in_strides, R* risk, R* mean_out,
                   R* var_out, R* first_two, int64_t chunk, R* sums, R* student,
                   double max_leverage, R* step_risk) {
    using V = typename Wide<R>::type;
    constexpr int W = LaneBlock<R>::kWidth;
    View<R> given[14];
    for (int i = 0; i < (first_two ? 14 : 10); ++i) given[i] = view<R>(in, in_strides, i);
    const int64_t n = 2 * m;
    const V zero{}, nan = splat<V>(NAN), two = splat<V>(2), three = splat<V>(3);
    const V one = splat<V>(1), tiny = splat<V>(1e-12), most = splat<V>(max_leverage);
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        std::vector<V> z(T), dt(T), weight(T), rec(10 * std::max<int64_t>(T, 1));
        std::vector<V> tangent(first_two ? 8 * T : 0);  // filtered, predicted (p, v) of each
        for (int64_t l = first * m; l < last * m; l += W) {
            const LaneBlock<R> lanes(l, last * m, m);
            for (int64_t t = 0; t < T; ++t)
                z[t] = lanes.at(given[0], t), dt[t] = lanes.at(given[1], t),
                weight[t] = lanes.at(given[2], t);
            const V r = lanes.at(given[8], 0);
            for (int64_t k = 0; k < K; ++k) {
                const V q = lanes.at(given[9], k);
                State<V> x{lanes.at(given[3], 0), lanes.at(given[4], 0), lanes.at(given[5], 0),
                           lanes.at(given[6], 0), lanes.at(given[7], 0), zero, zero};
                V g[kGiven] = {};
                g[kYv] = nan, g[kRp] = r, g[kRvv] = splat<V>(1), g[kWp] = g[kWv] = splat<V>(1);
                // the tangents (first, second observation), the observations so far and the
                // steps of the first two
                V tp[2] = {}, tv[2] = {}, seen = zero;
                V at_first = splat<V>(-1), at_second = at_first;
                if (first_two)
                    for (int i = 0; i < 2; ++i)
                        tp[i] = lanes.at(given[10 + 2 * i], 0),
                        tv[i] = lanes.at(given[11 + 2 * i], 0);
                for (int64_t t = 0; t < T; ++t) {  // the filter (Rule 0: Kalman)
                    const V d = dt[t];
                    // blocks.process_noise: Q of Eq. (48), Chen et al. 2020
                    g[kT] = d, g[kQa] = q * (d * d * d) / three, g[kQb] = q * (d * d) / two;
                    g[kQc] = q * d, g[kYp] = z[t];
                    const Step<V> s = predict_correct<V, 0>(x, g, zero);
                    x = s.next;
                    V* at = &rec[10 * t];
                    at[0] = x.p, at[1] = x.v, at[2] = x.a, at[3] = x.b, at[4] = x.c;
                    at[5] = s.p_pred, at[6] = s.v_pred, at[7] = s.a1, at[8] = s.b1, at[9] = s.c1;
                    if (!first_two) continue;
                    const auto observed = z[t] == z[t];
                    seen += observed ? splat<V>(1) : zero;
                    const V now = splat<V>(static_cast<double>(t));
                    at_first = (observed & (seen == splat<V>(1))) ? now : at_first;
                    at_second = (observed & (seen == splat<V>(2))) ? now : at_second;
                    V* tan = &tangent[8 * t];
                    for (int i = 0; i < 2; ++i) {
                        const V unit = (i == 0 ? at_first : at_second) == now ? splat<V>(1) : zero;
                        const V pp = tp[i] + d * tv[i], vp = tv[i];
                        const V e = observed ? unit - pp : zero;  // (the gain is 0 where unseen)
                        tp[i] = pp + s.kp * e, tv[i] = vp + s.kc * e;
                        tan[4 * i] = tp[i], tan[4 * i + 1] = tv[i];
                        tan[4 * i + 2] = pp, tan[4 * i + 3] = vp;
                    }
                }
                V found[2] = {nan, nan};  // the tangents at their own observation
                V residual = zero, divergence = zero, count = zero;  // of the chunk so far
                // the smoother, from the last step (as filtered) back
                V ps = x.p, vs = x.v, sa = x.a, sb = x.b, sc = x.c, total = zero;
                for (int64_t t = T - 1; t >= 0; --t) {
                    const V* at = &rec[10 * t];
                    if (!smooth) {
                        ps = at[0], vs = at[1], sa = at[2];
                    } else if (t < T - 1) {
                        const V* next = &rec[10 * (t + 1)];
                        rts_back(ps, vs, sa, sb, sc, at[0], at[1], at[2], at[3], at[4], next[5],
                                 next[6], next[7], next[8], next[9], dt[t + 1]);
                    }
                    const V e = z[t] - ps;
                    total += weight[t] != zero ? e * e - r + two * sa : zero;
                    if (first_two) {
                        const V* tan = &tangent[8 * t];
                        const V now = splat<V>(static_cast<double>(t));
                        for (int i = 0; i < 2; ++i) {
                            if (!smooth) {
                                tp[i] = tan[4 * i], tv[i] = tan[4 * i + 1];
                            } else if (t < T - 1) {
                                const V* next = &rec[10 * (t + 1)];
                                const M2<V> C = rts_gain(at[2], at[3], at[4], next[7], next[8],
                                                         next[9], dt[t + 1]);
                                const V dp = tp[i] - tan[8 + 4 * i + 2];
                                const V dv = tv[i] - tan[8 + 4 * i + 3];
                                tp[i] = tan[4 * i] + (C.a * dp + C.b * dv);
                                tv[i] = tan[4 * i + 1] + (C.c * dp + C.d * dv);
                            } else {
                                tp[i] = tan[4 * i], tv[i] = tan[4 * i + 1];
                            }
                            found[i] = (i == 0 ? at_first : at_second) == now ? tp[i] : found[i];
                        }
                        if (sums || step_risk) {
                            const auto observed = z[t] == z[t];
                            const V own = at_first == now    ? tp[0]
                                          : at_second == now ? tp[1]
                                                             : sa / r;
                            residual += observed ? e * e : zero;
                            divergence += observed ? own : zero;
                            count += observed ? splat<V>(1) : zero;
                            if (step_risk) {
                                const V term = observed ? e * e - r + two * r * own : zero;
                                for (int w = 0; w < lanes.count; ++w) {
                                    R& out = step_risk[lanes.b[w] * T + t];
                                    out = lanes.j[w] == 0 ? term[w] : out + term[w];
                                }
                            }
                        }
                    }
                    if (sums && t % chunk == 0) {  // the chunk's first step: its sums are done
                        const int64_t C = (T + chunk - 1) / chunk;
                        for (int w = 0; w < lanes.count; ++w) {
                            R* out = sums + ((lanes.b[w] * C + t / chunk) * m + lanes.j[w]) * 3;
                            out[0] = residual[w], out[1] = divergence[w], out[2] = count[w];
                        }
                        residual = divergence = count = zero;
                    }
                    if (student) {
                        const V h = sa / r, rest = one - h;
                        const V fit = (e * e) / (r * (rest > tiny ? rest : tiny));
                        const V d2 = h <= most ? fit : nan;  // (NaN: not judged)
                        for (int w = 0; w < lanes.count; ++w)
                            student[(lanes.b[w] * T + t) * m + lanes.j[w]] = d2[w];
                    }
                    if (!mean_out) continue;
                    for (int w = 0; w < lanes.count; ++w) {
                        const int64_t idx = lanes.b[w] * T + t, j = lanes.j[w];
                        mean_out[idx * n + 2 * j] = ps[w], mean_out[idx * n + 2 * j + 1] = vs[w];
                        if (var_out) var_out[idx * m + j] = sa[w];
                    }
                }
                if (first_two)
                    for (int w = 0; w < lanes.count; ++w)
                        for (int i = 0; i < 2; ++i)
                            first_two[(lanes.b[w] * m + lanes.j[w]) * 2 + i] = found[i][w];
                if (!risk) continue;
                for (int w = 0; w < lanes.count; ++w)
                    risk[(k * B + lanes.b[w]) * m + lanes.j[w]] = total[w];
            }
        }
    });
}

}  // namespace

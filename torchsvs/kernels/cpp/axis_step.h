// One predict-correct step of a lane of the per-axis kernel (part of fused.cpp). A deliberate
// twin of torchsvs/kernels/axes.py's _forward_step (its Kalman rule the Kalman update on 2×2
// blocks), transcribed line by line: tests/test_kernels.py (test_compiled_loops_equal_tensor_loops,
// test_compiled_loops_for_any_axis_count_on_threads) holds both to 1e-10 in float64.
//
// Rules: 0 Kalman (position-only), 1 SVSF, 2 the variable boundary layer ("vbl-innovation":
// the Kalman rule on the prior inflated by λ, one λ per track, the largest any of its axes asks
// for). Rule 2 couples a track's axes through λ only: each lane says what it asks for
// (wanted_inflation), the caller takes the track's largest (track_inflation) and the lane steps
// with it.
#pragma once

#include "lanes.h"

namespace {

// The per-step inputs of a lane (one track's axis) in axes._forward_step's order.
enum Given { kT, kQa, kQb, kQc, kYp, kYv, kRp, kRpv, kRvv, kWp, kWv, kGiven };
// A lane's results of a step: its state after the step, then what the step records.
enum Result {
    kP, kV, kA, kB, kC, kMemP, kMemV,  // the state carried to the next step
    kPp, kVp, kA1, kB1, kC1, kEp, kEv, kKa, kKc, kKd, kSp, kSpv, kSv, kSeenP, kSeenV, kLl,
    kResults
};
constexpr int64_t kLanes = 64;  // lanes (track axes) stepped together
constexpr int64_t kAdjointVectors = 4;  // vectors of lanes the adjoint takes back together

// The given inputs of a vector of lanes, step by step: each lane's address taken once, and
// an input constant in time (stride 0: a fixed interval, R, ψ) read once.
template <typename R>
struct LaneInputs {
    typedef typename Wide<R>::type V;
    static constexpr int kWidth = LaneBlock<R>::kWidth;
    const R* base[kGiven][kWidth];
    int64_t stride[kGiven];
    V fixed[kGiven];
    LaneInputs(const LaneBlock<R>& lanes, const View<R>* given) {
        for (int q = 0; q < kGiven; ++q) {
            stride[q] = given[q].st;
            for (int w = 0; w < kWidth; ++w) {
                base[q][w] = given[q].data + lanes.b[w] * given[q].sb + lanes.j[w] * given[q].sm;
                fixed[q][w] = base[q][w][0];
            }
        }
    }
    // The inputs at step t, in Given's order.
    void at(int64_t t, V* g) const {
        for (int q = 0; q < kGiven; ++q) {
            if (stride[q] == 0) {
                g[q] = fixed[q];
                continue;
            }
            V value{};
            for (int w = 0; w < kWidth; ++w) value[w] = base[q][w][t * stride[q]];
            g[q] = value;
        }
    }
};

// The state a lane carries from step to step: mean, covariance [[a, b], [b, c]], SVSF memory.
// X: one lane's scalar, or a vector of lanes (Wide).
template <typename X>
struct State {
    X p, v, a, b, c, mem_p, mem_v;
};

// One step of a lane: the state after it and everything it records.
template <typename X>
struct Step {
    State<X> next;
    X fp, fv;           // 1 where the position / velocity is observed, else 0
    X rp, rpv, rvv;     // R masked: an identity on missing components (blocks.masked_noise)
    X p_pred, v_pred, bT, a1, b1, c1;  // a1, b1, c1: the prior the gain is for (Rule 2: λ P)
    X ep, ev, Sp, Spv, Sv;
    X kp, kc, kv;       // the axis's gain [[kp, 0], [kc, kv]] (Kalman: kv = 0; SVSF: kc = 0)
    X ll;               // the log-likelihood's term without log S (Kalman)
    X a1r, b1r, c1r;    // Rule 2: the prior before its inflation
    X inflation;        // Rule 2: λ
};

// The prediction, Eqs. (11)-(12): F x and F P Fᵀ + Q with F = [[1, T], [0, 1]].
template <typename X>
struct Prediction {
    X p_pred, v_pred, bT, a1, b1, c1;
};
template <typename X>
inline Prediction<X> predict(const State<X>& x, const X* g) {
    const X dt = g[kT];
    Prediction<X> f;
    f.p_pred = x.p + dt * x.v, f.v_pred = x.v;
    f.bT = x.b + dt * x.c;
    f.a1 = x.a + dt * (x.b + f.bT) + g[kQa];
    f.b1 = f.bT + g[kQb];
    f.c1 = x.c + g[kQc];
    return f;
}

// linalg.boundary_inflation's max_gain: a gain of 1 would take an infinite prior.
constexpr double kMaxGain = 0.999;

// The inflation a lane asks for under the variable boundary layer (linalg.boundary_inflation,
// "innovation": covariance matching), before the largest over the track's axes and the clamp
// at 1: (Ē²/ψ² − r)/a with Ē = |e| + γ|e_post|, at most the λ of kMaxGain; 0 where missing.
template <typename X>
inline X wanted_inflation(const State<X>& x, const X* g, X gamma) {
    const X zero{};
    const Prediction<X> f = predict(x, g);
    const X yp = g[kYp], r = g[kRp];
    const auto seen = yp == yp;
    const X ep = seen ? yp - f.p_pred : zero;
    const X u = (magnitude_of(ep) + gamma * magnitude_of(x.mem_p)) / g[kWp];
    const X each = (u * u - r) / f.a1;
    const X most = r * splat<X>(kMaxGain) / (splat<X>(1.0 - kMaxGain) * f.a1);
    return seen ? (each < most ? each : most) : zero;
}

// wanted_inflation's adjoint: from `dwanted`, adds to the adjoints of the uninflated prior's
// a (da1), the innovation (dep), R (drp, where observed), the memory (dmem), ψ (dwp) and γ.
// torch's conventions: minimum splits a tie, d|x|/dx = 0 at 0.
template <typename X>
inline void wanted_inflation_adjoint(const State<X>& x, const X* g, X gamma, const Step<X>& s,
                                     X dwanted, X& da1, X& dep, X& drp, X& dmem, X& dwp,
                                     X& dgamma) {
    const X zero{};
    const X a1 = s.a1r, r = g[kRp], w = g[kWp], held = magnitude_of(x.mem_p);
    const X u = (magnitude_of(s.ep) + gamma * held) / w;
    const X each = (u * u - r) / a1;
    const X most = r * splat<X>(kMaxGain) / (splat<X>(1.0 - kMaxGain) * a1);
    const X dw = s.fp > zero ? dwanted : zero;
    const X to_each = each < most ? dw : (each == most ? splat<X>(0.5) * dw : zero);
    const X to_most = dw - to_each;
    // each = (u² − r)/a, most = r c/a
    const X du = to_each * 2 * u / a1;
    drp += (to_most * splat<X>(kMaxGain) / splat<X>(1.0 - kMaxGain) - to_each) / a1;
    da1 -= (to_each * each + to_most * most) / a1;
    // u = (|e| + γ|e_post|)/ψ
    const X dexcess = du / w;
    dwp -= du * u / w;
    dep += dexcess * sign_of(s.ep);
    dmem += dexcess * gamma * sign_of(x.mem_p);
    dgamma += dexcess * held;
}

// The most the lanes [first, first + m) of one track want (boundary_inflation's amax), of
// lane values indexed as wanted[i] (an array, or a vector of lanes).
template <typename R, typename Lanes>
inline R most_wanted(const Lanes& wanted, int64_t first, int64_t m) {
    R most = wanted[first];
    for (int64_t i = first + 1; i < first + m; ++i) most = std::max<R>(most, wanted[i]);
    return most;
}

// The inflation λ of each lane's track (boundary_inflation's amax and clamp_min): the largest
// its axes want, at least 1. The vector's lanes hold whole tracks from its first lane
// (lanes_per_vector); lanes past `count` repeat the last real one.
template <typename R>
inline typename Wide<R>::type track_inflation(const LaneBlock<R>& lanes,
                                              typename Wide<R>::type wanted) {
    typename Wide<R>::type out{};
    for (int w = 0; w < lanes.count; ++w)
        out[w] = std::max(most_wanted<R>(wanted, w - lanes.j[w], lanes.m), R(1));
    for (int w = lanes.count; w < LaneBlock<R>::kWidth; ++w) out[w] = out[lanes.count - 1];
    return out;
}

// track_inflation's adjoint: from each lane's share of dλ (a track's lanes share one λ, so
// their shares add), the adjoint of each lane's wanted inflation: all to the axes that want
// the most (a tie split evenly, as torch's amax), none where the clamp holds λ at 1 (torch's
// clamp_min passes the gradient at equality).
template <typename R>
inline typename Wide<R>::type track_inflation_adjoint(const LaneBlock<R>& lanes,
                                                      typename Wide<R>::type wanted,
                                                      typename Wide<R>::type dlam) {
    typename Wide<R>::type out{};
    for (int w = 0; w < lanes.count; ++w) {
        const int64_t first = w - lanes.j[w];
        const R most = most_wanted<R>(wanted, first, lanes.m);
        if (most < R(1) || wanted[w] != most) continue;
        R total = 0;
        int ties = 0;
        for (int64_t i = first; i < first + lanes.m; ++i) {
            ties += wanted[i] == most;
            total += dlam[i];
        }
        out[w] = total / R(ties);
    }
    return out;
}

// axes._forward_step for one lane (or a vector of lanes) under Rule (above); `inflation`: the
// λ of Rule 2 (track_inflation). g: the step's inputs in Given's order. Branch-free: a missing
// measurement's lane picks its values (NaN: missing).
template <typename X, int Rule>
inline Step<X> predict_correct(const State<X>& x, const X* g, X gamma,
                               X inflation = splat<X>(1.0)) {
    const X zero{}, one = zero + 1;
    Step<X> s;
    X yp = g[kYp], yv = g[kYv];
    const auto seen_p = yp == yp;
    s.fp = seen_p ? one : zero;
    s.rp = seen_p ? g[kRp] : one;
    const Prediction<X> f = predict(x, g);
    s.p_pred = f.p_pred, s.v_pred = f.v_pred, s.bT = f.bT;
    s.a1 = f.a1, s.b1 = f.b1, s.c1 = f.c1;
    if (Rule == 2) {  // the Kalman rule on the inflated prior λ P
        s.a1r = s.a1, s.b1r = s.b1, s.c1r = s.c1, s.inflation = inflation;
        s.a1 = inflation * s.a1, s.b1 = inflation * s.b1, s.c1 = inflation * s.c1;
    }
    s.ep = seen_p ? yp - s.p_pred : zero;
    s.Sp = s.a1 * s.fp + s.rp;
    State<X>& n = s.next;
    if (Rule != 1) {
        s.fv = zero, s.rpv = zero, s.rvv = one, s.ev = zero, s.Spv = zero, s.Sv = one;
        X kp = s.a1 * s.fp / s.Sp, kv_p = s.b1 * s.fp / s.Sp;
        X one_k = 1 - kp;
        n.a = one_k * one_k * s.a1 + kp * kp * s.rp;  // Joseph form
        n.b = one_k * (s.b1 - kv_p * s.a1) + kp * kv_p * s.rp;
        n.c = s.c1 - 2 * kv_p * s.b1 + kv_p * kv_p * (s.a1 + s.rp);
        n.p = s.p_pred + kp * s.ep;
        n.v = s.v_pred + kv_p * s.ep;
        // Rule 2: Eq. (24)'s a-posteriori innovation, carried where missing.
        n.mem_p = Rule == 2 ? (seen_p ? yp - n.p : x.mem_p) : x.mem_p, n.mem_v = x.mem_v;
        s.kp = kp, s.kc = kv_p, s.kv = zero;
        // log N(e; 0, S) over the observed positions (axes.run_axes), but log S.
        s.ll = splat<X>(-0.5) * (s.ep * s.ep / s.Sp + s.fp * splat<X>(1.8378770664093453));
    } else {
        const auto seen_v = yv == yv;
        s.fv = seen_v ? one : zero;
        s.rpv = (seen_p & seen_v) ? g[kRpv] : zero;
        s.rvv = seen_v ? g[kRvv] : one;
        s.ev = seen_v ? yv - s.v_pred : zero;
        X kp = gain_ratio(s.ep, x.mem_p, g[kWp], gamma) * s.fp;
        X kv = gain_ratio(s.ev, x.mem_v, g[kWv], gamma) * s.fv;
        X one_p = 1 - kp, one_v = 1 - kv;
        n.a = one_p * one_p * s.a1 + kp * kp * s.rp;  // Joseph form, diagonal gain
        n.b = one_p * one_v * s.b1 + kp * kv * s.rpv;
        n.c = one_v * one_v * s.c1 + kv * kv * s.rvv;
        n.p = s.p_pred + kp * s.ep, n.v = s.v_pred + kv * s.ev;
        // Eq. (24): the a-posteriori innovation, carried where missing.
        n.mem_p = seen_p ? yp - n.p : x.mem_p;
        n.mem_v = seen_v ? yv - n.v : x.mem_v;
        s.kp = kp, s.kc = zero, s.kv = kv;
        s.Spv = s.b1 * s.fp * s.fv + s.rpv, s.Sv = s.c1 * s.fv + s.rvv;
        s.ll = zero;
    }
    return s;
}

// predict_correct for `lanes` lanes at once, whole tracks of m lanes each. Every lane runs the
// same branch-free arithmetic, so the compiler vectorises the loop across lanes and the
// processor overlaps the lanes' dependent chains. g: the step's inputs, r: the state before
// (r[kP..kMemV]) and the results after; r[kLl] is the step's log-likelihood without log S
// (Likelihood adds it).
template <typename R, int Rule>
inline void step_lanes(int64_t lanes, int64_t m, R gamma, const R (*g)[kLanes],
                       R (*r)[kLanes]) {
    auto state = [r](int64_t l) {
        return State<R>{r[kP][l], r[kV][l], r[kA][l],   r[kB][l],
                        r[kC][l], r[kMemP][l], r[kMemV][l]};
    };
    auto inputs = [g](int64_t l, R* given) {
        for (int q = 0; q < kGiven; ++q) given[q] = g[q][l];
    };
    R inflation[kLanes];
    if (Rule == 2) {  // each track's λ: the largest its axes want, at least 1 (track_inflation)
        R wanted[kLanes];
        for (int64_t l = 0; l < lanes; ++l) {
            R given[kGiven];
            inputs(l, given);
            wanted[l] = wanted_inflation<R>(state(l), given, gamma);
        }
        for (int64_t l0 = 0; l0 < lanes; l0 += m)
            std::fill_n(inflation + l0, m, std::max(most_wanted<R>(wanted, l0, m), R(1)));
    }
    for (int64_t l = 0; l < lanes; ++l) {
        R given[kGiven];
        inputs(l, given);
        Step<R> s = predict_correct<R, Rule>(state(l), given, gamma,
                                             Rule == 2 ? inflation[l] : R(1));
        r[kP][l] = s.next.p, r[kV][l] = s.next.v;
        r[kA][l] = s.next.a, r[kB][l] = s.next.b, r[kC][l] = s.next.c;
        r[kMemP][l] = s.next.mem_p, r[kMemV][l] = s.next.mem_v;
        r[kPp][l] = s.p_pred, r[kVp][l] = s.v_pred;
        r[kA1][l] = s.a1, r[kB1][l] = s.b1, r[kC1][l] = s.c1;
        r[kEp][l] = s.ep, r[kEv][l] = s.ev;
        r[kKa][l] = s.kp, r[kKc][l] = s.kc, r[kKd][l] = s.kv;
        r[kSp][l] = s.Sp, r[kSpv][l] = s.Spv, r[kSv][l] = s.Sv;
        r[kSeenP][l] = s.fp, r[kSeenV][l] = s.fv, r[kLl][l] = s.ll;
    }
}

}  // namespace

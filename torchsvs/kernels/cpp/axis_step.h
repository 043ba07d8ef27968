// One predict-correct step of a lane of the per-axis kernel (part of fused.cpp). A deliberate
// twin of torchsvs/kernels/axes.py's _forward_step (its Kalman rule the Kalman update on 2×2
// blocks), transcribed line by line: tests/test_kernels.py (test_compiled_loops_equal_tensor_loops,
// test_compiled_loops_for_any_axis_count_on_threads) holds both to 1e-10 in float64.
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
    X p_pred, v_pred, bT, a1, b1, c1;
    X ep, ev, Sp, Spv, Sv;
    X kp, kc, kv;       // the axis's gain [[kp, 0], [kc, kv]] (Kalman: kv = 0; SVSF: kc = 0)
    X ll;               // the log-likelihood's term without log S (Kalman)
};

// axes._forward_step for one lane (or a vector of lanes): Rule 0 Kalman (position-only),
// 1 SVSF. g: the step's inputs in Given's order. Branch-free: a missing measurement's lane
// picks its values (NaN: missing).
template <typename X, int Rule>
inline Step<X> predict_correct(const State<X>& x, const X* g, X gamma) {
    const X zero{}, one = zero + 1;
    Step<X> s;
    X dt = g[kT], yp = g[kYp], yv = g[kYv];
    const auto seen_p = yp == yp;
    s.fp = seen_p ? one : zero;
    s.rp = seen_p ? g[kRp] : one;
    // Prediction, Eqs. (11)-(12): F P Fᵀ + Q with F = [[1, T], [0, 1]].
    s.p_pred = x.p + dt * x.v, s.v_pred = x.v;
    s.bT = x.b + dt * x.c;
    s.a1 = x.a + dt * (x.b + s.bT) + g[kQa];
    s.b1 = s.bT + g[kQb];
    s.c1 = x.c + g[kQc];
    s.ep = seen_p ? yp - s.p_pred : zero;
    s.Sp = s.a1 * s.fp + s.rp;
    State<X>& n = s.next;
    if (Rule == 0) {
        s.fv = zero, s.rpv = zero, s.rvv = one, s.ev = zero, s.Spv = zero, s.Sv = one;
        X kp = s.a1 * s.fp / s.Sp, kv_p = s.b1 * s.fp / s.Sp;
        X one_k = 1 - kp;
        n.a = one_k * one_k * s.a1 + kp * kp * s.rp;  // Joseph form
        n.b = one_k * (s.b1 - kv_p * s.a1) + kp * kv_p * s.rp;
        n.c = s.c1 - 2 * kv_p * s.b1 + kv_p * kv_p * (s.a1 + s.rp);
        n.p = s.p_pred + kp * s.ep;
        n.v = s.v_pred + kv_p * s.ep;
        n.mem_p = x.mem_p, n.mem_v = x.mem_v;
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

// predict_correct for `lanes` independent lanes at once. Every lane runs the same branch-free
// arithmetic, so the compiler vectorises the loop across lanes and the processor overlaps the
// lanes' dependent chains. g: the step's inputs, r: the state before (r[kP..kMemV]) and the
// results after; r[kLl] is the step's log-likelihood without log S (Likelihood adds it).
template <typename R, int Rule>
inline void step_lanes(int64_t lanes, R gamma, const R (*g)[kLanes], R (*r)[kLanes]) {
    for (int64_t l = 0; l < lanes; ++l) {
        R given[kGiven];
        for (int q = 0; q < kGiven; ++q) given[q] = g[q][l];
        State<R> x{r[kP][l], r[kV][l], r[kA][l], r[kB][l], r[kC][l], r[kMemP][l], r[kMemV][l]};
        Step<R> s = predict_correct<R, Rule>(x, given, gamma);
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

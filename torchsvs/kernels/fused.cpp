// The sequential time loops of the per-axis kernel (torchsvs/kernels/axes.py) as compiled C++.
//
// Each (track, axis) pair is an independent lane of two-state steps; blocks of lanes step
// together (a loop the compiler vectorises) and every step costs a few dozen flops instead of
// a few dozen tensor operations. The formulas are those of axes.py, transcribed line by line
// (the Python functions named in the comments are their home and the differentiable path);
// tests hold both to 1e-10 in float64.
//
// Every array input is a pointer and three element strides (track, step, axis) into a
// [B, T, m] view, so broadcast inputs (stride 0) need no copies. Outputs are contiguous, in
// the general layout (state p1, v1, p2, v2, ...; block-diagonal covariances and gains): what
// a FilterResult holds, written once, with no assembly pass after. Large batches run on
// threads, split by tracks. Built and loaded by torchsvs/kernels/fused.py (g++ -O3, ctypes).

#include <cmath>
#include <cstdint>
#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>
#if defined(__SSE2__)
#include <immintrin.h>
#endif

namespace {

// Largest state or measurement size of the dense steps.
constexpr int64_t kMax = 16;

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

// The smoother loops step W lanes (track axes) together: a lane's formulas above are
// templates on R, and with R a vector of W lanes (GCC/Clang vector extensions, 32 bytes) the
// same code runs W lanes at once, element by element, so each lane gets exactly the numbers
// it gets alone. A block's lanes are gathered from the inputs and scattered to the outputs; a
// short last block repeats its last lane.
template <typename R>
struct Wide;
template <>
struct Wide<float> {
    typedef float type __attribute__((vector_size(32)));
};
template <>
struct Wide<double> {
    typedef double type __attribute__((vector_size(32)));
};
template <typename R>
struct LaneBlock {
    static constexpr int kWidth = sizeof(typename Wide<R>::type) / sizeof(R);
    int64_t b[kWidth], j[kWidth];  // each lane's track and axis
    int count;                     // lanes that are real (the rest repeat the last)

    // The lanes [l, min(l + width, end)) of lane index track · m + axis.
    LaneBlock(int64_t l, int64_t end, int64_t m)
        : count(static_cast<int>(std::min<int64_t>(kWidth, end - l))) {
        for (int w = 0; w < kWidth; ++w) {
            const int64_t lane = l + std::min(w, count - 1);
            b[w] = lane / m, j[w] = lane % m;
        }
    }
    // The lanes' values of input `v` at step t.
    typename Wide<R>::type at(const View<R>& v, int64_t t) const {
        typename Wide<R>::type out;
        for (int w = 0; w < kWidth; ++w) out[w] = v.at(b[w], t, j[w]);
        return out;
    }
};

// Lane values X: a scalar R, or a Wide vector of lanes that runs the same code lane by lane
// (conditions are masks, `mask ? a : b` picks per lane; GCC/Clang vector extensions).
template <typename X>
struct Element {
    typedef X type;
};
template <>
struct Element<Wide<float>::type> {
    typedef float type;
};
template <>
struct Element<Wide<double>::type> {
    typedef double type;
};
// The constant c as an X (every lane).
template <typename X>
inline X splat(double c) {
    return X{} + static_cast<typename Element<X>::type>(c);
}
inline float magnitude_of(float x) { return std::fabs(x); }
inline double magnitude_of(double x) { return std::fabs(x); }
template <typename X>
inline X magnitude_of(X x) {
    return x < X{} ? -x : x;
}
// sign(x) as torch has it: −1, 0 or 1.
template <typename X>
inline X sign_of(X x) {
    const X zero{}, one = zero + 1;
    return (x > zero ? one : zero) - (x < zero ? one : zero);
}

// svsf_gain_ratio (torchsvs/linalg.py): (|e| + γ|e_post|) / max(|e|, ψ), Eq. (23).
template <typename X>
inline X gain_ratio(X e, X memory, X width, X gamma) {
    X magnitude = magnitude_of(e);
    return (magnitude + gamma * magnitude_of(memory)) / (magnitude > width ? magnitude : width);
}

// std::copy_n into a fresh output nobody reads soon: non-temporal stores write whole cache
// lines without reading them first (half the memory traffic); a plain copy without SSE2.
template <typename R>
inline void stream(const R* from, int64_t count, R* to) {
#if defined(__SSE2__)
    constexpr int64_t kPer = 16 / sizeof(R);  // elements of a 16-byte store
    int64_t i = 0;
    for (; i < count && reinterpret_cast<uintptr_t>(to + i) % 16 != 0; ++i) to[i] = from[i];
    for (; i + kPer <= count; i += kPer) {
        if constexpr (sizeof(R) == 4)
            _mm_stream_ps(reinterpret_cast<float*>(to + i),
                          _mm_loadu_ps(reinterpret_cast<const float*>(from + i)));
        else
            _mm_stream_pd(reinterpret_cast<double*>(to + i),
                          _mm_loadu_pd(reinterpret_cast<const double*>(from + i)));
    }
    for (; i < count; ++i) to[i] = from[i];
#else
    std::copy_n(from, count, to);
#endif
}

// Runs body(first, last) over track ranges on `threads` threads (the calling one included).
template <typename Body>
void over_tracks(int64_t B, int threads, const Body& body) {
    // Each range ends with a full fence: the non-temporal stores of `stream` are weakly
    // ordered, and the caller reads what every thread wrote.
    auto fenced = [&body](int64_t first, int64_t last) {
        body(first, last);
        std::atomic_thread_fence(std::memory_order_seq_cst);
    };
    if (threads > B) threads = static_cast<int>(B);
    if (threads <= 1) {
        fenced(int64_t(0), B);
        return;
    }
    std::vector<std::thread> pool;
    int64_t per = (B + threads - 1) / threads;
    for (int i = 1; i < threads; ++i) {
        int64_t first = i * per, last = std::min(B, first + per);
        if (first < last) pool.emplace_back([&fenced, first, last] { fenced(first, last); });
    }
    fenced(int64_t(0), std::min(B, per));
    for (auto& worker : pool) worker.join();
}

// The outputs in the general layout (state p1, v1, p2, v2, ...; FilterResult's fields), each
// contiguous [B, T, ...]; a track-step's record of every output is written in one go, so the
// block-diagonal zeros cost no extra pass. Any per-step output may be null (not kept: the
// estimators' `keep`); `post` is null for the KF and `loglik` [B] for the SVSF. The last
// state (mean [B, n], cov [B, n, n], SVSF memory [B, m_z]; null: not wanted) is what a
// filter's next chunk starts from when the history is not kept.
//
// With `smoothing` (1: Γ = K, the RTS; 2: Γ = P Hᵀ S⁻¹, the SVSS) the loop also writes the
// one-step-lag smoothed moments x̂_{k|k+1}, P_{k|k+1} (smooth_mean [B, T, n], smooth_cov
// [B, T, n, n]; the last step as filtered): what `backward` with lag 1 gives from the written
// record, computed from the lanes' registers as each step completes, so the record need not be
// written or read back.
template <typename R>
struct Layout {
    R *mean, *cov, *pred_mean, *pred_cov, *innovation, *gain, *S, *post, *loglik;
    uint8_t* mask;
    R *last_mean, *last_cov, *last_post;
    R *smooth_mean, *smooth_cov;
    int smoothing;
};

// Writes an axis's two rows (2j, 2j + 1) of a block-diagonal n × n record: [[a, b], [c, d]]
// on the diagonal, zeros elsewhere.
template <typename R>
inline void block_rows(R* record, int64_t n, int64_t j, R a, R b, R c, R d) {
    R* row0 = record + 2 * j * n;
    R* row1 = row0 + n;
    for (int64_t k = 0; k < n; ++k) row0[k] = row1[k] = 0;
    row0[2 * j] = a, row0[2 * j + 1] = b, row1[2 * j] = c, row1[2 * j + 1] = d;
}

// An axis's mean (p, v) and covariance [[a, b], [b, c]] into the general layout: entries 2j,
// 2j + 1 of the n-vector `mean` and rows 2j, 2j + 1 of the n × n `cov`.
template <typename R>
inline void write_axis(R* mean, R* cov, int64_t n, int64_t j, R p, R v, R a, R b, R c) {
    mean[2 * j] = p, mean[2 * j + 1] = v;
    block_rows(cov, n, j, a, b, b, c);
}

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
    X rp, rpv, rvv;     // R masked: an identity on missing components (axes._masked_noise)
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

// What axes.backward_terms reads at index k (the step k and its successor t = k + 1): P at k;
// the prediction, gain, noise (masked: an identity on missing components, as
// axes._masked_noise), masks, interval and innovation at t.
template <typename R>
struct TermArgs {
    R a, b, c, a1, b1, c1;
    M2<R> K;
    R rp, rpv, rvv, fp, fv, dt, ep, ev;
};

// TermArgs from a lane's values, the noise unmasked: masked here (an identity on missing
// components, as axes._masked_noise).
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

// axes.backward_terms at one index, with its intermediates (the reverse mode reads them):
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

// axes._recurse at a step whose 22 terms are `w` (C, d, ΓHF, ΓSΓᵀ, ΓX, AF in order):
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

// axes._smoothed at one step of a lane: `now` holds its filtered moments (p, v, a, b, c) and
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

// A lane's log-likelihood, Σ −(e²/S + log S + log 2π)/2 over its observed steps, summed in
// double. The logarithms are taken once per kLogEvery steps instead of every step (log does
// not vectorise; it cost more than the step): S multiplies into a double product, flushed
// into the sum before it could leave double's range; a factor far from 1 goes straight in.
struct Likelihood {
    static constexpr int kLogEvery = 16;  // 16 factors in (1e-15, 1e15) stay in double's range
    double terms = 0, sum = 0, product = 1;  // terms: the parts without log S
    int factors = 0;
    void add(double term, double S) {
        terms += term;
        if (S > 1e-15 && S < 1e15) {
            product *= S;
            if (++factors == kLogEvery) flush();
        } else {
            sum += std::log(S);
        }
    }
    double total() {
        flush();
        return terms - 0.5 * sum;
    }
    void flush() {
        sum += std::log(product);
        product = 1, factors = 0;
    }
};

// axes._forward_step over all steps, writing the general layout. rule 0: Kalman
// (position-only), 1: SVSF. `velocity`: the corrector measures velocities too (H = I, m_z = n),
// else positions only (m_z = m). M: the number of axes when known at compile time (1-3: the
// record loops unroll), else 0 and `m` says.
// Inputs (11, [B, T, m] views, in Given's order): T, Qa, Qb, Qc, yp, yv (NaN: missing), rp,
// rpv, rvv (R per axis, unmasked), wp, wv. Prior (5, [B, m] views as [B, 1, m]): p, v, a, b, c.
template <typename R, int Rule, int M>
void forward(int64_t B, int64_t T, int64_t m_runtime, int velocity, R gamma, int threads,
             const void* const* in, const int64_t* in_strides, const void* const* prior,
             const int64_t* prior_strides, const Layout<R>& out) {
    const int64_t m = M > 0 ? M : m_runtime;
    View<R> given[kGiven];
    // Inputs constant over steps (stride 0 in time, e.g. a fixed interval or R) are read once
    // per block of tracks; the others at every step.
    int per_step[kGiven], stepped = 0, fixed[kGiven], constant = 0;
    for (int q = 0; q < kGiven; ++q) {
        given[q] = view<R>(in, in_strides, q);
        if (given[q].st == 0)
            fixed[constant++] = q;
        else
            per_step[stepped++] = q;
    }
    const int64_t n = 2 * m, mz = velocity ? n : m;
    // Blocks of tracks step together, chunk by chunk of kChunk steps. A chunk's records are
    // staged per track and then copied out whole: each output gets one contiguous run per
    // track and chunk instead of a record at a time interleaved across the block's tracks.
    const int64_t block = kLanes / m;
    constexpr int64_t kChunk = 16;
    // Record sizes in Layout's order: mean, cov, pred_mean, pred_cov, innovation, gain, S, post,
    // then the smoothed mean and cov (kLagged on: a step's slot holds its predecessor's).
    constexpr int kOutputs = 10, kLagged = 8;
    const int64_t sizes[kOutputs] = {n, n * n, n, n * n, mz, n * mz, mz * mz, mz, n, n * n};
    R* const targets[kOutputs] = {out.mean,       out.cov,  out.pred_mean, out.pred_cov,
                                  out.innovation, out.gain, out.S,         out.post,
                                  out.smooth_mean, out.smooth_cov};
    int64_t offsets[kOutputs + 1] = {0};
    for (int o = 0; o < kOutputs; ++o)
        offsets[o + 1] = offsets[o] + (targets[o] ? sizes[o] : 0);
    const int64_t staged_size = block * kChunk * offsets[kOutputs];
    const bool smoothing = out.smoothing != 0, projection = out.smoothing == 2;
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        alignas(64) R g[kGiven][kLanes];
        alignas(64) R r[kResults][kLanes];
        alignas(64) R moments[5][kLanes];  // the filtered moments before a step (smoothing)
        Likelihood logs[kLanes];
        std::vector<R> staged(staged_size);
        std::vector<uint8_t> staged_mask(block * kChunk * mz);
        for (int64_t b0 = first; b0 < last; b0 += block) {
            const int64_t b1 = std::min(last, b0 + block), lanes = (b1 - b0) * m;
            for (int64_t bi = b0, l = 0; bi < b1; ++bi)
                for (int64_t j = 0; j < m; ++j, ++l) {
                    for (int q = 0; q < 5; ++q)
                        r[q][l] = view<R>(prior, prior_strides, q).at(bi, 0, j);
                    r[kMemP][l] = r[kMemV][l] = 0;
                    logs[l] = Likelihood();
                    for (int c = 0; c < constant; ++c) g[fixed[c]][l] = given[fixed[c]].at(bi, 0, j);
                }
            for (int64_t t0 = 0; t0 < T; t0 += kChunk) {
                const int64_t t1 = std::min(T, t0 + kChunk);
                for (int64_t t = t0; t < t1; ++t) {
                    for (int c = 0; c < stepped; ++c) {
                        const View<R> x = given[per_step[c]];
                        R* lane = g[per_step[c]];
                        for (int64_t bi = b0, l = 0; bi < b1; ++bi)
                            for (int64_t j = 0; j < m; ++j, ++l) lane[l] = x.at(bi, t, j);
                    }
                    if (smoothing)
                        for (int q = 0; q < 5; ++q) std::copy_n(r[kP + q], lanes, moments[q]);
                    step_lanes<R, Rule>(lanes, gamma, g, r);
                    if (smoothing && t > 0) {
                        if (projection)
                            smooth_lanes<R, true>(lanes, g, r, moments);
                        else
                            smooth_lanes<R, false>(lanes, g, r, moments);
                    }
                    if (Rule == 0)
                        for (int64_t l = 0; l < lanes; ++l) logs[l].add(r[kLl][l], r[kSp][l]);
                    for (int64_t bi = b0, l = 0; bi < b1; ++bi) {
                        // This track-step's records in the staging area: per output, its
                        // tracks' chunks one after the other, exactly as they are copied out.
                        const int64_t record = (bi - b0) * kChunk + (t - t0);
                        // Outputs not kept have no staging area (null here).
                        auto at = [&](int o) {
                            return targets[o] ? staged.data() + block * kChunk * offsets[o] +
                                                    record * sizes[o]
                                              : nullptr;
                        };
                        R *mean = at(0), *cov = at(1), *pred_mean = at(2), *pred_cov = at(3);
                        R *e = at(4), *K = at(5), *S = at(6), *post = at(7);
                        R *smooth_mean = t > 0 ? at(8) : nullptr, *smooth_cov = at(9);
                        for (int64_t j = 0; j < m; ++j, ++l) {
                            if (smooth_mean)
                                write_axis(smooth_mean, smooth_cov, n, j, moments[0][l],
                                           moments[1][l], moments[2][l], moments[3][l],
                                           moments[4][l]);
                            R ka = r[kKa][l], kc = r[kKc][l], Sp = r[kSp][l];
                            if (mean) mean[2 * j] = r[kP][l], mean[2 * j + 1] = r[kV][l];
                            if (cov) block_rows(cov, n, j, r[kA][l], r[kB][l], r[kB][l], r[kC][l]);
                            if (pred_mean)
                                pred_mean[2 * j] = r[kPp][l], pred_mean[2 * j + 1] = r[kVp][l];
                            if (pred_cov)
                                block_rows(pred_cov, n, j, r[kA1][l], r[kB1][l], r[kB1][l],
                                           r[kC1][l]);
                            if (velocity) {
                                if (e) e[2 * j] = r[kEp][l], e[2 * j + 1] = r[kEv][l];
                                if (K) block_rows(K, n, j, ka, R(0), kc, r[kKd][l]);
                                if (S) block_rows(S, n, j, Sp, r[kSpv][l], r[kSpv][l], r[kSv][l]);
                                if (post) post[2 * j] = r[kMemP][l], post[2 * j + 1] = r[kMemV][l];
                            } else {  // position columns j: K[2j][j], K[2j + 1][j]; S diagonal
                                if (e) e[j] = r[kEp][l];
                                for (int64_t col = 0; col < m && K; ++col) {
                                    K[2 * j * m + col] = col == j ? ka : R(0);
                                    K[(2 * j + 1) * m + col] = col == j ? kc : R(0);
                                }
                                for (int64_t col = 0; col < m && S; ++col)
                                    S[j * m + col] = col == j ? Sp : R(0);
                                if (post) post[j] = r[kMemP][l];
                            }
                        }
                        // Last: a byte store may alias anything, so nothing is reloaded after.
                        if (out.mask) {
                            uint8_t* mask = staged_mask.data() + record * mz;
                            for (int64_t j = 0, lj = l - m; j < m; ++j, ++lj) {
                                if (velocity) {
                                    mask[2 * j] = r[kSeenP][lj] > 0;
                                    mask[2 * j + 1] = r[kSeenV][lj] > 0;
                                } else {
                                    mask[j] = r[kSeenP][lj] > 0;
                                }
                            }
                        }
                    }
                }
                // Copy the chunk out: per track and output, one contiguous run.
                const int64_t steps = t1 - t0;
                for (int64_t bi = b0; bi < b1; ++bi) {
                    for (int o = 0; o < kOutputs; ++o) {
                        if (!targets[o]) continue;
                        // A lagged output's slots hold the steps before (none before step 0).
                        const int64_t lag = o >= kLagged, skip = lag && t0 == 0;
                        const R* from = staged.data() + block * kChunk * offsets[o] +
                                        ((bi - b0) * kChunk + skip) * sizes[o];
                        stream(from, (steps - skip) * sizes[o],
                               targets[o] + (bi * T + t0 - lag + skip) * sizes[o]);
                    }
                    if (out.mask)
                        std::copy_n(staged_mask.data() + (bi - b0) * kChunk * mz, steps * mz,
                                    out.mask + (bi * T + t0) * mz);
                }
            }
            for (int64_t bi = b0, l = 0; bi < b1; ++bi)  // the state after the last step
                for (int64_t j = 0; j < m; ++j, ++l) {
                    if (out.last_mean)
                        write_axis(out.last_mean + bi * n, out.last_cov + bi * n * n, n, j,
                                   r[kP][l], r[kV][l], r[kA][l], r[kB][l], r[kC][l]);
                    if (out.smooth_mean)  // the last step smoothed is the last filtered
                        write_axis(out.smooth_mean + (bi * T + T - 1) * n,
                                   out.smooth_cov + (bi * T + T - 1) * n * n, n, j, r[kP][l],
                                   r[kV][l], r[kA][l], r[kB][l], r[kC][l]);
                    if (!out.last_post) continue;
                    R* last_post = out.last_post + bi * mz;
                    if (velocity)
                        last_post[2 * j] = r[kMemP][l], last_post[2 * j + 1] = r[kMemV][l];
                    else
                        last_post[j] = r[kMemP][l];
                }
            if (out.loglik)
                for (int64_t bi = b0, l = 0; bi < b1; ++bi) {
                    double total = 0;
                    for (int64_t j = 0; j < m; ++j, ++l) total += logs[l].total();
                    out.loglik[bi] = R(total);
                }
        }
    });
}

// forward with the axis count fixed at compile time where it is small.
template <typename R, int Rule>
void forward_axes(int64_t B, int64_t T, int64_t m, int velocity, R gamma, int threads,
                  const void* const* in, const int64_t* s, const void* const* prior,
                  const int64_t* ps, const Layout<R>& out) {
    if (m == 1)
        forward<R, Rule, 1>(B, T, m, velocity, gamma, threads, in, s, prior, ps, out);
    else if (m == 2)
        forward<R, Rule, 2>(B, T, m, velocity, gamma, threads, in, s, prior, ps, out);
    else if (m == 3)
        forward<R, Rule, 3>(B, T, m, velocity, gamma, threads, in, s, prior, ps, out);
    else
        forward<R, Rule, 0>(B, T, m, velocity, gamma, threads, in, s, prior, ps, out);
}

// forward's entry: the output pointers `o` in Layout's order (15; see Layout for the nulls),
// and the smoothing (0: none).
template <typename R>
void forward_entry(int64_t B, int64_t T, int64_t m, int rule, int velocity, double gamma,
                   int threads, const void* const* in, const int64_t* s, const void* const* prior,
                   const int64_t* ps, void* const* o, int smoothing) {
    Layout<R> out{static_cast<R*>(o[0]),  static_cast<R*>(o[1]),       static_cast<R*>(o[2]),
                  static_cast<R*>(o[3]),  static_cast<R*>(o[4]),       static_cast<R*>(o[5]),
                  static_cast<R*>(o[6]),  static_cast<R*>(o[7]),       static_cast<R*>(o[8]),
                  static_cast<uint8_t*>(o[9]), static_cast<R*>(o[10]), static_cast<R*>(o[11]),
                  static_cast<R*>(o[12]), static_cast<R*>(o[13]),      static_cast<R*>(o[14]),
                  smoothing};
    R g = static_cast<R>(gamma);
    if (rule == 0)
        forward_axes<R, 0>(B, T, m, velocity, g, threads, in, s, prior, ps, out);
    else
        forward_axes<R, 1>(B, T, m, velocity, g, threads, in, s, prior, ps, out);
}

// axes._rts_interval: x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k}),
// Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ, C_k = P_k Fᵀ P_{k+1|k}⁻¹ (Eq. (17)).
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
                    R dt = Ts.at(bi, k + 1, j);
                    R a = A.at(bi, k, j), b = Bc.at(bi, k, j), c = Cc.at(bi, k, j);
                    R pa = A1.at(bi, k + 1, j), pb = B1.at(bi, k + 1, j);
                    R pc = C1.at(bi, k + 1, j);
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

// A lane's terms (written to `terms`, n indices) and recursion (in `states`, see
// lane_recursion), from its 20 inputs `at(i, step)`; returns the results' row.
template <typename R, typename At>
inline const Backward<R>* lane_backward(const At& at, int64_t n, int64_t lag, bool projection,
                                        std::vector<R>& terms, std::vector<Backward<R>>& states) {
    for (int64_t k = 0; k < n; ++k) terms_at(&terms[22 * k], projection, term_args<R>(at, k));
    return lane_recursion(terms.data(), n, lag, states);
}

// axes.smooth_axes: the backward recursion from zero at the end (fixed interval) or, with a
// lag L < T-1, L applications from zero at step k+L for each k (the fixed-lag form), then
// axes._smoothed: x̂ˢ_k = x̂_k + g_k, Pˢ_k = P_k − P_k G_kᵀ − G_k P_k + Z_k (symmetrised; the
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
    // The smoothed moments' adjoints (axes._smoothed).
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
    // The terms' adjoints, onto the inputs (the masked noise's onto the unmasked).
    for (int64_t k = 0; k < n; ++k) {
        const int64_t t = k + 1;
        const TermArgs<V> x = term_args<V>(at, k);
        const TermArgs<V> d = terms_adjoint(&dterms[22 * k], projection, x);
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

// The filter's steps for a vector of lanes with the record the smoother's recursion reads:
// the states before and after every step (xs[0..T]) and backward's 20 inputs, step by step
// (rec[i * T + t]: cov a, b, c; pred_cov a, b, c; gain a, b, c, d; noise pp, pv, vv
// (unmasked); observed p, v; T; innovation p, v; mean p, v), and (Kalman, `logs` not null)
// each lane's log-likelihood.
template <typename R, int Rule>
void filter_record(const LaneBlock<R>& lanes, const View<R>* given, const View<R>* start,
                   int64_t T, typename Wide<R>::type gamma, State<typename Wide<R>::type>* xs,
                   typename Wide<R>::type* rec, Likelihood* logs = nullptr) {
    using V = typename Wide<R>::type;
    const V zero{};
    xs[0] = {lanes.at(start[0], 0), lanes.at(start[1], 0), lanes.at(start[2], 0),
             lanes.at(start[3], 0), lanes.at(start[4], 0), zero, zero};
    const LaneInputs<R> inputs(lanes, given);
    for (int64_t t = 0; t < T; ++t) {
        V g[kGiven];
        inputs.at(t, g);
        const Step<V> s = predict_correct<V, Rule>(xs[t], g, gamma);
        xs[t + 1] = s.next;
        const V row[20] = {s.next.a, s.next.b, s.next.c, s.a1,    s.b1,    s.c1,    s.kp,
                           zero,     s.kc,     s.kv,     g[kRp],  g[kRpv], g[kRvv], s.fp,
                           s.fv,     g[kT],    s.ep,     s.ev,    s.next.p, s.next.v};
        for (int i = 0; i < 20; ++i) rec[i * T + t] = row[i];
        if (Rule == 0 && logs)
            for (int w = 0; w < lanes.kWidth; ++w) logs[w].add(s.ll[w], s.Sp[w]);
    }
}

// The filter and its smoother's general recursion (`backward`: fixed interval or lag) in one
// pass, for a smoother of a lag other than 1 that keeps less than the filter's whole record
// (torchsvs.kernels.axes.run_axes; training: _CompiledAxes): each
// vector of lanes runs the filter keeping its record in a buffer of its own (filter_record),
// then the recursion on it, and writes what `out` asks: the filter's mean and cov of every
// step (null: not kept), its state after the last step, the smoothed mean and cov. The
// filter's whole record never goes to memory; the reverse mode (`adjoint` with a lag)
// recomputes it.
template <typename R, int Rule>
void filter_smoother(int64_t B, int64_t T, int64_t m, int velocity, R gamma, int64_t lag,
                     int projection, int threads, const void* const* in,
                     const int64_t* in_strides, const void* const* prior,
                     const int64_t* prior_strides, const Layout<R>& out) {
    using V = typename Wide<R>::type;
    View<R> given[kGiven], start[5];
    for (int q = 0; q < kGiven; ++q) given[q] = view<R>(in, in_strides, q);
    for (int q = 0; q < 5; ++q) start[q] = view<R>(prior, prior_strides, q);
    const int64_t n = 2 * m, mz = velocity ? n : m;
    const V gam = splat<V>(gamma);
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        std::vector<State<V>> xs(T + 1);
        std::vector<V> rec(20 * T), terms(22 * std::max<int64_t>(T - 1, 1));
        std::vector<Backward<V>> states((sweeps_of(T - 1, lag) + 1) * T, Backward<V>{});
        std::vector<double> totals(last - first, 0.0);  // the tracks' log-likelihoods
        for (int64_t l = first * m; l < last * m; l += LaneBlock<R>::kWidth) {
            const LaneBlock<R> lanes(l, last * m, m);
            Likelihood logs[LaneBlock<R>::kWidth];
            filter_record<R, Rule>(lanes, given, start, T, gam, xs.data(), rec.data(),
                                   out.loglik ? logs : nullptr);
            if (out.loglik)  // summed over each track's axes in order, as `forward` does
                for (int w = 0; w < lanes.count; ++w) totals[lanes.b[w] - first] += logs[w].total();
            auto at = [&](int i, int64_t t) { return rec[i * T + t]; };
            const Backward<V>* result =
                lane_backward<V>(at, T - 1, lag, projection != 0, terms, states);
            for (int64_t k = 0; k < T; ++k) {
                V now[5] = {at(18, k), at(19, k), at(0, k), at(1, k), at(2, k)};
                const State<V>& x = xs[k + 1];
                if (k < T - 1) smoothed(now, result[k]);  // the last step as filtered
                for (int w = 0; w < lanes.count; ++w) {
                    const int64_t bi = lanes.b[w], j = lanes.j[w], idx = bi * T + k;
                    write_axis(out.smooth_mean + idx * n, out.smooth_cov + idx * n * n, n, j,
                               now[0][w], now[1][w], now[2][w], now[3][w], now[4][w]);
                    if (out.mean) out.mean[idx * n + 2 * j] = x.p[w];
                    if (out.mean) out.mean[idx * n + 2 * j + 1] = x.v[w];
                    if (out.cov)
                        block_rows(out.cov + idx * n * n, n, j, x.a[w], x.b[w], x.b[w], x.c[w]);
                }
            }
            const State<V>& x = xs[T];
            for (int w = 0; w < lanes.count; ++w) {
                const int64_t bi = lanes.b[w], j = lanes.j[w];
                write_axis(out.last_mean + bi * n, out.last_cov + bi * n * n, n, j, x.p[w],
                           x.v[w], x.a[w], x.b[w], x.c[w]);
                if (!out.last_post) continue;
                R* post = out.last_post + bi * mz;
                if (velocity)
                    post[2 * j] = x.mem_p[w], post[2 * j + 1] = x.mem_v[w];
                else
                    post[j] = x.mem_p[w];
            }
        }
        if (out.loglik)
            for (int64_t bi = first; bi < last; ++bi) out.loglik[bi] = R(totals[bi - first]);
    });
}

template <typename R>
void filter_smoother_entry(int64_t B, int64_t T, int64_t m, int rule, int velocity,
                           double gamma, int threads, const void* const* in, const int64_t* s,
                           const void* const* prior, const int64_t* ps, void* const* o,
                           int64_t lag, int projection) {
    Layout<R> out{static_cast<R*>(o[0]),  static_cast<R*>(o[1]),       static_cast<R*>(o[2]),
                  static_cast<R*>(o[3]),  static_cast<R*>(o[4]),       static_cast<R*>(o[5]),
                  static_cast<R*>(o[6]),  static_cast<R*>(o[7]),       static_cast<R*>(o[8]),
                  static_cast<uint8_t*>(o[9]), static_cast<R*>(o[10]), static_cast<R*>(o[11]),
                  static_cast<R*>(o[12]), static_cast<R*>(o[13]),      static_cast<R*>(o[14]),
                  0};
    R g = static_cast<R>(gamma);
    if (rule == 0)
        filter_smoother<R, 0>(B, T, m, velocity, g, lag, projection, threads, in, s, prior, ps,
                              out);
    else
        filter_smoother<R, 1>(B, T, m, velocity, g, lag, projection, threads, in, s, prior, ps,
                              out);
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
// order, overwritten) and of γ (added to dgamma). Branch-free, as predict_correct.
template <typename X, int Rule>
inline State<X> step_adjoint(const State<X>& x, const X* g, X gamma, const Step<X>& s,
                             const State<X>& dn, const Recorded<X>& o, X* dg, X& dgamma) {
    const X zero{};
    const X dt = g[kT];
    const auto seen_p = s.fp > zero, seen_v = s.fv > zero;
    State<X> d{zero, zero, zero, zero, zero, zero, zero};
    X drp = zero, drpv = zero, drvv = zero, dyp = zero, dyv = zero;
    X da1 = o.a1, db1 = o.b1, dc1 = o.c1, dep = o.ep, dev = o.ev;
    X dpp = o.p_pred, dvp = o.v_pred, dkp = o.kp, dkc = o.kc, dkv = o.kv, dSp = o.Sp;
    for (int q = 0; q < kGiven; ++q) dg[q] = zero;
    if (Rule == 0) {
        const X kp = s.kp, kvp = s.kc, one_k = 1 - kp;
        // p' = p_pred + kp ep, v' = v_pred + kvp ep
        dpp += dn.p, dvp += dn.v;
        dkp += dn.p * s.ep, dkc += dn.v * s.ep, dep += dn.p * kp + dn.v * kvp;
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
        d.mem_p = dn.mem_p, d.mem_v = dn.mem_v;
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
    // Sp = a1 fp + rp; ep = yp − p_pred where observed
    da1 += s.fp * dSp, drp += dSp;
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
        for (int64_t l0 = first * m; l0 < end; l0 += G * W) {
            lanes.clear(), inputs.clear();
            for (int64_t l = l0; l < end && l < l0 + G * W; l += W) {
                lanes.emplace_back(l, end, m);
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
                        states[(t + 1) * G + v] =
                            predict_correct<V, Rule>(states[t * G + v], g, gam).next;
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
                    const Step<V> s = predict_correct<V, Rule>(before, g, gam);
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
                    d = step_adjoint<V, Rule>(before, g, gam, s, d, o, dg, dgam[v]);
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
    else
        adjoint<R, 1>(B, T, m, velocity, gm, smoothing, lag, threads, in, s, prior, ps, g, dg, dp,
                      dgm);
}

// One predict-correct step of a dense linear-Gaussian filter for one track:
// GaussianFilter.predict, then KalmanFilter.correct (rule 0) or SVSF.correct with an H of
// orthonormal rows, whose H⁺ is Hᵀ (rule 1). n, m ≤ kMax; every array contiguous.
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
// but for the step's own pointers (a call from Python costs about 0.1 µs per argument):
// sizes: B, n, m, rule, psi_track; a: x, P, z, memory, psi, F, Q, H, R, the 10 outs,
// total_in, total_out.
template <typename R>
int dense_step(const int64_t* sizes, double gamma, void* const* a) {
    return dense_entry<R>(sizes[0], 1, sizes[1], sizes[2], static_cast<int>(sizes[3]), gamma,
                          a[0], a[1], a[2], a[3], a[4], sizes[4], 0, a + 5, a + 9, a[19], a[20]);
}

}  // namespace

extern "C" {

// The entry points of both dtypes.
#define TORCHSVS_ENTRIES(suffix, R)                                                            \
    void forward_##suffix(int64_t B, int64_t T, int64_t m, int rule, int velocity,            \
                          double gamma, int threads, const void* const* in, const int64_t* s, \
                          const void* const* prior, const int64_t* ps, void* const* o,        \
                          int smoothing) {                                                    \
        forward_entry<R>(B, T, m, rule, velocity, gamma, threads, in, s, prior, ps, o,        \
                         smoothing);                                                          \
    }                                                                                         \
    void adjoint_##suffix(int64_t B, int64_t T, int64_t m, int rule, int velocity,            \
                          double gamma, int threads, const void* const* in, const int64_t* s, \
                          const void* const* prior, const int64_t* ps, void* const* grads,    \
                          void* const* dgiven, void* const* dprior, void* dgamma,             \
                          int smoothing, int64_t lag) {                                       \
        adjoint_entry<R>(B, T, m, rule, velocity, gamma, smoothing, lag, threads, in, s, prior, \
                         ps, grads, dgiven, dprior, dgamma);                                  \
    }                                                                                         \
    void filter_smoother_##suffix(int64_t B, int64_t T, int64_t m, int rule, int velocity,    \
                                  double gamma, int threads, const void* const* in,           \
                                  const int64_t* s, const void* const* prior,                 \
                                  const int64_t* ps, void* const* o, int64_t lag,             \
                                  int projection) {                                           \
        filter_smoother_entry<R>(B, T, m, rule, velocity, gamma, threads, in, s, prior, ps, o,  \
                                 lag, projection);                                            \
    }                                                                                         \
    void backward_adjoint_##suffix(int64_t B, int64_t T, int64_t m, int64_t lag,             \
                                   int projection, int threads, const void* const* in,        \
                                   const int64_t* s, const void* g_mean, const void* g_cov,   \
                                   void* const* dgiven) {                                     \
        backward_adjoint<R>(B, T, m, lag, projection, threads, in, s,                         \
                            static_cast<const R*>(g_mean), static_cast<const R*>(g_cov),      \
                            reinterpret_cast<R* const*>(dgiven));                             \
    }                                                                                         \
    void rts_interval_##suffix(int64_t B, int64_t T, int64_t m, int threads,                  \
                               const void* const* in, const int64_t* s, void* mean,           \
                               void* cov) {                                                   \
        rts_interval<R>(B, T, m, threads, in, s, static_cast<R*>(mean),                       \
                        static_cast<R*>(cov));                                                \
    }                                                                                         \
    void backward_##suffix(int64_t B, int64_t T, int64_t m, int64_t lag, int projection,      \
                           int threads, const void* const* in, const int64_t* s, void* mean,  \
                           void* cov) {                                                       \
        backward<R>(B, T, m, lag, projection, threads, in, s, static_cast<R*>(mean),          \
                    static_cast<R*>(cov));                                                    \
    }                                                                                         \
    int dense_run_##suffix(int64_t B, int64_t T, int64_t n, int64_t m, int rule, double gamma, \
                           const void* x, const void* P, const void* z, const void* memory,   \
                           const void* psi, int64_t psi_track, int64_t psi_step,              \
                           const void* const* consts, void* o0, void* o1, void* o2, void* o3, \
                           void* o4, void* o5, void* o6, void* o7, void* o8, void* o9,        \
                           const void* total_in, void* total_out) {                           \
        void* const outs[10] = {o0, o1, o2, o3, o4, o5, o6, o7, o8, o9};                      \
        return dense_entry<R>(B, T, n, m, rule, gamma, x, P, z, memory, psi, psi_track,       \
                              psi_step, consts, outs, total_in, total_out);                   \
    }                                                                                          \
    int dense_step_##suffix(const int64_t* sizes, double gamma, void* const* a) {             \
        return dense_step<R>(sizes, gamma, a);                                                \
    }

TORCHSVS_ENTRIES(f32, float)
TORCHSVS_ENTRIES(f64, double)
#undef TORCHSVS_ENTRIES

}  // extern "C"

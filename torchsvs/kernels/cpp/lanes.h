// Lanes and layouts: what every compiled loop of the per-axis kernel shares (part of fused.cpp,
// the one compiled unit). A lane is one (track, axis) pair; its inputs are [B, T, m] views
// (View), vectors of lanes run the same code lane by lane (Wide, LaneBlock), large batches run
// on threads (over_tracks), and outputs go to the general layout (Layout, write_axis).
#pragma once

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
// templates on R, and with R a vector of W lanes (GCC/Clang vector extensions) the same code
// runs W lanes at once, element by element, so each lane gets exactly the numbers it gets
// alone, whatever W. A vector is one of the machine's registers (the library is built for the
// machine it runs on): wider than that, GCC splits the arithmetic but turns each `mask ? a : b`
// into a branch per lane through memory. On AVX2 (2026-12), 64 bytes against 32: the SURE
// curves' pass 16.9 against 8.1 ns per lane-step, `track --estimator ks` on 10^6 rows 0.53
// against 0.30 s of estimating. A block's lanes are gathered from the inputs and scattered to
// the outputs; a short last block repeats its last lane.
#if defined(__AVX512F__)
constexpr int kVectorBytes = 64;
#elif defined(__AVX__)
constexpr int kVectorBytes = 32;
#else
constexpr int kVectorBytes = 16;
#endif
template <typename R>
struct Wide;
template <>
struct Wide<float> {
    typedef float type __attribute__((vector_size(kVectorBytes)));
};
template <>
struct Wide<double> {
    typedef double type __attribute__((vector_size(kVectorBytes)));
};
template <typename R>
struct LaneBlock {
    static constexpr int kWidth = sizeof(typename Wide<R>::type) / sizeof(R);
    int64_t b[kWidth], j[kWidth];  // each lane's track and axis
    int count;                     // lanes that are real (the rest repeat the last)
    int64_t m;                     // axes per track

    // The lanes [l, min(l + per, end)) of lane index track · m + axis (per: lanes_per_vector).
    LaneBlock(int64_t l, int64_t end, int64_t m, int64_t per = kWidth)
        : count(static_cast<int>(std::min<int64_t>(per, end - l))), m(m) {
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

// The lanes a vector takes: all kWidth, or (`whole_tracks`: a rule that couples a track's axes,
// the variable boundary layer's) the most whole tracks that fit, so that a vector started at a
// track's first lane holds each of its tracks whole (m <= kWidth).
template <typename R>
inline int64_t lanes_per_vector(int64_t m, bool whole_tracks) {
    return whole_tracks ? LaneBlock<R>::kWidth / m * m : LaneBlock<R>::kWidth;
}

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

}  // namespace

// Each track's measurement noise read off its own positions (part of fused.cpp):
// torchsvs/datasets/track_noise.py's _read_chunk over datasets/differences.py's
// difference_residuals, track by track, in the same operations in the same order, so each
// track's reading is the tensor code's to the bit (tests/test_track_noise.py holds them
// equal). The tensor code is the formulas' home and the path where this is unavailable; it
// runs some hundred tensor operations over every residual, this one pass a track.
//
// Per track: the divided differences of each order k (orders given, in order) over each k + 1
// successive observed positions of an axis, at their own times t (the intervals' running
// sums), scaled to unit noise gain (u), kept where u and its white-acceleration weight b are
// finite; then the noise-alone fit of one scale of r per track: started from the lower median
// of the top order's u²/r over chi2_median (1 where none), `iterations` times moved to the
// mean of u²/(κ r) over the residuals with u² ≤ cutoff2 · scale · r whose stencil shares no
// step with one beyond maneuver2 · scale · r (any axis, any order).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "lanes.h"

namespace {

struct NoiseResidual {
    double u2, r;    // the residual squared, its axis's variance
    int64_t order;   // its order
    int64_t first;   // the step of its stencil's first point
    int64_t last;    // and of its last
};

// Left folds, as functools.reduce over a list of tensors.
inline double fold_product(const double* x, int n) {
    double out = x[0];
    for (int i = 1; i < n; ++i) out = out * x[i];
    return out;
}

// The highest order the stencils' fixed arrays hold (kernels/track_noise.py leaves higher ones
// to the tensors).
constexpr int64_t kMaxOrder = 7;

// One axis's observed positions, their times and steps, in time order (z and t of a track's
// T steps, z's `stride` apart): what difference_residuals' _observed_first moves to the front.
struct Observed {
    std::vector<double> z, t;
    std::vector<int64_t> steps;
    void read(int64_t T, int64_t stride, const double* zs, const double* ts) {
        z.clear(), t.clear(), steps.clear();
        for (int64_t s = 0; s < T; ++s) {
            const double value = zs[s * stride];
            if (!std::isfinite(value)) continue;
            z.push_back(value), t.push_back(ts[s]), steps.push_back(s);
        }
    }
};

// The divided differences of order k (at most kMaxOrder) over each k + 1 successive observed
// positions of one axis: `emit(col, u, b, first, last)` for each stencil (col: its first
// position's place among the observed), u and b as difference_residuals computes them, finite
// or not.
template <typename Emit>
inline void stencils(int64_t k, const Observed& x, const Emit& emit) {
    const int64_t count = static_cast<int64_t>(x.z.size());
    double times[kMaxOrder + 1], w[kMaxOrder + 1], c[kMaxOrder + 1], knots[kMaxOrder + 1];
    double terms[kMaxOrder];
    for (int64_t col = 0; col + k < count; ++col) {
        const double start = x.t[col];
        for (int64_t i = 0; i <= k; ++i) times[i] = x.t[col + i] - start;
        for (int64_t i = 0; i <= k; ++i) {  // w_i = 1 / prod_{l != i} (t_i - t_l)
            int n = 0;
            for (int64_t l = 0; l <= k; ++l)
                if (l != i) terms[n++] = times[i] - times[l];
            w[i] = 1.0 / fold_product(terms, n);
        }
        double norm = w[0] * w[0];
        for (int64_t i = 1; i <= k; ++i) norm = norm + w[i] * w[i];
        norm = std::sqrt(norm);
        for (int64_t i = 0; i <= k; ++i) c[i] = w[i] / norm;
        for (int64_t l = 0; l < k; ++l) {  // the Peano kernel at each knot
            double K = c[l + 1] * (times[l + 1] - times[l]);
            for (int64_t i = l + 2; i <= k; ++i) K = K + c[i] * (times[i] - times[l]);
            knots[l] = K;
        }
        knots[k] = 0.0;
        double b = 0.0;
        for (int64_t l = 0; l < k; ++l) {
            const double a = knots[l], e = knots[l + 1];
            const double term = (times[l + 1] - times[l]) * (a * a + a * e + e * e);
            b = l == 0 ? term : b + term;
        }
        b = b / 3.0;
        double u = c[0] * x.z[col];
        for (int64_t i = 1; i <= k; ++i) u = u + c[i] * x.z[col + i];
        emit(col, u, b, x.steps[col], x.steps[col + k]);
    }
}

// One track's finite residuals in difference_residuals' order (orders, then axes, then
// stencils), each axis's observed positions read once (`axes`: m of them).
inline void track_residuals(int64_t T, int64_t m, const double* z, const double* t,
                            const double* r, const int64_t* orders, int64_t n_orders,
                            std::vector<NoiseResidual>& out, std::vector<Observed>& axes) {
    out.clear();
    for (int64_t j = 0; j < m; ++j) axes[j].read(T, m, z + j, t);
    for (int64_t o = 0; o < n_orders; ++o) {
        const int64_t k = orders[o];
        if (T <= k) continue;
        for (int64_t j = 0; j < m; ++j)
            stencils(k, axes[j], [&](int64_t, double u, double b, int64_t first, int64_t last) {
                if (std::isfinite(u) && std::isfinite(b))
                    out.push_back({u * u, r[j], k, first, last});
            });
    }
}

// difference_residuals' residuals of every lane (track axis) of z [B, T, m] at the times t
// [B, T] (contiguous float64), each written at [o, lane, col] of the [K, B m, T] outputs:
// u, b, the first and last steps of its stencil, and ok (1 where u and b are finite, 0 where
// not or no stencil).
inline void residuals_entry(int64_t B, int64_t T, int64_t m, int threads, const double* z,
                            const double* t, const int64_t* orders, int64_t n_orders, double* u,
                            double* b, int64_t* first, int64_t* last, uint8_t* ok) {
    const int64_t lanes = B * m;
    over_tracks(B, threads, [&](int64_t from, int64_t to) {
        Observed axis;
        for (int64_t lane = from * m; lane < to * m; ++lane) {
            const int64_t track = lane / m, j = lane % m;
            axis.read(T, m, z + track * T * m + j, t + track * T);
            for (int64_t o = 0; o < n_orders; ++o) {
                const int64_t row = (o * lanes + lane) * T;
                std::fill(ok + row, ok + row + T, 0);
                if (T <= orders[o]) continue;
                stencils(orders[o], axis,
                         [&](int64_t col, double uu, double bb, int64_t f, int64_t l) {
                             const int64_t at = row + col;
                             u[at] = uu, b[at] = bb, first[at] = f, last[at] = l;
                             ok[at] = std::isfinite(uu) && std::isfinite(bb) ? 1 : 0;
                         });
            }
        }
    });
}

// z [B, T, m] and t [B, T] contiguous float64 (NaN: missing), r [m]; writes each track's
// scale [B] and its kept residuals' count [B] after the last iteration, and its top-order
// residuals' count [B].
inline void track_noise_entry(int64_t B, int64_t T, int64_t m, int threads, const double* z,
                              const double* t, const double* r, const int64_t* orders,
                              int64_t n_orders, int64_t top, double kappa, double chi2_median,
                              double cutoff2, double maneuver2, int iterations, double* scale_out,
                              double* count_out, int64_t* top_out) {
    over_tracks(B, threads, [&](int64_t first, int64_t last) {
        std::vector<NoiseResidual> res;
        std::vector<Observed> axes(m);
        std::vector<double> tops;
        std::vector<int64_t> edges(T + 2), seen(T + 2);
        for (int64_t b = first; b < last; ++b) {
            track_residuals(T, m, z + b * T * m, t + b * T, r, orders, n_orders, res, axes);
            tops.clear();
            for (const NoiseResidual& x : res)
                if (x.order == top) tops.push_back(x.u2 / x.r);
            top_out[b] = static_cast<int64_t>(tops.size());
            double scale = NAN;
            if (!tops.empty()) {  // the lower median
                const auto middle = tops.begin() + (tops.size() - 1) / 2;
                std::nth_element(tops.begin(), middle, tops.end());
                scale = *middle / chi2_median;
            }
            if (!(std::isfinite(scale) && scale > 0)) scale = 1.0;
            double count = 0.0;
            for (int it = 0; it < iterations; ++it) {
                // the steps a stencil beyond maneuver2 covers, and how many up to each step
                std::fill(edges.begin(), edges.end(), 0);
                bool any_far = false;
                for (const NoiseResidual& x : res)
                    if (x.u2 > maneuver2 * (scale * x.r))
                        ++edges[x.first], --edges[x.last + 1], any_far = true;
                int64_t running = 0, covered = 0;
                seen[0] = 0;
                for (int64_t s = 0; s <= T; ++s) {
                    running += edges[s];
                    covered += running > 0 ? 1 : 0;
                    seen[s + 1] = covered;
                }
                count = 0.0;
                double total = 0.0;
                for (const NoiseResidual& x : res) {
                    const double v = scale * x.r;
                    const bool touching = any_far && seen[x.last + 1] - seen[x.first] > 0;
                    const bool keep = x.u2 <= cutoff2 * v && !touching;
                    count = count + (keep ? 1.0 : 0.0);
                    total = total + (keep ? x.u2 / kappa : 0.0) / x.r;
                }
                const double ratio = total / count;
                if (std::isfinite(ratio) && ratio > 0) scale = ratio;
            }
            scale_out[b] = scale, count_out[b] = count;
        }
    });
}

}  // namespace

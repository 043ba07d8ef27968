// The trimmed Gaussian fit's weighted sums of the noise read off the data (part of fused.cpp):
// torchsvs/datasets/noise_estimate.py's _sums, one scoring step of every jackknife refit at once
// (the tensor code is their home, and the path without a compiler). For each fit g of G (a
// jackknife refit leaves out the residuals of its own group; G = 1 without groups: all of
// them), over the N residuals:
//   v_i     = r[g, axis_i] + b_i q[g]                                the model variance
//   far_i   = u2_i > maneuver2 v_i                                   a maneuver
//   kept_i  = u2_i <= cutoff2 v_i and no far stencil shares a step with i's (_kept, _touching)
//   w_i     = kept_i / v_i²
// it writes A[g] = Σ w_i cols_i cols_iᵀ [p, p], rhs[g] = Σ (w_i y_i) cols_i [p] (the normal
// equations of the scoring step), and per order k the sums of kept_i y_i / v_i and of kept_i
// (_per_order's). The sums run in residual order (the tensor code's matrix products sum in
// their own: the last bits may differ). The fits are the inner loop, held in arrays [.., G],
// so one pass over the residuals serves all of them and the compiler vectorises across fits;
// the far stencils are few, so the steps they cover are marked with a bit per fit.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

// At most this many fits in one call (a bit each in the covered steps' masks).
constexpr int64_t kMaxFits = 64;

// u2, y, b [N] float64 (b >= 0); cols [N, p]; axis, first, last (the stencils' steps as one
// numbering of size `steps`), order (0..K-1) [N] int64; group [N] int64 or null; r [G, m] and
// q [G] (>= 0); G at most kMaxFits. `Fits` is G where known when compiled (1: the full fit,
// whose loops over the fits then vanish), else 0.
template <int64_t Fits>
void trimmed_sums_of(int64_t N, int64_t G, int64_t m, int64_t p, int64_t K, int64_t steps,
                     const double* u2, const double* y, const double* b, const double* cols,
                     const int64_t* axis, const int64_t* first, const int64_t* last,
                     const int64_t* order, const int64_t* group, const double* r, const double* q,
                     double cutoff2, double maneuver2, double* A, double* rhs, double* ratio,
                     double* count) {
    if (Fits) G = Fits;
    // each axis's variances and the q's, fit by fit; the least of each (a bound below v)
    std::vector<double> R(m * G), lowest_r(m);
    double lowest_q = q[0];
    for (int64_t g = 0; g < G; ++g) lowest_q = std::min(lowest_q, q[g]);
    for (int64_t j = 0; j < m; ++j) {
        lowest_r[j] = r[j];
        for (int64_t g = 0; g < G; ++g)
            R[j * G + g] = r[g * m + j], lowest_r[j] = std::min(lowest_r[j], r[g * m + j]);
    }
    // the steps each fit's far stencils cover (bit g), marked stencil by stencil
    std::vector<uint64_t> covered(steps + 1, 0);
    bool any_far = false;
    for (int64_t i = 0; i < N; ++i) {
        const double* Rj = &R[axis[i] * G];
        // v is at least this at every fit (rounding is monotone), so most stencils need no more
        if (!(u2[i] > maneuver2 * (lowest_r[axis[i]] + b[i] * lowest_q))) continue;
        uint64_t far = 0;
        for (int64_t g = 0; g < G; ++g) {
            const double v = Rj[g] + b[i] * q[g];
            if (u2[i] > maneuver2 * v && (group == nullptr || group[i] != g)) far |= uint64_t(1) << g;
        }
        if (!far) continue;
        any_far = true;
        for (int64_t s = first[i]; s <= last[i]; ++s) covered[s] |= far;
    }
    std::vector<double> sA(p * p * G, 0.0), sR(p * G, 0.0), sRatio(K * G, 0.0), sCount(K * G, 0.0);
    std::vector<double> free_(G), weight(G), weight_y(G), part(G), kept_(G);
    double* __restrict open = free_.data();  // 1 where the fit may keep the residual
    double* __restrict w = weight.data();
    double* __restrict wy = weight_y.data();
    double* __restrict share = part.data();
    double* __restrict keep = kept_.data();
    const double* __restrict Q = q;
    for (int64_t i = 0; i < N; ++i) {
        const double* __restrict Rj = &R[axis[i] * G];
        const double* c = cols + i * p;
        uint64_t touch = 0;
        if (any_far)
            for (int64_t s = first[i]; s <= last[i]; ++s) touch |= covered[s];
        for (int64_t g = 0; g < G; ++g) open[g] = (touch >> g) & 1 ? 0.0 : 1.0;
        if (group != nullptr) open[group[i]] = 0.0;
        const double ui = u2[i], yi = y[i], bi = b[i];
        for (int64_t g = 0; g < G; ++g) {  // (vectorised across the fits)
            const double v = Rj[g] + bi * Q[g];
            const double k = ui <= cutoff2 * v ? open[g] : 0.0;
            keep[g] = k;
            w[g] = k / (v * v);
            wy[g] = w[g] * yi;
            share[g] = k * yi / v;  // (as the tensor code: 0 / v where not kept)
        }
        for (int64_t a = 0; a < p; ++a) {
            for (int64_t e = 0; e < p; ++e) {
                const double ce = c[a] * c[e];
                double* __restrict to = &sA[(a * p + e) * G];
                for (int64_t g = 0; g < G; ++g) to[g] += w[g] * ce;
            }
            double* __restrict to = &sR[a * G];
            for (int64_t g = 0; g < G; ++g) to[g] += wy[g] * c[a];
        }
        double* __restrict ratio_k = &sRatio[order[i] * G];
        double* __restrict count_k = &sCount[order[i] * G];
        for (int64_t g = 0; g < G; ++g) ratio_k[g] += share[g], count_k[g] += keep[g];
    }
    for (int64_t g = 0; g < G; ++g) {
        for (int64_t ae = 0; ae < p * p; ++ae) A[g * p * p + ae] = sA[ae * G + g];
        for (int64_t a = 0; a < p; ++a) rhs[g * p + a] = sR[a * G + g];
        for (int64_t k = 0; k < K; ++k)
            ratio[g * K + k] = sRatio[k * G + g], count[g * K + k] = sCount[k * G + g];
    }
}

// trimmed_sums_of: 0, or 1 where G is above kMaxFits.
inline int trimmed_sums_entry(int64_t N, int64_t G, int64_t m, int64_t p, int64_t K,
                              int64_t steps, const double* u2, const double* y, const double* b,
                              const double* cols, const int64_t* axis, const int64_t* first,
                              const int64_t* last, const int64_t* order, const int64_t* group,
                              const double* r, const double* q, double cutoff2, double maneuver2,
                              double* A, double* rhs, double* ratio, double* count) {
    if (G > kMaxFits) return 1;
    auto run = G == 1 ? trimmed_sums_of<1> : trimmed_sums_of<0>;
    run(N, G, m, p, K, steps, u2, y, b, cols, axis, first, last, order, group, r, q, cutoff2,
        maneuver2, A, rhs, ratio, count);
    return 0;
}

}  // namespace

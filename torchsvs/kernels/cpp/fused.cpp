// The compiled loops of torchsvs: the one compiled unit, built and loaded by
// torchsvs/kernels/build.py (g++ -O3, ctypes). It holds the C interface; the loops are in one
// header per concern, in this directory:
//   lanes.h          views, vectors of lanes, threads, the general layout
//   axis_step.h      one predict-correct step of a lane (axes._forward_step's twin)
//   axis_smoother.h  the backward recursions (axes_smoother's twins)
//   axis_filter.h    the forward loops over all steps
//   curves.h         the Kalman smoother's SURE curves (kernels/curves.py)
//   adjoints.h       the hand-written reverse modes of the per-axis loops
//   dense.h          the dense linear filters' step (online steps, dense runs)
//   imm.h            the IMM(CV, CT) of `track --estimator imm` and Kim's smoother (float64)
//   track_noise.h    each track's noise read off its positions (float64)
//   noise_fit.h      the sums of the trimmed fit of the noise read off the data (float64)
//
// The per-axis kernel: each (track, axis) pair is an independent lane of two-state steps;
// blocks of lanes step together (a loop the compiler vectorises) and every step costs a few
// dozen flops instead of a few dozen tensor operations. The formulas are those of
// torchsvs/kernels/axes.py and axes_smoother.py, transcribed line by line (the Python
// functions named in the comments are their home and the differentiable path); tests hold
// both to 1e-10 in float64.
//
// Every array input is a pointer and three element strides (track, step, axis) into a
// [B, T, m] view, so broadcast inputs (stride 0) need no copies. Outputs are contiguous, in
// the general layout (state p1, v1, p2, v2, ...; block-diagonal covariances and gains): what
// a FilterResult holds, written once, with no assembly pass after. Large batches run on
// threads, split by tracks.

#include "lanes.h"
#include "axis_step.h"
#include "axis_smoother.h"
#include "axis_filter.h"
#include "curves.h"
#include "adjoints.h"
#include "dense.h"
#include "imm.h"
#include "track_noise.h"
#include "noise_fit.h"

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
    }                                                                                         \
    void kalman_curves_##suffix(int64_t B, int64_t T, int64_t m, int64_t K, int smooth,       \
                                int threads, const void* const* in, const int64_t* s,         \
                                void* risk, void* mean, void* var, void* first_two,           \
                                int64_t chunk, void* sums, void* student,                     \
                                double max_leverage, void* step_risk) {                       \
        kalman_curves<R>(B, T, m, K, smooth, threads, in, s, static_cast<R*>(risk),           \
                         static_cast<R*>(mean), static_cast<R*>(var),                         \
                         static_cast<R*>(first_two), chunk, static_cast<R*>(sums),            \
                         static_cast<R*>(student), max_leverage,                              \
                         static_cast<R*>(step_risk));                                         \
    }                                                                                         \
    /* how many lanes a vector steps together (lanes.h's kWidth): the most axes a rule that \
       couples a track's axes runs compiled */                                                \
    int lane_width_##suffix() { return LaneBlock<R>::kWidth; }

TORCHSVS_ENTRIES(f32, float)
TORCHSVS_ENTRIES(f64, double)
#undef TORCHSVS_ENTRIES

// The IMM(CV, CT) and its smoother, float64 only (imm.h; torchsvs/kernels/fused_imm.py).
int turn_imm_f64(int64_t B, int64_t T, int64_t ndim, int64_t lag, int cov, int threads,
                 const double* params, const void* const* in, int64_t dt_track, int64_t dt_step,
                 void* const* out) {
    if (ndim == 2) return turn_imm_of<2>(B, T, lag, cov, threads, params, in, dt_track, dt_step, out);
    if (ndim == 3) return turn_imm_of<3>(B, T, lag, cov, threads, params, in, dt_track, dt_step, out);
    return 3;
}

// Each track's noise reading, float64 only (track_noise.h; torchsvs/kernels/track_noise.py).
void track_noise_f64(int64_t B, int64_t T, int64_t m, int threads, const double* z,
                     const double* t, const double* r, const int64_t* orders, int64_t n_orders,
                     int64_t top, double kappa, double chi2_median, double cutoff2,
                     double maneuver2, int iterations, double* scale, double* count,
                     int64_t* top_count) {
    track_noise_entry(B, T, m, threads, z, t, r, orders, n_orders, top, kappa, chi2_median,
                      cutoff2, maneuver2, iterations, scale, count, top_count);
}
// The divided differences the noise is read from, float64 only (track_noise.h).
void difference_residuals_f64(int64_t B, int64_t T, int64_t m, int threads, const double* z,
                              const double* t, const int64_t* orders, int64_t n_orders,
                              double* u, double* b, int64_t* first, int64_t* last,
                              uint8_t* ok) {
    residuals_entry(B, T, m, threads, z, t, orders, n_orders, u, b, first, last, ok);
}
// The trimmed fit's weighted sums, float64 only (noise_fit.h): 0, or 1 above kMaxFits fits.
int trimmed_sums_f64(int64_t N, int64_t G, int64_t m, int64_t p, int64_t K, int64_t steps,
                     const double* u2, const double* y, const double* b, const double* cols,
                     const int64_t* axis, const int64_t* first, const int64_t* last,
                     const int64_t* order, const int64_t* group, const double* r,
                     const double* q, double cutoff2, double maneuver2, double* A, double* rhs,
                     double* ratio, double* count) {
    return trimmed_sums_entry(N, G, m, p, K, steps, u2, y, b, cols, axis, first, last, order,
                              group, r, q, cutoff2, maneuver2, A, rhs, ratio, count);
}
}  // extern "C"

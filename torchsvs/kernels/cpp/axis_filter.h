// The per-axis kernel's forward loops (part of fused.cpp): the filter over all steps (twin of
// torchsvs/kernels/axes.py's tensor loop in run_axes), with the one-step-lag smoothing as it
// steps, and the filter with the smoother's general recursion in one pass (filter_smoother).
#pragma once

#include "axis_smoother.h"

namespace {

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

// axes._forward_step over all steps, writing the general layout. Rule (axis_step.h): 0
// Kalman (position-only), 1 SVSF, 2 the variable boundary layer. `velocity`: the corrector measures velocities too (H = I, m_z = n),
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
                    step_lanes<R, Rule>(lanes, m, gamma, g, r);
                    if (smoothing && t > 0) {
                        if (projection)
                            smooth_lanes<R, true>(lanes, g, r, moments);
                        else
                            smooth_lanes<R, false>(lanes, g, r, moments);
                    }
                    if (Rule != 1)
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
    else if (rule == 1)
        forward_axes<R, 1>(B, T, m, velocity, g, threads, in, s, prior, ps, out);
    else
        forward_axes<R, 2>(B, T, m, velocity, g, threads, in, s, prior, ps, out);
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
        const V inflation = Rule == 2
                                ? track_inflation(lanes, wanted_inflation<V>(xs[t], g, gamma))
                                : splat<V>(1.0);
        const Step<V> s = predict_correct<V, Rule>(xs[t], g, gamma, inflation);
        xs[t + 1] = s.next;
        const V row[20] = {s.next.a, s.next.b, s.next.c, s.a1,    s.b1,    s.c1,    s.kp,
                           zero,     s.kc,     s.kv,     g[kRp],  g[kRpv], g[kRvv], s.fp,
                           s.fv,     g[kT],    s.ep,     s.ev,    s.next.p, s.next.v};
        for (int i = 0; i < 20; ++i) rec[i * T + t] = row[i];
        if (Rule != 1 && logs)
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
        const int64_t per = lanes_per_vector<R>(m, Rule == 2);
        for (int64_t l = first * m; l < last * m; l += per) {
            const LaneBlock<R> lanes(l, last * m, m, per);
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
    else if (rule == 1)
        filter_smoother<R, 1>(B, T, m, velocity, g, lag, projection, threads, in, s, prior, ps,
                              out);
    else
        filter_smoother<R, 2>(B, T, m, velocity, g, lag, projection, threads, in, s, prior, ps,
                              out);
}

}  // namespace

"""Each step's own ``q``: the Kalman smoother's ``q`` chosen by SURE over a window of steps.

One ``q`` per track serves a track that flies level for ten minutes and then turns badly: the
turn wants a ``q`` the level flight is noisier with. Here the smoother runs at each of the
factors :data:`~torchsvs.fitting.noise.Q_FACTORS` on the file's ``q`` (one compiled pass
each), and each step's estimate is a blend of the passes', weighted by their SURE
(:mod:`torchsvs.accuracy`: squared residual ``+ 2 r ∂x̂/∂z − r`` per observed component, the
divergence exact from the pass's covariances and its tangents) summed over the ``window`` steps
around it: a softmax of minus those sums over :data:`WEIGHT_SCALE` measurement variances, so
the pass of the least SURE weighs most and near-ties share (the least alone was 0.7% worse).

The step's own term is left out of its weights, so the term it adds to the run's SURE is that of
an estimate weighted by other steps' residuals: the composite's SURE (what the run reports and
what :func:`choose_window` compares) stays close to unbiased, where the window's sums with the
step in would score it by its own noise. With its weights held fixed the estimate at each step
is linear in the measurements, its divergence there the weighted sum of the passes'.

The window is counted in the smoother's memory: ``span / h̄`` steps (at least
:data:`MIN_WINDOW`), ``h̄`` the mean leverage (position variance over ``r``) of the smoother at
each track's own ``q``, about the reciprocal of the number of measurements it averages.
:func:`choose_window` keeps a window only where the sample's SURE says it beats each track's own
``q`` at every noise level the reading allows. Measured on the recorded-tracks benchmark (44
aircraft runs: 11 sets × 4 modes), against each track's own ``q``: 0.956× on average, 0.90× at
best (airliners at their own report times, σ 100 m), never above 1.00×; on a held-out draw of
the same kinds (seed 1, 22 runs) 0.958× and never above 1.00×; on the simulated vehicles
0.989× (0.96× on the ships at σ 10 m), never above 1.00× (``experiments/results/
recorded_tracks.md``, ``recorded_vehicles.md``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.accuracy import CHUNK, chunk_sum_array, exact_divergence, sure
from torchsvs.fitting import noise

#: The windows :func:`choose_window` tries, in the smoother's memories (``1 / h̄`` steps).
WINDOW_SPANS = (8.0, 16.0)
#: The fewest steps of a window. Where the smoother follows each measurement closely (``h̄``
#: near 1, sparse reports), a window of a few steps scores its choice on the neighbours'
#: residuals, which share the step's own noise through the smoother: on airliners at irregular
#: 1-10 s reports (``h̄`` 0.76) a window of 5 steps (each step the least alone) estimated its
#: error 4% low and was 0.5% worse than each track's own ``q`` by the truth; 11 steps and more
#: were 0.99×.
MIN_WINDOW = 11
#: The softness of a step's weights on the factors (:func:`window_weights`), in measurement
#: variances of windowed SURE: a pass a variance worse over the window weighs 1/e of the best.
#: Measured by the truth on the recorded-tracks benchmark's 11 aircraft sets (a window of 8
#: memories, against each track's own ``q``): the least alone 0.972×, weights at 0.25, 0.5, 1
#: and 2 variances 0.969, 0.967, 0.964, 0.964×; on the 8 vehicle sets 0.985× and 0.982, 0.981,
#: 0.980, 0.981× (the 1 s scans and the walkers, where the least alone lost, lost less).
WEIGHT_SCALE = 1.0


class WindowedRuns(NamedTuple):
    """What :func:`windowed_runs` gives."""

    runs: noise.CurveRuns  #: the composite's means, position variances and SURE sums
    #: [B] float64 each track's factors on ``q``, their geometric mean over its observed steps
    #: (1 for a track with none): what the run reports as the track's factor
    factor: Tensor
    weights: Tensor  #: [K, B, T] each step's weights on the factors' passes


def box_sums(x: Tensor, window: int) -> Tensor:
    """``x [..., T]`` summed over the ``window`` steps centred on each step (fewer at the
    ends)."""
    T = x.shape[-1]
    half = min(window // 2, T)
    total = torch.nn.functional.pad(x.cumsum(-1), (1, 0))  # [..., T + 1]
    upper = torch.cat([total[..., half + 1 :], total[..., -1:].expand(*x.shape[:-1], half)], -1)
    lower = torch.nn.functional.pad(total[..., : T - half], (half, 0))
    return upper[..., :T] - lower


class _FirstTwo(NamedTuple):
    """Where each axis's first two observations are: ``at [B, 2, m]`` their steps (0 where
    none), ``real [B, 2, m]`` whether there is one."""

    at: Tensor
    real: Tensor


def _first_two(z: Tensor) -> _FirstTwo:
    observed = ~torch.isnan(z)
    seen = observed.cumsum(1)
    found = [(observed & (seen == j + 1)) for j in (0, 1)]
    at = torch.stack([f.to(torch.int8).argmax(1) for f in found], 1)
    real = torch.stack([f.any(1) for f in found], 1)
    return _FirstTwo(at, real)


def step_terms(
    z: Tensor, positions: noise.curves.Positions, r: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """``[B, T, m]`` each observed component's squared residual, divergence and count (0 where
    unobserved) of a compiled pass with its tangents: the divergence its position variance over
    ``r`` (:func:`~torchsvs.accuracy.exact_divergence`) but at each axis's first two
    observations, where it is the pass's derivative through the two-point prior
    (``first_two``)."""
    assert positions.first_two is not None, "the pass's tangents give the first two's divergence"
    observed = ~torch.isnan(z)
    firsts = _first_two(z)
    divergence = exact_divergence(z, positions.var, r)  # (NaN at the first two, unobserved)
    tangents = positions.first_two.transpose(1, 2).to(divergence.dtype)  # [B, 2, m]
    # The second, then the first: an axis observed once has no second, whose index (0) is the
    # first's step where that is the track's first; one scatter of both wrote either (a
    # one-point track's error read 0).
    for j in (1, 0):
        at = firsts.at[:, j : j + 1]
        here = divergence.gather(1, at)
        divergence.scatter_(
            1, at, torch.where(firsts.real[:, j : j + 1], tangents[:, j : j + 1], here)
        )
    residual = torch.where(observed, z - positions.mean[..., 0::2], 0.0).square()
    return residual, divergence.nan_to_num_(0.0), observed.to(z.dtype)


class _Passes(NamedTuple):
    passes: list[noise.curves.Positions]  #: the smoother's pass at each factor
    risk: Tensor  #: [K, B, T] each pass's SURE per step (its components summed)
    firsts: _FirstTwo  #: where each axis's first two observations are


def _factor_passes(
    z: Tensor, dt: Tensor, prior: Any, r: Tensor, q: float, factors: Sequence[float]
) -> _Passes | None:
    passes = []
    firsts = _first_two(z)
    risk = z.new_empty(len(factors), *z.shape[:2])
    for k, f in enumerate(factors):
        found = noise.kalman_positions(z, dt, prior.x0, prior.P0, r, q * f, True, CHUNK, risk[k])
        if found.step_risk is None:
            return None
        passes.append(found)
    return _Passes(passes, risk, firsts)


def _composite(found: _Passes, weight: Tensor) -> noise.curves.Positions:
    """The passes' means, position variances and first two observations' tangents, each step's
    weighted by ``weight [K, B, T]``: the blend's mean, and (the weights held fixed, as a step's
    own measurement does not set its weights) its derivative by each measurement, the
    ``var`` whose ratio to ``r`` is the blend's divergence."""
    at = found.firsts.at  # [B, 2, m]
    mean = var = first_two = None
    for k, p in enumerate(found.passes):  # (summed in one order, elementwise: the same bits
        assert p.first_two is not None  # whatever tracks share the batch)
        w = weight[k].unsqueeze(-1)
        there = weight[k].gather(1, at.flatten(1)).reshape(at.shape).transpose(1, 2)
        mean = w * p.mean if mean is None else mean.add_(w * p.mean)
        var = w * p.var if var is None else var.add_(w * p.var)
        tangent = there * p.first_two
        first_two = tangent if first_two is None else first_two.add_(tangent)
    assert mean is not None and var is not None
    return noise.curves.Positions(mean, var, first_two)


def window_weights(risk: Tensor, window: int, scale: float) -> Tensor:
    """``[K, B, T]`` each step's weights on the ``K`` passes: a softmax of minus each pass's
    ``risk [K, B, T]`` summed over the ``window`` steps around the step, its own left out,
    over ``scale`` (:data:`WEIGHT_SCALE` measurement variances)."""
    around = box_sums(risk, window) - risk
    odds = ((around.amin(0, keepdim=True) - around) / scale).exp_()
    total = odds[0].clone()
    for k in range(1, len(odds)):  # (not torch.softmax: its sum's order follows the batch)
        total.add_(odds[k])
    return odds.div_(total)


def windowed_runs(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float | Sequence[float],
    q: float,
    window: int,
    factors: tuple[float, ...] = noise.Q_FACTORS,
) -> WindowedRuns | None:
    """The Kalman smoother (:func:`~torchsvs.fitting.noise.kalman`) on ``z [B,
    T, m]`` (NaN: missing), intervals ``dt [B, T]``, from the tracks' two-point prior, each
    step's estimate its passes at the factors on ``q`` blended by their SURE over the
    ``window`` steps around it, its own left out (:func:`window_weights`, module doc); float64,
    :data:`~torchsvs.fitting.noise.CHUNK_CELLS` at a time.
    None where the compiled loops are unavailable (they give the divergence at each axis's
    first two observations)."""
    z64, dt64, r, prior = noise.curve_inputs(z, dt, meas_var)
    B, T, m = z64.shape
    grid = torch.tensor(factors, dtype=torch.float64)
    mean = z64.new_empty(B, T, 2 * m)
    var = z64.new_empty(B, T, m)
    weights = z64.new_empty(len(factors), B, T)
    factor = z64.new_ones(B)
    sums = z64.new_empty(B, -(-T // CHUNK), m, 3)
    usable = [True]

    def chunk(part: slice) -> None:
        zs = z64[part]
        found = _factor_passes(zs, dt64[part], _part(prior, part), r, q, factors)
        if found is None:
            usable[0] = False
            return
        weight = window_weights(found.risk, window, WEIGHT_SCALE * float(r.mean()))
        weights[:, part] = weight
        composite = _composite(found, weight)
        mean[part], var[part] = composite.mean, composite.var
        sums[part] = chunk_sum_array(step_terms(zs, composite, r), CHUNK)
        seen = (~torch.isnan(zs)).any(-1).to(torch.float64)
        logs = sum(float(g) * weight[k] for k, g in enumerate(grid.log()))
        factor[part] = ((logs * seen).sum(1) / seen.sum(1).clamp_min(1.0)).exp()

    noise.over_chunks(B, T, chunk)
    if not usable[0]:
        return None
    runs = noise.CurveRuns(mean, var, torch.ones(B, dtype=torch.bool), sums)
    return WindowedRuns(runs, factor, weights)


def _part(prior: Any, part: slice) -> Any:
    return type(prior)(*(x[part] for x in prior))


def window_sums(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float | Sequence[float],
    q: float,
    windows: Sequence[int],
    factors: tuple[float, ...] = noise.Q_FACTORS,
    lowest: Tensor | None = None,
) -> Tensor | None:
    """``[len(windows), m, 3]`` SURE's sums (squared residual, divergence, count per axis) of
    :func:`windowed_runs` at each window over every observed component (:func:`sure_of` reads
    them at any noise level); None where the compiled loops are unavailable. The tracks'
    passes run once for all the windows. ``lowest [len(windows)]``, where given, gets the
    observed steps that weigh the lowest factor's pass most at each window."""
    z64, dt64, r, prior = noise.curve_inputs(z, dt, meas_var)
    B, T, m = z64.shape
    totals = z64.new_zeros(B, len(windows), m, 3)
    at_lowest = z64.new_zeros(B, len(windows))
    usable = [True]

    def chunk(part: slice) -> None:
        found = _factor_passes(z64[part], dt64[part], _part(prior, part), r, q, factors)
        if found is None:
            usable[0] = False
            return
        for i, window in enumerate(windows):
            weight = window_weights(found.risk, window, WEIGHT_SCALE * float(r.mean()))
            composite = _composite(found, weight)
            terms = step_terms(z64[part], composite, r)
            totals[part, i] = torch.stack([x.sum(1) for x in terms], -1)
            seen = (~torch.isnan(z64[part])).any(-1)
            at_lowest[part, i] = ((weight.argmax(0) == 0) & seen).sum(1).to(z64.dtype)

    noise.over_chunks(B, T, chunk)
    if lowest is not None:
        lowest.copy_(at_lowest.sum(0))
    return totals.sum(0) if usable[0] else None


def sure_of(sums: Tensor, meas_var: Sequence[float]) -> Tensor:
    """SURE summed over the components of the sums ``[..., m, 3]`` (squared residual,
    divergence, count per axis; any leading dimensions summed but the first) at the noise
    variances ``meas_var [m]``: ``[len(sums)]``, or a scalar for sums of one run."""
    r = torch.as_tensor(meas_var, dtype=torch.float64)
    risk = sure(sums[..., 0], sums[..., 1], sums[..., 2], r)
    return risk.reshape(len(risk), -1).sum(1) if risk.dim() > 1 else risk.sum()


def spans_to_windows(mean_leverage: float, spans: Sequence[float] = WINDOW_SPANS) -> list[int]:
    """The windows (odd step counts, at least :data:`MIN_WINDOW`) of ``spans`` smoother
    memories, a memory ``1 / mean_leverage`` steps."""
    out = []
    for span in spans:
        steps = min(span / max(mean_leverage, 1e-9), 1e9)
        out.append(max(MIN_WINDOW, 2 * int(steps // 2) + 1))
    return sorted(set(out))


def choose_window(
    z: Tensor,
    dt: Tensor,
    meas_var: Sequence[float],
    q: float,
    own: noise.CurveRuns,
    noise_range: tuple[list[float], list[float]] | None = None,
    factors: tuple[float, ...] = noise.Q_FACTORS,
    lowest: list[float] | None = None,
) -> int | None:
    """The window of :data:`WINDOW_SPANS` (in memories of ``own``, the pass at each track's own
    ``q`` with its chunk sums) whose :func:`windowed_runs` has the least SURE on the tracks,
    where that is below ``own``'s at the noise ``meas_var`` and, where given, at both ends of
    ``noise_range`` (the noise reading's interval, :func:`~torchsvs.fitting.defaults.
    meas_var_range`: SURE weighs the divergence by the noise, and a window follows the data
    more; on airliners at 10 s scans and σ 3 m, the noise read as 5 ± 7.6 m, a window chosen
    at the reading alone was 1.027× each track's own ``q`` by the truth); else None. None
    also where the compiled loops are unavailable. ``lowest``, where given, gets the share of
    the observed steps that weigh the lowest factor most at the window chosen."""
    if own.sums is None:
        return None
    observed = ~torch.isnan(z)
    r = torch.as_tensor(meas_var, dtype=torch.float64)
    seen = int(observed.sum())
    if not seen:
        return None
    leverage = float(torch.where(observed, own.position_var / r, 0.0).sum()) / seen
    windows = spans_to_windows(leverage)
    at_lowest = torch.zeros(len(windows), dtype=torch.float64)
    found = window_sums(z, dt, meas_var, q, windows, factors, at_lowest)
    if found is None:
        return None
    best = int(sure_of(found, meas_var).argmin())
    if lowest is not None:
        lowest.append(float(at_lowest[best]) / seen)
    mine = own.sums.reshape(-1, *own.sums.shape[-2:]).sum(0)  # [m, 3]
    for level in [list(meas_var), *(noise_range or ())]:
        if not float(sure_of(found[best], level)) < float(sure_of(mine, level)):
            return None
    return windows[best]

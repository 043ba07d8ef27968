"""The process noise ``q`` a Kalman smoother works well with, read off the data.

:func:`~torchsvs.datasets.estimate_noise` reads the measurement noise from short-scale
differences; the white-acceleration ``q`` it also gives is only what those short scales see
once the maneuvers are set aside (for a slow target at long scans the noise swamps it there).
The smoother's ``q`` decides how much of the wander and the turns it follows: :func:`smoother_q`
picks it by a one-dimensional search over ``q`` with the measurement noise fixed at its robust
estimate, minimising Stein's unbiased estimate of the smoother's position error (default) or
maximising the Kalman filter's innovation likelihood.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.accuracy import CHUNK
from torchsvs.datasets import two_point_prior
from torchsvs.datasets.priors import prior_tangents
from torchsvs.estimator import prepare_inputs, threads_for
from torchsvs.filters import KalmanFilter
from torchsvs.fitting.losses import innovation_nll
from torchsvs.fitting.q_kinds import kind_table, kind_targets
from torchsvs.kernels import curves
from torchsvs.models import ConstantVelocity
from torchsvs.smoothers import RTSSmoother

#: Steps (all windows together) the criterion is computed on: a sample of larger data.
MAX_STEPS = 20_000
#: Steps per window the tracks are cut into (each window starts from its own two-point prior).
WINDOW = 512
#: The coarse grid of :func:`smoother_q`: ``q`` in units of ``r / h³`` (``h`` the median
#: interval), a factor of 10 apart. A still target wants the low end; at 60 s scans an airliner
#: that turns 1 deg/s wants ``10⁴ r/h³``.
GRID = tuple(10.0**k for k in range(-8, 9))
#: The golden-section search stops when the bracket of ``log q`` is this narrow.
LOG_TOLERANCE = 0.01
#: Criteria of :func:`smoother_q`.
CRITERIA = ("sure", "nll")
#: The factors on the file's ``q`` that each track's own ``q`` is chosen from
#: (:func:`track_q_factors`): half a decade apart, 1/30 to 30. Each factor in a group of tracks
#: is one more estimator call; a quarter decade apart gained at most 0.3% of RMSE on the
#: recorded-tracks benchmark (2.4% on its irregular set), for up to twice the calls.
Q_FACTORS = tuple(10.0 ** (k / 2) for k in range(-3, 4))
#: The factors :func:`q_factors` adds below :data:`Q_FACTORS` for a file whose still targets
#: want less than 1/30 of its ``q`` (:func:`~torchsvs.fitting.defaults.with_q_curve`), sparser
#: as they go down: a parked car's ``q`` is 0, and the file's ``q`` is the moving ones'. Parked
#: cars among moving ones (σ 5 m, 1 s reports, ``q`` per step): 1.86 m with the factors down to
#: 1/30, 1.14 m down to 10^-3.5 by half decades, 0.74 m with these (0.59 m for the parked cars
#: alone, whose file ``q`` is their own); the moving cars alike (2.87 m).
LOW_FACTORS = (10.0**-7, 10.0**-5, 10.0**-3.5, 10.0**-2.5)


def q_factors(low: bool = False) -> tuple[float, ...]:
    """:data:`Q_FACTORS`, with ``low`` also :data:`LOW_FACTORS` below them."""
    return LOW_FACTORS + Q_FACTORS if low else Q_FACTORS


#: A track's own SURE curve counts ``n / (n + SHRINK_COMPONENTS)`` in its choice of ``q`` (``n``
#: its scored position components), the file's the rest: a track of 50 two-axis positions
#: halfway. Measured on the recorded-tracks benchmark's sets (30 to 400 positions a track):
#: halfway at 50 or 200 positions chose alike (within 0.5% of RMSE); no shrinkage (each track's
#: own curve alone) lost 0.7% to one ``q`` for all on the 1 s scans, where short tracks'
#: curves are flat and noisy.
SHRINK_COMPONENTS = 100.0


class QEstimate(NamedTuple):
    """The ``q`` of :func:`smoother_q`."""

    q: float  #: white-acceleration power spectral density (units²/s³)
    value: float  #: the criterion at ``q`` (SURE: mean squared position error per component)
    #: standard error of ``log q`` from the likelihood's curvature ("nll"; NaN for "sure")
    log_se: float
    evaluations: int  #: smoother or filter passes
    steps: int  #: steps the criterion was computed on


def _windows(z: Tensor, dt: Tensor, window: int, max_steps: int) -> tuple[Tensor, Tensor, Tensor]:
    """The tracks cut into windows of ``window`` steps, at most ``max_steps`` steps spread evenly
    over them: ``z [N, W, m]`` (each window moved to start near 0), ``dt [N, W]`` and the steps
    scored ``[N, W]`` (from the third observed one of a window on: the first two make its
    prior)."""
    B, T, m = z.shape
    W = min(window, T)
    count = -(-T // W)
    pad = count * W - T
    zp = torch.cat([z, z.new_full((B, pad, m), math.nan)], 1).reshape(B * count, W, m)
    dtp = torch.cat([dt, dt[:, -1:].expand(B, pad)], 1).reshape(B * count, W)
    scored = _scored(zp)
    useful = scored.any(1)
    zp, dtp, scored = zp[useful], dtp[useful], scored[useful]
    keep = max(1, max_steps // W)
    if len(zp) > keep:
        pick = torch.linspace(0, len(zp) - 1, keep).round().long().unique()
        zp, dtp, scored = zp[pick], dtp[pick], scored[pick]
    first = (~torch.isnan(zp)).to(torch.int64).argmax(1, keepdim=True)
    zp = zp - zp.nan_to_num(0.0).gather(1, first)
    return zp, dtp, scored


def _scored(z: Tensor) -> Tensor:
    """``[B, T]`` the steps SURE scores: from a track's third observed step on (the first two
    make its two-point prior)."""
    seen = (~torch.isnan(z)).any(-1)
    return seen & (seen.cumsum(1) >= 3)


def kalman(m: int, q: float, r: Tensor, smoothed: bool = True) -> Any:
    """The float64 nearly-constant-velocity Kalman smoother (RTS, fixed interval), or with
    ``smoothed=False`` filter, with ``q`` and measurement variances ``r [m]``: the estimator
    every SURE curve here is of."""
    kf = KalmanFilter(ConstantVelocity(ndim=m, q=q, r=r.tolist()).double())
    return RTSSmoother(kf) if smoothed else kf


def smoother_run(estimator: Any, z: Tensor, dt: Tensor, prior: Any) -> Any:
    """The means and covariances of ``estimator`` (:func:`kalman`'s) on ``z`` from ``prior``
    (no gradients). The smoother's filter pass keeps its means alone (the compiled pass then
    never writes the filter's covariances: a third less time)."""
    with torch.no_grad():
        if not isinstance(estimator, RTSSmoother):
            return estimator(z, prior.x0, prior.P0, dt=dt, keep="moments")
        inputs = prepare_inputs(estimator.model, z, prior.x0, prior.P0, dt=dt, keep="mean")
        with threads_for(inputs.batch, estimator.model.state_dim):
            return estimator.run(inputs)  # (a smoother's run has its moments whatever it keeps)


def _sure_of(z: Tensor, r: Tensor, mean: Tensor, leverage: Tensor, clip: float) -> Tensor:
    """:func:`_sure`'s terms from the positions' estimate ``mean`` and variance ``leverage``."""
    risk = (z - mean).square_().sub_(r).add_(leverage, alpha=2.0)  # (2·leverage: exact)
    return risk if clip == math.inf else risk.clamp_max(clip * r)


def kalman_positions(
    z: Tensor,
    dt: Tensor,
    x0: Tensor,
    P0: Tensor,
    r: Tensor,
    q: float | Tensor,
    smoothed: bool = True,
    chunk: int | None = None,
    step_risk: Tensor | None = None,
) -> curves.Positions:
    """The means ``[B, T, 2m]`` and the positions' variances ``[B, T, m]`` of :func:`kalman`
    (the smoother, or with ``smoothed=False`` the filter) with ``q`` (a number, or one per
    track ``[B]``) and variances ``r [m]`` on ``z`` from the prior ``x0 [B, 2m]``, ``P0 [B,
    2m, 2m]``, in ``z``'s dtype: the compiled loop that writes nothing else
    (:func:`torchsvs.kernels.curves.positions`), else the estimator's run (one per distinct
    ``q``). With ``chunk`` (``x0`` :func:`~torchsvs.datasets.two_point_prior`'s) and the
    compiled loop, also the estimate's derivative by each axis's first two measurements and
    SURE's sums per chunk of that many steps, and each step's SURE written to ``step_risk``
    (``[B, T]``, where given; :class:`~torchsvs.kernels.curves.Positions`)."""
    B, T, m = z.shape
    dtype = z.dtype
    qs = torch.as_tensor(q, dtype=dtype).expand(B).contiguous()
    r = r.to(dtype)
    tangents = None if chunk is None else prior_tangents(z, dt)
    found = curves.positions(z, dt, x0, P0, r, qs, smoothed, tangents, chunk, step_risk)
    if found is not None:
        return found
    mean, var = z.new_empty(B, T, 2 * m), z.new_empty(B, T, m)
    for value in torch.unique(qs).tolist():
        index = torch.nonzero(qs == value).flatten()
        estimator = kalman(m, value, r.double(), smoothed).to(dtype)
        with torch.no_grad():
            out = estimator(z[index], x0[index], P0[index], dt=dt[index], keep="moments")
        mean[index] = out.mean
        var[index] = out.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2]
    return curves.Positions(mean, var)


def _sure(
    z: Tensor, dt: Tensor, prior: Any, r: Tensor, q: float, smoothed: bool, clip: float = math.inf
) -> Tensor:
    """``[B, T, m]`` the exact SURE per position component of the nearly-constant-velocity
    Kalman smoother (or filter) with ``q`` (:func:`smoother_q`'s formula), float64; with
    ``clip``, each term at most ``clip`` times ``r`` (no longer unbiased: a criterion that
    outliers do not drive, as their terms stay at the clip whatever ``q``)."""
    found = kalman_positions(z, dt, prior.x0, prior.P0, r, q, smoothed)
    mean, leverage = found.mean, found.var
    return _sure_of(z, r, mean[..., 0::2], leverage, clip)


def smoother_q(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float,
    criterion: str = "sure",
    max_steps: int = MAX_STEPS,
    window: int = WINDOW,
    smoothed: bool = True,
    clip: float = math.inf,
) -> QEstimate:
    r"""The ``q`` of a nearly-constant-velocity Kalman smoother (RTS) for these tracks, with the
    measurement noise ``meas_var`` fixed; with ``smoothed=False`` the Kalman filter's.

    ``"sure"`` minimises Stein's unbiased risk estimate (Stein 1981) of the smoothed position's
    mean squared error, per observed component :math:`i` of step :math:`t`,

    .. math::
        \mathrm{SURE} = (z_{ti} - \hat z_{ti})^2 - r_i + 2\,(P_{t|T})_{ii},

    where :math:`\hat z = H\hat x_{t|T}`. The divergence term is exact and needs no probes: for
    ``z = Hx + v``, ``v ~ N(0, R)`` independent of ``x``, the smoothed fit is
    :math:`\hat z = E[z - v \mid z] = z - R\Sigma_z^{-1}(z - Ez)`, so its hat matrix is
    :math:`I - R\Sigma_z^{-1}`; and :math:`H P H^\top = \mathrm{Cov}(v \mid z) = R - R
    \Sigma_z^{-1} R`, so :math:`I - R\Sigma_z^{-1} = H P H^\top R^{-1}`, whose diagonal at
    ``t`` is :math:`H P_{t|T} H^\top R^{-1}` (the two-point prior reads only a window's first
    two positions, which are not scored). SURE is unbiased whatever the true path (turns
    included) as long as the noise is white Gaussian of variance :math:`r`, so its minimiser is
    the ``q`` that serves the smoother, not the ``q`` of a model the path does not follow; as
    ``q`` grows the smoother tends to the measurements and SURE to ``r``: the pick is never
    expected to be worse than the raw measurements.

    The filter's fit :math:`H\hat x_{t|t}` depends on :math:`z_t` through the gain alone,
    :math:`\partial H\hat x_{t|t}/\partial z_t = HK_t = HP_{t|t}H^\top R^{-1}` (for the
    optimal gain :math:`K_t = P_{t|t}H^\top R^{-1}`), so its SURE is the same with
    :math:`P_{t|t}`. A filter serves best with a larger ``q`` than a smoother (it cannot look
    ahead into a turn): the smoother's ``q`` left a Kalman filter above the raw measurements on
    hard turns (1.02×).

    ``"nll"`` maximises the likelihood of the Kalman filter's innovations
    (:func:`~torchsvs.fitting.losses.innovation_nll`; Harvey 1989, Sec. 3.4), efficient when
    the tracks follow the model, and gives the standard error of :math:`\log q` from the
    observed information.

    The criterion is computed on windows of ``window`` steps (at most ``max_steps`` in all),
    each from its own two-point prior (:func:`~torchsvs.datasets.two_point_prior`) and scored
    from its third observed step on. A grid of ``q`` (:data:`GRID`, in units of ``r/h³`` for
    the median interval ``h``) brackets the minimum, which a golden-section search on
    :math:`\log q` narrows to :data:`LOG_TOLERANCE`.

    Args:
        z: measurements ``[B, T, m]``, NaN where missing.
        dt: intervals ``[B, T]``.
        meas_var: measurement noise variance, a number or one per axis ``[m]``.
        criterion: ``"sure"`` or ``"nll"``.
        max_steps: at most this many steps are used (windows spread evenly over the data).
        window: steps per window.
        smoothed: the smoother's ``q`` (default), or the filter's.
        clip: ``"sure"`` with each component's term at most ``clip`` times ``r``: a 10σ outlier
            otherwise drives the choice toward following it (5× the ``q`` on hard turns with
            1% of them, 30× with the noise given).

    References:
        Stein, "Estimation of the mean of a multivariate normal distribution", Ann. Statist.
        9(6):1135-1151, 1981. doi:10.1214/aos/1176345632

        Harvey, "Forecasting, Structural Time Series Models and the Kalman Filter", Cambridge
        University Press, 1989. doi:10.1017/CBO9781107049994
    """
    if z.ndim != 3 or dt.shape != z.shape[:2]:
        raise ValueError(
            f"z, dt: expected [B, T, m] and [B, T], got {tuple(z.shape)}, {tuple(dt.shape)}"
        )
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
    m = z.shape[-1]
    r = torch.as_tensor(meas_var, dtype=torch.float64).reshape(-1).expand(m)
    if r.numel() != m or not bool(((r > 0) & torch.isfinite(r)).all()):
        raise ValueError(f"meas_var: expected one or {m} finite variances > 0, got {r.tolist()}")
    zw, dtw, scored = _windows(z.to(torch.float64), dt.to(torch.float64), window, max_steps)
    if not bool(scored.any()):
        raise ValueError("z: too few observed positions in a row to read q off the data")
    prior = two_point_prior(zw, dtw, r)
    counted = ~torch.isnan(zw) & scored.unsqueeze(-1)
    h = float(dtw[~torch.isnan(zw).all(-1)].median())
    unit = float(r.mean()) / h**3
    cache: dict[float, float] = {}

    def value(log_q: float) -> float:
        if log_q not in cache:
            if criterion == "nll":
                model = ConstantVelocity(ndim=m, q=math.exp(log_q), r=r.tolist()).double()
                with torch.no_grad():
                    out = KalmanFilter(model)(zw, prior.x0, prior.P0, dt=dtw)
                cache[log_q] = float(innovation_nll(out, scored))
            else:
                risk = _sure(zw, dtw, prior, r, math.exp(log_q), smoothed, clip)
                cache[log_q] = float(risk[counted].mean())
        return cache[log_q]

    with threads_for(1, 1):  # windows of a few small matrices: one intra-op thread
        x = _golden_search(value, [math.log(unit * g) for g in GRID])
        log_se = math.nan
        if criterion == "nll":
            step = 0.05
            curvature = (value(x + step) - 2.0 * value(x) + value(x - step)) / step**2
            curvature *= float(counted.sum())  # the NLL is a mean per observed component
            log_se = 1.0 / math.sqrt(curvature) if curvature > 0 else math.inf
        best = value(x)
    return QEstimate(math.exp(x), best, log_se, len(cache), int(scored.sum()))


class QCurves(NamedTuple):
    """SURE of a Kalman smoother (or filter) per track at ``q`` times :data:`Q_FACTORS`."""

    risk: Tensor  #: [F, B] float64 sums over each track's scored components
    counts: Tensor  #: [B] float64 scored components per track
    #: [B] int64 each track's kind of motion (:func:`~torchsvs.fitting.q_kinds.track_kinds`),
    #: where the tracks' own factors are shrunk toward their kinds' curves
    kinds: Tensor | None = None

    def pooled(self) -> list[float]:
        """The mean SURE per scored component of all the tracks, one per factor."""
        return (self.risk.sum(1) / self.counts.sum().clamp_min(1.0)).tolist()

    def by_kind(self) -> list[list[float]] | None:
        """Each kind's pooled curve (:func:`~torchsvs.fitting.q_kinds.kind_table`), where the
        tracks' kinds are known and more than one."""
        if self.kinds is None:
            return None
        return kind_table(self.risk, self.counts, self.kinds)


class CurveRuns(NamedTuple):
    """The passes behind :class:`QCurves` at each track's chosen factor
    (:func:`q_curve_runs`): what the Kalman smoother (or filter) estimates there, float64."""

    mean: Tensor  #: [B, T, 2m] the state's mean
    position_var: Tensor  #: [B, T, m] the positions' variances
    ran: Tensor  #: [B] bool the chosen factor is among the curves' (else mean, var unset)
    #: [B, C, m, 3] SURE's sums over each track's chunks of :data:`~torchsvs.accuracy.CHUNK`
    #: steps (:func:`~torchsvs.accuracy.terms_of_sums`), where compiled
    sums: Tensor | None = None


#: Tracks × steps per pass of the outlier screen and of :func:`q_curve_runs` where the
#: compiled curves are unavailable (several passes of a large group in turn,
#: :func:`over_chunks`): a pass's outputs stay in cache for what is read off them, in memory
#: the allocator reuses. Measured with the estimator's passes (~200 bytes a cell), before the
#: compiled curves: ``track --estimator ks`` on 10^6 rows (2 groups of 2^19 cells, one
#: thread) took 3.05 s of CPU with a whole group a pass (1.69 s of it in the system: page
#: faults), 1.63 s at 2^17 cells, 1.46-1.55 s at 2^16, 1.60-1.67 s at 2^15.
CHUNK_CELLS = 1 << 16


def over_chunks(batch: int, steps: int, work: Callable[[slice], None]) -> None:
    """``work`` on the tracks of a batch of ``batch`` tracks × ``steps``, :data:`CHUNK_CELLS`
    cells (a slice of tracks) at a time: the chunks spread over as many Python threads as
    torch's intra-op count, every operation inside on one (the compiled passes and torch's
    operations release the GIL; torch's OpenMP threads would spin between the passes). Each
    chunk's ``work`` must write apart from the others'."""
    rows = max(1, CHUNK_CELLS // max(steps, 1))
    parts = [slice(start, start + rows) for start in range(0, batch, rows)]
    workers = min(torch.get_num_threads(), len(parts))
    with threads_for(1, 1):
        if workers <= 1:
            for part in parts:
                work(part)
            return
        with ThreadPoolExecutor(workers) as pool:
            for done in pool.map(work, parts):  # (raises a chunk's error)
                del done


def q_curves(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float | Sequence[float],
    q: float,
    smoothed: bool = True,
    factors: tuple[float, ...] = Q_FACTORS,
    inputs: CurveInputs | None = None,
) -> QCurves:
    """SURE (:func:`smoother_q`'s, exact) of the nearly-constant-velocity Kalman smoother
    (``smoothed``) or filter with ``q`` times each factor, per track: each whole track from its
    two-point prior, scored from its third observed step on (``inputs``: :func:`curve_inputs`
    of these arguments, made once for a search that reads the tracks at many ``q``)."""
    return q_curve_runs(z, dt, meas_var, q, smoothed, factors, inputs=inputs)[0]


class CurveInputs(NamedTuple):
    """What the curves' passes read off the tracks whatever ``q`` (:func:`curve_inputs`)."""

    z: Tensor  #: [B, T, m] float64
    dt: Tensor  #: [B, T] float64
    r: Tensor  #: [m] float64 the measurement variances
    prior: Any  #: the tracks' two-point prior (:func:`~torchsvs.datasets.priors.two_point_prior`)


def curve_inputs(z: Tensor, dt: Tensor, meas_var: Tensor | float | Sequence[float]) -> CurveInputs:
    """``z``, ``dt`` and the variances ``[m]`` in float64, and the tracks' two-point prior."""
    m = z.shape[-1]
    r = torch.as_tensor(meas_var, dtype=torch.float64).reshape(-1).expand(m)
    z64, dt64 = z.to(torch.float64), dt.to(torch.float64)
    # (whole: an axis seen once reads it)
    return CurveInputs(z64, dt64, r, two_point_prior(z64, dt64, r))


def curve_runs(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float | Sequence[float],
    q: float | Tensor,
    smoothed: bool = True,
) -> CurveRuns:
    """What :func:`q_curve_runs` keeps, at ``q`` (one for all tracks, or each track's
    ``[B]``) without the curves: :func:`kalman`'s pass on the tracks from their two-point
    prior."""
    z64, dt64, r, prior = curve_inputs(z, dt, meas_var)
    found = kalman_positions(z64, dt64, prior.x0, prior.P0, r, q, smoothed, CHUNK)
    every = torch.ones(z.shape[0], dtype=torch.bool)
    return CurveRuns(found.mean, found.var, every, found.sums)


def q_curve_runs(
    z: Tensor,
    dt: Tensor,
    meas_var: Tensor | float | Sequence[float],
    q: float,
    smoothed: bool = True,
    factors: tuple[float, ...] = Q_FACTORS,
    choose: Callable[[QCurves], Tensor] | None = None,
    keep: bool = False,
    inputs: CurveInputs | None = None,
    kinds: Tensor | None = None,
) -> tuple[QCurves, Tensor | None, CurveRuns | None]:
    """:func:`q_curves`; with ``choose`` (a track's curve to its factor, track by track:
    :func:`track_q_factors`) each track's factor ``[B]``, and with ``keep`` the pass at it
    (:class:`CurveRuns`): :func:`kalman` with ``q`` times that factor on the tracks from their
    two-point prior (:func:`~torchsvs.datasets.with_prior`'s), which a Kalman smoother's
    (filter's) run at that ``q`` need not repeat: at each track's factor, on the grid or not
    (every track's ``ran``). Compiled, every factor runs in one pass that writes each track's
    sums alone (:func:`torchsvs.kernels.curves.sure_risks`), then the kept pass; else the
    estimator runs a chunk of tracks at a time (:data:`CHUNK_CELLS`) at each factor, each
    from the whole batch's prior, and keeps the tracks whose factor is on the grid
    (``inputs``: as :func:`q_curves`')."""
    z64, dt64, r, prior = inputs if inputs is not None else curve_inputs(z, dt, meas_var)
    counted = ~torch.isnan(z64) & _scored(z64).unsqueeze(-1)
    B, T, m = z64.shape
    grid = torch.tensor(factors, dtype=torch.float64)
    counts = counted.sum((1, 2)).to(torch.float64)
    every = (q * grid).unsqueeze(0).expand(B, len(factors))
    compiled = curves.sure_risks(z64, dt64, counted, prior.x0, prior.P0, r, every, smoothed)
    if compiled is not None:  # every factor in one pass that writes the sums alone
        found = QCurves(compiled, counts, kinds)
        if choose is None:
            return found, None, None
        factor = choose(found)
        if not keep:
            return found, factor, None
        # each track's pass at its own factor (on the grid or not)
        kept = kalman_positions(z64, dt64, prior.x0, prior.P0, r, q * factor, smoothed, CHUNK)
        every = torch.ones(B, dtype=torch.bool)
        return found, factor, CurveRuns(kept.mean, kept.var, every, kept.sums)
    # the estimator's passes, factor by factor, a chunk of tracks at a time
    risk = z64.new_empty(len(factors), B)
    chosen = z64.new_empty(B) if choose is not None else None
    runs = None
    if keep and chosen is not None:
        ran = torch.zeros(B, dtype=torch.bool)
        runs = CurveRuns(z64.new_empty(B, T, 2 * m), z64.new_empty(B, T, m), ran)
    estimators = [kalman(m, q * factor, r, smoothed) for factor in factors]

    def chunk(part: slice) -> None:
        zs, seen = z64[part], counted[part]
        unseen = ~seen
        at = type(prior)(*(x[part] for x in prior))
        outs = []
        for i, estimator in enumerate(estimators):
            out = smoother_run(estimator, zs, dt64[part], at)
            leverage = out.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2]
            terms = _sure_of(zs, r, out.mean[..., 0::2], leverage, math.inf)
            risk[i, part] = terms.masked_fill_(unseen, 0.0).sum((1, 2))
            outs.append((out.mean, leverage.contiguous()) if runs is not None else None)
            del out  # (before the next pass: its buffers are the allocator's again)
        if chosen is None or choose is None:
            return
        counts_part = seen.sum((1, 2)).to(torch.float64)
        chosen[part] = choose(
            QCurves(risk[:, part], counts_part, None if kinds is None else kinds[part])
        )
        if runs is None:
            return
        close = torch.isclose(chosen[part].unsqueeze(0), grid.unsqueeze(1), rtol=1e-9, atol=0.0)
        runs.ran[part] = close.any(0)
        for i, kept in enumerate(outs):
            assert kept is not None
            pick = close[i]
            runs.mean[part][pick] = kept[0][pick]
            runs.position_var[part][pick] = kept[1][pick]

    over_chunks(B, T, chunk)
    return QCurves(risk, counts, kinds), chosen, runs


def track_q_factors(
    curves: QCurves,
    pooled: list[float],
    factors: tuple[float, ...] = Q_FACTORS,
    shrink: float = SHRINK_COMPONENTS,
    kinds: list[list[float]] | None = None,
) -> Tensor:
    r"""Each track's factor on the file's ``q``: the minimiser over ``factors`` of its own SURE
    per component, shrunk toward the curve of its kind in ``kinds`` (:meth:`QCurves.by_kind`,
    itself shrunk toward the file's: :func:`~torchsvs.fitting.q_kinds.kind_targets`), or with
    no kinds toward the file's curve ``pooled`` (:meth:`QCurves.pooled` of the file's tracks),

    .. math::
        c_b(f) = w_b\,rac{S_b(f)}{n_b} + (1 - w_b)\,ar S(f),\qquad
        w_b = rac{n_b}{n_b + n_0},

    divided by the file curve's own minimiser, so the factor is relative to the ``q`` the file
    serves best with (a track like the file's keeps it). SURE is unbiased for each track as for
    the file, but a short track's curve is noisy: the weight keeps its choice near the file's
    until it has the positions to say otherwise (``n_0`` = ``shrink``).

    Returns:
        ``[B]`` float64 factors (1 for a track with nothing scored).
    """
    if len(pooled) != len(factors) or curves.risk.shape[0] != len(factors):
        raise ValueError(
            f"pooled, curves: expected one value per factor ({len(factors)}), got "
            f"{len(pooled)} and {curves.risk.shape[0]}"
        )
    file_curve = torch.tensor(pooled, dtype=torch.float64)
    n = curves.counts
    weight = n / (n + shrink)
    own = curves.risk / n.clamp_min(1.0)
    target = kind_targets(curves.kinds, file_curve, kinds)
    criterion = weight * own + (1.0 - weight) * target
    grid = torch.tensor(factors, dtype=torch.float64)
    chosen = grid[criterion.argmin(0)] / grid[file_curve.argmin()]
    return torch.where(n > 0, chosen, torch.ones_like(chosen))


def _golden_search(
    value: Callable[[float], float],
    grid: list[float],
    many: Callable[[list[float]], list[float]] | None = None,
) -> float:
    """The minimum of ``value`` bracketed by the grid's best point and its neighbours, narrowed
    by golden section to :data:`LOG_TOLERANCE` (``many``: the values at a list of points at
    once, for the grid)."""
    values = many(grid) if many is not None else [value(x) for x in grid]
    best = min(range(len(grid)), key=values.__getitem__)
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
    while hi - lo > LOG_TOLERANCE:
        if value(a) < value(b):
            hi, b = b, a
            a = hi - golden * (hi - lo)
        else:
            lo, a = a, b
            b = lo + golden * (hi - lo)
    return 0.5 * (lo + hi)

r"""How good an estimate is, without truth: Stein's unbiased risk estimate of the position error.

For measurements :math:`z = p + v` of positions :math:`p` with white Gaussian noise
:math:`v \sim N(0, r_j)` on axis :math:`j`, and an estimate :math:`f(z)` of the positions that
is weakly differentiable in :math:`z`, Stein (1981, Theorem 1 and Eq. (2.2)) gives, per observed
component :math:`i` on axis :math:`j`,

.. math::
    E\,(f_i - p_i)^2 = E\,\big[(z_i - f_i)^2 - r_j + 2\,r_j\,\partial f_i/\partial z_i\big].

The divergence is estimated with one Rademacher probe :math:`\varepsilon` and a finite
difference, :math:`\partial f_i/\partial z_i \approx \varepsilon_i\,(f_i(z + h\sigma\varepsilon)
- f_i(z))/(h\sigma_j)` (Ramani, Blu & Unser 2008, Eq. (9) and Theorem 2), which is unbiased for
the sum over components up to the finite difference. So every run costs one more pass of the
estimator, on the probed measurements (the same random draws for a particle filter, so that the
difference measures the estimator and not its sampling).

The terms are kept as sums per chunk of :data:`CHUNK` steps of every track and axis
(:class:`RiskTerms`): the residual :math:`\sum (z - f)^2`, the divergence
:math:`\sum \partial f/\partial z` and the count. The risk is linear in :math:`r`, so one pass
serves any noise level (:meth:`RiskTerms.mse`): the interval of an estimated noise becomes an
interval of the error. Chunks give the sampling uncertainty (batch means: the chunks' errors are
nearly independent once a chunk is longer than the estimator's memory).

Where the measurement noise is not white Gaussian of the stated variance, the estimate is
biased by the difference; that is why the noise level and its uncertainty are reported beside
it (``torchsvs track``).

References:
    Stein, "Estimation of the mean of a multivariate normal distribution", Ann. Statist. 9(6),
    1981. doi:10.1214/aos/1176345632 · Ramani, Blu & Unser, "Monte-Carlo SURE: a black-box
    optimization of regularization parameters for general denoising algorithms", IEEE Trans.
    Image Process. 17(9), 2008. doi:10.1109/TIP.2008.2001404
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

#: Steps per chunk of the sampling uncertainty (longer than a smoother's memory on most tracks).
CHUNK = 32
#: Finite-difference step of the divergence, in noise standard deviations. The variable
#: boundary layer's inflation bends within a fraction of σ, and a step of 0.3 (the training
#: loss's, :func:`torchsvs.fitting.losses.stein_risk`) overstated the SVSS's error by 17% on
#: slow targets (taxiing aircraft, σ 50), 8-10% elsewhere; 0.1 by 11% and 2-7%; 0.03 by 8%. A
#: Kalman smoother is linear: any step gives its estimate. Smaller steps lose digits in float32.
PROBE_STEP = 0.1


@dataclass
class RiskTerms:
    """SURE's sums per chunk of steps: ``[C, m]`` arrays, and the track of each chunk."""

    residual: np.ndarray  #: [C, m] Σ (z - f)² over the chunk's observed components (units²)
    divergence: np.ndarray  #: [C, m] Σ ∂f/∂z (dimensionless)
    count: np.ndarray  #: [C, m] observed components
    track: np.ndarray  #: [C] int64 the chunk's track (an index the caller gives meaning to)

    @classmethod
    def empty(cls, m: int) -> RiskTerms:
        zeros = np.zeros((0, m))
        return cls(zeros, zeros.copy(), zeros.copy(), np.zeros(0, dtype=np.int64))

    @classmethod
    def concat(cls, parts: Sequence[RiskTerms], m: int) -> RiskTerms:
        if not parts:
            return cls.empty(m)
        return cls(
            np.concatenate([p.residual for p in parts]),
            np.concatenate([p.divergence for p in parts]),
            np.concatenate([p.count for p in parts]),
            np.concatenate([p.track for p in parts]),
        )

    def select(self, chunks: np.ndarray) -> RiskTerms:
        """These chunks (``[C]`` bool, or indices in the order wanted)."""
        return RiskTerms(
            self.residual[chunks], self.divergence[chunks], self.count[chunks], self.track[chunks]
        )

    def in_track_order(self) -> RiskTerms:
        """The chunks ordered by track, each track's in their own order (the order of a run of
        all the tracks at once, whatever parts they ran in)."""
        return self.select(np.argsort(self.track, kind="stable"))

    def mse(self, meas_var: Sequence[float]) -> tuple[float, float]:
        """The position MSE per point (the axes' MSEs summed) and its standard error."""
        totals = RiskTotals(self.residual.shape[1])
        totals.add(self)
        return totals.mse(meas_var)

    def difference(self, other: RiskTerms, meas_var: Sequence[float]) -> tuple[float, float]:
        r"""The estimated MSE per point of these terms less ``other``'s, two estimators' on
        the same measurements (the same chunks), and its standard error: paired chunk by
        chunk, so what the two share (the measurements' noise, the path) cancels and a
        difference far smaller than either's own standard error can be sure,
        :math:`D = \sum_c d_c / \bar N`, :math:`\mathrm{Var}\,D \approx \sum_c (d_c - D
        n_c)^2 / \bar N^2` (:meth:`RiskTotals.mse`'s ratio estimator on the chunks'
        differences). Of one chunk the error is unknown (NaN), not 0: nothing to spread."""
        if self.count.shape != other.count.shape or not np.array_equal(self.count, other.count):
            raise ValueError("other: expected the terms of the same chunks")
        counts = self.count.sum(axis=0)
        if not len(self.count) or not (counts > 0).all():
            return math.nan, math.nan
        mean_count = counts.mean()
        scale = mean_count / counts  # each axis over its own observations
        d = ((self.errors(meas_var) - other.errors(meas_var)) * scale).sum(axis=1)
        D = float(d.sum() / mean_count)
        if len(d) < 2:
            return D, math.nan
        spread = float(((d - D * self.count.mean(axis=1)) ** 2).sum())
        return D, math.sqrt(spread) / mean_count

    def errors(self, meas_var: Sequence[float]) -> np.ndarray:
        r"""``[C, m]`` each chunk's SURE of the squared position error, :math:`\Sigma(z-f)^2
        + r_j\,\Sigma(2\,\partial f/\partial z - 1)` (:meth:`RiskTotals.mse`'s
        :math:`e_{c,j}`)."""
        return sure(self.residual, self.divergence, self.count, np.asarray(meas_var, np.float64))

    @property
    def points(self) -> int:
        return int(round(self.count.mean(axis=1).sum())) if len(self.count) else 0

    def per_track(self, meas_var: Sequence[float], tracks: int) -> tuple[np.ndarray, np.ndarray]:
        """Each track's estimated position RMSE ``[tracks]`` (NaN without observations) and
        its observed points."""
        error = self.errors(meas_var)
        axes = range(error.shape[1])
        total = np.stack([np.bincount(self.track, error[:, j], tracks) for j in axes], 1)
        count = np.stack([np.bincount(self.track, self.count[:, j], tracks) for j in axes], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mse = (total / count).sum(axis=1)
        return np.sqrt(np.clip(mse, 0.0, None)), count.mean(axis=1)

    def per_track_ranges(
        self,
        meas_var: Sequence[float],
        tracks: int,
        levels: Sequence[Sequence[float]] = (),
        errors: float = 2.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        r"""Each track's estimated position RMSE's range ``(low, high)``, ``[tracks]`` each: its
        MSE ``errors`` standard errors below and above, at ``meas_var`` and at the other noise
        ``levels`` (the noise reading's interval), as the run's range is made. The standard
        error is :meth:`RiskTotals.mse`'s ratio estimator over the track's own chunks; NaN for
        a track of fewer than two chunks (nothing to spread: unknown, not 0) and for one whose
        whole range is below zero."""
        m = self.count.shape[1]
        count = np.stack([np.bincount(self.track, self.count[:, j], tracks) for j in range(m)], 1)
        chunks = np.bincount(self.track, minlength=tracks)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_count = count.mean(axis=1)  # [K]
            scale = mean_count[:, None] / count  # [K, m] each axis over its own observations
            low = np.full(tracks, np.inf)
            high = np.full(tracks, -np.inf)
            for level in [meas_var, *levels]:
                e = self.errors(level)  # [C, m]
                total = np.stack([np.bincount(self.track, e[:, j], tracks) for j in range(m)], 1)
                mse = (total / count).sum(axis=1)  # [K]
                e_c = (e * scale[self.track]).sum(axis=1)  # [C]
                d = e_c - mse[self.track] * self.count.mean(axis=1)
                se = np.sqrt(np.bincount(self.track, d * d, tracks)) / mean_count
                se = np.where(chunks >= 2, se, np.nan)
                low = np.minimum(low, mse - errors * se)
                high = np.maximum(high, mse + errors * se)
        # (a range wholly below zero is unknown, not [0, 0]: the noise assumed is above what
        # the track's residuals allow; one such track read 0 m for a true 1.7 m)
        unknown = high <= 0.0
        low, high = np.where(unknown, np.nan, low), np.where(unknown, np.nan, high)
        return np.sqrt(np.clip(low, 0.0, None)), np.sqrt(np.clip(high, 0.0, None))


class Probe(NamedTuple):
    """SURE's probe of measurements ``z [..., m]`` (:func:`draw_probe`)."""

    signs: Tensor  #: ±1 at the probed components, 0 elsewhere (missing, not scored)
    measurements: Tensor  #: the probed measurements ``z + step·σ·signs``
    step: float  #: the finite-difference step in noise standard deviations


def draw_probe(
    z: Tensor,
    std: Tensor,
    step: float,
    generator: torch.Generator | None,
    scored: Tensor | None = None,
    ids: Sequence[str] | None = None,
) -> Probe:
    """A Rademacher probe of ``z [B, T, m]`` (NaN where missing) with noise standard
    deviations ``std [m]``: ±1 at random (from ``generator``, or with ``ids`` from
    :func:`track_signs`) at the observed components of the ``scored [B, T]`` steps (default:
    all), 0 elsewhere."""
    if ids is None:
        signs = torch.randint(0, 2, z.shape, generator=generator).to(z.dtype) * 2 - 1
    else:
        signs = track_signs(ids, z.shape).to(z.dtype)
    signs = signs * ~torch.isnan(z)
    if scored is not None:
        signs = signs * scored.unsqueeze(-1)
    return Probe(signs, z + step * std.to(z.dtype) * signs, step)


def track_signs(ids: Sequence[str], shape: Sequence[int]) -> Tensor:
    """``[B, T, m]`` ±1 for the components of tracks ``ids``, each a hash (SplitMix64, Steele
    et al. 2014) of its track's id, step and axis: a track gets the same probe whichever
    tracks it is batched with, so its error estimate (and what depends on it) does not depend
    on how a dataset was split. Tracks sharing signs do no harm: the probe's error comes from
    the cross terms within a track, where the signs are independent."""
    B, T, m = shape
    key = np.array([zlib.crc32(str(i).encode()) for i in ids], dtype=np.uint64)
    cell = np.arange(T * m, dtype=np.uint64).reshape(1, T, m)
    x = (key.reshape(B, 1, 1) << np.uint64(32)) + cell + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    bit = (x >> np.uint64(63)).astype(np.int8)
    return torch.from_numpy(bit * 2 - 1)


@dataclass
class Reference:
    r"""A control variate for the probe's divergence: a linear Gaussian estimator (a Kalman
    filter or smoother) whose divergence is known exactly, run on the same probe.

    One Rademacher probe estimates :math:`\sum_i \partial f_i/\partial z_i` with the variance
    of its cross terms :math:`2\sum_{i \ne j} A_{ij}^2`, large for a smoother that averages
    over many steps: on taxiing aircraft at σ 10 the Kalman smoother's estimate moved
    0.89-1.06x the true error with the probe's seed alone. For a Kalman filter or smoother
    the divergence is exact, :math:`\partial H\hat x_t/\partial z_t = H P_t H^\top R^{-1}`
    (:func:`torchsvs.fitting.noise.smoother_q`), except at each axis's first two observations,
    which the two-point prior reads too. The probe's error on the reference,
    :math:`y = \hat d_{ref} - d_{ref}` (0 where ``exact`` is unknown), has mean 0; the
    estimator's divergence is taken as :math:`\hat d - \beta y`: for the reference itself
    (``beta`` 1) the exact value; for an estimator near it (an SVSS, whose gain is the
    Kalman gain inside its boundary layer) most of the probe's error cancels (0.99-1.01x on
    that set), with :math:`\beta` fitted over the run's chunks where not given
    (:math:`\sum x_c y_c / \sum y_c^2`, within [0, 1]: no worse than no control where the two
    do not move together).

    Attributes:
        exact: the reference's exact divergence per component ``[B, T, m]``, NaN where not
            known.
        shifted: its position estimate of the probe's measurements (the ``probe`` given to
            :func:`risk_terms`); ``None``: the estimator is its own reference (a Kalman
            filter or smoother).
        estimate: its position estimate of the measurements ``[B, T, m]`` (with ``shifted``).
        beta: the control's weight; ``None``: fitted.
    """

    exact: Tensor
    shifted: Tensor | None = None
    estimate: Tensor | None = None
    beta: float | None = None


def exact_divergence(z: Tensor, position_var: Tensor, meas_var: Tensor) -> Tensor:
    """A Kalman filter's or smoother's divergence per component ``[B, T, m]``: its position
    variance ``position_var [B, T, m]`` over the model's measurement variance ``meas_var
    [m]``, NaN where not known (unobserved, or among an axis's first two observations, which
    the two-point prior reads)."""
    observed = ~torch.isnan(z)
    later = observed & (observed.cumsum(dim=1) >= 3)
    return torch.where(later, position_var.double() / meas_var.double(), math.nan)


def risk_terms(
    rerun: Callable[[Tensor], Tensor],
    z: Tensor,
    estimate: Tensor,
    meas_std: Tensor,
    generator: torch.Generator | None,
    chunk: int = CHUNK,
    step: float = PROBE_STEP,
    reference: Reference | None = None,
    probe: Probe | None = None,
) -> RiskTerms:
    """SURE's sums for positions ``estimate [B, T, m]`` of measurements ``z [B, T, m]`` (NaN
    where missing), ``rerun`` mapping probed measurements to their position estimate; with a
    ``reference``, its control variate on the divergence (:class:`Reference`). The probe is
    ``probe`` where given (drawn beforehand, e.g. for a paired run), else drawn from
    ``generator`` with ``step``.

    Chunk ``c`` of track ``b`` covers steps ``c·chunk ... (c+1)·chunk - 1``; its ``track`` is
    ``b``. Chunks without an observation are left out.
    """
    with torch.no_grad():
        observed = ~torch.isnan(z)
        std = meas_std.to(z.dtype)
        if probe is None:
            if reference is not None and reference.shifted is not None:
                raise ValueError("probe: a reference's shifted estimate is of a given probe")
            probe = draw_probe(z, std, step, generator)
        probed = probe.measurements
        scale = probe.step * std.double()

        def divergence_of(shifted: Tensor, base: Tensor) -> Tensor:
            quotient = probe.signs.double() * (shifted.double() - base) / scale
            return torch.where(observed, quotient, 0.0)

        estimate = estimate.to(torch.float64)
        zd = z.to(torch.float64)
        residual = torch.where(observed, zd - estimate, 0.0).square()
        divergence = divergence_of(rerun(probed), estimate)
        control = None
        if reference is not None:
            found = divergence
            if reference.shifted is not None:
                assert reference.estimate is not None
                found = divergence_of(reference.shifted, reference.estimate.double())
            unknown = reference.exact.isnan()
            control = torch.where(unknown, 0.0, found - reference.exact)
    if control is not None:
        assert reference is not None
        beta = reference.beta
        if beta is None:  # the slope of the estimator's probe error on the reference's
            ys = chunk_sums(control, chunk)
            spread = float((ys * ys).sum())
            centred = torch.where(reference.exact.isnan(), 0.0, divergence - reference.exact)
            moved = float((chunk_sums(centred, chunk) * ys).sum())
            beta = float(np.clip(moved / spread, 0.0, 1.0)) if spread else 0.0
        divergence = divergence - beta * control
    return chunk_terms(observed, residual, divergence, chunk)


def chunk_sums(x: Tensor, chunk: int = CHUNK) -> np.ndarray:
    """``[B·C, m]`` the sums of ``x [B, T, m]`` over each track's chunks of ``chunk`` steps
    (the last padded with zeros), track by track."""
    B, T, m = x.shape
    x = torch.nn.functional.pad(x, (0, 0, 0, (-T) % chunk))
    return x.reshape(B, -1, chunk, m).sum(dim=2).reshape(-1, m).numpy()


def chunk_terms(
    observed: Tensor, residual: Tensor, divergence: Tensor, chunk: int = CHUNK
) -> RiskTerms:
    """:class:`RiskTerms` of squared residuals and divergences per component ``[B, T, m]``
    (0 where not ``observed``): their sums over each track's chunks of ``chunk`` steps, the
    chunks without an observation left out."""
    return terms_of_sums(chunk_sum_array((residual, divergence, observed.double()), chunk))


def sure(residual: Any, divergence: Any, count: Any, meas_var: Any) -> Any:
    r"""SURE of the squared position error from its sums per axis (the last dimension: one
    variance of ``meas_var`` each), :math:`\Sigma(z-f)^2 + r\,(2\,\Sigma\,\partial f/\partial z
    - n)`, of numpy arrays or torch tensors alike: the formula's one home."""
    return residual + meas_var * (2.0 * divergence - count)


def chunk_sum_array(parts: Sequence[Tensor], chunk: int = CHUNK) -> Tensor:
    """``[B, C, m, len(parts)]`` float64: each of ``parts [B, T, m]`` summed over each track's
    chunks of ``chunk`` steps (:func:`terms_of_sums` reads squared residuals, divergences and
    counts)."""
    B = parts[0].shape[0]
    sums = np.stack([chunk_sums(x.double(), chunk) for x in parts], axis=-1)  # [B·C, m, k]
    return torch.from_numpy(sums.reshape(B, -1, *sums.shape[1:]))


def terms_of_sums(sums: np.ndarray | Tensor) -> RiskTerms:
    """:class:`RiskTerms` of the sums ``[B, C, m, 3]`` (squared residual, divergence, count)
    over each track's chunks, the chunks without an observation left out."""
    sums = np.asarray(sums, dtype=np.float64)
    B, C, m, _ = sums.shape
    flat = sums.reshape(B * C, m, 3)
    keep = flat[..., 2].sum(axis=1) > 0
    track = np.repeat(np.arange(B), C)
    return RiskTerms(flat[keep, :, 0], flat[keep, :, 1], flat[keep, :, 2], track[keep])


def exact_risk_terms(
    z: Tensor, estimate: Tensor, divergence: Tensor, chunk: int = CHUNK
) -> RiskTerms:
    """:func:`risk_terms` of a linear estimator whose divergence is known exactly at every
    observed component (``divergence [B, T, m]``; a Kalman smoother's or filter's,
    :func:`exact_divergence` with the first two observations' own): no probe, no rerun."""
    observed = ~torch.isnan(z)
    zd = z.to(torch.float64)
    residual = torch.where(observed, zd - estimate.to(torch.float64), 0.0).square()
    return chunk_terms(observed, residual, torch.where(observed, divergence, 0.0), chunk)


class RiskTotals:
    r"""Running totals of :class:`RiskTerms` over a whole run, in memory independent of its
    size: the sums and the Gram matrix of each chunk's vector
    :math:`u_c = (\Sigma(z-f)^2_j,\ \Sigma(2\,\partial f/\partial z - 1)_j,\ n_{c,j})`
    over the axes :math:`j`, from which any noise level's estimate and its batch-means
    variance follow (:meth:`mse`)."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.chunks = 0
        self.first = np.zeros(3 * m)
        self.gram = np.zeros((3 * m, 3 * m))

    def add(self, terms: RiskTerms) -> None:
        u = np.concatenate(
            [terms.residual, 2.0 * terms.divergence - terms.count, terms.count], axis=1
        )
        self.chunks += len(u)
        self.first += u.sum(axis=0)
        self.gram += u.T @ u

    def merge(self, other: RiskTotals) -> None:
        """Adds another run's totals (of the same axes) to these."""
        if other.m != self.m:
            raise ValueError(f"other: expected totals of {self.m} axes, got {other.m}")
        self.chunks += other.chunks
        self.first += other.first
        self.gram += other.gram

    def mse(self, meas_var: Sequence[float]) -> tuple[float, float]:
        r"""The position MSE per point, :math:`\sum_j \sum_c e_{c,j} / N_j` with
        :math:`e_{c,j} = \Sigma(z-f)^2 + r_j\,\Sigma(2\,\partial f/\partial z - 1)` (each axis
        over its own observations), and its standard error: a ratio estimator over chunks,
        :math:`\mathrm{Var} \approx \sum_c (e_c - \mathrm{mse}\,n_c)^2 / \bar N^2` with
        :math:`e_c = \sum_j e_{c,j} \bar N / N_j` and :math:`n_c` the chunk's mean count."""
        m = self.m
        counts = self.first[2 * m :]
        if not (counts > 0).all():
            return math.nan, math.nan
        mean_count = counts.mean()
        scale = mean_count / counts  # each axis over its own observations
        r = np.asarray(meas_var, dtype=np.float64)
        w = np.concatenate([scale, r * scale, np.zeros(m)])
        v = np.concatenate([np.zeros(2 * m), np.full(m, 1.0 / m)])
        mse = float(w @ self.first / mean_count)
        if self.chunks < 2:
            return mse, math.inf
        d = w - mse * v  # e_c − mse·n_c = d·u_c
        spread = float(d @ self.gram @ d)
        return mse, math.sqrt(max(spread, 0.0)) / mean_count

    @property
    def points(self) -> int:
        return int(round(self.first[2 * self.m :].mean()))

    def of_axes(self, axes: Sequence[int]) -> RiskTotals:
        """These totals over some of the axes alone (the horizontal ones of a 3-D run)."""
        index = [block * self.m + j for block in range(3) for j in axes]
        part = RiskTotals(len(axes))
        part.chunks = self.chunks
        part.first = self.first[index].copy()
        part.gram = self.gram[np.ix_(index, index)].copy()
        return part


@dataclass
class Accuracy:
    """The truth-free error estimate of a run (position RMSE over the axes, metres)."""

    estimated_rmse: float  #: position RMSE (root of the summed per-axis MSE), estimated
    standard_error: float  #: its sampling standard error (chunks of steps)
    measurement_rmse: float  #: the measurements' own RMSE, √Σ r_j
    interval: tuple[float, float]  #: with the noise level's uncertainty and 2 standard errors
    points: int  #: observed positions the estimate averages over
    noise_estimated: bool  #: r was read off the data (not given)
    meas_std: list[float]  #: the noise standard deviation per axis it assumes
    #: the interval of its sampling error alone (2 standard errors), without the noise level's
    sampling_interval: tuple[float, float]
    #: the MSE per point and its standard error before the root (m²; below zero by chance
    #: where the error is small, surely so where the noise assumed is too high)
    mse: float = math.nan
    mse_standard_error: float = math.nan
    #: the whole interval is below zero (2 standard errors, over the noise level's range):
    #: no error estimate, the noise it assumes is more than the residuals about the estimate
    #: allow (SURE at the true noise averages the MSE, never below zero)
    below_zero: bool = False
    #: where :attr:`below_zero`: the noise standard deviation per axis, the assumed one scaled
    #: by one factor, at which the estimate would be zero: about the most the residuals allow
    zero_at_noise: list[float] | None = None
    #: the noise read off the data cannot be told from the motion between reports (``noise_lag``,
    #: :func:`~torchsvs.datasets.noise_lags.motion_checked`): the run took a noise far below
    #: the reading, and an estimate at it would be that arbitrary choice's; no point estimate,
    #: the range (over the reading's uncertainty) stands
    noise_unknown: bool = False

    @property
    def ratio(self) -> float:
        """Estimated error ÷ the measurements' (below 1: better than the raw measurements)."""
        return self.estimated_rmse / self.measurement_rmse

    @property
    def clearly_better(self) -> bool:
        """The upper end of the interval is below the measurements' RMSE."""
        return self.interval[1] < self.measurement_rmse

    def part_line(self, name: str) -> str:
        """This estimate of some of the axes (``name``), as the run's line lists it."""
        if self.below_zero:
            return f"{name} unknown (below zero), measurements {self.measurement_rmse:.3g} m"
        low, high = self.interval
        if self.noise_unknown:
            return f"{name} unknown (within {low:.3g}-{high:.3g} m)"
        return (
            f"{name} {self.estimated_rmse:.3g} m (range {low:.3g}-{high:.3g}), measurements "
            f"{self.measurement_rmse:.3g} m"
        )

    def part_summary(self) -> dict[str, Any]:
        """This estimate of some of the axes as the run's summary writes it."""
        unknown = self.below_zero
        return {
            "estimated": math.nan if unknown or self.noise_unknown else self.estimated_rmse,
            "interval": [math.nan] * 2 if unknown else list(self.interval),
            "measurement_rmse": self.measurement_rmse,
            "meas_std": self.meas_std,
        }

    def line(self) -> str:
        low, high = self.interval
        noise = "estimated from the data" if self.noise_estimated else "as given"
        if self.below_zero:  # (not "0 m": no error is that small; the warning says why)
            return (
                f"estimated position error unknown: below zero at the noise assumed (MSE "
                f"{self.mse:.3g} ± {self.mse_standard_error:.2g} m² per point), measurements "
                f"{self.measurement_rmse:.3g} m at that noise ({noise}); {self.points} "
                "positions, no truth used"
            )
        if self.noise_unknown:
            return (
                f"estimated position error unknown, within {low:.3g}-{high:.3g} m: the "
                "measurement noise cannot be told from the motion between reports (see the "
                f"warnings), and the estimates keep close to the measurements; {self.points} "
                "positions, no truth used"
            )
        return (
            f"estimated position error {self.estimated_rmse:.3g} m (range {low:.3g}-{high:.3g}), "
            f"measurements {self.measurement_rmse:.3g} m (noise {noise}); "
            f"{self.points} positions, no truth used"
        )


def accuracy(
    terms: RiskTerms | RiskTotals,
    meas_var: Sequence[float],
    noise_estimated: bool = False,
    meas_var_range: tuple[Sequence[float], Sequence[float]] | None = None,
) -> Accuracy:
    """The :class:`Accuracy` of summed terms at noise ``meas_var``; ``meas_var_range`` (low,
    high) widens the interval by the noise level's own uncertainty."""
    mse, se = terms.mse(meas_var)
    ends = [mse - 2 * se, mse + 2 * se]
    for variance in meas_var_range or ():
        value, _ = terms.mse(variance)
        ends += [value - 2 * se, value + 2 * se]
    rmse = math.sqrt(max(mse, 0.0))
    below = max(ends) < 0
    zero_at = None
    if below:  # SURE is linear in the noise: the residuals' part, less c times the rest
        residual_part, _ = terms.mse([0.0] * len(meas_var))
        noise_part = mse - residual_part
        if noise_part < 0:
            factor = residual_part / -noise_part
            zero_at = [math.sqrt(factor * v) for v in meas_var]

    def root(value: float) -> float:
        return math.sqrt(max(value, 0.0))

    return Accuracy(
        estimated_rmse=rmse,
        standard_error=se / (2 * rmse) if rmse > 0 else se,
        measurement_rmse=math.sqrt(sum(meas_var)),
        interval=(root(min(ends)), root(max(ends))),
        points=terms.points,
        noise_estimated=noise_estimated,
        meas_std=[math.sqrt(v) for v in meas_var],
        sampling_interval=(root(mse - 2 * se), root(mse + 2 * se)),
        mse=mse,
        mse_standard_error=se,
        below_zero=below,
        zero_at_noise=zero_at,
    )

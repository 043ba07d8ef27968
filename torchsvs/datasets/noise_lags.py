r"""A check of the noise reading against the one thing motion of the model cannot fake: the
covariance of second differences two reports apart (:func:`lag_reading`, :func:`motion_checked`).

The three-point residual :math:`u_i = \sum_j c_{ij} z_{i+j}` of
:func:`~torchsvs.datasets.differences.difference_residuals` (order 2, unit noise gain) and the one
two reports on, :math:`u_{i+2}`, share one position, :math:`z_{i+2}`. Under white measurement
noise of variance :math:`r` and white acceleration (any ``q``), :math:`E[u_i u_{i+2}] = r\,
c_{i2} c_{i+2,0}` exactly, at any report times: the noise enters through the shared position
alone, and the two stencils' Peano kernels (:math:`[t_i, t_{i+2}]` and :math:`[t_{i+2},
t_{i+4}]`) do not overlap, so the motion adds nothing. Where the report interval is long against
the target's manoeuvres (a van's corners and stops between reports 60 s apart), the motion
between reports is not white acceleration: its second differences read as noise at every order
(:func:`~torchsvs.datasets.estimate_noise`, 62-77 m for a 5 m sensor), but two reports apart they
correlate negatively (a stop follows a start), where noise makes them positive. On the
recorded-tracks benchmark's kinds (aircraft at 1-10 s and irregular reports, taxiing, turning,
simulated walkers, cars, ships and drones, σ 0.5-100 m, with white, mixed and heavy-tailed noise
and outliers) the lag reading is never surely below the noise reading: it reads 0.24-0.65 of it
at irregular reports (turns between them raise the noise reading too), else 0.76 and more (turns
held over several reports raise the lag reading). Noise correlated over seconds reads lower
(0.14 on aircraft on 1 s scans).

Motion whose covariance two reports apart is not 0 but changes little to three reports apart (a
stop-and-go between 10 s reports) moves the lag reading where the noise reading is right; the
covariance three reports apart, 0 for noise and white acceleration at any report times (the
stencils share no position and their kernels do not overlap), cancels it: the check acts only
where the lag-2 less lag-3 reading agrees (:data:`LAG_SHARE`).

Motion that covaries two and three reports apart as noise does (a city bus's runs, block after
block, between reports 30 s apart) escapes both; the positions' smallest changes then bound the
noise from above (:mod:`~torchsvs.datasets.noise_ceiling`), and :func:`motion_checked` reads
that too.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.datasets.differences import observed_first, unit_weights
from torchsvs.datasets.noise_ceiling import ceiling_reading
from torchsvs.datasets.noise_estimate import (
    CUTOFF,
    MANEUVER,
    NoiseEstimate,
    truncated_second_moment,
)

#: Groups of the delete-a-group jackknife of the lag reading's standard error (blocks of
#: :data:`BLOCK` reports of a track, assigned to groups in turn).
GROUPS = 20
BLOCK = 16
#: The lag reading contradicts the noise reading where it is below it by this many standard
#: errors (of their ratio): then the difference joins the reading's standard error
#: (:func:`motion_checked`), so that the guards that read the noise's uncertainty act on it.
#: The products of residuals are heavy-tailed (a manoeuvre's), so the bar is higher than the
#: shortest stencils' (``noise_estimate.SHORT_ERRORS``).
LAG_ERRORS = 4.0
#: ... and where it is below this share of the reading (its σ below half the reading's): the
#: motion at other report times also moves the lag reading, where the reading is right. Walkers
#: reported every 10 s with σ 3 m read 3.2 m, and the lag reading 0.52 ± 0.05 of it (waits and
#: corners): at its low end (2.1 m) the Kalman smoother was 15% worse than at the reading;
#: vans in a city every 10 s 0.83 ± 0.02. Where the reading is motion, it is far lower: vans
#: every 60 s -0.87, cars every 30 s -1.4, ships every 2-60 min -1.1. The lag-2 less lag-3
#: reading (``LagReading.beyond``) must be below it too: a stop-and-go's covariance changes
#: little from two reports apart to three and cancels in it. Bicycles and scooters on 10 s
#: reports, σ 5 m read 6.1-7.0 m, read -0.10 to -0.64 two apart but 0.31-0.80 less three apart,
#: and the Kalman smoother at the reading was 8-19% below the measurements (at the low end, 0);
#: buses every 15-60 s, read 18-59 m for 5-10 m, -3.2 to 0.08.
LAG_SHARE = 0.25
#: ... or where it is below that share by this many of its own standard errors, whatever the
#: reading's uncertainty: a reading that is motion is as uncertain as the motion (ships by
#: satellite AIS, 5-60 min apart, σ 10 m, read 400 ± 170 m, the lag reading -0.5 ± 0.18 of it).
FAR_ERRORS = 2.0
#: ... and the difference that joins the standard error reaches the lag reading's low end, this
#: many of its standard errors down: motion contradicts the reading, and a noise read too low
#: costs little (the estimates follow the measurements) where one read too high smooths away
#: motion without bound (``sample_accuracy.lowered_noise``).
LOW_ERRORS = 2.0
#: Noise trimmed to its core at ``CUTOFF`` standard deviations on both residuals of a pair
#: covaries at this share of the untrimmed (to first order in the pair's small correlation:
#: the truncated second moment squared).
CORE_PRODUCT = truncated_second_moment(CUTOFF) ** 2
#: Fewest pairs of residuals two reports apart for the check.
LEAST_PAIRS = 200
#: The smallest changes contradict the reading where it is above this many times the most
#: noise they allow (:func:`~torchsvs.datasets.noise_ceiling.ceiling_reading`). Where the
#: reading was noise (within a fifth of it, or below it): 1.20 at most, on the 128 sets of the
#: recorded-tracks benchmarks (every kind, white, mixed, heavy-tailed and correlated noise,
#: faults), a probe's vehicles and a radar's errors (range and cross-range 1:10, turning with
#: the bearing); where motion raised it to 3.5 times the noise and more: 1.5-34, on buses,
#: trams, vans, trucks, scooters, aircraft in turns and ships by satellite, reported 15 s to an
#: hour apart.
CEILING_RATIO = 1.5
#: ... and where the lag reading is below this share of the reading by :data:`LAG_ERRORS_BELOW`
#: of its standard errors: noise whose level changes from row to row (two sensors interleaved,
#: 30% of rows at 40 m and 70% at 5 m; a receiver switching between 3 and 30 m every few
#: reports; a level drawn for each row) puts more residuals near 0 than one level does, and the
#: bound read 1.5-2.6 times below it with no motion at all; but noise of any level, row by row
#: too, covaries two reports apart as the reading says (0.86-1.09 of it there), where motion
#: that raises the reading makes that covariance smaller (buses every 30-45 s: 0.24-0.60).
CEILING_LAG = 0.8
LAG_ERRORS_BELOW = 2.0


class LagReading(NamedTuple):
    """The lag reading of :func:`lag_reading`, as shares of the noise reading."""

    ratio: float  #: the lag-2 covariance over what noise at the reading would make it: 1 if fit
    se: float  #: its standard error (the jackknife's)
    pairs: int  #: pairs of residuals two reports apart it was read from
    #: the lag-2 covariance less the lag-3 one, over the same: 1 if fit (noise and white
    #: acceleration make the lag-3 one 0), and motion whose covariance changes little from one
    #: lag to the next (a stop-and-go's, a turn's) cancels in it
    beyond: float = math.nan
    beyond_se: float = math.nan  #: its standard error


def lag_reading(z: Tensor, dt: Tensor, meas_var: Tensor) -> LagReading | None:
    """The covariance of three-point residuals two reports apart over the one noise of
    variance ``meas_var [m]`` makes (module docstring), pooled over the axes of ``z [B, T, m]``
    (NaN: missing; ``dt [B, T]`` the intervals), and the same less the covariance three reports
    apart, each with the delete-a-group jackknife's standard error; None with fewer than
    :data:`LEAST_PAIRS` pairs."""
    B, T, m = z.shape
    if T < 6:
        return None
    t = torch.cumsum(dt.to(torch.float64), dim=1)
    zc, tc, _, count = observed_first(z.to(torch.float64), t)
    h1, h2 = tc[:, 1:-1] - tc[:, :-2], tc[:, 2:] - tc[:, 1:-1]
    valid = (torch.arange(T - 2) + 2 < count.unsqueeze(1)) & (h1 > 0) & (h2 > 0)
    # (a stencil with two times alike is not valid: its weights, not finite, are left out)
    c0, c1, c2 = unit_weights([tc[:, :-2], tc[:, 1:-1], tc[:, 2:]])
    u = c0 * zc[:, :-2] + c1 * zc[:, 1:-1] + c2 * zc[:, 2:]
    scale = meas_var.to(torch.float64).repeat(B).unsqueeze(1)  # rows are (track, axis)
    u = torch.where(valid, u, 0.0) / scale.sqrt()
    # the reading's own trimming (noise_estimate.CUTOFF, MANEUVER): pairs of the Gaussian core,
    # none within a stencil of a residual that marks a manoeuvre (u_{i-2} .. u_{i+4}, u_{i+5}
    # three reports apart)
    far = (u.abs() > MANEUVER).to(torch.float64).unsqueeze(1)
    pad = torch.nn.functional.pad

    def near(after: int) -> Tensor:
        window = torch.nn.functional.max_pool1d(pad(far, (2, after)), after + 3, stride=1)
        return window.squeeze(1)[:, : T - after] > 0

    core = valid & (u.abs() <= CUTOFF)
    second = u[:, :-2] * u[:, 2:] / CORE_PRODUCT
    third = u[:, :-3] * u[:, 3:] / CORE_PRODUCT
    shared = c2[:, :-2] * c0[:, 2:]  # c_{i2} c_{i+2,0}
    ok = core[:, :-2] & core[:, 2:] & ~near(4) & torch.isfinite(second)
    both = ok[:, :-1] & core[:, 3:] & ~near(5) & torch.isfinite(third)
    pairs = int(ok.sum())
    if pairs < LEAST_PAIRS:
        return None
    ratio, se = _pooled(second, shared, ok, m)
    beyond, beyond_se = _pooled(second[:, :-1] - third, shared[:, :-1], both, m)
    return LagReading(ratio, se, pairs, beyond, beyond_se)


def _pooled(product: Tensor, shared: Tensor, ok: Tensor, m: int) -> tuple[float, float]:
    """``Σ product·shared / Σ shared²`` over ``ok`` (each ``[B·m, n]``) and its delete-a-group
    jackknife standard error over blocks of :data:`BLOCK` steps of a track."""
    rows, cols = ok.nonzero(as_tuple=True)
    group = ((rows // m) * 7 + cols // BLOCK) % GROUPS
    fit = torch.zeros(2, GROUPS, dtype=torch.float64)
    fit[0].scatter_add_(0, group, (product * shared)[ok])
    fit[1].scatter_add_(0, group, shared[ok].square())
    total = fit.sum(1)
    if not float(total[1]) > 0:
        return math.nan, math.nan
    left_out = (total[0] - fit[0]) / (total[1] - fit[1]).clamp_min(1e-300)
    se = float(((GROUPS - 1) / GROUPS * (left_out - left_out.mean()).square().sum()).sqrt())
    return float(total[0] / total[1]), se


def motion_checked(noise: NoiseEstimate, z: Tensor, dt: Tensor) -> NoiseEstimate:
    """The noise estimate ``noise`` with the contradiction of its reading by the motion between
    reports, else ``noise`` itself, each axis group apart (the altitude of 3-D positions: its
    noise and its motion are its own). Two readings can contradict it:

    - the lag reading (``lag_ratio``, per axis), where it is surely below the noise reading and
      below :data:`LAG_SHARE` of it (:data:`LAG_ERRORS` standard errors of the two, or
      :data:`FAR_ERRORS` of its own below that share) and the lag-2 less lag-3 reading
      (``beyond``) is below that share too: its difference joins the reading's standard error
      (``meas_std_se``, in quadrature), whose low end is then the lag reading's,
      :data:`LOW_ERRORS` down. Vans in a city reporting every 60 s with σ 5 m read 62-77 m,
      and the Kalman smoother there was 9.3 times the measurements' error without a word;
    - the smallest changes (``noise_ceiling``, :func:`~torchsvs.datasets.noise_ceiling.
      ceiling_reading`), where the reading is above :data:`CEILING_RATIO` times the most noise
      they allow and the lag reading is surely below :data:`CEILING_LAG`: the reading's low
      end is then 0, and its high end that most (vans every 60 s: the error range was
      0.5-208 m for a true 7 m, now 0.5-16 m). Buses every 30-45 s, σ 3-10 m, read 42-49 m
      (their lag readings 0.24-0.60), and the Kalman smoother was 3.3-9.8 times the
      measurements' error without a word.

    The run's guards then act on the reading's uncertainty: ``sample_accuracy.lowered_noise``
    runs at its low end (at least :data:`~torchsvs.sample_accuracy.MOTION_NOISE_SHARE` of the
    reading), the error estimate gives its range and no point, and the run warns; each of the
    cases above came out at 1.00 times the measurements' error.
    """
    if noise.meas_std_se is None:
        return noise
    se = noise.meas_std_se.to(torch.float64)
    sigma = noise.meas_var.to(torch.float64).sqrt()
    below = torch.zeros_like(sigma)
    lags, ceilings = torch.full_like(sigma, math.nan), torch.full_like(sigma, math.nan)
    for axes in ([0, 1], [2]) if sigma.numel() == 3 else (list(range(sigma.numel())),):
        lag = lag_reading(z[..., axes], dt, noise.meas_var[axes])
        ceiling = ceiling_reading(z[..., axes], dt, noise.meas_var[axes])
        lag_agrees = lag is not None and lag.ratio + LAG_ERRORS_BELOW * lag.se < CEILING_LAG
        if ceiling is not None and ceiling.ratio > CEILING_RATIO and lag_agrees:
            below[axes] = sigma[axes]
            ceilings[axes] = sigma[axes] / ceiling.ratio
        if lag is not None and _lag_contradicts(lag, float((se[axes] / sigma[axes]).mean())):
            low = math.sqrt(max(lag.ratio - LOW_ERRORS * lag.se, 0.0))
            below[axes] = torch.maximum(below[axes], sigma[axes] * (1.0 - low))
            lags[axes] = lag.ratio
    checked = noise._replace(
        meas_std_se=torch.hypot(se, below).to(noise.meas_std_se.dtype),
        lag_ratio=lags if bool(lags.isfinite().any()) else None,
        noise_ceiling=ceilings.to(noise.meas_var.dtype)
        if bool(ceilings.isfinite().any())
        else None,
    )
    return checked if checked.contradicted else noise


def _lag_contradicts(lag: LagReading, relative: float) -> bool:
    """Whether the lag reading contradicts the noise reading (:func:`motion_checked`), the
    reading's σ uncertain by ``relative`` (its ratio of variances by twice that)."""
    below_reading = 1.0 - lag.ratio > LAG_ERRORS * math.hypot(lag.se, 2 * relative)
    far_below = lag.ratio + FAR_ERRORS * lag.se < LAG_SHARE
    if not (far_below or (below_reading and lag.ratio < LAG_SHARE)):
        return False
    return lag.beyond < LAG_SHARE  # (NaN, no pairs three apart: the lag-2 reading stands)

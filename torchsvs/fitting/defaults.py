"""Settings from the data: what ``torchsvs track`` fills in where the user left it open.

The measurement noise (and its standard error) from :func:`~torchsvs.datasets.estimate_noise`,
``q`` as the Kalman smoother's (for a filter, the Kalman filter's) by its exact SURE
(:func:`torchsvs.fitting.noise.smoother_q`), the SVSF's boundary layer from the rule of thumb
(:func:`~torchsvs.recipes.rule_of_thumb_psi`), the IMM's mode noises from :func:`turn_settings`
(:func:`complete_settings`), and the file's SURE curve of ``q`` each track's own ``q`` is
chosen against (:func:`with_q_curve`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets import RecordedTracks, estimate_noise
from torchsvs.datasets.noise_lags import motion_checked
from torchsvs.fitting.noise import (
    QCurves,
    _golden_search,
    curve_inputs,
    q_curve_runs,
    q_curves,
    q_factors,
    smoother_q,
    track_q_factors,
)
from torchsvs.fitting.noise_classes import classes_of
from torchsvs.fitting.noise_read import with_noise_read
from torchsvs.fitting.outliers import (
    AGILITY,
    STRICT_GROSS_SHARE,
    has_gross_errors,
    outlier_distances,
    screen_outliers,
)
from torchsvs.fitting.q_kinds import track_kinds
from torchsvs.fitting.q_windows import choose_window
from torchsvs.recipes import FILTERS, Settings, rule_of_thumb_psi

#: The IMM's CV mode's ``q`` as a fraction of the data's (:func:`turn_settings`).
IMM_QUIET = 0.03
#: The IMM's turn-rate scale in units of ``√(q/T) / v̄`` (:func:`turn_settings`).
TURN_RATE_SCALE = 0.3


def typical_speed(tracks: RecordedTracks) -> float:
    """The median horizontal speed of the tracks (their first two axes) between successive
    observed positions (noise included), or 0 where no two successive positions are
    observed."""
    z = tracks.z[..., :2].to(torch.float64)
    step = (z[:, 1:] - z[:, :-1]).norm(dim=-1) / tracks.dt[:, 1:].to(torch.float64)
    step = step[torch.isfinite(step)]
    return float(step.median()) if step.numel() else 0.0


def imm_base_q(tracks: RecordedTracks, meas_var: Sequence[float]) -> float:
    """The ``q`` the IMM's mode noises are derived from (:func:`turn_settings`): the Kalman
    filter's SURE ``q`` of the horizontal axes. Short differences
    (:func:`~torchsvs.datasets.estimate_noise`'s ``q``) read circling gliders at 10-30 s as a
    quiet CV target and left the IMM at 1.9× raw; the turn is horizontal, and a calm height
    would dilute its scale."""
    horizontal = replace(tracks, z=tracks.z[..., :2])
    return _sure_q(horizontal, list(meas_var)[:2], "kf")


def turn_settings(
    q: float,
    meas_var: Sequence[float],
    interval: float,
    speed: float,
    quiet: float = IMM_QUIET,
    rate_scale: float = TURN_RATE_SCALE,
) -> dict[str, float]:
    r"""The IMM's mode noises from the data's ``q`` (the spectral density of a single CV model,
    which counts the maneuvers as noise: :func:`complete_settings` passes the Kalman filter's
    SURE ``q``), the measurement noise, the typical interval ``T``
    and the typical horizontal speed :math:`\bar v` (:func:`typical_speed`):

    * CV mode: ``q_CV = quiet · q`` (:data:`IMM_QUIET`): quiet, the turns go to the CT mode;
    * CT mode: white acceleration variance ``turn_q = q / T`` (the velocity noise per step of
      the single CV model) and a turn-rate scale :math:`\omega_s = s\,\sqrt{q/T}/\bar v`
      with ``s = rate_scale`` (:data:`TURN_RATE_SCALE`): :math:`\sqrt{q/T}/\bar v` is the
      turn rate whose centripetal acceleration at the typical speed is the CV model's
      acceleration noise over a step. :math:`\omega_s` is the prior standard deviation of
      the turn rate and its standard deviation of change per typical step
      (``turn_rate_q = (ω_s / T)²``).

    For a three-axis file ``q`` is read off the horizontal axes (the turn is horizontal; a calm
    height would dilute the one ``q`` of all three). The speed is floored at the speed the
    measurement noise alone shows between two steps
    (:math:`\sqrt{2r}/T`), so still or slow targets get a finite, small turn rate. The factors
    were chosen on the training half of the recorded calibration flights at σ = 50, 100 and
    200 m (``experiments/results/real_flights.md``, IMM section: a grid of CV shares 0.01-1
    and turn-rate scales 0.1-1). With :func:`imm_base_q` as the base (the study first ran on
    the ``q`` of short differences, to the same choice) the defaults are within 0.5% of the
    grid's best position RMSE at every level, and a quieter CV mode is better down to 0.03
    there (and on simulated turns); a turn-rate scale of 1 let the turn mode's turn rate
    wander to aliasing values (ωT of several radians between scans) on some flights, with
    velocity errors of thousands of m/s.
    """
    r = sum(meas_var[:2]) / len(meas_var[:2])
    speed = max(speed, math.sqrt(2.0 * r) / interval)
    scale = rate_scale * math.sqrt(q / interval) / speed
    return {
        "q": quiet * q,
        "turn_q": q / interval,
        "turn_rate_q": (scale / interval) ** 2,
        "turn_rate_std": scale,
    }


def complete_settings(settings: Settings, tracks: RecordedTracks) -> Settings:
    """Fills what the settings leave open from the data: noise levels and the typical interval
    (and the IMM's mode noises, :func:`turn_settings`)."""
    settings = with_noise_read(settings, tracks)
    assert settings.meas_var is not None
    source = settings.noise or "given"
    meas_std_se, spread = settings.meas_std_se, settings.noise_spread
    interval = float(tracks.dt[tracks.mask].median()) if len(tracks) else 1.0
    meas_var, q = settings.meas_var, settings.q
    imm = settings.estimator == "imm"
    turn_open = imm and None in (settings.turn_q, settings.turn_rate_q, settings.turn_rate_std)
    m = tracks.z.shape[-1]
    if len(meas_var) == 1 and m > 1:
        meas_var = list(meas_var) * m
    if len(meas_var) != m:
        raise ValueError(f"meas_std: expected one value or one per axis ({m}), got {len(meas_var)}")
    data_q = None
    if q is None or turn_open:
        try:
            data_q = (
                imm_base_q(tracks, meas_var)
                if imm
                else file_sure_q(settings, tracks, meas_var, settings.estimator)
            )
        except ValueError:  # too little data to say: the measurement noise over one step
            data_q = sum(meas_var) / len(meas_var) / interval**3
    if q is None and not imm:
        q = data_q
    turn_q, turn_rate_q, turn_rate_std = (
        settings.turn_q,
        settings.turn_rate_q,
        settings.turn_rate_std,
    )
    if imm:
        if m not in (2, 3):
            raise ValueError(
                f"estimator: imm turns in the horizontal plane of 2 or 3 position axes, got {m}"
            )
        if data_q is not None:
            derived = turn_settings(data_q, meas_var, interval, typical_speed(tracks))
            q = derived["q"] if q is None else q
            turn_q = turn_q or derived["turn_q"]
            turn_rate_q = turn_rate_q or derived["turn_rate_q"]
            turn_rate_std = turn_rate_std or derived["turn_rate_std"]
    psi = settings.psi
    if psi is None and settings.estimator in ("svsf", "svss", "svstps", "spvsf"):
        psi = rule_of_thumb_psi(m, settings.velocity, settings.estimator)
    elif psi is not None and len(psi) == 1 and m > 1:
        psi = list(psi) * m  # one value for every axis, as --psi's help says
    assert q is not None  # (an open q sent the IMM through the data too)
    if meas_std_se is not None and len(meas_std_se) == 1 and m > 1:
        meas_std_se = list(meas_std_se) * m
    return replace(
        settings,
        meas_var=[float(v) for v in meas_var],
        noise=source,
        meas_std_se=meas_std_se,
        noise_spread=spread,
        q=float(q),
        interval=interval,
        psi=psi,
        turn_q=turn_q,
        turn_rate_q=turn_rate_q,
        turn_rate_std=turn_rate_std,
    )


#: The first reading of the screen's ``q`` clips SURE's terms at this many ``r`` (a 5σ
#: residual; on rows that fit, a chance of 6e-7).
SCREEN_CLIP = 25.0


class Screened(NamedTuple):
    """What :func:`screened` found."""

    settings: Settings  #: with ``outlier_q`` (unchanged where the screen is off)
    tracks: RecordedTracks  #: the tracks with the outliers' positions missing
    flagged: Tensor  #: [B, T] bool the rows set aside


def screened(settings: Settings, tracks: RecordedTracks) -> Screened:
    """The tracks with their isolated outliers set aside (:mod:`torchsvs.fitting.outliers`),
    and the ``q`` that judges them (``outlier_q``) for the rest of the file: the Kalman
    smoother's SURE ``q`` (:func:`_sure_q`), read first with every term clipped at
    :data:`SCREEN_CLIP` ``r`` (outliers otherwise raise it, and the screen turns lenient),
    then after each of two screens, unclipped, without the outliers that screen found. The
    measurement noise is the settings' where given, else read off the data
    (:func:`~torchsvs.datasets.estimate_noise`, robust to isolated outliers: 50.1 m read for
    50 m with 1% of 10σ ones; :func:`with_noise_read`) and returned in the settings, the
    screen on or off, so it is read once."""
    settings = checked_given_noise(with_noise_read(settings, tracks), tracks)
    if not settings.outliers:
        return Screened(settings, tracks, torch.zeros(tracks.z.shape[:2], dtype=torch.bool))
    first = complete_settings(Settings("ks", meas_var=settings.meas_var, q=1.0), tracks)
    assert first.meas_var is not None
    q = settings.outlier_q
    if q is None:
        try:
            r = torch.tensor(first.meas_var, dtype=torch.float64)
            q = (
                smoother_q(tracks.z, tracks.dt, r, clip=SCREEN_CLIP).q
                if not settings.own_noise
                else class_sure_q(settings, tracks, first.meas_var, "ks")
            )
        except ValueError:  # too little data to say: the measurement noise over one step
            q = sum(first.meas_var) / len(first.meas_var) / first.interval**3
        q = _judging_q(tracks, first.meas_var, q)
    gross = False  # (the sensor errs so often that SURE follows its errors)
    observed = int((~torch.isnan(tracks.z)).any(-1).sum())
    before = None
    for _ in range(1 if settings.outlier_q else 2):
        flagged = screen_outliers(tracks.z, tracks.dt, first.meas_var, q)
        if before is None and settings.outlier_q is None and not settings.own_noise:
            gross = has_gross_errors(int(flagged.sum()), observed, STRICT_GROSS_SHARE)
        if before is not None and torch.equal(flagged, before):
            break  # (the same outliers: the same tracks, the same q)
        before = flagged
        clean = replace(tracks, z=tracks.z.masked_fill(flagged.unsqueeze(-1), math.nan))
        if settings.outlier_q is None:
            try:
                q = file_sure_q(settings, clean, first.meas_var, "ks")
                if gross:  # (the few outliers it left would raise the unclipped one again)
                    r = torch.tensor(first.meas_var, dtype=torch.float64)
                    q = min(q, smoother_q(clean.z, clean.dt, r, clip=SCREEN_CLIP).q)
            except ValueError:
                break
    return Screened(replace(settings, outlier_q=q), clean, flagged)


#: The screen's ``q`` judges at least this share of the observed rows (:func:`_judging_q`).
JUDGED_SHARE = 0.5


def _judging_q(tracks: RecordedTracks, meas_var: Sequence[float], q: float) -> float:
    """The screen's ``q``: ``q`` (the smoother's clipped SURE ``q``), or where the screen at it
    could judge fewer than :data:`JUDGED_SHARE` of the observed rows (the smoother follows the
    measurements, every row's leverage above :data:`~torchsvs.fitting.outliers.MAX_LEVERAGE`),
    the white-acceleration ``q`` the positions' differences read (:func:`~torchsvs.datasets.
    estimate_noise`, trimmed: robust to isolated outliers) where the screen judges at that.
    A few wild rows in a small file drive the clipped SURE to follow them: one row 5,000 km off
    among 300 (three tracks of 100 rows, 5 s, σ 20 m) read ``q`` at 3e8, where the screen judged
    no row and the row stayed; at the differences' 0.003 it is set aside, and the file smoothed
    (4.3 m against 28.5 m)."""
    observed = (~torch.isnan(tracks.z)).any(-1)
    total = int(observed.sum())

    def judged(at: float) -> float:
        d2 = outlier_distances(tracks.z, tracks.dt, meas_var, AGILITY * at)
        return int(torch.isfinite(d2).sum()) / max(total, 1)

    if total == 0 or judged(q) >= JUDGED_SHARE:
        return q
    try:
        robust = estimate_noise(tracks.z, tracks.dt).q
    except ValueError:
        return q
    return robust if robust < q and judged(robust) >= JUDGED_SHARE else q


def spread_tracks(tracks: RecordedTracks, points: int) -> RecordedTracks:
    """The most tracks spread evenly over ``tracks`` whose observed positions number at most
    ``points`` (at least one track)."""
    observed = (~tracks.z[..., 0].isnan()).sum(dim=1)
    count = len(observed)

    def pick(k: int) -> torch.Tensor:
        return torch.linspace(0, count - 1, k).round().long().unique()

    low, high = 1, count  # the largest k whose pick fits
    while low < high:
        middle = (low + high + 1) // 2
        if int(observed[pick(middle)].sum()) <= points:
            low = middle
        else:
            high = middle - 1
    return tracks.subset(pick(low))


#: Where the noise is given, it is checked against the noise read off this many observed
#: positions of the sample (tracks spread over it: 0.035 s; 4,000 took 0.08 s and found no
#: more), ...
GIVEN_CHECK_POINTS = 2000
#: ... and is above what the data show where it exceeds that reading by this many of its
#: standard errors. Motion only raises the reading: given at σ on 63 sets of every kind at
#: σ 3-250 m, none is above it; given at 1.5σ, 50 are, at 2σ 54.
GIVEN_CHECK_ERRORS = 3.0


def checked_given_noise(settings: Settings, tracks: RecordedTracks) -> Settings:
    """The settings with ``noise_above_data`` set where the noise is given (one level for
    all) and above what the data show (:data:`GIVEN_CHECK_ERRORS` standard errors above the
    noise read off :data:`GIVEN_CHECK_POINTS` positions of ``tracks``): a bound given as σ.
    The estimates then smooth more than the data need and the error estimate, resting on the
    noise given, comes out low without being below zero (10 s scans, σ 10 m given as 20: 11.6 m
    estimated for 15.7 m): the run warns, and makes its error estimate at the reading, its
    range reaching the noise given (:attr:`~torchsvs.track_run.TrackRun.accuracy`). With
    ``noise_below_data`` where the noise given is below the reading: the estimates follow the
    measurements more than the data need, and SURE at the noise given counts too little of the
    noise left in them; the error estimate's range reaches the estimate at the reading, and
    where it is well below (:func:`well_below_data`) the same as above."""
    if settings.meas_var is None or settings.noise not in (None, "given"):
        return settings
    variances, m = settings.meas_var, tracks.z.shape[-1]
    if settings.own_noise or len(variances) not in (1, m):
        return settings  # (complete_settings names a count of values that fits no axis)
    part = spread_tracks(tracks, GIVEN_CHECK_POINTS)
    try:
        read = estimate_noise(part.z, part.dt)
    except ValueError:
        return settings
    if read.meas_std_se is None:
        return settings
    given = [v**0.5 for v in (variances * m if len(variances) == 1 else variances)]
    std = read.meas_var.double().sqrt().tolist()
    se = read.meas_std_se.double().tolist()
    levels = list(zip(given, std, se, strict=True))
    above = any(g > s + GIVEN_CHECK_ERRORS * e for g, s, e in levels)
    below = any(s > g + GIVEN_CHECK_ERRORS * e for g, s, e in levels)
    if not (above or below):
        return settings
    # the error estimate is made at the reading: read off the whole sample, as any run's noise
    # (2,000 positions put walkers at 1.95 m for 4.17, the whole sample at 3.76)
    reading = estimate_noise(tracks.z, tracks.dt)
    whole = reading.meas_var.double().sqrt().tolist()
    if above:
        return replace(settings, noise_above_data=whole)
    if motion_checked(reading, tracks.z, tracks.dt).contradicted:
        return settings  # (the reading is motion between reports: no measure of the noise given)
    return replace(settings, noise_below_data=whole)


def class_sure_q(
    settings: Settings, tracks: RecordedTracks, meas_var: Sequence[float], estimator: str
) -> float:
    """:func:`_sure_q` with each track at its own noise (``settings.noise_column``,
    :func:`~torchsvs.fitting.noise_classes.classes_of`, around the file's ``meas_var``): the
    ``q`` of the least SURE summed over the noise classes, each at its own noise (at the file's,
    the noisier tracks' noise reads as motion: 1,514 for 3.5 on 1 s scans whose tracks' σ spans
    3-30 m), by golden section in ``log q`` (:func:`~torchsvs.fitting.noise._golden_search`).
    Whole tracks, unclipped (the screen's first reading clips each term where one noise serves
    all)."""
    around = replace(settings, meas_var=list(meas_var))
    parts = []  # (each class's tracks and their prior, once: the search reads them at every q)
    for each in classes_of(tracks, np.arange(len(tracks)), around):
        part, own = tracks.subset(each.members), each.settings.meas_var
        assert own is not None
        parts.append(curve_inputs(part.z, part.dt, own))
    smoothed = estimator not in FILTERS
    found: dict[float, float] = {}

    def totals(log_qs: list[float]) -> list[float]:
        """SURE summed over the classes at each ``q``: every new one in one pass a class."""
        new = [x for x in dict.fromkeys(log_qs) if x not in found]
        if new:
            risk = [0.0] * len(new)
            qs = tuple(math.exp(x) for x in new)  # (1 × each: the q itself, bit for bit)
            for inputs in parts:
                curves = q_curves(inputs.z, inputs.dt, inputs.r, 1.0, smoothed, qs, inputs)
                for i in range(len(new)):
                    risk[i] += float(curves.risk[i].sum())
            found.update(zip(new, risk, strict=True))
        return [found[x] for x in log_qs]

    # bracketed from the file-noise reading (on windows: cheap), which the noisier tracks' noise
    # pushes up: half decades from 4 below it to 1 above (smoother_q's whole grid took about 1.3x
    # the plan's time on 1 s scans for the same q, to its tolerance)
    start = math.log(_sure_q(tracks, meas_var, estimator))
    step = 0.5 * math.log(10.0)
    grid = [start + k * step for k in range(-8, 3)]
    return math.exp(_golden_search(lambda x: totals([x])[0], grid, totals))


def file_sure_q(
    settings: Settings, tracks: RecordedTracks, meas_var: Sequence[float], estimator: str
) -> float:
    """The ``q`` the file's tracks are served with at the noise ``meas_var``: :func:`_sure_q`,
    or with each track at its own noise (``settings.noise_column``) :func:`class_sure_q`."""
    if not settings.own_noise:
        return _sure_q(tracks, meas_var, estimator)
    return class_sure_q(settings, tracks, meas_var, estimator)


def _sure_q(tracks: RecordedTracks, meas_var: Sequence[float], estimator: str) -> float:
    """The q a Kalman smoother (or, for :data:`~torchsvs.recipes.FILTERS`, a Kalman filter)
    serves these tracks with (:func:`torchsvs.fitting.noise.smoother_q`: its exact SURE, the
    noise fixed): the motion that short differences show (``estimate_noise``'s q) is no guide
    at long scans or for slow targets."""
    r = torch.tensor(meas_var, dtype=torch.float64)
    return smoother_q(tracks.z, tracks.dt, r, smoothed=estimator not in FILTERS).q


#: Where the noise was read off the data, a choice that SURE makes at the reading holds only if
#: it holds at every noise level within this many standard errors of it: the IMM's smoothed
#: pass over its filtered one (:func:`~torchsvs.smoother_guard.smoothed_or_filtered`), the
#: SVSF family's layer and ``auto``'s candidates (:func:`~torchsvs.selection.compared`), the
#: Kalman smoother's window of ``q`` (:func:`~torchsvs.fitting.q_windows.choose_window`).
#: Measured with the IMM on the recorded-tracks benchmark's sets: at the estimate alone (0) the
#: gliders and survey aircraft at irregular times (σ 50 read as 71.8 ± 17 m) kept smoothers
#: that were worse than their filters, 1.07x raw; at 2 the airliners at 1 s (σ 10 read as 10.9
#: ± 1.7 m) lost good smoothers, 0.58 -> 0.70x raw; at 1 both held (1.00x and 0.58x raw).
GUARD_ERRORS = 1.0


def meas_var_range(
    settings: Settings, errors: float = 2.0
) -> tuple[list[float], list[float]] | None:
    """The measurement variance ``errors`` standard errors (of its standard deviation) below and
    above the settings' own, where the noise was read off the data with a standard error (else
    None)."""
    if settings.noise == "given" or settings.meas_var is None or settings.meas_std_se is None:
        return None
    std = [v**0.5 for v in settings.meas_var]
    se = settings.meas_std_se
    low = [max(s - errors * e, 0.0) ** 2 for s, e in zip(std, se, strict=True)]
    high = [(s + errors * e) ** 2 for s, e in zip(std, se, strict=True)]
    if settings.noise_ceiling is not None:  # (the most noise the smallest changes allow)
        ceiling = [math.inf if c is None or c != c else c * c for c in settings.noise_ceiling]
        high = [min(h, c) for h, c in zip(high, ceiling, strict=True)]
    return low, high


def settings_note(settings: Settings) -> str:
    """One line on the model's noise levels and where the measurement noise came from."""
    assert settings.meas_var is not None
    std = ", ".join(f"{v**0.5:.4g}" for v in settings.meas_var)
    source = {"given": "as given", "fit": "learned"}.get(settings.noise or "", "read off the data")
    if settings.noise_column is not None:
        source = f"the rows' root mean square of {settings.noise_column!r}; each track at its own"
    elif settings.track_noise is not None:
        source = (
            f"read off the data; each track at its own, read off its positions (they differ "
            f"by about {settings.track_noise[1]:.0%})"
        )
    if settings.noise == "data" and settings.meas_std_se is not None:
        source += " ± " + ", ".join(f"{e:.2g}" for e in settings.meas_std_se)
    return (
        f"model: measurement noise std [{std}] ({source}), q = {settings.q:.4g}, "
        f"typical interval {settings.interval:.4g} s"
    )


def noise_class_curves(
    settings: Settings, tracks: RecordedTracks, smoothed: bool, factors: tuple[float, ...]
) -> QCurves:
    """The tracks' SURE curves of ``q`` at ``factors`` (:func:`~torchsvs.fitting.noise.
    q_curves`), each track at its own noise (``settings.noise_column``,
    :func:`~torchsvs.fitting.noise_classes.classes_of`): so the file's pooled curve is in the
    units each track runs in."""
    assert settings.q is not None
    risk = torch.zeros(len(factors), len(tracks), dtype=torch.float64)
    counts = torch.zeros(len(tracks), dtype=torch.float64)
    for each in classes_of(tracks, np.arange(len(tracks)), settings):
        part, rows = tracks.subset(each.members), each.members
        assert each.settings.meas_var is not None
        found = q_curves(part.z, part.dt, each.settings.meas_var, settings.q, smoothed, factors)
        risk[:, rows], counts[rows] = found.risk, found.counts
    return QCurves(risk, counts, track_kinds(tracks.z, tracks.dt))


#: The share of the sample's scored positions, in tracks whose own SURE is least at the lowest
#: of :data:`~torchsvs.fitting.noise.Q_FACTORS`, from which the file's grid reaches lower
#: (:data:`~torchsvs.fitting.noise.LOW_FACTORS`): still targets among moving ones.
LOW_EDGE_SHARE = 0.05


def wants_lower_q(curves: QCurves) -> bool:
    """Whether tracks holding :data:`LOW_EDGE_SHARE` of the scored positions of ``curves``
    (at :data:`~torchsvs.fitting.noise.Q_FACTORS`) have their own SURE least at the lowest
    factor, below the next: they would take a smaller ``q`` than the grid offers."""
    own = curves.risk / curves.counts.clamp_min(1.0)
    edge = (own.argmin(0) == 0) & (own[0] < own[1]) & (curves.counts > 0)
    total = float(curves.counts.sum())
    return total > 0 and float(curves.counts[edge].sum()) >= LOW_EDGE_SHARE * total


#: :func:`axes_q` reports the axes' own factors on ``q`` where the least and the largest are at
#: least this far apart: a decade (3-D aircraft, σ 5, 5, 50 m: the horizontal axes alone want
#: 3.2 times the file's ``q``, the altitude 0.32 times; one ``q`` left the horizontal 4.02 m
#: from the truth against 2.92 m without the altitude, its 95% intervals holding 75%).
AXES_APART = 10.0


def axes_q(settings: Settings, tracks: RecordedTracks) -> Settings:
    """The settings with each axis's own factor on ``q`` (``axis_q``), where positions of three
    axes want ``q``'s :data:`AXES_APART` or more apart: each axis's SURE curve of the Kalman
    smoother (filter) on ``tracks`` alone, its least factor (the run then warns: one ``q``
    serves every axis). Unchanged for fewer axes (the horizontal axes move alike) and where
    ``q`` was given."""
    m = tracks.z.shape[-1]
    if m < 3 or settings.q is None or settings.meas_var is None:
        return settings
    grid = q_factors(settings.q_low)
    smoothed = settings.estimator not in FILTERS
    least = []
    for j in range(m):
        curves = q_curves(
            tracks.z[..., j : j + 1], tracks.dt, [settings.meas_var[j]], settings.q, smoothed, grid
        )
        if float(curves.counts.sum()) == 0:
            return settings
        least.append(grid[int(np.argmin(curves.pooled()))])
    if max(least) < AXES_APART * min(least):
        return settings
    return replace(settings, axis_q=least)


def with_q_curve(settings: Settings, tracks: RecordedTracks, widen: bool = True) -> Settings:
    """The settings with the file's SURE curve of ``q`` (``q_curve``, read off ``tracks``), so
    that each track runs with its own ``q``; unchanged where ``settings.track_q`` is off, for
    the IMM (its modes' noises are one design) and where the tracks give nothing to score. For
    the Kalman smoother also the window of its ``q`` per step (``q_window``,
    :func:`~torchsvs.fitting.q_windows.choose_window`), where SURE finds one below each
    track's own ``q``. Where still targets want less than the grid's lowest factor
    (:func:`wants_lower_q`), with ``widen`` the curve is read again on a grid reaching lower
    (``q_low``; :func:`~torchsvs.sample_accuracy.checked_low` then holds it to the sample's
    SURE)."""
    if settings.blend is not None:  # each of a blend's estimators its own curve
        settings = replace(settings, blend=with_q_curve(settings.blend, tracks, widen))
    if not settings.track_q or settings.estimator in ("imm", "auto"):
        return settings
    assert settings.meas_var is not None and settings.q is not None
    smoothed = settings.estimator not in FILTERS
    factors = q_factors(settings.q_low)

    def lower() -> Settings | None:  # read again on the lower grid, where the tracks want it
        if widen and not settings.q_low and wants_lower_q(curves):
            return with_q_curve(replace(settings, q_low=True), tracks)
        return None

    def curve_of(found: QCurves) -> Settings:  # the file's curve and its kinds'
        return replace(settings, q_curve=found.pooled(), q_kinds=found.by_kind(), q_window=None)

    kinds = track_kinds(tracks.z, tracks.dt)
    if settings.own_noise:  # each noise class's curves at its own noise
        curves = noise_class_curves(settings, tracks, smoothed, factors)
        if float(curves.counts.sum()) == 0:
            return settings
        return lower() or curve_of(curves)
    if settings.estimator != "ks" or not settings.step_q:  # (a window: the smoother's alone)
        curves = q_curve_runs(
            tracks.z, tracks.dt, settings.meas_var, settings.q, smoothed, factors, kinds=kinds
        )[0]
        if float(curves.counts.sum()) == 0:
            return settings
        return lower() or curve_of(curves)

    def choose(found: QCurves) -> Tensor:
        return track_q_factors(found, found.pooled(), factors, kinds=found.by_kind())

    curves, _, own = q_curve_runs(
        tracks.z, tracks.dt, settings.meas_var, settings.q, True, factors, choose, True, None, kinds
    )
    if float(curves.counts.sum()) == 0:
        return settings
    again = lower()
    if again is not None:
        return again
    window = None
    lowest: list[float] = []  # the share of steps weighing the lowest factor most
    if own is not None:
        noise_range = meas_var_range(settings, GUARD_ERRORS)
        window = choose_window(
            tracks.z, tracks.dt, settings.meas_var, settings.q, own, noise_range, factors, lowest
        )
    if widen and window is not None and not settings.q_low and lowest[0] >= LOW_EDGE_SHARE:
        # still steps of moving tracks (a car parked between drives) want less there
        return with_q_curve(replace(settings, q_low=True), tracks)
    return replace(curve_of(curves), q_window=window)

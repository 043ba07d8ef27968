"""The measurement noise read off the data where the user leaves it open
(:func:`with_noise_read`): :func:`~torchsvs.datasets.estimate_noise`'s reading of the file, its
standard error, how much the tracks differ (:func:`~torchsvs.datasets.noise_spread`) and how much
the noise changes within them (:func:`~torchsvs.datasets.track_noise.within_spread`).

The reading is robust: it keeps the Gaussian core of the divided differences and sets aside what
looks like motion. Where a sensor's noise changes within the tracks (5 m, then 40 m after a
switch of receiver), that core is the quiet stretches' alone, and the loud ones then read as
motion the smoother follows: on 150 cars, 5 m for 150 s then 40 m, the noise read 5.0 m, the
Kalman smoother's estimates came out at 0.99 of the measurements' error and its error estimate
at 0.14 of the truth, in a range that missed it. There the file's noise is the mean of its pieces'
(:data:`WITHIN_SPREAD`) and the run says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import torch

from torchsvs.datasets import RecordedTracks, estimate_noise, noise_spread
from torchsvs.datasets.noise_estimate import NoiseFreeError
from torchsvs.datasets.noise_lags import motion_checked
from torchsvs.datasets.track_noise import PIECE_POINTS, within_spread
from torchsvs.fitting.noise_classes import column_noise
from torchsvs.recipes import Settings, short

#: The noise read on pieces of the tracks (:func:`~torchsvs.datasets.track_noise.within_spread`)
#: changes within them beyond this spread of ``log σ``: the file's noise is then the mean of the
#: pieces' variances, not the reading's core. Read on pieces of 80 positions: a sensor going
#: from 5 to 40 m 1.3 and from 5 to 15 m 0.58; two sensors interleaved row by row (30% of rows
#: at 40 m, the others at 5 m) 0.28; white noise on the benchmark's recorded kinds and
#: simulated vehicles, their tracks at one noise or each at its own, 0.15 at most.
WITHIN_SPREAD = 0.4


#: A noise given is below what the data show where their reading is 3 of its standard errors
#: above it (:func:`~torchsvs.fitting.defaults.checked_given_noise`): the error estimate's range
#: then reaches the estimate at the reading; where the reading is also this many times the noise
#: given, the estimate is made there and the run warns. Motion raises the reading: on the 20
#: white-noise sets of the recorded and kinds benchmarks it is at most 1.21 times the noise (own
#: report times, σ 10 m). Drones with gaps at σ 20 m: given as 10, the Kalman smoother estimated
#: its error 13.2 m [13.18, 13.23] for a true 25.2 m, given as 14 16.7 m [16.6, 16.7] for 19.6,
#: as 17 16.2 m [16.0, 16.4] for 11.5, without a word; now 24.5 m [13.1, 24.6] and a warning,
#: 16.7 m [16.6, 18.9], 16.2 m [11.3, 16.4].
GIVEN_BELOW_RATIO = 1.5


def well_below_data(settings: Settings) -> bool:
    """Whether the noise given is well below the data's reading (``noise_below_data``,
    :data:`GIVEN_BELOW_RATIO`): the run's error estimate is made at the reading, and it warns."""
    read, given = settings.noise_below_data, settings.meas_var
    if read is None or given is None:
        return False
    given = given * len(read) if len(given) == 1 else given
    return any(s > GIVEN_BELOW_RATIO * g**0.5 for s, g in zip(read, given, strict=True))


def with_noise_read(settings: Settings, tracks: RecordedTracks) -> Settings:
    """The settings with the measurement noise read off ``tracks`` where they leave it open
    (:func:`~torchsvs.datasets.estimate_noise`; ``noise="data"``, its standard error and the
    between-track spread), where it changes within the tracks the mean of their pieces'
    (``noise_within``, :data:`WITHIN_SPREAD`); unchanged where it is given."""
    if settings.meas_var is not None:
        return settings
    column = settings.noise_column
    if column is not None:  # each row's own: the file's is their mean square
        observed = ~torch.isnan(tracks.z).all(-1)
        var = column_noise(tracks.extra[column], observed, column)
        return replace(settings, meas_var=[var] * tracks.z.shape[-1], noise="given")
    try:
        noise = motion_checked(estimate_noise(tracks.z, tracks.dt), tracks.z, tracks.dt)
    except ValueError as err:
        if isinstance(err, NoiseFreeError):
            raise ValueError(
                "meas_std: the positions carry no measurement noise to read: most lie exactly "
                "on smooth paths (noise-free, simulated or interpolated data); give the noise "
                "(--meas-std) and the process noise (--q)"
            ) from err
        longest = int((~torch.isnan(tracks.z).any(-1)).sum(1).max()) if len(tracks) else 0
        raise ValueError(
            "meas_std: too few observed positions within a track to read the measurement noise "
            "off the data (it takes differences over several positions of one track; the "
            f"longest track read has {longest}); give it (--meas-std) and the process noise "
            "(--q)"
        ) from err
    meas_var = noise.meas_var.double().tolist()
    spread = noise_spread(tracks.z, tracks.dt)
    within = within_spread(tracks.z, tracks.dt, meas_var)
    changes = None
    uncertain = spread
    if within is not None and within.tau > WITHIN_SPREAD:
        core = sum(v**0.5 for v in meas_var) / len(meas_var)
        mean = core * within.mean_ratio**0.5
        changes = [within.tau, within.low * core, within.high * core, core, mean]
        meas_var = [v * within.mean_ratio for v in meas_var]
        # (the standard error of the jackknife is the core's, scaled; the pieces' spread adds
        # the uncertainty of one level for stretches of several)
        if noise.meas_std_se is not None:
            noise = noise._replace(meas_std_se=noise.meas_std_se * within.mean_ratio**0.5)
        uncertain = math.hypot(spread or 0.0, within.tau)
    meas_std_se = _noise_standard_error(noise, meas_var, uncertain)
    return replace(
        settings,
        meas_var=meas_var,
        noise="data",
        meas_std_se=meas_std_se,
        noise_spread=spread,
        noise_within=changes,
        noise_lag=None if noise.lag_ratio is None else noise.lag_ratio.tolist(),
        noise_ceiling=None if noise.noise_ceiling is None else noise.noise_ceiling.tolist(),
    )


def _noise_standard_error(
    noise: Any, meas_var: Sequence[float], spread: float | None
) -> list[float] | None:
    """The standard error of the noise standard deviation per axis that
    :func:`~torchsvs.datasets.estimate_noise` reports, if it does, with the between-track
    spread (:func:`~torchsvs.datasets.noise_spread`) added in quadrature: where one noise level
    does not fit every track, the pooled reading is that uncertain, whatever its jackknife."""
    se = getattr(noise, "meas_std_se", None)
    if se is None:
        return None
    extra = [(spread or 0.0) * v**0.5 for v in meas_var]
    return [
        math.hypot(float(v), e) for v, e in zip(torch.as_tensor(se).reshape(-1), extra, strict=True)
    ]


def within_warning(settings: Settings) -> str | None:
    """The run's warning where the noise changes within the tracks (``noise_within``)."""
    if not settings.noise_within or settings.meas_var is None:
        return None
    tau, low, high, core, mean = settings.noise_within
    read = (
        f"measurement noise: it changes within the tracks: read on pieces of "
        f"{PIECE_POINTS} positions it spans {low:.3g}-{high:.3g} m (the quietest and the "
        f"noisiest tenth; a spread of {tau:.0%} beyond the pieces' own uncertainty), where the "
        f"file's reading ({core:.3g} m) is the quiet stretches' alone; "
    )
    if not within_mean_taken(settings):
        return read + (
            f"at the pieces' mean ({mean:.3g} m) the Kalman smoother's leave-one-out error was "
            "not lower, so the run kept the file's reading: the loud pieces are of tracks "
            "whose motion between reports reads as noise there, or of a few tracks of another "
            "kind (two targets under one id), and the error estimate may miss them; where the "
            "sensor's noise changes, estimate each stretch apart with --meas-std of its own"
        )
    return read + (
        f"one noise level serves every step, so the run took the pieces' mean, {mean:.3g} m: "
        "the loud stretches are smoothed less and the quiet ones more than each alone would "
        "be, and the error estimate is the run's as a whole (its range takes in the spread), "
        "not each stretch's; where the sensor's noise changes (a new receiver, a mode switch), "
        "estimate each stretch apart with --meas-std of its own"
    )


def within_mean_taken(settings: Settings) -> bool:
    """Whether the settings run at the pieces' mean where the noise changes within the tracks
    (``noise_within``), not at the file's reading
    (:func:`~torchsvs.sample_accuracy.checked_within` kept it)."""
    if not settings.noise_within or settings.meas_var is None:
        return False
    level = sum(v**0.5 for v in settings.meas_var) / len(settings.meas_var)
    core, mean = settings.noise_within[3], settings.noise_within[4]
    return abs(level - mean) < abs(level - core)


#: Between-track spread of the noise read off the data (relative) above which a run warns:
#: 0.27 on gliders and survey aircraft at 6-33 s reports, at most 0.12 on the benchmark's other
#: recorded kinds (``experiments/results/recorded_tracks.md``).
NOISE_SPREAD_WARNING = 0.2


def noise_warnings(settings: Settings, run_std: Sequence[float]) -> list[str]:
    """The run's warnings on its measurement noise (``run_std`` the noise its error estimate
    was made at): changing within the tracks, differing between them, given above or well
    below what the data show, or lowered from the reading."""
    out: list[str] = []
    spread = settings.noise_spread
    own = settings.track_noise
    changes = within_warning(settings)
    if changes is not None:
        out.append(changes)
    if own is not None:
        out.append(
            f"measurement noise: read off each track alone it differs between tracks by "
            f"about {own[1]:.0%}, more than their own uncertainty: each track ran at its own "
            "reading (shrunk towards the file's), and the error estimate rests on those "
            "readings; where the sensor states each row's accuracy, give it with --noise-col "
            "(a column of its standard deviation)"
        )
    elif settings.noise == "data" and spread is not None and spread > NOISE_SPREAD_WARNING:
        out.append(
            f"measurement noise: read off each track alone it differs between tracks by "
            f"about {spread:.0%}, more than their own uncertainty: one noise level does not "
            "fit every track (different sensors, or motion the model does not follow at "
            "these report times), and the error estimate rests on it; give --meas-std with "
            "the sensor's noise if known, and where the tracks come from sensors of "
            "different quality, each row's with --noise-col (a column of its standard "
            "deviation) or each sensor's tracks apart with its own: one noise for all fits "
            "none (on tracks whose noise spans a third to three times the file's, the "
            "estimates came out at 0.6-1.0 of the measurements' error)"
        )
    above = settings.noise_above_data
    if above is not None and settings.meas_var is not None:
        out.append(
            f"measurement noise: given as {short([v**0.5 for v in settings.meas_var])} "
            f"m, above what the data show (read off them: {short(above)} m; motion only "
            "raises that reading): a bound given as the standard deviation, errors "
            "correlated from report to report, or errors with heavy tails (the reading "
            "counts their Gaussian core); the estimates smooth more than the data "
            "need, and the error estimate is made at the reading, its range reaching the "
            "noise given; give --meas-std as the sensor's 1σ, or leave it out to read it "
            "off the data"
        )
    below = settings.noise_below_data
    if below is not None and settings.meas_var is not None and well_below_data(settings):
        out.append(
            f"measurement noise: given as {short([v**0.5 for v in settings.meas_var])} "
            f"m, well below what the data show (read off them: {short(below)} m): the "
            "estimates follow the measurements more than the data need, and the error "
            "estimate is made at the reading, its range reaching the noise given (motion "
            "between sparse reports also raises the reading); give --meas-std as the "
            "sensor's 1σ, or leave it out to read it off the data"
        )
    motion = motion_warning(settings)
    if motion is not None:
        out.append(motion)
    lowered = settings.noise_lowered_from
    if lowered is not None and motion is not None:
        out.append(
            f"measurement noise: read off the data as {short(lowered)} m, contradicted as "
            f"above; ran at the low end of its uncertainty, {short(run_std)} m (a noise read "
            "too high smooths away motion the model does not follow; one too low leaves the "
            "estimates near the measurements)"
        )
    elif lowered is not None:
        out.append(
            f"measurement noise: read off the data as {short(lowered)} m, at which the "
            f"Kalman smoother was not clearly below the measurements over that reading's "
            f"uncertainty; ran at its low end, {short(run_std)} m (a noise read too "
            "high smooths away motion the model does not follow); give --meas-std with the "
            "sensor's noise if known"
        )
    return out


#: A noise read below this (m) is float rounding, not noise (:func:`motion_warning`).
NO_NOISE = 1e-6
#: The lag reading's other cause (:func:`motion_warning`).
CORRELATED = ", or the noise is correlated from report to report"


def motion_warning(settings: Settings) -> str | None:
    """The warning where the noise reading is contradicted as motion between reports
    (:func:`~torchsvs.datasets.noise_lags.motion_checked`): by the second differences two
    reports apart (``noise_lag``) or by the smallest changes (``noise_ceiling``)."""
    if not settings.reading_is_motion:
        return None
    read = settings.noise_lowered_from or [v**0.5 for v in settings.meas_var or []]
    flagged = [j for j in range(len(read)) if settings.reading_is_motion_on([j])]
    if flagged and all(read[j] < NO_NOISE for j in flagged):
        return (
            f"measurement noise: the positions read no noise on axes {flagged} (at float "
            f"rounding, {short([read[j] for j in flagged])} m: noise-free, quantized or "
            "interpolated positions, such as ADS-B's barometric altitude in 25 ft steps), so "
            "their error cannot be read off them and the error estimate there is unknown; "
            "give --meas-std with the sensor's noise if known"
        )
    lags = [v for v in settings.noise_lag or [] if v is not None and v == v]
    ratio = min(lags) if lags else None
    ceiling = settings.noise_ceiling or []
    why = (
        f"the positions' second differences two reports apart covary at {ratio:.2g} times what "
        "noise at the reading makes (noise of any level makes it 1, and steady motion or "
        "white acceleration adds nothing)"
        if ratio is not None
        else "more of the positions' smallest changes are small than noise at the reading "
        f"allows: they allow at most {short([c for c in ceiling if c is not None and c == c])} "
        "m, whatever the motion (motion only spreads them)"
    )
    return (
        f"measurement noise: the reading off the data is mostly motion between reports: {why}, "
        "so the reports' changes of speed and direction (corners, stops) read as noise at "
        f"these report times{CORRELATED if ratio is not None else ''}; the reading's "
        "uncertainty takes in the difference, and the error estimate's range with it; give "
        "--meas-std with the sensor's noise if known"
    )

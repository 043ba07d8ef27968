"""Whether the noise read off a file serves, judged on a sample before anything is written:
the truth-free error estimate of an estimator on padded tracks (:func:`sample_accuracy`,
used by ``--estimator auto`` to compare candidates) and the noise to run at where the Kalman
smoother on the reading is not clearly below the measurements (:func:`lowered_noise`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.accuracy import Accuracy, RiskTerms, exact_divergence
from torchsvs.accuracy import accuracy as accuracy_of
from torchsvs.blending import best_weight, blended_terms
from torchsvs.datasets import RecordedTracks
from torchsvs.datasets.steps import length_batches
from torchsvs.datasets.track_noise import read_track_noise, shrunk_ratios, spread_of
from torchsvs.estimating import (
    _estimate_factors,
    blend_parts,
    by_noise_class,
    estimate_group,
    in_batch_order,
)
from torchsvs.fitting import noise_classes
from torchsvs.fitting.defaults import (
    GUARD_ERRORS,
    complete_settings,
    meas_var_range,
    spread_tracks,
    with_q_curve,
)
from torchsvs.fitting.noise_read import with_noise_read, within_mean_taken
from torchsvs.fitting.tuning import FitResult
from torchsvs.recipes import NOISE_READ, Settings, make_estimator, make_model
from torchsvs.step_estimates import GroupBatch, StepEstimates, centred


def sample_accuracy(settings: Settings, tracks: RecordedTracks) -> Accuracy:
    """The truth-free error estimate (:mod:`torchsvs.accuracy`) of the estimator of complete
    ``settings`` on padded ``tracks`` (run as ``torchsvs track`` runs it, in float64)."""
    return accuracy_of_terms(settings, sample_terms(settings, tracks))


def sample_terms(settings: Settings, tracks: RecordedTracks) -> RiskTerms:
    """:func:`sample_accuracy`'s SURE sums per chunk (the same chunks for every estimator on
    the same ``tracks``: :meth:`~torchsvs.accuracy.RiskTerms.difference` pairs them). Where
    the settings carry the file's curve of ``q`` (``q_curve``), each track runs with its own
    ``q``: every estimator runs as ``track`` runs it (:func:`~torchsvs.estimating.
    estimate_group` after the screen), a Kalman smoother's divergence exact from its pass;
    tracks of like length together where the padded batch is large (:func:`length_groups`)."""
    assert settings.meas_var is not None
    estimator = make_estimator(settings, make_model(settings)).double()

    def run(each: nn.Module, tracks: GroupBatch, std: Tensor, own: Settings) -> StepEstimates:
        return _estimate_factors(each, tracks, std, False, True, own)

    def terms_of(part: RecordedTracks) -> RiskTerms:
        batch, meas_std = _sample_batch(settings, part)
        found = by_noise_class(estimator, batch, meas_std, settings, run)  # (each at its own)
        assert found.risk is not None
        return found.risk.in_track_order()

    groups = length_groups(tracks)
    if groups is None:
        return terms_of(tracks)
    parts = []
    for rows in groups:
        terms = terms_of(tracks.subset(rows))
        parts.append(replace(terms, track=rows.numpy()[terms.track]))
    return RiskTerms.concat(parts, len(settings.meas_var)).in_track_order()


#: A sample's padded batch of more steps than this (tracks × the longest's steps) runs in
#: groups of tracks of like length (:func:`length_groups`): a few long tracks among thousands of
#: short ones padded them all (2,000 tracks of 3-6 rows and one of 500, with 16 probes each: a
#: batch of 16 M steps, 17 GB and four minutes for 14,000 rows).
SAMPLE_CELLS = 1 << 19


def length_groups(tracks: RecordedTracks, cells: int | None = None) -> list[Tensor] | None:
    """The tracks in groups of like length (indices,
    :func:`~torchsvs.datasets.steps.length_batches`), each group's tracks × its longest's steps
    at most ``cells`` (default :data:`SAMPLE_CELLS`; or one track); None where the padded batch
    is within it (one run of all, as before). A track's estimates do not depend on the tracks
    beside it, so the groups give each track what one run gives (the particle filters' draws
    aside)."""
    cells = SAMPLE_CELLS if cells is None else cells
    if len(tracks) * tracks.z.shape[1] <= cells:
        return None
    return [torch.from_numpy(g) for g in length_batches(tracks.lengths.numpy(), cells)]


def _sample_batch(settings: Settings, tracks: RecordedTracks) -> tuple[GroupBatch, Tensor]:
    """``tracks`` as one group (float64, centred) and the settings' noise ``[m]``."""
    assert settings.meas_var is not None
    moved, offset = centred(tracks.to(torch.float64))
    batch = GroupBatch(0, np.arange(len(tracks)), moved, offset)
    return batch, torch.tensor(settings.meas_var, dtype=torch.float64).sqrt()


def sample_blend(
    first: Settings, second: Settings, tracks: RecordedTracks
) -> tuple[float, RiskTerms]:
    """The weight of ``second``'s estimates in the blend with ``first``'s of the least
    estimated MSE on ``tracks`` (:func:`~torchsvs.blending.best_weight`), both run as
    ``track`` runs them (the same noise), and the blend's SURE sums at it (what
    :func:`sample_terms` gives for the blend, from the same runs; tracks of like length
    together where the padded batch is large, :func:`length_groups`)."""
    assert first.meas_var is not None
    m = len(first.meas_var)

    def built(settings: Settings) -> nn.Module:
        return make_estimator(settings, make_model(settings)).double()

    estimators = (built(first), built(second))
    groups = length_groups(tracks)
    parts: list[tuple[RiskTerms, RiskTerms, RiskTerms]] = []
    for rows in groups if groups is not None else [None]:
        part = tracks if rows is None else tracks.subset(rows)
        found = _blend_terms(estimators, first, second, part)
        if rows is not None:  # (the group's tracks by their place in ``tracks``)
            index = rows.numpy()
            mine, other, cross = (replace(t, track=index[t.track]) for t in found)
            found = (mine, other, cross)
        parts.append(found)
    if len(parts) == 1:
        terms = parts[0]
    else:  # (track order, as one run gives)
        mine, other, cross = (RiskTerms.concat([p[k] for p in parts], m) for k in range(3))
        order = np.argsort(mine.track, kind="stable")
        terms = (mine.select(order), other.select(order), cross.select(order))
    weight = best_weight(*terms, first.meas_var)
    return weight, blended_terms(*terms, weight)


def _blend_terms(
    estimators: tuple[nn.Module, nn.Module],
    first: Settings,
    second: Settings,
    tracks: RecordedTracks,
) -> tuple[RiskTerms, RiskTerms, RiskTerms]:
    """:func:`sample_blend`'s terms on ``tracks`` (one run): the two estimators' and their
    cross term, in track order."""
    assert first.meas_var is not None
    batch, meas_std = _sample_batch(first, tracks)
    if not first.own_noise:
        found = blend_parts(estimators, (first, second), batch, meas_std, False, True)
        assert found.terms is not None
        return found.terms
    # each noise class at its own, the two's terms at the file's (the cross term has none)
    parts: list[tuple[RiskTerms, RiskTerms, RiskTerms]] = []
    for each in noise_classes.classes_of(batch.tracks, batch.group, first):
        pair = (each.settings, noise_classes.scaled_settings(second, each.factor))
        std = meas_std * math.sqrt(each.factor)
        with (
            noise_classes.noise_scaled(estimators[0], each.factor) as one,
            noise_classes.noise_scaled(estimators[1], each.factor) as two,
        ):
            found = blend_parts((one, two), pair, batch.subset(each.members), std, False, True)
        assert found.terms is not None
        mine, other, cross = found.terms
        parts.append((each.at_file_noise(mine), each.at_file_noise(other), cross))
    m = len(first.meas_var)
    mine, other, cross = (RiskTerms.concat([p[k] for p in parts], m) for k in range(3))
    order = np.argsort(mine.track, kind="stable")  # (track order, as one run gives)
    return mine.select(order), other.select(order), cross.select(order)


def probed_terms(settings: Settings, tracks: RecordedTracks, probes: int) -> list[RiskTerms]:
    """:func:`sample_terms` with ``probes`` probes of the divergence, in one run: the tracks
    repeated, each copy under its own id and so with its own probe
    (:func:`~torchsvs.accuracy.track_signs`; the first copy's the run's own), the control
    variate's weight fitted over them all (:class:`~torchsvs.accuracy.Reference`). A run of
    the copies side by side costs little more than one: an estimator's steps cost per step,
    not per track."""
    B = len(tracks)
    names = tracks.ids if tracks.ids is not None else [str(b) for b in range(B)]
    ids = [str(i) if k == 0 else f"{i}\0probe {k}" for k in range(probes) for i in names]
    copies = replace(tracks.subset(torch.arange(B).repeat(probes)), ids=ids)
    terms = sample_terms(settings, copies)
    copy = terms.track // B
    draws = [terms.select(copy == k) for k in range(probes)]
    return [replace(draw, track=draw.track % B) for draw in draws]


def accuracy_of_terms(settings: Settings, terms: RiskTerms) -> Accuracy:
    """The error estimate of ``settings``' estimator from its SURE sums ``terms``."""
    assert settings.meas_var is not None
    return accuracy_of(
        terms,
        settings.meas_var,
        noise_estimated=settings.noise != "given",
        meas_var_range=meas_var_range(settings),
    )


def checked_low(settings: Settings, tracks: RecordedTracks) -> Settings:
    """Settings whose grid of ``q`` reaches lower (``q_low``, :func:`~torchsvs.fitting.
    defaults.with_q_curve`), kept only where the sample's SURE, as the run runs, is lower with
    it than with the grid as it was; else those. The widening is a rule on the sample's
    shares of tracks and steps at the lowest factor: on airliners at their own report times
    (σ 10 m) it took the Kalman smoother from 7.9 to 8.2 m by the truth (SURE: 7.2 to 7.5 m),
    where on the same flights at σ 50 and 100 m it gained 1-2%."""
    if not settings.q_low or settings.meas_var is None:
        return settings
    plain = replace(settings, q_low=False, q_curve=None, q_kinds=None, q_window=None)
    narrow = with_q_curve(plain, tracks, widen=False)
    gain, _ = sample_terms(narrow, tracks).difference(
        sample_terms(settings, tracks), settings.meas_var
    )
    return settings if gain > 0.0 else narrow


def anchored_fit(fit: FitResult, start: Settings, tracks: RecordedTracks) -> FitResult:
    """The fit of a Kalman filter or smoother (:func:`~torchsvs.fitting.tuning.self_tune`,
    which learns its ``q``) as the run will use it: where each track runs with its own ``q``
    (``track_q``: the file's curve, :func:`~torchsvs.fitting.defaults.with_q_curve`), the
    fitted ``q`` is only the anchor of the factors each track picks from, and it is kept only
    where the sample's SURE with each track's own ``q`` is lower from it than from ``start``'s
    (the file's ``q`` as read off windows of the tracks,
    :func:`~torchsvs.fitting.defaults.complete_settings`). The fit lowers the SURE of one ``q``
    for every track, which is not what runs. Measured on simulated walkers at σ 25 m (1.2 m/s
    and stops, noise read off the data): the fit took ``q`` from 0.035 to 0.018 (SURE of one
    ``q`` 0.0316 → 0.0307 of r); each track's own ``q`` from it was estimated 5.96 m (6.59 m
    by the truth) against 5.44 m (6.25 m) from the file's, and ``auto``, whose candidates are
    fitted, chose a blend with the IMM 1.04x the plain smoother. Other estimators' divergences
    are probed (:func:`sample_terms`'s one probe would decide): their fits stand."""
    fitted = fit.settings
    if not (fitted.exact_divergence and fitted.track_q) or fitted.q == start.q:
        return fit
    assert fitted.meas_var is not None and start.q is not None
    anchors = (replace(fitted, q=start.q), fitted)
    own = [sample_terms(with_q_curve(s, tracks), tracks) for s in anchors]
    gain, gain_se = own[0].difference(own[1], fitted.meas_var)  # the fit's MSE lower by
    if gain > 0.0:
        return fit
    fit.settings = anchors[0]
    fit.stages.append(
        f"kept the file's q = {start.q:.4g}: with each track's own q, the fit's was not lower "
        f"(MSE {-gain:+.3g} ± {gain_se:.2g} m² per point)"
    )
    return fit


#: :func:`lowered_noise` takes the noise no lower than this share of the variance read.
LOWEST_NOISE_SHARE = 0.01
#: ... and no lower than this where the reading is motion between reports
#: (``noise_lag``, :func:`~torchsvs.datasets.noise_lags.motion_checked`): the noise is then
#: anywhere below the reading, and lower costs least. Aircraft in hard turns on 30 s reports,
#: σ 10 m, read 1,400 m: at a tenth of it 19.8 m, at a hundredth 14.2 (the measurements 14.2).
MOTION_NOISE_SHARE = 1e-4


def checked_below(settings: Settings, tracks: RecordedTracks) -> Settings:
    """The settings with ``noise_below_data`` (a noise given below the data's reading,
    :func:`~torchsvs.fitting.defaults.checked_given_noise`) kept only where the Kalman smoother
    at that reading is clearly below the measurements on ``tracks``: else the reading is motion
    between reports, not noise (aircraft turning between reports 120 s apart, σ 30 m given, read
    1,786 m; an error estimate made there was 2,495 m for a true 42 m)."""
    if settings.noise_below_data is None:
        return settings
    try:
        read = with_noise_read(Settings("ks"), tracks)
    except ValueError:
        return replace(settings, noise_below_data=None)
    return (
        settings
        if kalman_clearly_better(read, tracks)
        else replace(settings, noise_below_data=None)
    )


def kalman_clearly_better(read: Settings, tracks: RecordedTracks) -> bool:
    """Whether the Kalman smoother at the noise read off the data (``read``'s, each track at its
    own where it carries ``track_noise``) is clearly below the measurements on ``tracks``
    (:func:`sample_accuracy`, the file's ``q`` for that noise): the test of the data, not of an
    estimator, that :func:`lowered_noise` and :func:`with_track_noise` make."""
    kalman = Settings("ks", **{name: getattr(read, name) for name in NOISE_READ})
    return sample_accuracy(complete_settings(kalman, tracks), tracks).clearly_better


def lowered_noise(settings: Settings, tracks: RecordedTracks) -> list[float] | None:
    """The measurement variance to run at instead of the one read off the data, or None.

    Where the noise was read off the data and the Kalman smoother on it (with the file's ``q``
    for that noise, :func:`sample_accuracy` on ``tracks``) is not clearly below the
    measurements over the reading's uncertainty, the run takes the low end of it,
    :data:`GUARD_ERRORS` standard errors down (at least :data:`LOWEST_NOISE_SHARE` of the
    reading). The test is the data's, not the estimator's: every estimator of a file runs at
    the same noise (a fit that over-smooths on an inflated reading judges itself clearly
    better there). The two errors do not cost alike: a noise read too low makes the estimator
    follow the measurements, so its error stays near theirs, while one read too high smooths
    away motion the model does not follow, without bound. Measured on airliners on 10 s scans
    with σ 3 m (their motion between scans reads as 4-16 m of noise, 12.5 ± 7.6 m pooled):
    every default was 1.4-2.0× the raw measurements' error, and 0.99-1.02× at the low end
    (5.0 m). Not where the run takes the pieces' mean of a noise that changes within the
    tracks (``noise_within``, :func:`checked_within`): its level is then above the reading on
    purpose, and the low end is the quiet stretches', the reading that made the smoother follow
    the loud ones. Where the second differences two reports apart contradict the reading
    (``noise_lag``, ``noise_ceiling``, :func:`~torchsvs.datasets.noise_lags.motion_checked`),
    the run takes the low end of those axes without the test (the measurements' error the test
    compares with is the reading's), and the others' reading."""
    if settings.noise != "data" or settings.meas_var is None or within_mean_taken(settings):
        return None
    ends = meas_var_range(settings, GUARD_ERRORS)
    if ends is None:
        return None
    if not settings.reading_is_motion and kalman_clearly_better(settings, tracks):
        return None
    low, _ = ends
    if not settings.reading_is_motion:
        return [max(v, LOWEST_NOISE_SHARE * r) for v, r in zip(low, settings.meas_var, strict=True)]
    # (an axis group whose reading stands keeps it: a flat road's altitude beside vans' motion)
    return [
        max(v, MOTION_NOISE_SHARE * r) if settings.reading_is_motion_on([j]) else r
        for j, (v, r) in enumerate(zip(low, settings.meas_var, strict=True))
    ]


#: Where the tracks' noise read each alone differs by more than this (``τ`` of ``log σ``,
#: :func:`~torchsvs.datasets.track_noise.spread_of`), the run tries each track at its own
#: (:func:`with_track_noise`): the spread the run warns at (``track_run``).
TRACK_NOISE_SPREAD = 0.2
#: ... and runs so where leave-one-out cross-validation finds it better by this many standard
#: errors (:func:`with_track_noise`).
TRACK_NOISE_ERRORS = 2.0
#: ... on the points whose weight in their own estimate is at most this under one of the two noises.
MOST_WEIGHT = 0.5
#: ... over at most this many positions of the sample's tracks (spread over it).
GATE_POINTS = 50_000


def with_track_noise(read: Settings, tracks: RecordedTracks) -> tuple[Settings, str] | None:
    """The settings ``read`` (the noise read off the data) with each track at its own noise
    read off its positions (``track_noise``, :mod:`torchsvs.datasets.track_noise`), and a line
    on why, where the tracks' readings differ by more than :data:`TRACK_NOISE_SPREAD` and the
    Kalman smoother at each track's own is clearly better on ``tracks`` than at the file's
    reading; else None.

    Clearly better by leave-one-out cross-validation: the Kalman smoother is linear in the
    measurements, so a point's residual with the point left out is its residual over ``1 − h``
    (``h`` its position variance over the measurement noise: the hat matrix's diagonal,
    :func:`~torchsvs.accuracy.exact_divergence`), and the mean square of those is each
    smoother's own error plus the measurements' true noise, whatever noise each assumed. SURE
    cannot judge this choice: it reads the error at the noise it is given, so a track's noise
    read too high (its motion taken for noise) judges its own over-smoothing good. Points that
    weigh more than :data:`MOST_WEIGHT` in both smoothers' own estimates are left out: their
    left-out residual is the motion over the gap the neighbours leave. The gain must be clear
    in m² or in each track's gain per point over its own noise (:data:`TRACK_NOISE_ERRORS`
    standard errors over the tracks), and positive in m². Measured on the recorded-tracks
    benchmark's kinds (``ks``, defaults): on 18 sets where each track's σ spans a third to three
    times the file's, all took each track's own noise, 0.59-1.00 of the measurements' error ->
    0.19-0.86 (as with the true σ given, ``--noise-col``, but for 0.86 against 0.79 at
    irregular times), the error estimate 0.15-0.79 of the truth -> 0.74-1.21; on 15 sets of one
    noise, none did (airliners at σ 3 m, whose motion between reports reads as noise that
    differs between tracks: at each track's own reading 0.73 -> 0.96 of the measurements'
    error)."""
    spread = read.noise_spread  # (:func:`~torchsvs.datasets.noise_spread`'s, on a few tracks)
    if read.noise != "data" or read.meas_var is None or read.own_noise:
        return None
    if spread is None or spread <= TRACK_NOISE_SPREAD:  # (one level fits, or too few to tell)
        return None
    each = read_track_noise(tracks.z, tracks.dt, read.meas_var)
    found = spread_of(each)
    if found is None or found[1] <= TRACK_NOISE_SPREAD:
        return None
    mean, tau = found
    # The file's noise: the mean over the rows of each track's own (as a column's mean square),
    # the tracks' readings taken relative to it; its level as uncertain as the mean of the
    # tracks' readings (random effects).
    rows = (~torch.isnan(tracks.z).all(-1)).sum(1).double()
    k = float((rows * shrunk_ratios(each, mean, tau)).sum() / rows.sum())
    weight = (each.se.square() + tau**2).reciprocal()
    level = float(weight[torch.isfinite(weight)].sum()) ** -0.5
    own = replace(
        read,
        meas_var=[v * k for v in read.meas_var],
        track_noise=[mean - 0.5 * math.log(k), tau],
        meas_std_se=[(v * k) ** 0.5 * level for v in read.meas_var],
    )
    part = spread_tracks(tracks, GATE_POINTS)
    kalman = [
        complete_settings(Settings("ks", meas_var=s.meas_var, track_noise=s.track_noise), part)
        for s in (read, own)
    ]
    gain, count = _left_out_gain(kalman[0], kalman[1], part)
    points = float(count.sum())
    if points == 0 or not float(gain.sum()) > 0.0:
        return None
    lower, se = _gain_per_point(gain, points)
    # each track's gain per point in units of its own noise: the noisiest tracks' gains, the
    # largest, no longer drown the others' (own report times at σ 50 m: 1.3 standard errors in
    # m², 2.3 so; on airliners at σ 3 m, whose motion reads as noise, -1.1 and -0.8)
    some = count > 0
    assert own.meas_var is not None
    noise = sum(own.meas_var) / len(own.meas_var) * noise_classes.track_ratios(part, kalman[1])
    relative = (gain / count.clamp_min(1) / noise)[some]
    relative_se = float(relative.std()) * math.sqrt(len(relative)) if len(relative) > 1 else 0.0
    if not (
        lower > TRACK_NOISE_ERRORS * se or float(relative.sum()) > TRACK_NOISE_ERRORS * relative_se
    ):
        return None
    # ... and where the smoother at each track's own is clearly below the measurements: else
    # motion read as noise inflates each reading (gliders at 3-60 s reports, σ 5 m, read 40 m
    # track by track: 4.6 times the measurements' error, where the low end of the file's
    # reading, :func:`lowered_noise`, gave 1.0)
    if not kalman_clearly_better(own, tracks):
        return None
    return own, (
        f"noise: read off each track alone it differs between tracks by about {tau:.0%}; each "
        f"track runs at its own reading (shrunk towards the file's): the Kalman smoother's "
        f"leave-one-out error is {lower:.3g} ± {se:.2g} m² per point lower so"
    )


def checked_within(read: Settings, tracks: RecordedTracks) -> Settings:
    """The settings ``read`` off the data, at the file's reading (the pieces' core) instead of
    the pieces' mean where the noise changes within the tracks (``noise_within``) and the
    Kalman smoother's leave-one-out error on ``tracks`` is not clearly lower at the mean
    (:data:`TRACK_NOISE_ERRORS` standard errors over the tracks, the points of little weight
    in one, as :func:`with_track_noise` judges).

    The mean of the pieces' variances is right where a sensor's noise changes (5 to 40 m
    halfway: the smoother at the core follows the loud stretches), but a few pieces of another
    kind decide it: 30-min buoys whose turns read as 100 times the noise in some pieces made
    the drones beside them run at 338 m for 3 (13 times the measurements' error), and two
    ships under one id (3 tracks of 57) made the file's noise 45 km."""
    within = read.noise_within
    if read.noise != "data" or not within or read.meas_var is None:
        return read
    core, mean = within[3], within[4]
    at_core = [v * (core / mean) ** 2 for v in read.meas_var]
    part = spread_tracks(tracks, GATE_POINTS)
    kalman = [
        complete_settings(Settings("ks", meas_var=variance), part)
        for variance in (at_core, read.meas_var)
    ]
    gain, count = _left_out_gain(kalman[0], kalman[1], part)
    points = float(count.sum())
    if points > 0 and len(gain) > 1:
        lower, se = _gain_per_point(gain, points)
        if lower > TRACK_NOISE_ERRORS * se:
            return read
    std_se = read.meas_std_se
    scaled = None if std_se is None else [e * core / mean for e in std_se]
    return replace(read, meas_var=at_core, meas_std_se=scaled)


def _left_out_gain(
    first: Settings, second: Settings, tracks: RecordedTracks
) -> tuple[Tensor, Tensor]:
    """``([B], [B])`` each track's squared leave-one-out residuals (:func:`_left_out_squares`)
    of the Kalman smoother of ``first`` less those of ``second`` (m², summed), and how many
    points they are summed over: those weighing at most :data:`MOST_WEIGHT` in their own
    estimate under one of the two. Where a point weighs much in its own estimate, its left-out
    residual is the motion over the gap its neighbours leave, not the error at it: on
    airliners at 8-20 s those points judged the smoother that took motion for noise better,
    against the truth."""
    (at_first, h_first), (at_second, h_second) = (
        _left_out_squares(s, tracks) for s in (first, second)
    )
    usable = torch.minimum(h_first, h_second) <= MOST_WEIGHT
    return torch.where(usable, at_first - at_second, 0.0).sum((1, 2)), usable.sum((1, 2))


def _gain_per_point(gain: Tensor, points: float) -> tuple[float, float]:
    """The tracks' leave-one-out ``gain`` (:func:`_left_out_gain`) per point over ``points``,
    and its standard error over the tracks."""
    return float(gain.sum()) / points, float(gain.std()) * math.sqrt(len(gain)) / points


def _left_out_squares(settings: Settings, tracks: RecordedTracks) -> tuple[Tensor, Tensor]:
    """``([B, T, m], [B, T, m])`` the squared leave-one-out residuals of the Kalman smoother of
    ``settings`` and the weight ``h`` of each point in its own estimate, ``h`` NaN where not a
    point past each axis's first two (which the two-point prior reads)
    (:func:`with_track_noise`)."""
    assert settings.meas_var is not None
    estimator = make_estimator(settings, make_model(settings)).double()
    batch, meas_std = _sample_batch(settings, tracks)
    found = estimate_group(estimator, batch, meas_std, True, False, settings)
    assert found.cov is not None
    mean = in_batch_order(found, batch, found.mean)[..., 0::2]
    cov = in_batch_order(found, batch, found.cov)
    m = mean.shape[-1]
    variance = cov.diagonal(dim1=-2, dim2=-1)[..., 0::2]  # (the positions')
    factor = (
        noise_classes.on_grid(noise_classes.track_ratios(tracks, settings))
        if settings.own_noise
        else None
    )
    r = torch.tensor(settings.meas_var, dtype=torch.float64).expand(len(tracks), m)
    if factor is not None:
        r = r * factor.unsqueeze(-1)
    z = tracks.z.double()
    h = exact_divergence(z, variance / r.unsqueeze(1), torch.ones(m, dtype=torch.float64))
    h = torch.where(torch.isfinite(mean), h, math.nan)
    left_out = (z - mean) / (1.0 - h).clamp_min(1e-12)
    return left_out.square(), h

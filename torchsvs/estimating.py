"""Estimating: an estimator run over padded groups of tracks, with the truth-free error terms.

Each call of ``torchsvs track`` is one group of a block's tracks of similar length
(:class:`GroupBatch`, :func:`group_batch`), centred so float32 keeps its resolution;
:func:`estimate_group` runs the estimator on it (each track with its own ``q`` where the settings
carry the file's SURE curve, :func:`settings_q_factors`) and, with ``risk``, once more on probed
measurements for Stein's unbiased risk estimate (:mod:`torchsvs.accuracy`), and hands back the
estimates at the block's flat steps (:class:`StepEstimates`). An IMM smoother's tracks each keep
their smoothed or their filtered pass, whichever SURE rates lower
(:func:`~torchsvs.smoother_guard.smoothed_or_filtered`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.accuracy import (
    PROBE_STEP,
    Probe,
    RiskTerms,
    draw_probe,
    risk_terms,
)
from torchsvs.blending import blended_terms, cross_terms
from torchsvs.constraints import Positive, scaled_copy
from torchsvs.curve_estimates import (
    curve_run,
    is_curves_estimator,
    run_risk_terms,
)
from torchsvs.datasets import RecordedTracks, with_prior
from torchsvs.datasets.tracks import short_track_notes
from torchsvs.datasets.writing import flat_steps
from torchsvs.error_references import reference_for
from torchsvs.estimator import split_batch
from torchsvs.filters.particle import degenerate_share
from torchsvs.fitting import noise, noise_classes, q_windows
from torchsvs.fitting.defaults import GUARD_ERRORS, meas_var_range
from torchsvs.fitting.outliers import screen_outliers
from torchsvs.fitting.q_kinds import track_kinds
from torchsvs.models import ConstantVelocity
from torchsvs.recipes import FILTERS, UPWARD_Q_ONLY, Blend, Settings
from torchsvs.runs import run_result
from torchsvs.smoother_guard import smoothed_or_filtered
from torchsvs.smoothers import RTSSmoother
from torchsvs.smoothers.imm import IMMSmootherResult
from torchsvs.step_estimates import GroupBatch, StepEstimates, without_still


def estimate_group(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool = False,
    risk: bool = True,
    settings: Settings | None = None,
) -> StepEstimates:
    """Priors from ``meas_std [m]`` (:func:`~torchsvs.datasets.with_prior`), the estimator's
    run and the offsets added back. Random draws (particle filters) come from a generator
    seeded with the group's position, so a group's estimates do not depend on which groups ran
    before it, nor in which process. With ``risk``, a second run on probed measurements gives
    the truth-free error estimate's terms (:func:`~torchsvs.accuracy.risk_terms`).

    Where ``settings`` carry the file's SURE curve (``q_curve``), each track runs with its own
    ``q`` (:func:`settings_q_factors`): the tracks of one factor together, ``estimator``'s ``q``
    scaled by it for the call (:func:`scaled_q`).

    Where ``settings`` screen for outliers (``outliers`` and ``outlier_q``), the group's
    isolated outliers are set aside first (:func:`screen_group`): missing to the estimator and
    to the error estimate, listed in the result's ``outliers``."""
    if settings is not None and settings.own_noise:

        def each(scaled: nn.Module, part: GroupBatch, std: Tensor, own: Settings) -> StepEstimates:
            return estimate_group(scaled, part, std, covariance, risk, own)

        return by_noise_class(estimator, batch, meas_std, settings, each)
    outliers = None
    if settings is not None and settings.screens:
        batch, outliers = screen_group(batch, settings)
    found = without_still(
        _estimate_factors(estimator, batch, meas_std, covariance, risk, settings), batch
    )
    if outliers is None:
        return found
    notes = dict(found.notes)
    notes["outliers"] = notes.get("outliers", 0) + len(outliers)
    return found._replace(outliers=outliers, notes=notes)


def by_noise_class(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    settings: Settings,
    run: Callable[[nn.Module, GroupBatch, Tensor, Settings], StepEstimates],
) -> StepEstimates:
    """``run`` (the estimator, the tracks, their noise and settings) on each noise class of the
    group (:func:`~torchsvs.fitting.noise_classes.classes_of`): the class as a file of its
    noise, its error estimate's terms written at the file's noise from each track's own; on the
    whole group as it is where the settings have no noise column."""
    if not settings.own_noise:
        return run(estimator, batch, meas_std, settings)
    parts = []
    for each in noise_classes.classes_of(batch.tracks, batch.group, settings):
        part = batch.subset(each.members)
        with noise_classes.noise_scaled(estimator, each.factor) as scaled:
            found = run(scaled, part, meas_std * math.sqrt(each.factor), each.settings)
        if found.risk is not None:
            found = found._replace(risk=each.at_file_noise(found.risk))
        parts.append(found)
    return StepEstimates.merge(parts, len(meas_std))


def screen_group(batch: GroupBatch, settings: Settings) -> tuple[GroupBatch, np.ndarray]:
    """The group with its isolated outliers' positions missing
    (:func:`~torchsvs.fitting.outliers.screen_outliers` with the settings' noise and
    ``outlier_q``), and the block's flat steps of those rows (``[o]`` int64)."""
    assert settings.meas_var is not None and settings.outlier_q is not None
    tracks = batch.tracks
    flagged = screen_outliers(tracks.z, tracks.dt, settings.meas_var, settings.outlier_q)
    assert tracks.steps is not None
    steps = tracks.steps[flagged & (tracks.steps >= 0)].numpy()
    if not len(steps):
        return batch, steps
    z = tracks.z.masked_fill(flagged.unsqueeze(-1), math.nan)
    return batch._replace(tracks=replace(tracks, z=z)), steps


def _estimate_factors(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool,
    risk: bool,
    settings: Settings | None,
) -> StepEstimates:
    """:func:`estimate_group` after the screen: each track with its own ``q`` where the
    settings carry the file's curve; a :class:`~torchsvs.recipes.Blend`'s two estimators each
    so, their estimates blended (:func:`_estimate_blend`)."""
    if isinstance(estimator, Blend):
        assert settings is not None, "a blend's settings say how each of its estimators runs"
        return _estimate_blend(estimator, batch, meas_std, covariance, risk, settings)
    noise_range = None if settings is None else meas_var_range(settings, GUARD_ERRORS)
    if settings is None or settings.q_curve is None:
        if settings is not None and not covariance and is_curves_estimator(estimator, settings):
            return _estimate_one_q(estimator, batch, meas_std, risk, settings)
        return _estimate_part(estimator, batch, meas_std, covariance, risk, noise_range)
    curves_estimator = is_curves_estimator(estimator, settings)
    if settings.q_window is not None and curves_estimator and settings.estimator not in FILTERS:
        found = _estimate_windowed(estimator, batch, meas_std, covariance, risk, settings)
        if found is not None:
            return found
    reuse = not covariance and curves_estimator
    factors, runs = _q_factors(settings, batch.tracks, reuse)
    assert settings.q is not None
    if runs is not None and bool(runs.ran.all()):  # every track's pass at its own q
        q = settings.q * factors
        found = _estimate_from_run(estimator, batch, meas_std, risk, runs, q)
        return found._replace(q_factor=factors.numpy())
    parts = []
    for factor in torch.unique(factors).tolist():
        index = torch.nonzero(factors == factor).flatten()
        part = batch.subset(index)
        steps = part.tracks.z.shape[1]
        run = None if runs is None else curve_run(runs, index, steps, settings.q * factor)
        if run is not None:
            found = _estimate_from_run(estimator, part, meas_std, risk, *run)
        else:
            with scaled_q(estimator, factor) as scaled:
                found = _estimate_part(scaled, part, meas_std, covariance, risk, noise_range)
        parts.append(found._replace(q_factor=np.full(len(index), factor)))
    return StepEstimates.merge(parts, len(meas_std))


class BlendParts(NamedTuple):
    """Two estimators' runs on one group, as a blend of them needs them (:func:`blend_parts`)."""

    parts: tuple[StepEstimates, StepEstimates]
    means: tuple[Tensor, Tensor]  #: each's mean, the batch's padded ``[B, T, n]`` (offsets in)
    #: the first's, the second's SURE sums and their ``C`` (:func:`~torchsvs.blending.
    #: cross_terms`), in track order; None without ``risk``
    terms: tuple[RiskTerms, RiskTerms, RiskTerms] | None


def blend_parts(
    estimators: tuple[nn.Module, nn.Module],
    pair: tuple[Settings, Settings],
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool,
    risk: bool,
) -> BlendParts:
    """Each estimator's run on the group as :func:`_estimate_factors` runs it with its own
    settings, its mean in the batch's padded order and (``risk``) the terms a blend's error and
    weight are made of."""
    first, second = (
        _estimate_factors(estimator, batch, meas_std, covariance, risk, own)
        for estimator, own in zip(estimators, pair, strict=True)
    )
    means = (in_batch_order(first, batch, first.mean), in_batch_order(second, batch, second.mean))
    if not risk:
        return BlendParts((first, second), means, None)
    assert first.risk is not None and second.risk is not None
    observed = ~torch.isnan(batch.tracks.z)
    cross = cross_terms(observed, means[0][..., 0::2], means[1][..., 0::2], batch.group)
    terms = (first.risk.in_track_order(), second.risk.in_track_order(), cross)
    return BlendParts((first, second), means, terms)


def _estimate_blend(
    blend: Blend,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool,
    risk: bool,
    settings: Settings,
) -> StepEstimates:
    """The blend ``(1 − w) x̂₁ + w x̂₂`` of its two estimators' runs on the group
    (:func:`blend_parts`) and the blend's error terms (:func:`~torchsvs.blending.
    blended_terms`). Its covariance is the blend of theirs, a bound: the error covariance of
    ``(1 − w) e₁ + w e₂`` is at most that in every direction (the cross term of two errors is at
    most the geometric mean of their variances). Notes and each track's ``q`` factor are the
    first's."""
    pair = settings.blended
    assert pair is not None
    found = blend_parts((blend.first, blend.second), pair, batch, meas_std, covariance, risk)
    (first, second), means = found.parts, found.means
    w = blend.weight
    mean = (1 - w) * means[0] + w * means[1]
    cov = None
    if covariance:
        assert first.cov is not None and second.cov is not None, "asked for, so written"
        cov = (1 - w) * in_batch_order(first, batch, first.cov)
        cov = cov + w * in_batch_order(second, batch, second.cov)
    tracks = batch.tracks
    target, values, covs_flat = flat_steps(tracks, mean, cov)
    terms = None if found.terms is None else blended_terms(*found.terms, w)
    never = ((~torch.isnan(tracks.z)).sum(dim=1) == 0).numpy()
    q_factor = first.q_factor
    if q_factor is not None:
        q_factor = in_batch_order(first, batch, q_factor, per_track=True).numpy()
    notes = {**second.notes, **first.notes}
    return StepEstimates(
        batch.position, batch.group, target, values, covs_flat, never, notes, terms, q_factor
    )


def in_batch_order(
    found: StepEstimates, batch: GroupBatch, values: np.ndarray, per_track: bool = False
) -> Tensor:
    """``values`` given at ``found``'s steps (``[s, ...]``, in the order of its tracks, which
    its parts may have changed) as the batch's padded ``[B, T, ...]`` float64 (NaN past a
    track's end); ``per_track``: one value per track ``[B, ...]``, in the batch's order."""
    order = np.argsort(batch.group)
    local = torch.from_numpy(order[np.searchsorted(batch.group, found.group, sorter=order)])
    steps = batch.tracks.steps
    assert steps is not None
    rows = torch.from_numpy(np.ascontiguousarray(values)).double()
    if per_track:
        out = rows.new_full(rows.shape, math.nan)
        out[local] = rows
        return out
    mine = steps[local] >= 0
    part = rows.new_full((*mine.shape, *rows.shape[1:]), math.nan)
    part[mine] = rows
    out = part.new_full(part.shape, math.nan)
    out[local] = part
    return out


def _estimate_one_q(
    estimator: nn.Module, batch: GroupBatch, meas_std: Tensor, risk: bool, settings: Settings
) -> StepEstimates:
    """:func:`_estimate_factors` with one ``q`` for every track (``--shared-q``, or ``q``
    given) for the Kalman smoother or filter: its pass as the curves run it
    (:func:`~torchsvs.fitting.noise.curve_runs`), its error terms exact from that pass
    (:func:`_estimate_from_run`): one float64 pass, where the plain run, the probed run and
    the Kalman reference's two took four."""
    assert settings.meas_var is not None and settings.q is not None
    tracks = batch.tracks
    smoothed = settings.estimator not in FILTERS
    runs = noise.curve_runs(tracks.z, tracks.dt, settings.meas_var, settings.q, smoothed)
    return _estimate_from_run(estimator, batch, meas_std, risk, runs, settings.q)


def _estimate_windowed(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool,
    risk: bool,
    settings: Settings,
) -> StepEstimates | None:
    """:func:`_estimate_factors` for the Kalman smoother with its ``q`` per step (the passes
    at the factors blended by their SURE over ``settings.q_window`` steps,
    :func:`~torchsvs.fitting.q_windows.windowed_runs`): the means
    and error terms from the compiled passes, with ``covariance`` each step's the weighted
    mixture of the estimator's runs at the factors (their covariances and their means' spread
    about the blend); None where the compiled loops are unavailable (each
    track then runs with its own ``q``)."""
    assert settings.q is not None and settings.meas_var is not None
    assert settings.q_window is not None
    tracks = batch.tracks
    factors = noise.q_factors(settings.q_low)
    found = q_windows.windowed_runs(
        tracks.z, tracks.dt, settings.meas_var, settings.q, settings.q_window, factors
    )
    if found is None:
        return None
    cov = None
    if covariance:  # each step's passes' covariances and spread, weighted (moment matched)
        prior = with_prior(tracks, meas_std)
        generator = torch.Generator().manual_seed(batch.position)
        for i, factor in enumerate(factors):  # (one pass's covariances at a time)
            with scaled_q(estimator, factor) as scaled:
                out = run_result(scaled, prior, generator, "all")
            spread = (out.mean - found.runs.mean.to(out.mean.dtype)).unsqueeze(-1)
            weight = found.weights[i].to(out.cov.dtype)[..., None, None]
            term = weight * (out.cov + spread @ spread.transpose(-1, -2))
            cov = term if cov is None else cov.add_(term)
    q = settings.q * found.factor
    estimates = _estimate_from_run(estimator, batch, meas_std, risk, found.runs, q, cov)
    return estimates._replace(q_factor=found.factor.numpy())


def settings_q_factors(settings: Settings, tracks: RecordedTracks) -> Tensor:
    """``[B]`` each track's factor on ``settings.q`` (:func:`torchsvs.fitting.noise.
    track_q_factors` against the file's curve ``settings.q_curve``)."""
    return _q_factors(settings, tracks, False)[0]


def _q_factors(
    settings: Settings, tracks: RecordedTracks, keep: bool
) -> tuple[Tensor, noise.CurveRuns | None]:
    """:func:`settings_q_factors`, and with ``keep`` the curves' passes at them
    (:func:`~torchsvs.fitting.noise.q_curve_runs`)."""
    assert settings.q_curve is not None and settings.meas_var is not None
    assert settings.q is not None
    pooled = settings.q_curve
    grid = noise.q_factors(settings.q_low)

    def choose(curves: noise.QCurves) -> Tensor:
        factors = noise.track_q_factors(curves, pooled, grid, kinds=settings.q_kinds)
        return factors.clamp_min(1.0) if settings.estimator in UPWARD_Q_ONLY else factors

    _, factors, runs = noise.q_curve_runs(
        tracks.z,
        tracks.dt,
        settings.meas_var,
        settings.q,
        settings.estimator not in FILTERS,
        grid,
        choose=choose,
        keep=keep,
        kinds=None if settings.q_kinds is None else track_kinds(tracks.z, tracks.dt),
    )
    assert factors is not None
    return factors, runs


def scaled_q(estimator: nn.Module, factor: float) -> contextlib.AbstractContextManager[nn.Module]:
    """A copy of the estimator with its motion model's ``q`` times ``factor`` (the estimator
    itself where the factor is 1; :func:`~torchsvs.constraints.scaled_copy`), for the block."""

    def motion_q(scaled: nn.Module) -> list[Positive]:
        assert isinstance(scaled.model, ConstantVelocity), "scaled_q: a constant-velocity q"
        return [scaled.model.q]

    return scaled_copy(estimator, factor, motion_q)


def _estimate_part(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool = False,
    risk: bool = True,
    noise_range: tuple[list[float], list[float]] | None = None,
) -> StepEstimates:
    """:func:`estimate_group` with the estimator as it is (``noise_range``: the measurement
    variance's interval, :func:`~torchsvs.fitting.defaults.meas_var_range`, where it was read
    off the data)."""

    def positions(z: Tensor, keep: str = "all", rows: RecordedTracks = batch.tracks) -> Any:
        tracks = with_prior(replace(rows, z=z), meas_std)
        generator = torch.Generator().manual_seed(batch.position)
        return run_result(estimator, tracks, generator, keep)

    step = getattr(estimator, "probe_step", PROBE_STEP)
    # probes per track (not per group): a table's estimates do not depend on its other tracks
    probe = draw_probe(batch.tracks.z, meas_std, step, None, ids=batch.tracks.ids)
    if getattr(estimator, "paired_probes", False):
        # the plain and the probed run in one batch; the means alone unless covariances are
        # written (nothing else reads them)
        out, shifted = _paired_run(positions, batch.tracks, probe, "all" if covariance else "mean")

        def probed(z: Tensor) -> Any:  # z: the probe's measurements, run above
            return shifted

    else:
        out = positions(batch.tracks.z)

        def probed(z: Tensor) -> Any:  # SURE's probed run reads the means alone
            return positions(z, "mean")

    tracks = with_prior(batch.tracks, meas_std)
    mean, cov = out.mean, out.cov
    notes = short_track_notes(tracks)
    if getattr(out, "ess", None) is not None:  # a particle filter: how often it degenerated
        measured = (~torch.isnan(tracks.z)).any(-1).sum(-1)  # [B] steps with a measurement
        notes["particle_steps"] = int(measured.sum())
        low = degenerate_share(out, tracks.z) * measured
        notes["particle_steps_degenerate"] = int(low.sum().round())
    terms = None
    control = reference_for(estimator, out, tracks, meas_std, probe) if risk else None
    if isinstance(out, IMMSmootherResult):  # (a Kalman smoother or SVSS is kept whole)
        out, terms, fell_back = smoothed_or_filtered(
            out, probed, tracks.z, meas_std, probe, noise_range, control
        )
        mean, cov = out.mean, out.cov
        if fell_back.any():
            notes["smoother_fallback"] = int(fell_back.sum())
        terms = terms if risk else None
    elif risk:
        terms = risk_terms(
            lambda z: probed(z).mean[..., 0::2],
            tracks.z,
            mean[..., 0::2],
            meas_std,
            None,
            reference=None if control is None else control.reference(out),
            probe=probe,
        )
    return _step_estimates(batch, tracks, mean, cov if covariance else None, notes, terms)


def _step_estimates(
    batch: GroupBatch,
    tracks: RecordedTracks,
    mean: Tensor,
    cov: Tensor | None,
    notes: dict[str, int],
    terms: RiskTerms | None,
) -> StepEstimates:
    """The group's estimates ``mean`` (and ``cov``) at the block's flat steps, the offsets
    added back (``tracks``: the group's with their priors)."""
    if terms is not None:
        terms.track = batch.group[terms.track]
    # (a numerical breakdown is said, never written as empty estimates without a word)
    broken = (~torch.isnan(tracks.z) & ~torch.isfinite(mean[..., 0::2])).flatten(1).any(1)
    if bool(broken.any()):
        notes = {**notes, "tracks_not_finite": int(broken.sum())}
    mean = mean.double()
    mean[..., 0::2] += batch.offset.unsqueeze(1)
    target, values, covs = flat_steps(tracks, mean, cov)
    assert tracks.never_observed is not None
    never = tracks.never_observed.numpy()
    return StepEstimates(batch.position, batch.group, target, values, covs, never, notes, terms)


def _estimate_from_run(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    risk: bool,
    run: noise.CurveRuns,
    q: float | Tensor,
    cov: Tensor | None = None,
) -> StepEstimates:
    """:func:`_estimate_part` of a Kalman smoother or filter
    (:func:`~torchsvs.curve_estimates.is_curves_estimator`) whose run on the group is given
    (from the SURE curves' pass, float64, at ``q``: one, or one per track ``[B]``): its means,
    position variances and, where compiled, the divergence at each axis's first two
    observations; the error terms from them (:func:`~torchsvs.curve_estimates.
    run_risk_terms`: exact, or with the probe drawn as :func:`_estimate_part` draws it); the
    covariances ``cov [B, T, n, n]`` where given."""
    # what the output needs of a prior: the axes never observed (their estimates are NaN)
    seen = (~torch.isnan(batch.tracks.z)).sum(dim=1)  # [B, m]
    tracks = replace(batch.tracks, never_observed=seen == 0)
    terms = None
    mean = run.mean
    if risk:
        step = getattr(estimator, "probe_step", PROBE_STEP)
        smoothed = isinstance(estimator, RTSSmoother)
        terms = run_risk_terms(
            batch.tracks, meas_std, mean, run.position_var, q, smoothed, step, run.sums
        )
    return _step_estimates(batch, tracks, mean, cov, short_track_notes(tracks, seen), terms)


def _paired_run(
    positions: Callable[..., Any], tracks: RecordedTracks, probe: Probe, keep: str
) -> tuple[Any, Any]:
    """An estimator's run (``positions(z, keep, rows)``) on the tracks and on the probe's
    measurements in one batch of the tracks twice over, keeping ``keep``: the two results
    (:attr:`~torchsvs.estimator.Estimator.paired_probes`)."""
    B = len(tracks.z)
    rows = tracks.subset(torch.arange(B).repeat(2))
    assert rows.z.shape == (2 * B, *tracks.z.shape[1:]), "every track twice over, steps kept"
    return split_batch(positions(torch.cat([tracks.z, probe.measurements]), keep, rows), B)

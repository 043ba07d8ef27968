"""A Kalman smoother's (or filter's) estimates in ``torchsvs track`` read off the SURE curves'
passes.

Where each track runs with its own ``q`` (:func:`torchsvs.estimating.estimate_group`), the
curves that choose it (:func:`~torchsvs.fitting.noise.q_curve_runs`) have scored the Kalman
smoother at every factor on the very same tracks from the same prior, and kept its pass at
each track's own: a Kalman smoother's estimate is that pass (:func:`is_curves_estimator`,
:func:`curve_run`), and its error estimate's divergence is exact from the pass's covariances
and, at each axis's first two observations, from its tangents (:func:`run_risk_terms`). Only
where the compiled loops are unavailable does a probe's run estimate it there.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor, nn

from torchsvs.accuracy import (
    Reference,
    RiskTerms,
    draw_probe,
    exact_divergence,
    risk_terms,
    terms_of_sums,
)
from torchsvs.datasets import RecordedTracks, with_prior
from torchsvs.filters import KalmanFilter
from torchsvs.fitting import noise
from torchsvs.models import ConstantVelocity
from torchsvs.models.base import LinearModel
from torchsvs.recipes import FILTERS, Settings
from torchsvs.smoothers import RTSSmoother


def meas_var_of(estimator: nn.Module) -> Tensor:
    """``[m]`` the estimator's own measurement variances (its gain's ``R``)."""
    model: Any = estimator.model
    return model.meas_cov().detach().diagonal()


def linear_gaussian(estimator: nn.Module) -> bool:
    """Whether the estimator is a Kalman filter or an RTS smoother over one (its estimate
    linear in ``z``, with the gain ``P Hᵀ R⁻¹``)."""
    if type(estimator) is RTSSmoother:
        return not estimator.projection_gain and linear_gaussian(estimator.filter)
    return (
        type(estimator) is KalmanFilter
        and estimator.adaptive_noise is None
        and isinstance(estimator.model, LinearModel)
    )


def is_curves_estimator(estimator: nn.Module, settings: Settings) -> bool:
    """Whether ``estimator`` is the Kalman smoother (fixed interval) or filter that the
    settings' SURE curves run (:func:`~torchsvs.fitting.noise.kalman`, up to the estimator's
    dtype): the same model, ``q`` and noise, so a track's estimate at its factor is that
    curve's pass."""
    if not linear_gaussian(estimator) or settings.q is None or settings.meas_var is None:
        return False
    smoothed = isinstance(estimator, RTSSmoother)
    if smoothed != (settings.estimator not in FILTERS) or getattr(estimator, "lag", None):
        return False
    model = estimator.model
    if type(model) is not ConstantVelocity:
        return False
    q = float(model.q().detach().double())
    r = meas_var_of(estimator).double()
    wanted = torch.tensor(settings.meas_var, dtype=torch.float64)
    return math.isclose(q, settings.q, rel_tol=CURVE_MATCH) and bool(
        torch.allclose(r, wanted, rtol=CURVE_MATCH, atol=0.0)
    )


#: :func:`is_curves_estimator`'s relative tolerance on ``q`` and the noise: a float32
#: estimator's parameters hold the settings' to ~1e-7.
CURVE_MATCH = 1e-5


def curve_run(
    runs: noise.CurveRuns, index: Tensor, steps: int, q: float
) -> tuple[noise.CurveRuns, float] | None:
    """The tracks ``index``'s passes at their factor (one ``q`` for all of them) among the
    curves', over their first ``steps`` steps, and ``q``; or None where the curves ran no such
    ``q``. (A smoother's estimates do not depend on the padding after a track's last step, so
    the group's pass serves tracks trimmed to their own longest length.)"""
    if not bool(runs.ran[index].all()):
        return None
    sums = None if runs.sums is None else runs.sums[index]  # (chunks past `steps`: empty)
    mean, var = runs.mean[index, :steps], runs.position_var[index, :steps]
    return noise.CurveRuns(mean, var, runs.ran[index], sums), q


def run_risk_terms(
    tracks: RecordedTracks,
    meas_std: Tensor,
    mean: Tensor,
    position_var: Tensor,
    q: float | Tensor,
    smoothed: bool,
    step: float,
    sums: Tensor | None = None,
) -> RiskTerms:
    """SURE's sums (:func:`~torchsvs.accuracy.risk_terms`) of the Kalman smoother (filter)
    :func:`~torchsvs.fitting.noise.kalman` with ``q`` (or each track's ``[B]``) whose run on
    ``tracks`` gave ``mean [B, T, 2m]`` and ``position_var [B, T, m]``: the divergence exact
    from the covariances (:func:`~torchsvs.accuracy.exact_divergence`, the estimator its own
    control) but at each axis's first two observations, which the two-point prior reads.
    Where the compiled pass gave its chunk sums ``sums`` (its tangents make the divergence
    there exact too: :func:`~torchsvs.accuracy.terms_of_sums`), nothing is left to compute;
    else the divergence there is the probe's (each track's own signs,
    :func:`~torchsvs.accuracy.track_signs`, with ``step``): the estimate is linear in the
    measurements (its two-point prior's mean too), so its run on the probed measurements less
    its run on them is its run on the probe's shift alone, one run in ``meas_std``'s dtype."""
    if sums is not None:
        return terms_of_sums(sums)
    z = tracks.z.double()
    std = meas_std.double()
    r = std.square()
    probe = draw_probe(z, std, step, None, ids=tracks.ids)
    dtype = meas_std.dtype
    shift = (probe.step * std * probe.signs).masked_fill(torch.isnan(z), math.nan)
    moved = with_prior(replace(tracks.to(dtype), z=shift.to(dtype)), meas_std)
    assert moved.x0 is not None and moved.P0 is not None
    response = noise.kalman_positions(moved.z, moved.dt, moved.x0, moved.P0, r, q, smoothed)[0]
    positions = mean[..., 0::2]
    return risk_terms(
        lambda _: positions + response[..., 0::2].double(),  # (the probed run, as above)
        z,
        positions,
        std,
        None,
        reference=Reference(exact_divergence(z, position_var, r), beta=1.0),
        probe=probe,
    )

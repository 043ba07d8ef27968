"""The truth-free error estimate's control variates (:class:`~torchsvs.accuracy.Reference`):
for a Kalman filter or smoother its own exact divergence (:class:`SelfReference`); for another
deterministic estimator on a constant-velocity model (the SVSF family, the IMM, the other
Gaussian filters) the Kalman smoother or filter on its model, run on the same tracks and probe
(:class:`LinearReference`); chosen by :func:`reference_for`."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch
from torch import Tensor, nn

from torchsvs.accuracy import Probe, Reference, exact_divergence
from torchsvs.curve_estimates import linear_gaussian, meas_var_of
from torchsvs.datasets import RecordedTracks, with_prior
from torchsvs.filters import KalmanFilter, ParticleFilter
from torchsvs.fitting import noise
from torchsvs.kernels.curves import Positions
from torchsvs.models import ConstantVelocity
from torchsvs.runs import run_result
from torchsvs.smoothers import RTSSmoother
from torchsvs.smoothers.imm import IMMSmootherResult
from torchsvs.types import SmootherResult


class LinearReference:
    """The truth-free error estimate's control variate (:class:`~torchsvs.accuracy.Reference`)
    from a Kalman smoother (or filter) on the tracks and on a probe's measurements
    (:func:`reference_for`).

    It needs the reference's means and position variances alone: on a nearly-constant-velocity
    model with a diagonal ``R`` they come from the compiled loop that writes nothing else
    (:func:`~torchsvs.fitting.noise.kalman_positions`, the per-axis Kalman smoother's twin), a
    pass for each of the smoother and its filter when asked; else from the estimator's run
    (its whole covariances, several times the memory traffic)."""

    def __init__(
        self, kalman: nn.Module, tracks: RecordedTracks, meas_std: Tensor, probe: Probe
    ) -> None:
        self.meas_var = meas_var_of(kalman)
        self.kalman = kalman
        self.tracks = tracks
        self.shifted = with_prior(replace(tracks, z=probe.measurements), meas_std)
        self.smoother = isinstance(kalman, RTSSmoother)
        self.runs: dict[bool, tuple[Positions, Positions]] = {}  # (plain, shifted) by `filtered`
        model, dt = getattr(kalman, "model", None), tracks.dt
        R = model.meas_cov().detach() if isinstance(model, ConstantVelocity) else None
        #: the positions loop gives it (it takes a diagonal R and an interval per step)
        diagonal = R is not None and bool((R == torch.diag(R.diagonal())).all())
        self.positions = diagonal and dt is not None and dt.shape == tracks.z.shape[:2]

    def _pass(self, filtered: bool) -> tuple[Positions, Positions]:
        """The plain and the shifted runs' means and position variances: the smoother's, or
        its filter's with ``filtered`` (a filter's reference has its own pass alone)."""
        filtered = filtered and self.smoother
        if filtered not in self.runs:
            if self.positions:
                model: Any = self.kalman.model
                q, r = model.q().detach(), model.meas_cov().detach().diagonal()
                found = []
                for t in (self.tracks, self.shifted):
                    assert t.dt is not None and t.x0 is not None and t.P0 is not None
                    smoothed = self.smoother and not filtered
                    found.append(noise.kalman_positions(t.z, t.dt, t.x0, t.P0, r, q, smoothed))
                self.runs[filtered] = (found[0], found[1])
            else:  # the estimator's runs: one for both passes
                plain = run_result(self.kalman, self.tracks, keep="moments")
                shifted = run_result(self.kalman, self.shifted, keep="mean")
                self.runs[False] = (_positions_of(plain), _positions_of(shifted))
                if self.smoother:
                    self.runs[True] = (
                        _positions_of(plain.filtered),
                        _positions_of(shifted.filtered),
                    )
        return self.runs[filtered]

    def reference(self, result: Any = None, filtered: bool = False) -> Reference:
        """The reference for the estimator's positions (its filter pass's with ``filtered``:
        the reference's forward pass)."""
        plain, shifted = self._pass(filtered)
        exact = exact_divergence(self.tracks.z, plain.var, self.meas_var)
        return Reference(exact, shifted.mean[..., 0::2], plain.mean[..., 0::2])


def _positions_of(result: Any) -> Positions:
    """A run's means and position variances (``None`` where it kept no covariance)."""
    var = None if result.cov is None else result.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2]
    return Positions(result.mean, var)  # type: ignore[arg-type]


class SelfReference:
    """The control variate of a Kalman filter or smoother: its own divergence, exact."""

    def __init__(self, estimator: nn.Module, tracks: RecordedTracks) -> None:
        self.meas_var = meas_var_of(estimator)
        self.z = tracks.z

    def reference(self, result: Any, filtered: bool = False) -> Reference:
        position_var = result.cov.diagonal(dim1=-2, dim2=-1)[..., 0::2]
        return Reference(exact_divergence(self.z, position_var, self.meas_var), beta=1.0)


def reference_for(
    estimator: nn.Module, out: Any, tracks: RecordedTracks, meas_std: Tensor, probe: Probe
) -> LinearReference | SelfReference | None:
    """The control variate of an estimator's error estimate: the estimator itself where it is
    a Kalman filter or smoother (its divergence exact); else, for a deterministic estimator on
    a constant-velocity model (the SVSF family, the IMM, the other Gaussian filters), the
    Kalman smoother (the Kalman filter for a filter's output ``out``) on the estimator's own
    model, run on the same tracks and ``probe``; ``None`` for the particle filters (their
    draws differ between runs)."""
    if linear_gaussian(estimator):
        return SelfReference(estimator, tracks)
    model = getattr(estimator, "model", None)
    if isinstance(estimator, ParticleFilter) or not isinstance(model, ConstantVelocity):
        return None
    kf = KalmanFilter(model)
    smoothed = isinstance(out, (SmootherResult, IMMSmootherResult))
    return LinearReference(RTSSmoother(kf) if smoothed else kf, tracks, meas_std, probe)

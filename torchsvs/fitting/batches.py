"""Training batches and their losses, without Lightning: what the truth-free fit
(:func:`~torchsvs.fitting.tuning.self_tune`, ``torchsvs track --fit`` and ``--estimator auto``)
needs, kept apart from the LightningModules so that those commands do not import Lightning."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchsvs.accuracy import draw_probe
from torchsvs.datasets.tracks import RecordedTracks
from torchsvs.estimator import split_batch
from torchsvs.fitting.losses import (
    LOSSES,
    SURE_STEP,
    innovation_nll,
    prediction_error,
    stein_risk,
    supervised_mse,
)
from torchsvs.models.base import LinearModel
from torchsvs.types import FilterResult, SmootherResult


class TrackBatch(NamedTuple):
    """One training batch: measurements, the filters' prior, and truth where there is any."""

    z: Tensor  #: [B, T, m], NaN where missing
    truth: Tensor | None  #: [B, T, n] (simulated tracks), None for recorded ones
    x0: Tensor  #: [B, n] (simulated: drawn from N(true initial state, P0))
    P0: Tensor  #: [n, n] or [B, n, n]
    dt: Tensor | None = None  #: [B, T] per-step intervals (recorded tracks)
    scored: Tensor | None = None  #: [B, T] steps the losses count (default: all)
    #: [m] measurement variance the priors were built from: when set, ``x0, P0`` are two-point
    #: priors of ``z`` and are rebuilt from any perturbed ``z`` (SURE's second pass)
    prior_var: Tensor | None = None


def recorded_batches(
    tracks: RecordedTracks,
    meas_var: Tensor,
    window: int | None = 128,
    burn_in: int = 16,
    batch_size: int | None = None,
    dtype: torch.dtype = torch.float64,
) -> list[TrackBatch]:
    """Recorded tracks as training batches: cut into windows (:func:`~torchsvs.datasets.tracks.
    windows`; ``window=None`` keeps whole tracks), each moved to start near 0, with two-point
    priors rebuilt from its own measurements (``prior_var``), in batches of ``batch_size``
    windows (``None``: one batch)."""
    from torchsvs.datasets import two_point_prior
    from torchsvs.datasets.tracks import windows as cut_windows

    if window is not None:
        pieces, scored = cut_windows(tracks, window, burn_in)
    else:
        pieces, scored = tracks, tracks.mask
    z = pieces.z.to(dtype)
    observed = ~torch.isnan(z)
    first = observed.to(torch.int64).argmax(dim=1, keepdim=True)
    offset = z.nan_to_num(0.0).gather(1, first)  # [N, 1, m]
    z = z - offset
    truth = pieces.truth
    if truth is not None:
        truth = truth.to(dtype).clone()
        truth[..., 0::2] -= offset
    dt = pieces.dt.to(dtype)
    var = meas_var.to(dtype)
    size = batch_size or len(pieces)
    batches = []
    for start in range(0, len(pieces), size):
        part = slice(start, start + size)
        prior = two_point_prior(z[part], dt[part], var)
        batches.append(
            TrackBatch(
                z=z[part],
                truth=None if truth is None else truth[part],
                x0=prior.x0,
                P0=prior.P0,
                dt=dt[part],
                scored=scored[part],
                prior_var=var,
            )
        )
    return batches


def known_meas_cov(estimator: nn.Module, meas_cov: Tensor | None, dtype: torch.dtype) -> Tensor:
    """The sensor's measurement covariance SURE measures risk in: ``meas_cov`` if given, else the
    model's ``R`` when it is fixed. A learnable ``R`` is refused: the fit could lower the risk
    estimate by inflating it."""
    if meas_cov is not None:
        return meas_cov.to(dtype)
    R = estimator.model.meas_cov()  # type: ignore[union-attr, operator]
    if R.requires_grad:
        raise ValueError(
            "meas_cov: loss 'sure' needs the sensor's known measurement covariance, and the "
            "model's R is being learned; pass meas_cov=... (or fix R, or use loss='nll')"
        )
    return R.detach().to(dtype)


def batch_loss(
    estimator: nn.Module,
    batch: TrackBatch,
    loss: str,
    components: list[int] | None = None,
    meas_cov: Tensor | None = None,
    generator: torch.Generator | None = None,
    keep: str = "all",
) -> tuple[Tensor, Any]:
    """The estimator's result on a batch and its ``loss`` (one of :data:`LOSSES`); ``keep`` as
    every estimator takes it (``"mean"`` serves ``"sure"`` and ``"supervised"``, faster).

    Priors built from the data (``batch.prior_var`` set) are rebuilt from every ``z`` the loss
    evaluates, so SURE's divergence includes their dependence on the measurements. Only
    ``"supervised"`` reads ``batch.truth``.
    """
    from torchsvs.datasets.priors import two_point_prior

    def run(z: Tensor, rows: TrackBatch = batch) -> Any:
        x0, P0 = rows.x0, rows.P0
        if rows.prior_var is not None:
            assert rows.dt is not None
            prior = two_point_prior(z, rows.dt, rows.prior_var)
            x0, P0 = prior.x0, prior.P0
        kwargs: dict[str, Any] = {"keep": keep}
        if rows.dt is not None:
            kwargs["dt"] = rows.dt
        return estimator(z, x0, P0, **kwargs)

    if loss == "sure" and getattr(estimator, "paired_probes", False):  # (any nn.Module)
        return _paired_sure(estimator, batch, run, meas_cov, generator)
    out = run(batch.z)
    if loss in ("nll", "prediction") and not isinstance(out, (FilterResult, SmootherResult)):
        raise ValueError(
            f"loss: {loss!r} scores a Gaussian filter's innovations, which "
            f"{type(estimator).__name__} does not form; use 'supervised' or 'sure'"
        )
    if loss == "supervised":
        if batch.truth is None:
            raise ValueError(
                "loss: 'supervised' needs truth and this batch has none (recorded tracks); "
                "use a truth-free loss ('sure', 'nll', 'prediction')"
            )
        return supervised_mse(out, batch.truth, components or [0, 2], batch.scored), out
    if loss == "nll":
        return innovation_nll(out, batch.scored), out
    if loss == "prediction":
        return prediction_error(out, batch.scored), out
    if loss != "sure":
        raise ValueError(f"loss: expected one of {sorted(LOSSES)}, got {loss!r}")
    H, R = _sure_matrices(estimator, batch, meas_cov)
    return stein_risk(run, out, batch.z, H, R, generator, scored=batch.scored), out


def _sure_matrices(
    estimator: nn.Module, batch: TrackBatch, meas_cov: Tensor | None
) -> tuple[Tensor, Tensor]:
    """``H`` and the known ``R`` that SURE measures the estimator's risk with."""
    model: LinearModel = estimator.model  # type: ignore[assignment]
    H = model.meas_matrix().to(batch.z.dtype)
    return H, known_meas_cov(estimator, meas_cov, batch.z.dtype)


def _paired_sure(
    estimator: nn.Module,
    batch: TrackBatch,
    run: Callable[[Tensor, TrackBatch], Any],
    meas_cov: Tensor | None,
    generator: torch.Generator | None,
) -> tuple[Tensor, Any]:
    """:func:`batch_loss`'s ``"sure"`` for an estimator with ``paired_probes``: the plain and
    the probed measurements in one run of the batch's rows twice over (the same probe as the
    two runs would draw, so the same risk)."""
    H, R = _sure_matrices(estimator, batch, meas_cov)
    B = len(batch.z)
    std = R.diagonal(dim1=-2, dim2=-1).sqrt()
    probe = draw_probe(batch.z, std, SURE_STEP, generator, batch.scored)  # as stein_risk draws

    rows = batch._replace(
        x0=torch.cat([batch.x0, batch.x0]),
        P0=torch.cat([batch.P0, batch.P0]) if batch.P0.ndim == 3 else batch.P0,  # or shared
        dt=None if batch.dt is None else torch.cat([batch.dt, batch.dt]),
    )
    out, shifted = split_batch(run(torch.cat([batch.z, probe.measurements]), rows), B)
    risk = stein_risk(lambda _: shifted, out, batch.z, H, R, scored=batch.scored, probe=probe)
    return risk, out

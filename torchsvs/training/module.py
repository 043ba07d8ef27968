"""Any torchsvs estimator as a LightningModule."""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from torchsvs.estimator import Estimator, threads_for
from torchsvs.filters.svsf import SVSF
from torchsvs.metrics import pooled_rmse
from torchsvs.models.base import LinearModel
from torchsvs.training.data import TrackBatch
from torchsvs.training.losses import (
    LOSSES,
    innovation_nll,
    prediction_error,
    stein_risk,
    supervised_mse,
)
from torchsvs.types import FilterResult, SmootherResult


def boundary_layer_modules(module: nn.Module) -> list[SVSF]:
    """The SVSFs inside ``module`` (to log their ψ and γ)."""
    return [m for m in module.modules() if isinstance(m, SVSF)]


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
) -> tuple[Tensor, Any]:
    """The estimator's result on a batch and its ``loss`` (one of :data:`LOSSES`).

    Priors built from the data (``batch.prior_var`` set) are rebuilt from every ``z`` the loss
    evaluates, so SURE's divergence includes their dependence on the measurements. Only
    ``"supervised"`` reads ``batch.truth``.
    """
    from torchsvs.datasets.priors import two_point_prior

    def run(z: Tensor) -> Any:
        x0, P0 = batch.x0, batch.P0
        if batch.prior_var is not None:
            assert batch.dt is not None
            prior = two_point_prior(z, batch.dt, batch.prior_var)
            x0, P0 = prior.x0, prior.P0
        kwargs = {} if batch.dt is None else {"dt": batch.dt}
        return estimator(z, x0, P0, **kwargs)

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
    model: LinearModel = estimator.model  # type: ignore[assignment]
    H = model.meas_matrix().to(batch.z.dtype)
    R = known_meas_cov(estimator, meas_cov, batch.z.dtype)
    return stein_risk(run, out, batch.z, H, R, generator, scored=batch.scored), out


class EstimatorModule(L.LightningModule):
    """Fits an estimator's parameters (ψ, γ, and Q, R when learnable) to tracks.

    Works on simulated tracks (:class:`ManeuveringTargetDataModule`, with truth) and on recorded
    ones (:class:`RecordedTracksDataModule`, without): the truth-free losses never read
    ``batch.truth``, and the RMSE to truth is logged only where a batch has it.

    Args:
        estimator: any torchsvs estimator (filter or smoother), or a module with the same call
            signature (e.g. a network that drives an SVSF's per-step ψ).
        loss: ``"supervised"`` (MSE to truth on ``components``), ``"sure"`` (Stein's unbiased
            estimate of the measured components' MSE, from the known R), ``"nll"`` (negative
            log-likelihood of the innovations) or ``"prediction"`` (next-measurement prediction
            error); all but the first need no truth.
        components: state components of the supervised loss and of the logged RMSE.
        lr: Adam learning rate (on ``log ψ`` and ``logit γ``, so steps are relative).
        seed: seed of the SURE probes.
        meas_cov: the sensor's measurement covariance ``[m, m]`` for ``"sure"`` (default: the
            model's R, which must then be fixed).
    """

    def __init__(
        self,
        estimator: nn.Module,
        loss: str = "supervised",
        components: list[int] | None = None,
        lr: float = 0.05,
        seed: int = 0,
        meas_cov: Tensor | None = None,
    ) -> None:
        super().__init__()
        if loss not in LOSSES:
            raise ValueError(f"loss: expected one of {sorted(LOSSES)}, got {loss!r}")
        if not any(p.requires_grad for p in estimator.parameters()):
            raise ValueError("estimator: has no learnable parameter (learn=False everywhere?)")
        self.save_hyperparameters(ignore=["estimator", "meas_cov"])
        self.estimator = estimator
        self.loss_name = loss
        self.components = list(components) if components is not None else [0, 2]
        self.lr = lr
        self.probes = torch.Generator().manual_seed(seed)
        self.meas_cov = None if meas_cov is None else torch.as_tensor(meas_cov).detach().clone()
        if loss == "sure":
            known_meas_cov(estimator, self.meas_cov, torch.float64)  # refuse a learnable R early

    def forward(self, z: Tensor, x0: Tensor, P0: Tensor, **kwargs: Any) -> Any:
        return self.estimator(z, x0, P0, **kwargs)

    def _step(self, batch: TrackBatch, stage: str) -> Tensor:
        loss, out = batch_loss(
            self.estimator, batch, self.loss_name, self.components, self.meas_cov, self.probes
        )
        size = batch.z.shape[0]
        self.log(f"{stage}_loss", loss, prog_bar=True, batch_size=size, sync_dist=stage != "train")
        if batch.truth is not None:
            index = self.components
            truth = batch.truth[..., index]
            self.log(
                f"{stage}_rmse",
                pooled_rmse(out.mean[..., index], truth, batch.scored),
                prog_bar=stage != "train",
                batch_size=size,
                sync_dist=stage != "train",
            )
        return loss

    def on_train_batch_start(self, batch: TrackBatch, batch_idx: int) -> None:
        # The forward pass scopes its own threads; this covers the backward pass and the
        # optimiser too (see torchsvs.estimator.threads_for).
        self._threads: AbstractContextManager[None] | None = threads_for(
            batch.z.shape[0], batch.x0.shape[-1]
        )
        self._threads.__enter__()

    def on_train_batch_end(self, outputs: Any, batch: TrackBatch, batch_idx: int) -> None:
        self._restore_threads()

    def on_exception(self, exception: BaseException) -> None:
        self._restore_threads()

    def _restore_threads(self) -> None:
        threads, self._threads = getattr(self, "_threads", None), None
        if threads is not None:
            threads.__exit__(None, None, None)

    def training_step(self, batch: TrackBatch, batch_idx: int) -> Tensor:
        loss = self._step(batch, "train")
        for i, svsf in enumerate(boundary_layer_modules(self.estimator)):
            tag = "" if i == 0 else f"{i}_"
            psi = svsf.psi.detach().reshape(-1)
            for j, value in enumerate(psi):
                self.log(f"{tag}psi_{j}", value, batch_size=batch.z.shape[0])
            self.log(f"{tag}gamma", svsf.gamma.detach(), batch_size=batch.z.shape[0])
        return loss

    def validation_step(self, batch: TrackBatch, batch_idx: int) -> Tensor:
        return self._step(batch, "val")

    def test_step(self, batch: TrackBatch, batch_idx: int) -> Tensor:
        return self._step(batch, "test")

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam([p for p in self.parameters() if p.requires_grad], lr=self.lr)


__all__ = ["EstimatorModule", "Estimator", "boundary_layer_modules"]

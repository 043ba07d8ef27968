"""Any torchsvs estimator as a LightningModule."""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from torchsvs.estimator import Estimator, threads_for
from torchsvs.filters.svsf import SVSF
from torchsvs.fitting.batches import TrackBatch, batch_loss, known_meas_cov
from torchsvs.fitting.losses import (
    LOSSES,
)
from torchsvs.metrics import pooled_rmse


def boundary_layer_modules(module: nn.Module) -> list[SVSF]:
    """The SVSFs inside ``module`` (to log their ψ and γ)."""
    return [m for m in module.modules() if isinstance(m, SVSF)]


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

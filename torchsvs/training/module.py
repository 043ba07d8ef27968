"""Any torchsvs estimator as a LightningModule."""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from torchsvs.estimator import Estimator
from torchsvs.filters.svsf import SVSF
from torchsvs.metrics import accumulative_rmse
from torchsvs.models.base import LinearModel
from torchsvs.training.data import TrackBatch
from torchsvs.training.losses import (
    LOSSES,
    innovation_nll,
    prediction_error,
    stein_risk,
    supervised_mse,
)


def boundary_layer_modules(module: nn.Module) -> list[SVSF]:
    """The SVSFs inside ``module`` (to log their ψ and γ)."""
    return [m for m in module.modules() if isinstance(m, SVSF)]


class EstimatorModule(L.LightningModule):
    """Fits an estimator's parameters (ψ, γ, and Q, R when learnable) to simulated tracks.

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
    """

    def __init__(
        self,
        estimator: nn.Module,
        loss: str = "supervised",
        components: list[int] | None = None,
        lr: float = 0.05,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if loss not in LOSSES:
            raise ValueError(f"loss: expected one of {sorted(LOSSES)}, got {loss!r}")
        if not any(p.requires_grad for p in estimator.parameters()):
            raise ValueError("estimator: has no learnable parameter (learn=False everywhere?)")
        self.save_hyperparameters(ignore=["estimator"])
        self.estimator = estimator
        self.loss_name = loss
        self.components = list(components) if components is not None else [0, 2]
        self.lr = lr
        self.probes = torch.Generator().manual_seed(seed)

    def forward(self, z: Tensor, x0: Tensor, P0: Tensor, **kwargs: Any) -> Any:
        return self.estimator(z, x0, P0, **kwargs)

    def _step(self, batch: TrackBatch, stage: str) -> Tensor:
        out = self(batch.z, batch.x0, batch.P0)
        loss = self._loss(out, batch)
        rmse = accumulative_rmse(out.mean[..., self.components], batch.truth[..., self.components])
        size = batch.z.shape[0]
        self.log(f"{stage}_loss", loss, prog_bar=True, batch_size=size, sync_dist=stage != "train")
        self.log(
            f"{stage}_rmse",
            rmse.square().mean().sqrt(),
            prog_bar=stage != "train",
            batch_size=size,
            sync_dist=stage != "train",
        )
        return loss

    def _loss(self, out: Any, batch: TrackBatch) -> Tensor:
        if self.loss_name == "supervised":
            return supervised_mse(out, batch.truth, self.components)
        if self.loss_name == "nll":
            return innovation_nll(out)
        if self.loss_name == "prediction":
            return prediction_error(out)
        model: LinearModel = self.estimator.model  # type: ignore[assignment]
        H, R = model.meas_matrix().to(batch.z.dtype), model.meas_cov().to(batch.z.dtype)
        return stein_risk(self.estimator, out, batch.z, batch.x0, batch.P0, H, R, self.probes)

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

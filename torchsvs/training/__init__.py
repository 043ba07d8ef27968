"""Training torchsvs estimators with Lightning (the only package, with the CLI, that imports it).

* :class:`ManeuveringTargetDataModule`: random maneuvering tracks, seeded splits.
* :class:`EstimatorModule`: any torchsvs estimator as a LightningModule, with supervised and
  self-supervised losses.
* ``torchsvs fit --config CONFIG.yaml``: the LightningCLI.
"""

from torchsvs.training.data import ManeuverDataset, ManeuveringTargetDataModule, TrackBatch
from torchsvs.training.losses import (
    LOSSES,
    innovation_nll,
    prediction_error,
    stein_risk,
    supervised_mse,
)
from torchsvs.training.module import EstimatorModule, boundary_layer_modules

__all__ = [
    "LOSSES",
    "EstimatorModule",
    "ManeuverDataset",
    "ManeuveringTargetDataModule",
    "TrackBatch",
    "boundary_layer_modules",
    "innovation_nll",
    "prediction_error",
    "stein_risk",
    "supervised_mse",
]

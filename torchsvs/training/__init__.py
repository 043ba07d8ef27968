"""Training torchsvs estimators with Lightning (the only package, with the CLI, that imports it).

* :class:`ManeuveringTargetDataModule`: random maneuvering tracks, seeded splits.
* :class:`RecordedTracksDataModule`: a fixed set of recorded tracks (no truth needed).
* :func:`self_tune`: the fast truth-free fit behind ``torchsvs track --fit``.
* :mod:`torchsvs.training.predict`: ``torchsvs track --processes N``, a track file estimated by
  ``Trainer.predict`` with DDP on CPU (:func:`~torchsvs.training.predict.predict_file`).
* :class:`EstimatorModule`: any torchsvs estimator as a LightningModule, with supervised and
  self-supervised losses.
* ``torchsvs fit --config CONFIG.yaml``: the LightningCLI; ``--config`` also takes the name of a
  config shipped with the package (:func:`shipped_configs`: ``atc_svss``, ``complex_svss``;
  :func:`config_path` gives its file).
"""

from torchsvs.training.configs import config_path, shipped_configs
from torchsvs.training.data import (
    ManeuverDataset,
    ManeuveringTargetDataModule,
    RecordedTracksDataModule,
    TrackBatch,
    recorded_batches,
)
from torchsvs.training.losses import (
    LOSSES,
    innovation_nll,
    prediction_error,
    stein_risk,
    supervised_mse,
)
from torchsvs.training.module import EstimatorModule, batch_loss, boundary_layer_modules
from torchsvs.training.tuning import FitResult, self_tune

__all__ = [
    "LOSSES",
    "EstimatorModule",
    "ManeuverDataset",
    "ManeuveringTargetDataModule",
    "RecordedTracksDataModule",
    "FitResult",
    "TrackBatch",
    "batch_loss",
    "boundary_layer_modules",
    "config_path",
    "recorded_batches",
    "self_tune",
    "shipped_configs",
    "innovation_nll",
    "prediction_error",
    "stein_risk",
    "supervised_mse",
]

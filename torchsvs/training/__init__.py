"""Training torchsvs estimators with Lightning (the only package, with the CLI, that imports it).

* :class:`ManeuveringTargetDataModule`: random maneuvering tracks, seeded splits.
* :class:`RecordedTracksDataModule`: a fixed set of recorded tracks (no truth needed).
* :func:`self_tune`: the fast truth-free fit behind ``torchsvs track --fit`` (it, the losses and
  the batches live in the Lightning-free :mod:`torchsvs.fitting`; named here too).
* :mod:`torchsvs.training.predict`: ``torchsvs track --processes N``, a track file estimated by
  ``Trainer.predict`` with DDP on CPU (:func:`~torchsvs.training.predict.predict_file`).
* :class:`EstimatorModule`: any torchsvs estimator as a LightningModule, with supervised and
  self-supervised losses.
* ``torchsvs fit --config CONFIG.yaml``: the LightningCLI; ``--config`` also takes the name of a
  config shipped with the package (:func:`shipped_configs`: ``atc_svss``, ``complex_svss``;
  :func:`config_path` gives its file).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from torchsvs.lazy_names import lazy_names

# Names resolved on first use (PEP 562), so that importing a Lightning-free part, e.g.
# ``torchsvs.training.configs``, does not import Lightning (~2 s); the truth-free fits live in
# :mod:`torchsvs.fitting` (Lightning-free).
_HOMES = {
    "config_path": "torchsvs.training.configs",
    "shipped_configs": "torchsvs.training.configs",
    "ManeuverDataset": "torchsvs.training.data",
    "ManeuveringTargetDataModule": "torchsvs.training.data",
    "RecordedTracksDataModule": "torchsvs.training.data",
    "TrackBatch": "torchsvs.fitting.batches",
    "recorded_batches": "torchsvs.fitting.batches",
    "LOSSES": "torchsvs.fitting.losses",
    "innovation_nll": "torchsvs.fitting.losses",
    "prediction_error": "torchsvs.fitting.losses",
    "stein_risk": "torchsvs.fitting.losses",
    "supervised_mse": "torchsvs.fitting.losses",
    "EstimatorModule": "torchsvs.training.module",
    "batch_loss": "torchsvs.fitting.batches",
    "boundary_layer_modules": "torchsvs.training.module",
    "FitResult": "torchsvs.fitting.tuning",
    "self_tune": "torchsvs.fitting.tuning",
}

if TYPE_CHECKING:
    from torchsvs.fitting.batches import TrackBatch, batch_loss, recorded_batches
    from torchsvs.fitting.losses import (
        LOSSES,
        innovation_nll,
        prediction_error,
        stein_risk,
        supervised_mse,
    )
    from torchsvs.fitting.tuning import FitResult, self_tune
    from torchsvs.training.configs import config_path, shipped_configs
    from torchsvs.training.data import (
        ManeuverDataset,
        ManeuveringTargetDataModule,
        RecordedTracksDataModule,
    )
    from torchsvs.training.module import EstimatorModule, boundary_layer_modules


__getattr__, __dir__ = lazy_names(__name__, _HOMES, globals())


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

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

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Names resolved on first use (PEP 562), so that importing a Lightning-free part, e.g.
# ``torchsvs.training.noise`` on every ``torchsvs track`` run, does not import Lightning (~2 s).
_HOMES = {
    "config_path": "configs",
    "shipped_configs": "configs",
    "ManeuverDataset": "data",
    "ManeuveringTargetDataModule": "data",
    "RecordedTracksDataModule": "data",
    "TrackBatch": "batches",
    "recorded_batches": "batches",
    "LOSSES": "losses",
    "innovation_nll": "losses",
    "prediction_error": "losses",
    "stein_risk": "losses",
    "supervised_mse": "losses",
    "EstimatorModule": "module",
    "batch_loss": "batches",
    "boundary_layer_modules": "module",
    "FitResult": "tuning",
    "self_tune": "tuning",
}

if TYPE_CHECKING:
    from torchsvs.training.batches import TrackBatch, batch_loss, recorded_batches
    from torchsvs.training.configs import config_path, shipped_configs
    from torchsvs.training.data import (
        ManeuverDataset,
        ManeuveringTargetDataModule,
        RecordedTracksDataModule,
    )
    from torchsvs.training.losses import (
        LOSSES,
        innovation_nll,
        prediction_error,
        stein_risk,
        supervised_mse,
    )
    from torchsvs.training.module import EstimatorModule, boundary_layer_modules
    from torchsvs.training.tuning import FitResult, self_tune


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'torchsvs.training' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"torchsvs.training.{_HOMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))


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

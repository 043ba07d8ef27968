"""torchsvs: smooth variable structure estimation in PyTorch.

Batched, differentiable state estimators as ``nn.Module`` s: the Kalman filter and RTS smoother,
the extended and unscented Kalman filters, the interacting multiple model estimator (IMM) and
its smoother, the separate-modeling road tracker built on it, the smooth variable structure filter
(SVSF) and smoother (SVSS), with learnable boundary layer ψ and memory γ. See ``torchsvs.types``
for the shape conventions.
"""

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from torchsvs import datasets, metrics, models, scenarios
    from torchsvs.filters import (
        IMM,
        SPVSF,
        SVSF,
        AdaptiveNoise,
        ArtificialKalmanFilter,
        ExtendedKalmanFilter,
        FiniteDifferenceVelocity,
        IMMResult,
        IMMState,
        KalmanFilter,
        ParticleFilter,
        RobustStudentTKalmanFilter,
        SeparateModelingResult,
        SeparateModelingTracker,
        SlidingInnovationFilter,
        TurnIMM,
        UnscentedKalmanFilter,
        VariableBoundarySVSF,
    )
    from torchsvs.smoothers import (
        SVSS,
        IMMSmoother,
        IMMSmootherResult,
        RTSSmoother,
        TurnIMMSmoother,
    )
    from torchsvs.types import FilterResult, FilterState, SmootherResult

#: Where each name lives: imported when first used (``import torchsvs.datasets.rows`` imports
#: no estimator, nor torch: a file is read while torch is imported, ``torchsvs track``).
_HOMES = {
    **dict.fromkeys(("datasets", "metrics", "models", "scenarios")),
    "IMM": "filters",
    "SPVSF": "filters",
    "SVSF": "filters",
    "AdaptiveNoise": "filters",
    "ArtificialKalmanFilter": "filters",
    "ExtendedKalmanFilter": "filters",
    "FiniteDifferenceVelocity": "filters",
    "IMMResult": "filters",
    "IMMState": "filters",
    "KalmanFilter": "filters",
    "ParticleFilter": "filters",
    "RobustStudentTKalmanFilter": "filters",
    "SeparateModelingResult": "filters",
    "SeparateModelingTracker": "filters",
    "SlidingInnovationFilter": "filters",
    "TurnIMM": "filters",
    "UnscentedKalmanFilter": "filters",
    "VariableBoundarySVSF": "filters",
    "SVSS": "smoothers",
    "IMMSmoother": "smoothers",
    "IMMSmootherResult": "smoothers",
    "RTSSmoother": "smoothers",
    "TurnIMMSmoother": "smoothers",
    "FilterResult": "types",
    "FilterState": "types",
    "SmootherResult": "types",
}


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    home = _HOMES[name]
    if home is None:  # a subpackage
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value  # (found directly from now on)
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


__all__ = [
    "AdaptiveNoise",
    "ArtificialKalmanFilter",
    "SVSF",
    "SPVSF",
    "SVSS",
    "ParticleFilter",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "FilterResult",
    "FilterState",
    "FiniteDifferenceVelocity",
    "IMM",
    "IMMResult",
    "IMMSmoother",
    "IMMSmootherResult",
    "IMMState",
    "KalmanFilter",
    "RTSSmoother",
    "RobustStudentTKalmanFilter",
    "SeparateModelingResult",
    "SeparateModelingTracker",
    "SlidingInnovationFilter",
    "SmootherResult",
    "TurnIMM",
    "TurnIMMSmoother",
    "VariableBoundarySVSF",
    "datasets",
    "metrics",
    "models",
    "scenarios",
]
__version__ = "0.1.0"

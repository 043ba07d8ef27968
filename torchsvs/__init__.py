"""torchsvs: smooth variable structure estimation in PyTorch.

Batched, differentiable state estimators as ``nn.Module`` s: the Kalman filter and RTS smoother,
the extended and unscented Kalman filters, the interacting multiple model estimator (IMM) and
its smoother, the separate-modeling road tracker built on it, the smooth variable structure filter
(SVSF) and smoother (SVSS), with learnable boundary layer ψ and memory γ. See ``torchsvs.types``
for the shape conventions.
"""

from typing import TYPE_CHECKING

from torchsvs.lazy_names import lazy_names

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


__getattr__, __dir__ = lazy_names(__name__, _HOMES, globals())


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

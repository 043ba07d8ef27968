"""torchsvs: smooth variable structure estimation in PyTorch.

Batched, differentiable state estimators as ``nn.Module`` s: the Kalman filter and RTS smoother,
the extended and unscented Kalman filters, the interacting multiple model estimator (IMM) and
its smoother, the separate-modeling road tracker built on it, the smooth variable structure filter
(SVSF) and smoother (SVSS), with learnable boundary layer ψ and memory γ. See ``torchsvs.types``
for the shape conventions.
"""

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
from torchsvs.smoothers import SVSS, IMMSmoother, IMMSmootherResult, RTSSmoother, TurnIMMSmoother
from torchsvs.types import FilterResult, FilterState, SmootherResult

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

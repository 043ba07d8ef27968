"""Filters: how we estimate x_t from z_1..z_t."""

from torchsvs.filters.adaptive import AdaptiveNoise
from torchsvs.filters.artificial import (
    BallisticCoefficientFromDrag,
    FiniteDifferenceVelocity,
    ModulusFromAcceleration,
)
from torchsvs.filters.gaussian import GaussianFilter
from torchsvs.filters.imm import IMM, IMMResult, IMMState
from torchsvs.filters.kalman import KalmanFilter
from torchsvs.filters.nonlinear import ExtendedKalmanFilter, UnscentedKalmanFilter
from torchsvs.filters.particle import ParticleFilter, ParticleResult
from torchsvs.filters.robust import RobustStudentTKalmanFilter
from torchsvs.filters.separate.tracker import SeparateModelingResult, SeparateModelingTracker
from torchsvs.filters.sif import SlidingInnovationFilter
from torchsvs.filters.spvsf import SPVSF
from torchsvs.filters.svsf import SVSF, ArtificialKalmanFilter, VariableBoundarySVSF
from torchsvs.filters.turn_imm import TurnIMM

__all__ = [
    "AdaptiveNoise",
    "ArtificialKalmanFilter",
    "BallisticCoefficientFromDrag",
    "IMM",
    "IMMResult",
    "IMMState",
    "SPVSF",
    "SVSF",
    "ParticleFilter",
    "ParticleResult",
    "ExtendedKalmanFilter",
    "UnscentedKalmanFilter",
    "FiniteDifferenceVelocity",
    "GaussianFilter",
    "KalmanFilter",
    "ModulusFromAcceleration",
    "RobustStudentTKalmanFilter",
    "SeparateModelingResult",
    "SeparateModelingTracker",
    "SlidingInnovationFilter",
    "TurnIMM",
    "VariableBoundarySVSF",
]

"""State-space models: what the system is (F, H, Q, R, dt). Models never import estimators."""

from torchsvs.models.ballistic import BallisticReentry
from torchsvs.models.base import LinearModel, StateSpaceModel
from torchsvs.models.eha import ElectrohydrostaticActuator
from torchsvs.models.linear import LinearGaussian
from torchsvs.models.mileage import (
    MileageConstantAcceleration,
    MileageConstantVelocity,
    SeparateModel,
)
from torchsvs.models.motion import ConstantAcceleration, ConstantVelocity, CoordinatedTurn
from torchsvs.models.sensors import SlantRanges
from torchsvs.models.turn import CoordinatedTurn3D

__all__ = [
    "BallisticReentry",
    "ConstantAcceleration",
    "ConstantVelocity",
    "CoordinatedTurn",
    "CoordinatedTurn3D",
    "ElectrohydrostaticActuator",
    "LinearGaussian",
    "LinearModel",
    "MileageConstantAcceleration",
    "MileageConstantVelocity",
    "SeparateModel",
    "SlantRanges",
    "StateSpaceModel",
]

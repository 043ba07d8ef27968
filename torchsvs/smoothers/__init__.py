"""Smoothers: estimates of x_t that also use later measurements, from a stored filter pass."""

from torchsvs.smoothers.imm import IMMSmoother, IMMSmootherResult, TurnIMMSmoother
from torchsvs.smoothers.rts import RTSSmoother
from torchsvs.smoothers.svss import SVSS

__all__ = ["SVSS", "IMMSmoother", "IMMSmootherResult", "RTSSmoother", "TurnIMMSmoother"]

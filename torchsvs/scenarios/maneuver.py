"""A batched maneuvering-target generator built from motion segments.

Targets move in the plane with state ``[x, vx, y, vy]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Segment:
    """One maneuver of a target, applied for ``duration`` seconds.

    Attributes:
        duration: seconds, a positive multiple of the sampling interval.
        turn_rate: initial turn rate ω in rad/s (positive: counter-clockwise).
        turn_accel: angular acceleration in rad/s² (ω grows linearly during the segment).
        accel: linear acceleration ``(ax, ay)`` in m/s², in the plane's axes.

    Each parameter may also be a tensor ``[B]`` (``accel`` ``[B, 2]``) to give every track its own
    maneuver of the same duration.
    """

    duration: float
    turn_rate: float | Tensor = 0.0
    turn_accel: float | Tensor = 0.0
    accel: tuple[float, float] | Tensor = (0.0, 0.0)


def simulate_segments(
    initial_state: Tensor, segments: Sequence[Segment], dt: float, substeps: int = 20
) -> Tensor:
    """Noise-free truth sampled every ``dt`` seconds, ``[B, T, 4]`` (``T = Σ duration / dt``).

    The velocity rotates by ``ω h`` and gains ``a h`` over each substep ``h = dt/substeps`` (ω at
    the substep's midpoint), and the position advances by the trapezoid of the velocities, so a
    constant turn is followed with error O(h²) in position per step.

    Args:
        initial_state: ``[B, 4]`` or ``[4]`` as ``[x, vx, y, vy]`` at time 0.
        segments: the maneuvers in order.
        dt: sampling interval in seconds.
        substeps: integration substeps per interval.
    """
    state = initial_state if initial_state.ndim == 2 else initial_state.unsqueeze(0)
    dtype = state.dtype
    pos = state[:, [0, 2]].clone()
    vel = state[:, [1, 3]].clone()
    h = dt / substeps
    samples = []
    for seg in segments:
        count = round(seg.duration / dt)
        if count < 1 or abs(count * dt - seg.duration) > 1e-9 * max(1.0, seg.duration):
            raise ValueError(
                f"segments: duration {seg.duration} is not a positive multiple of dt={dt}"
            )
        rate = torch.as_tensor(seg.turn_rate, dtype=dtype).reshape(-1, 1)
        rate_accel = torch.as_tensor(seg.turn_accel, dtype=dtype).reshape(-1, 1)
        accel = torch.as_tensor(seg.accel, dtype=dtype).reshape(-1, 2)
        elapsed = 0.0
        for _ in range(count):
            for _ in range(substeps):
                omega = rate + rate_accel * (elapsed + 0.5 * h)
                cos, sin = torch.cos(omega * h), torch.sin(omega * h)
                turned = torch.cat(
                    [cos * vel[:, :1] - sin * vel[:, 1:], sin * vel[:, :1] + cos * vel[:, 1:]],
                    dim=1,
                )
                new_vel = turned + accel * h
                pos = pos + 0.5 * h * (vel + new_vel)
                vel = new_vel
                elapsed += h
            samples.append(torch.stack([pos[:, 0], vel[:, 0], pos[:, 1], vel[:, 1]], dim=-1))
    return torch.stack(samples, dim=1)


def add_measurement_noise(
    truth: Tensor, H: Tensor, R: Tensor, generator: torch.Generator | None = None
) -> Tensor:
    """``z = H x + v`` with ``v ~ N(0, R)``, ``[B, T, n] → [B, T, m]``, noise from ``generator``."""
    L = torch.linalg.cholesky(R.to(truth.dtype))
    noise = torch.randn(*truth.shape[:-1], R.shape[-1], generator=generator, dtype=truth.dtype)
    return truth @ H.to(truth.dtype).mT + noise @ L.mT

"""A batched maneuvering-target generator built from motion segments.

Targets move in the plane with state ``[x, vx, y, vy]``. A trajectory is driven by per-step
controls (turn rate, angular acceleration, linear acceleration); segments (constant velocity,
constant turn, turn with angular acceleration, constant acceleration) are a convenient way to
write them, and :func:`random_maneuvers` draws a different random segment sequence per track.
Everything random takes a ``torch.Generator``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.models.base import gaussian_noise


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


class Controls(NamedTuple):
    """Per-step controls ``[B, T]`` (``accel`` ``[B, T, 2]``), constant within a step except ω."""

    turn_rate: Tensor  #: ω at the start of each step (rad/s)
    turn_accel: Tensor  #: dω/dt during the step (rad/s²)
    accel: Tensor  #: linear acceleration during the step (m/s²)


def segments_to_controls(
    segments: Sequence[Segment], dt: float, dtype: torch.dtype = torch.float64
) -> Controls:
    """Per-step controls of a segment sequence (batch axis 1, or ``B`` for tensor parameters)."""
    rates, rate_accels, accels = [], [], []
    for seg in segments:
        count = round(seg.duration / dt)
        if count < 1 or abs(count * dt - seg.duration) > 1e-9 * max(1.0, seg.duration):
            raise ValueError(
                f"segments: duration {seg.duration} is not a positive multiple of dt={dt}"
            )
        elapsed = torch.arange(count, dtype=dtype) * dt
        rate = torch.as_tensor(seg.turn_rate, dtype=dtype).reshape(-1, 1)
        rate_accel = torch.as_tensor(seg.turn_accel, dtype=dtype).reshape(-1, 1)
        accel = torch.as_tensor(seg.accel, dtype=dtype).reshape(-1, 1, 2)
        rates.append(rate + rate_accel * elapsed)
        rate_accels.append(rate_accel.expand(-1, count))
        accels.append(accel.expand(-1, count, 2))
    batch = max(r.shape[0] for r in rates)
    return Controls(
        torch.cat([r.expand(batch, -1) for r in rates], dim=1),
        torch.cat([r.expand(batch, -1) for r in rate_accels], dim=1),
        torch.cat([a.expand(batch, -1, -1) for a in accels], dim=1),
    )


def simulate_controls(
    initial_state: Tensor,
    controls: Controls,
    dt: float,
    substeps: int = 20,
    speed_limits: tuple[float, float] | None = None,
) -> Tensor:
    """Noise-free truth sampled every ``dt`` seconds, ``[B, T, 4]``.

    Over each substep ``h = dt/substeps`` the velocity rotates by ``ω h`` (ω at the substep's
    midpoint) and gains ``a h``, and the position advances by the trapezoid of the velocities:
    a constant turn is followed with an O(h²) position error per step.

    Args:
        initial_state: ``[B, 4]`` or ``[4]`` as ``[x, vx, y, vy]`` at time 0.
        controls: per-step controls, batch 1 or ``B``.
        dt: sampling interval in seconds.
        substeps: integration substeps per interval.
        speed_limits: optional ``(min, max)`` speed in m/s; the velocity is rescaled into it after
            every substep (keeps random accelerations physical).
    """
    state = initial_state if initial_state.ndim == 2 else initial_state.unsqueeze(0)
    batch = max(state.shape[0], controls.turn_rate.shape[0])
    state = state.expand(batch, 4)
    pos, vel = state[:, [0, 2]], state[:, [1, 3]]
    h = dt / substeps
    samples = []
    for k in range(controls.turn_rate.shape[1]):
        rate = controls.turn_rate[:, k : k + 1]
        rate_accel = controls.turn_accel[:, k : k + 1]
        accel = controls.accel[:, k]
        for j in range(substeps):
            omega = rate + rate_accel * ((j + 0.5) * h)
            cos, sin = torch.cos(omega * h), torch.sin(omega * h)
            turned = torch.cat(
                [cos * vel[:, :1] - sin * vel[:, 1:], sin * vel[:, :1] + cos * vel[:, 1:]], dim=1
            )
            new_vel = turned + accel * h
            if speed_limits is not None:
                speed = new_vel.norm(dim=1, keepdim=True)
                new_vel = new_vel * (speed.clamp(*speed_limits) / speed.clamp_min(1e-12))
            pos = pos + 0.5 * h * (vel + new_vel)
            vel = new_vel
        samples.append(torch.stack([pos[:, 0], vel[:, 0], pos[:, 1], vel[:, 1]], dim=-1))
    return torch.stack(samples, dim=1)


def simulate_segments(
    initial_state: Tensor, segments: Sequence[Segment], dt: float, substeps: int = 20
) -> Tensor:
    """Noise-free truth of a segment sequence, ``[B, T, 4]`` with ``T = Σ duration / dt``."""
    controls = segments_to_controls(segments, dt, initial_state.dtype)
    return simulate_controls(initial_state, controls, dt, substeps)


def add_measurement_noise(
    truth: Tensor, H: Tensor, R: Tensor, generator: torch.Generator | None = None
) -> Tensor:
    """``z = H x + v`` with ``v ~ N(0, R)``, ``[B, T, n] → [B, T, m]``, noise from ``generator``.

    ``R`` is ``[m, m]`` or per track ``[B, m, m]``.
    """
    noise = gaussian_noise(R.to(truth.dtype), truth.shape[:-1], generator)
    return truth @ H.to(truth.dtype).mT + noise


@dataclass(frozen=True)
class ManeuverRanges:
    """Ranges (uniform) from which :func:`random_maneuvers` draws each track.

    Angles in degrees, distances in m, times in s. A segment is constant velocity, constant
    turn, turn with angular acceleration, or constant acceleration, with probabilities
    ``kind_weights``; its duration is a whole number of steps in ``segment_duration``. Speeds are
    kept within ``speed`` throughout.
    """

    steps: int = 200
    dt: float = 1.0
    speed: tuple[float, float] = (50.0, 350.0)
    segment_duration: tuple[float, float] = (10.0, 40.0)
    turn_rate_deg: tuple[float, float] = (1.0, 6.0)  #: magnitude; the sign is random
    turn_accel_deg: tuple[float, float] = (0.05, 0.5)  #: magnitude; the sign is random
    accel: tuple[float, float] = (2.0, 20.0)  #: magnitude; the direction is random
    meas_std: tuple[float, float] = (50.0, 250.0)
    kind_weights: tuple[float, float, float, float] = (0.4, 0.3, 0.1, 0.2)


class ManeuverBatch(NamedTuple):
    """Random maneuvering tracks: truth ``[B, T, 4]``, ``z [B, T, 2]`` and per-track noise."""

    truth: Tensor
    z: Tensor
    initial: Tensor  #: [B, 4] true state at time 0, one step before z[:, 0]
    meas_std: Tensor  #: [B] position noise standard deviation of each track (m)
    kinds: Tensor  #: [B, T] segment kind per step: 0 CV, 1 CT, 2 turn + ang. accel, 3 CA
    dt: float


def _uniform(lo_hi: tuple[float, float], shape: tuple[int, ...], gen, dtype) -> Tensor:
    lo, hi = lo_hi
    return lo + (hi - lo) * torch.rand(shape, generator=gen, dtype=dtype)


def random_maneuvers(
    num_tracks: int,
    ranges: ManeuverRanges = ManeuverRanges(),
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> ManeuverBatch:
    """Draws ``num_tracks`` random segment sequences and simulates them, all in one batch.

    Each track starts at the origin with a random heading and a speed in ``ranges.speed``;
    segments follow each other with random kinds, durations and parameters; positions are
    measured with a per-track noise level in ``ranges.meas_std``.
    """
    B, T, dt = num_tracks, ranges.steps, ranges.dt
    lo, hi = (max(1, round(d / dt)) for d in ranges.segment_duration)
    max_segments = T // lo + 1
    lengths = torch.randint(lo, hi + 1, (B, max_segments), generator=generator)
    starts = torch.cumsum(lengths, dim=1) - lengths  # [B, S]
    step = torch.arange(T).expand(B, T).contiguous()
    seg = torch.searchsorted(torch.cumsum(lengths, dim=1), step, right=True)  # [B, T]
    elapsed = (step - starts.gather(1, seg)).to(dtype) * dt

    weights = torch.tensor(ranges.kind_weights, dtype=torch.float64)
    kinds = torch.multinomial(weights, B * max_segments, replacement=True, generator=generator)
    kinds = kinds.reshape(B, max_segments)
    sign = torch.where(torch.rand(B, max_segments, generator=generator) < 0.5, -1.0, 1.0)
    deg = math.pi / 180.0
    rate = sign.to(dtype) * _uniform(ranges.turn_rate_deg, (B, max_segments), generator, dtype)
    rate_accel = sign.to(dtype) * _uniform(
        ranges.turn_accel_deg, (B, max_segments), generator, dtype
    )
    accel_mag = _uniform(ranges.accel, (B, max_segments), generator, dtype)
    accel_dir = _uniform((0.0, 2 * math.pi), (B, max_segments), generator, dtype)
    is_turn = (kinds == 1) | (kinds == 2)
    is_turn_accel = kinds == 2
    is_accel = kinds == 3
    per_step = seg
    turn_accel = torch.where(is_turn_accel, rate_accel * deg, 0.0).gather(1, per_step)
    turn_rate = torch.where(is_turn, rate * deg, 0.0).gather(1, per_step) + turn_accel * elapsed
    accel = torch.stack([accel_mag * torch.cos(accel_dir), accel_mag * torch.sin(accel_dir)], -1)
    accel = torch.where(is_accel.unsqueeze(-1), accel, 0.0)
    accel = accel.gather(1, per_step.unsqueeze(-1).expand(B, T, 2))

    heading = _uniform((0.0, 2 * math.pi), (B,), generator, dtype)
    speed = _uniform(ranges.speed, (B,), generator, dtype)
    start = torch.stack(
        [
            torch.zeros(B, dtype=dtype),
            speed * torch.cos(heading),
            torch.zeros(B, dtype=dtype),
            speed * torch.sin(heading),
        ],
        dim=-1,
    )
    controls = Controls(turn_rate, turn_accel, accel)
    truth = simulate_controls(start, controls, dt, speed_limits=ranges.speed)
    meas_std = _uniform(ranges.meas_std, (B,), generator, dtype)
    H = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=dtype)
    R = meas_std.square()[:, None, None] * torch.eye(2, dtype=dtype)
    z = add_measurement_noise(truth, H, R, generator)
    return ManeuverBatch(truth, z, start, meas_std, kinds.gather(1, per_step), dt)

"""Scenario batches: the tracking scenarios of Chen et al. 2020 (Sec. 4) and random maneuvers,
each with the filters' model and prior, as seeded batches of Monte Carlo runs."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.models.base import StateSpaceModel, gaussian_noise
from torchsvs.models.motion import ConstantVelocity
from torchsvs.scenarios.maneuver import (
    ManeuverRanges,
    Segment,
    random_maneuvers,
    simulate_segments,
)


class Scenario(NamedTuple):
    """A batch of Monte Carlo runs: what an estimator needs and the truth to score it."""

    truth: Tensor  #: [B, T, 4] states at the measurement times
    z: Tensor  #: [B, T, 2] position measurements
    model: StateSpaceModel  #: the filters' model (Chen et al.: ConstantVelocity, Eqs. (43)-(48))
    x0: Tensor  #: [4] or [B, 4] filter prior, one step before z[:, 0]
    P0: Tensor  #: [4, 4]
    dt: float  #: sampling interval (s)
    meas_std: Tensor | None = None  #: [B] per-track noise level, when it varies
    u: Tensor | None = None  #: [B, T, p] control inputs, for models that take them


def atc_scenario(
    num_runs: int = 500,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    turn_directions: tuple[int, int] = (-1, 1),
) -> Scenario:
    """The air traffic control scenario of Sec. 4.1 (Table 1, Figs. 4-7).

    Truth (no process noise): from ``(−25000, −10000)`` m at 120 m/s along x, straight 125 s, a
    3°/s turn for 30 s, straight 125 s, a 1°/s turn for 90 s, straight 120 s (490 s, T = 1 s).
    The text does not give the turn directions (``turn_directions``: +1 counter-clockwise, −1
    clockwise). The default has the first clockwise (the figures' geometry) and the second
    counter-clockwise: the SVSF of Sec. 4.1 never corrects the velocity (``H⁺ = Hᵀ``), so its
    error depends on the final heading, and only this choice fits Table 1 (x/y RMSE of SVSF with
    500 runs: cw-ccw 146/151, cw-cw 182/151, ccw-cw 146/157, ccw-ccw 182/157; paper 146/148).
    Measurements: position with
    200 m noise (Eq. (46)). Filters: ``x0 = [−25000, 80, −10000, −10]``, ``P0 =
    diag(10000, 1000, 10000, 1000)`` (Eq. (47)), ``Q`` of Eq. (48) with ``L = 0.16``.
    """
    dt = 1.0
    deg = math.pi / 180.0
    segments = [
        Segment(125.0),
        Segment(30.0, turn_rate=turn_directions[0] * 3.0 * deg),
        Segment(125.0),
        Segment(90.0, turn_rate=turn_directions[1] * 1.0 * deg),
        Segment(120.0),
    ]
    start = torch.tensor([-25000.0, 120.0, -10000.0, 0.0], dtype=dtype)
    truth = simulate_segments(start, segments, dt).expand(num_runs, -1, -1)
    model = ConstantVelocity(ndim=2, dt=dt, q=0.16, r=200.0**2).to(dtype)
    z = model.observe(truth, generator)
    x0 = torch.tensor([-25000.0, 80.0, -10000.0, -10.0], dtype=dtype)
    P0 = torch.diag(torch.tensor([10000.0, 1000.0, 10000.0, 1000.0], dtype=dtype))
    return Scenario(truth.contiguous(), z, model, x0, P0, dt)


def complex_scenario(
    num_runs: int = 500,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    turn_directions: tuple[int, int] = (1, -1),
) -> Scenario:
    """The complex maneuvering scenario of Sec. 4.2 (Table 3, Figs. 8-9).

    Truth (no process noise): from ``(−25000, −10000)`` m at ``(300, 250)`` m/s, straight 20 s,
    a 3°/s turn for 55 s, a turn starting at 1°/s with 0.5°/s² angular acceleration for 25 s, then
    25 s of ``(20, 10)`` m/s² acceleration (125 s, T = 1 s). The paper writes the first rate as
    −3°/s and the second as +1°/s; the KF and KS of Table 3 fit only if its angles count clockwise
    (x/y position RMSE of the KF, 500 runs: ccw-cw 463/303, cw-ccw 346/415, ccw-ccw 420/383, cw-cw
    442/372; paper 461/297), so the default ``turn_directions`` is (+1, −1) in this library's
    counter-clockwise convention. Measurements: position
    with 100 m noise (Eq. (49)). Filters: ``x0`` the true initial state, ``P0 = diag(400, 100,
    400, 100)`` (Eq. (50)), ``Q`` of Eq. (48) with ``L = 15``.
    """
    dt = 1.0
    deg = math.pi / 180.0
    segments = [
        Segment(20.0),
        Segment(55.0, turn_rate=turn_directions[0] * 3.0 * deg),
        Segment(
            25.0, turn_rate=turn_directions[1] * deg, turn_accel=turn_directions[1] * 0.5 * deg
        ),
        Segment(25.0, accel=(20.0, 10.0)),
    ]
    start = torch.tensor([-25000.0, 300.0, -10000.0, 250.0], dtype=dtype)
    truth = simulate_segments(start, segments, dt).expand(num_runs, -1, -1)
    model = ConstantVelocity(ndim=2, dt=dt, q=15.0, r=100.0**2).to(dtype)
    z = model.observe(truth, generator)
    P0 = torch.diag(torch.tensor([400.0, 100.0, 400.0, 100.0], dtype=dtype))
    return Scenario(truth.contiguous(), z, model, start.clone(), P0, dt)


def random_scenario(
    num_tracks: int,
    ranges: ManeuverRanges | None = None,
    q: float = 1.0,
    prior_std: tuple[float, float] = (100.0, 30.0),
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> Scenario:
    """Random maneuvering tracks (:func:`random_maneuvers`) with a model and a prior.

    ``x0`` is drawn per track from ``N(true initial state, P0)`` with
    ``P0 = diag(σ_p², σ_v², σ_p², σ_v²)`` from ``prior_std``; the model is a
    :class:`ConstantVelocity` with power spectral density ``q`` and, when the noise level varies
    between tracks, the middle of ``ranges.meas_std`` as its ``R`` (``meas_std`` holds each
    track's own level).
    """
    ranges = ranges if ranges is not None else ManeuverRanges()
    tracks = random_maneuvers(num_tracks, ranges, generator, dtype)
    pos_std, vel_std = prior_std
    P0 = torch.diag(torch.tensor([pos_std, vel_std, pos_std, vel_std], dtype=dtype) ** 2)
    x0 = tracks.initial + gaussian_noise(P0, (num_tracks,), generator)
    r = (0.5 * (ranges.meas_std[0] + ranges.meas_std[1])) ** 2
    model = ConstantVelocity(ndim=2, dt=ranges.dt, q=q, r=r).to(dtype)
    return Scenario(tracks.truth, tracks.z, model, x0, P0, ranges.dt, tracks.meas_std)

"""Example 4 of Bermúdez Ordoñez et al. 2020: DME-DME navigation of an aircraft from slant
ranges to two ground stations, as a seeded batch of Monte Carlo runs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.models.base import gaussian_noise
from torchsvs.models.sensors import SlantRanges
from torchsvs.scenarios.maneuver import Segment, segments_to_controls, simulate_controls

#: Cruising speed, 583 km/h (m/s).
SPEED = 583.0 / 3.6
#: Sampling interval T and flight duration (s).
DT, DURATION = 2.0, 3000.0
#: The final turn: 270° on a radius of 20 km ("gyro of 20 km").
TURN_ANGLE, TURN_RADIUS = 1.5 * math.pi, 20e3
#: Mean initial position (m), from x₀ ~ N(60, 10 km²), y₀ ~ N(210, 10 km²) read in km.
START = (60e3, 210e3)
#: Variance of each initial coordinate (m²): 10 km².
START_VAR = 10e6
#: The two DME stations on the x axis (m): not given in the text, chosen.
STATIONS = ((-20e3, 0.0), (20e3, 0.0))
#: Standard deviation of the truth's small random accelerations, σ_a max = 0.001 m/s².
ACCEL_STD = 1e-3
#: Range noise standard deviation (m): not given in the text (``diag(σ_x², σ_y²)``), chosen.
RANGE_STD = 100.0
#: Prior standard deviation of each velocity component (m/s): not given, chosen.
VELOCITY_STD = 10.0


class DMEScenario(NamedTuple):
    """A batch of DME flights: what an estimator needs and the truth to score it."""

    truth: Tensor  #: [B, T, 4] states [x, vx, y, vy] at the measurement times
    z: Tensor  #: [B, T, k] slant ranges to the stations
    model: SlantRanges  #: the filters' model (its R: ``model_std``)
    x0: Tensor  #: [4] filter prior, one step before z[:, 0] (the nominal start)
    P0: Tensor  #: [4, 4]
    dt: float  #: sampling interval (s)
    range_std: Tensor  #: [T, k] the truth's range noise standard deviation per step and station
    turn_start: float  #: time (s) at which the 270° turn begins


def dme_scenario(
    num_runs: int = 100,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    range_std: float | Sequence[float] | Tensor = RANGE_STD,
    model_std: float | Sequence[float] | None = None,
    q: float = 1.0,
    stations: Sequence[Sequence[float]] = STATIONS,
    turn_direction: int = 1,
) -> DMEScenario:
    """Example 4 (Figs. 20-23): a level flight at 583 km/h for 3000 s sampled every 2 s, straight
    toward the origin (between the two stations, where ``H`` is singular), then a 270° turn of
    radius 20 km at the end of the flight.

    Truth: the initial position is drawn per run from ``N((60, 210) km, 10 km² I)`` and the
    heading points from the mean start to the origin, so each run crosses the stations' baseline
    near the origin, after ``|start| / v = 1349`` s (the paper's figure reads 1063 s, which its
    stated start and speed cannot both give; we keep the stated numbers). The straight leg lasts
    2418 s and the turn (``turn_direction``: +1 counter-clockwise) 582 s (270° at the speed on a
    radius of 20.001 km, a whole number of steps). Small random accelerations ``N(0, σ_a²)`` per
    axis and step, ``σ_a = 0.001 m/s²`` (the paper's ``σ_a max``), perturb the path.

    What the text lost, chosen here: the stations at ``(∓20 km, 0)`` (``stations``), the range
    noise ``range_std = 100`` m (a float, one per station ``[k]`` or per step and station
    ``[T, k]``: a sensor whose quality changes), the filters' prior ``x0`` = the nominal start
    state, ``P0 = diag(10 km², (10 m/s)², 10 km², (10 m/s)²)``, and the filters' model:
    :class:`~torchsvs.models.SlantRanges` with ``q`` (m²/s³; the paper's ``σ_a max`` would
    leave a filter unable to follow the turn's 1.3 m/s²) and ``R`` from ``model_std`` (default
    the truth's noise at the first step).

    Args:
        num_runs: Monte Carlo runs ``B``.
        generator: the source of every random draw (start, accelerations, noise), in that order.
        dtype: float32 or float64.
    """
    if isinstance(num_runs, bool) or not isinstance(num_runs, int) or num_runs < 1:
        raise ValueError(f"num_runs: expected a positive integer, got {num_runs!r}")
    if turn_direction not in (1, -1):
        raise ValueError(f"turn_direction: expected +1 or -1, got {turn_direction!r}")
    steps = round(DURATION / DT)
    turn_steps = round(TURN_ANGLE * TURN_RADIUS / SPEED / DT)
    k = len(stations)
    std = torch.as_tensor(range_std, dtype=dtype)
    if std.ndim == 0 or std.shape == (k,):
        std = std.expand(steps, k)
    if std.shape != (steps, k):
        raise ValueError(
            f"range_std: expected a number, [{k}] or [{steps}, {k}], got {tuple(std.shape)}"
        )
    if not bool(torch.isfinite(std).all()) or bool((std <= 0).any()):
        raise ValueError("range_std: expected finite standard deviations > 0")
    nominal = std[0] if model_std is None else torch.as_tensor(model_std, dtype=dtype)
    model = SlantRanges(stations, dt=DT, q=q, r=nominal.square().expand(k)).to(dtype)

    start = torch.tensor(START, dtype=dtype)
    heading = -start / start.norm()
    velocity = SPEED * heading
    mean = torch.stack([start[0], velocity[0], start[1], velocity[1]])
    P0 = torch.diag(torch.tensor([START_VAR, VELOCITY_STD**2] * 2, dtype=dtype))
    offset = gaussian_noise(START_VAR * torch.eye(2, dtype=dtype), (num_runs,), generator)
    initial = mean.expand(num_runs, 4).clone()
    initial[:, [0, 2]] += offset

    rate = turn_direction * TURN_ANGLE / (turn_steps * DT)
    segments = [Segment((steps - turn_steps) * DT), Segment(turn_steps * DT, turn_rate=rate)]
    controls = segments_to_controls(segments, DT, dtype)
    accel = gaussian_noise(ACCEL_STD**2 * torch.eye(2, dtype=dtype), (num_runs, steps), generator)
    controls = controls._replace(
        turn_rate=controls.turn_rate.expand(num_runs, -1),
        turn_accel=controls.turn_accel.expand(num_runs, -1),
        accel=accel,
    )
    truth = simulate_controls(initial, controls, DT, substeps=2)
    # One covariance per step: drawn step-major, then batch first.
    noise = gaussian_noise(torch.diag_embed(std.square()), (steps, num_runs), generator)
    z = model.h(truth) + noise.transpose(0, 1)
    return DMEScenario(
        truth.contiguous(),
        z.contiguous(),
        model,
        mean,
        P0,
        DT,
        std,
        (steps - turn_steps) * DT,
    )

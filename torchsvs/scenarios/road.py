r"""The road-target scenarios of Zhang & Zhou (2022, Sec. 5) as seeded Monte Carlo batches.

A target moves along a road by arc length: its speed follows a piecewise-constant acceleration
profile, its travelled distance is the integral of the speed, and its position is the road's
point at that distance, so the trajectory's shape does not depend on the speed (the paper's
premise). Measurements are positions with white Gaussian noise, Eq. (11).

Time convention: samples ``k = 1..N`` (``z[:, k-1]``) at interval ``T``; the target is at the
road's start with the initial speed at ``k = 1``; "accelerates from step ``k₁`` to ``k₂``" means
the acceleration acts over the intervals ending at samples ``k₁..k₂``, so the speed gains
``(k₂ − k₁ + 1)·a·T``. Within an interval the acceleration is constant, so the arc length grows
by the trapezoid ``T (v_{k-1} + v_k)/2`` (exact).

Readings of the paper's numbers (its text lost the equations, and some values are not given):

* (i) straight road, Eq. (46): from (200, 300) m at θ = 65° (counter-clockwise from x),
  ``x = x₁ + s cos θ``, ``y = y₁ + s sin θ``; 1 m/s, +5 m/s² over steps 41-70 and 121-150
  (46 m/s, then 91 m/s); ``T = 0.3`` s, ``σ_x = σ_y = 2`` m. The number of steps is not stated;
  Fig. 2's axis suggests 200 (2894.7 m travelled).
* (ii) circular arc, Eq. (47): start (100, 30) m, centre (60, 60) m, radius 50 m: consistent
  (the start is 50 m from the centre). The direction of travel is not stated: counter-clockwise
  (the paper's angle convention) by default. Initial speed 5 m/s, +3 m/s² over steps 41-70,
  +2 m/s² over 111-150, 200 steps. ``T`` is not stated: 0.1 s, the round value for which the
  200 steps stay on one arc of the circle (286 m of its 314 m; 0.3 s as in (i) would lap the
  circle more than six times at up to 56 m/s, 0.2 s about three times). ``σ`` is not stated either:
  2 m, carried over from (i).
* (iii) curve road I, Eq. (48): a natural cubic spline in chord length through supporting points
  (:mod:`torchsvs.scenarios.spline`). The paper's text suggests its Eq. (48) re-fits the spline
  with the chord spline's arc lengths at the points as knots (a parameter only close to arc
  length); here the chord-length spline itself is reparameterised by arc length exactly. The
  paper's points were lost, so
  :data:`CURVE_ROAD_I_POINTS` is a designed road from (−400, 0) m with a few gentle bends
  (1107.7 m long, smallest radius of curvature 123 m) that fits the 981.7 m travelled. 2.3 m/s,
  +3.7 m/s² over steps 41-70, +2.2 m/s² over 111-150, 200 steps, ``T = 0.2`` s. The text's
  "measurement noise variances 0.8 m" is read as a standard deviation of 0.8 m per axis (the
  unit is metres).
* (iv) curve road II: as (iii) ("the rest parameters unchanged") with 250 steps, from
  (−700, 260) m at 16.5 m/s, +1.9 m/s² over 41-80, +1.6 m/s² over 111-150, +0.1 m/s² over
  181-210; :data:`CURVE_ROAD_II_POINTS` is a designed winding road (1822.1 m, with bends
  alternately left and right, smallest radius 110 m) for the 1713.1 m travelled.

Each scenario also carries the paper's estimator settings for it: the standard deviation of the
mileage models' process noise ``q``, of the artificial process noise of the trajectory
parameters ``eta_std`` and the window length. ``q`` is kept as the paper gives it; whether the
estimators follow the scenarios' acceleration steps with so small a ``q`` is studied by
``experiments/road_tracking.py``, which reports every estimator at the paper's ``q`` and at the
smallest ``q`` with which the SM tracker follows them (``experiments/results/road_tracking.md``).

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Sec. 5.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from torchsvs.scenarios.spline import ArcLengthSpline

#: Supporting points (m) of curve road I (Sec. 5.3), designed: the paper's were lost.
CURVE_ROAD_I_POINTS = (
    (-400.0, 0.0),
    (-300.0, 60.0),
    (-200.0, 80.0),
    (-100.0, 40.0),
    (0.0, -30.0),
    (100.0, -50.0),
    (200.0, 0.0),
    (300.0, 70.0),
    (400.0, 80.0),
    (500.0, 40.0),
    (600.0, 0.0),
)

#: Supporting points (m) of curve road II (Sec. 5.4), designed: the paper's were lost.
CURVE_ROAD_II_POINTS = (
    (-700.0, 260.0),
    (-600.0, 330.0),
    (-480.0, 340.0),
    (-400.0, 260.0),
    (-380.0, 140.0),
    (-300.0, 60.0),
    (-180.0, 60.0),
    (-100.0, 140.0),
    (-20.0, 230.0),
    (100.0, 250.0),
    (200.0, 180.0),
    (240.0, 60.0),
    (320.0, -20.0),
    (440.0, -20.0),
    (540.0, 60.0),
    (600.0, 160.0),
)


class Road(Protocol):
    """A road as a curve in its natural (arc-length) parameterisation (Eq. (12)), float64."""

    length: float

    def position(self, s: Tensor) -> Tensor:
        """Points ``[..., 2]`` at arc lengths ``s [...]``."""
        ...

    def direction(self, s: Tensor) -> Tensor:
        """Unit tangents ``[..., 2]`` (direction of travel) at ``s [...]``."""
        ...


class StraightRoad:
    r"""A straight road from ``start`` at ``heading`` (rad, counter-clockwise from x), Eq. (46):
    :math:`x = x_1 + s\cos\theta,\ y = y_1 + s\sin\theta`."""

    length = math.inf

    def __init__(self, start: tuple[float, float], heading: float) -> None:
        self.start = torch.tensor(start, dtype=torch.float64)
        self.unit = torch.tensor([math.cos(heading), math.sin(heading)], dtype=torch.float64)

    def position(self, s: Tensor) -> Tensor:
        return self.start + s.to(torch.float64).unsqueeze(-1) * self.unit

    def direction(self, s: Tensor) -> Tensor:
        return self.unit.expand(*s.shape, 2)


class CircularRoad:
    r"""A circle of ``radius`` about ``centre`` entered at ``start`` (which must lie on it),
    Eq. (47): :math:`x = x_c + R\cos(\varphi_1 + \sigma s/R),\ y = y_c + R\sin(\varphi_1 +
    \sigma s/R)` with :math:`\varphi_1` the start's polar angle and :math:`\sigma = +1`
    (counter-clockwise) or ``−1``."""

    def __init__(
        self,
        start: tuple[float, float],
        centre: tuple[float, float],
        radius: float,
        clockwise: bool = False,
    ) -> None:
        self.centre = torch.tensor(centre, dtype=torch.float64)
        offset = torch.tensor(start, dtype=torch.float64) - self.centre
        if not radius > 0 or abs(float(offset.norm()) - radius) > 1e-9 * max(1.0, radius):
            raise ValueError(
                f"start: expected a point at radius {radius} from centre {centre}, got "
                f"{start} at distance {float(offset.norm())}"
            )
        self.radius = float(radius)
        self.start_angle = math.atan2(float(offset[1]), float(offset[0]))
        self.turn = -1.0 if clockwise else 1.0
        self.length = 2.0 * math.pi * self.radius  # once round

    def _angle(self, s: Tensor) -> Tensor:
        return self.start_angle + self.turn * s.to(torch.float64) / self.radius

    def position(self, s: Tensor) -> Tensor:
        phi = self._angle(s)
        return self.centre + self.radius * torch.stack([phi.cos(), phi.sin()], dim=-1)

    def direction(self, s: Tensor) -> Tensor:
        phi = self._angle(s)
        return self.turn * torch.stack([-phi.sin(), phi.cos()], dim=-1)


class SpeedProfile(NamedTuple):
    """A target's motion along its road at the samples ``k = 1..N``, ``[N]`` each (float64)."""

    arc_length: Tensor  #: travelled distance from the start (m)
    speed: Tensor  #: (m/s)
    acceleration: Tensor  #: over the interval ending at each sample (m/s²; 0 at k = 1)


def speed_profile(
    initial_speed: float,
    accelerations: Sequence[tuple[int, int, float]],
    steps: int,
    dt: float,
) -> SpeedProfile:
    """Speed and travelled distance of a piecewise-constant acceleration profile.

    Args:
        initial_speed: speed at sample 1 (m/s).
        accelerations: ``(first, last, a)``: acceleration ``a`` (m/s²) over the intervals ending
            at samples ``first..last`` (1-based, as the paper counts steps); 0 elsewhere.
        steps: number of samples ``N``.
        dt: sampling interval ``T`` (s).
    """
    if not (isinstance(steps, int) and steps >= 1):
        raise ValueError(f"steps: expected a positive integer, got {steps!r}")
    if not dt > 0:
        raise ValueError(f"dt: expected a positive number, got {dt!r}")
    accel = torch.zeros(steps, dtype=torch.float64)
    k = torch.arange(1, steps + 1)
    for first, last, a in accelerations:
        if not 2 <= first <= last:
            raise ValueError(
                f"accelerations: expected 2 ≤ first ≤ last, got ({first}, {last}, {a})"
            )
        accel[(k >= first) & (k <= last)] += a
    speed = initial_speed + torch.cumsum(accel * dt, 0)
    increments = dt * (speed[1:] + speed[:-1]) / 2.0
    arc = torch.cat([speed.new_zeros(1), increments.cumsum(0)])
    return SpeedProfile(arc, speed, accel)


class RoadScenario(NamedTuple):
    """A batch of Monte Carlo runs on one road: the truth (the same in every run) and its
    noisy measurements, with the paper's estimator settings for the scenario."""

    position: Tensor  #: [B, T, 2] true positions (m)
    velocity: Tensor  #: [B, T, 2] true velocities (m/s), speed times the road's direction
    speed: Tensor  #: [B, T] (m/s)
    arc_length: Tensor  #: [B, T] travelled distance from the road's start (m)
    acceleration: Tensor  #: [B, T] along the road (m/s²)
    z: Tensor  #: [B, T, 2] position measurements, Eq. (11)
    dt: float  #: sampling interval T (s)
    meas_std: float  #: measurement noise standard deviation per axis (m)
    road: Road  #: the road (float64 geometry)
    q: float  #: the paper's process noise std of the NCV and NCA mileage models (m/s²)
    eta_std: float  #: the paper's artificial process noise std of the trajectory parameters
    window: int  #: the paper's sliding-window length

    @property
    def truth(self) -> Tensor:
        """``[B, T, 4]`` Cartesian truth ``[x, vx, y, vy]`` (the layout of
        :class:`~torchsvs.models.ConstantVelocity`)."""
        p, v = self.position, self.velocity
        return torch.stack([p[..., 0], v[..., 0], p[..., 1], v[..., 1]], dim=-1)

    @property
    def mileage(self) -> Tensor:
        """``[B, T, 3]`` true mileage state ``[s, ṡ, s̈]``."""
        return torch.stack([self.arc_length, self.speed, self.acceleration], dim=-1)


def road_scenario(
    road: Road,
    profile: SpeedProfile,
    dt: float,
    meas_std: float,
    num_runs: int,
    generator: torch.Generator | None,
    dtype: torch.dtype,
    q: float,
    eta_std: float,
    window: int,
) -> RoadScenario:
    """Truth of ``profile`` along ``road`` and measurements with ``meas_std`` (m) per axis."""
    if not (isinstance(num_runs, int) and num_runs >= 1):
        raise ValueError(f"num_runs: expected a positive integer, got {num_runs!r}")
    if not meas_std >= 0:
        raise ValueError(f"meas_std: expected a number ≥ 0, got {meas_std!r}")
    travelled = float(profile.arc_length[-1])
    if travelled > road.length:
        raise ValueError(
            f"profile: the target travels {travelled:.1f} m, the road is {road.length:.1f} m long"
        )
    position = road.position(profile.arc_length)
    velocity = profile.speed.unsqueeze(-1) * road.direction(profile.arc_length)
    steps = profile.arc_length.shape[0]

    def runs(x: Tensor) -> Tensor:
        return x.to(dtype).expand(num_runs, *x.shape).contiguous()

    noise = torch.randn(num_runs, steps, 2, generator=generator, dtype=dtype)
    pos = runs(position)
    return RoadScenario(
        position=pos,
        velocity=runs(velocity),
        speed=runs(profile.speed),
        arc_length=runs(profile.arc_length),
        acceleration=runs(profile.acceleration),
        z=pos + meas_std * noise,
        dt=dt,
        meas_std=meas_std,
        road=road,
        q=q,
        eta_std=eta_std,
        window=window,
    )


def straight_road_scenario(
    num_runs: int = 100,
    generator: torch.Generator | None = None,
    steps: int = 200,
    dt: float = 0.3,
    meas_std: float = 2.0,
    dtype: torch.dtype = torch.float64,
) -> RoadScenario:
    """Sec. 5.1: a straight road from (200, 300) m at 65°, Eq. (46); 1 m/s, +5 m/s² over steps
    41-70 and 121-150; ``T = 0.3`` s, ``σ = 2`` m; settings ``q = 0.008``, ``σ_η = 1e-5``,
    window 16. ``steps`` is not stated (module docstring)."""
    road = StraightRoad((200.0, 300.0), math.radians(65.0))
    profile = speed_profile(1.0, [(41, 70, 5.0), (121, 150, 5.0)], steps, dt)
    return road_scenario(
        road, profile, dt, meas_std, num_runs, generator, dtype, q=0.008, eta_std=1e-5, window=16
    )


def circular_road_scenario(
    num_runs: int = 100,
    generator: torch.Generator | None = None,
    dt: float = 0.1,
    meas_std: float = 2.0,
    clockwise: bool = False,
    dtype: torch.dtype = torch.float64,
) -> RoadScenario:
    """Sec. 5.2: a circle of radius 50 m about (60, 60) m entered at (100, 30) m, Eq. (47);
    5 m/s, +3 m/s² over steps 41-70, +2 m/s² over 111-150, 200 steps; settings ``q = 0.008``,
    ``σ_η = 0.001``, window 12 (the paper also uses 14 and 16). ``dt``, ``meas_std`` and the
    direction are not stated (module docstring)."""
    road = CircularRoad((100.0, 30.0), (60.0, 60.0), 50.0, clockwise=clockwise)
    profile = speed_profile(5.0, [(41, 70, 3.0), (111, 150, 2.0)], 200, dt)
    return road_scenario(
        road, profile, dt, meas_std, num_runs, generator, dtype, q=0.008, eta_std=1e-3, window=12
    )


def curve_road_scenario(
    variant: int = 1,
    num_runs: int = 100,
    generator: torch.Generator | None = None,
    dt: float = 0.2,
    meas_std: float = 0.8,
    points: Sequence[tuple[float, float]] | Tensor | None = None,
    dtype: torch.dtype = torch.float64,
) -> RoadScenario:
    """Secs. 5.3-5.4: curve road I (``variant=1``) or II (``variant=2``), natural cubic splines
    through supporting points in chord length (Eq. (48)), ``T = 0.2`` s, ``σ = 0.8`` m.

    I: 2.3 m/s from (−400, 0) m, +3.7 m/s² over steps 41-70, +2.2 m/s² over 111-150, 200 steps.
    II: 16.5 m/s from (−700, 260) m, +1.9 m/s² over 41-80, +1.6 m/s² over 111-150, +0.1 m/s²
    over 181-210, 250 steps. Settings ``q = 0.01``, ``σ_η = 0.002``, window 12 (the paper also
    uses 10 and 14 on road II). ``points`` replaces the designed supporting points
    (:data:`CURVE_ROAD_I_POINTS`, :data:`CURVE_ROAD_II_POINTS`; the road starts at the first).
    """
    default: Sequence[tuple[float, float]]
    if variant == 1:
        default = CURVE_ROAD_I_POINTS
        profile = speed_profile(2.3, [(41, 70, 3.7), (111, 150, 2.2)], 200, dt)
    elif variant == 2:
        default = CURVE_ROAD_II_POINTS
        profile = speed_profile(16.5, [(41, 80, 1.9), (111, 150, 1.6), (181, 210, 0.1)], 250, dt)
    else:
        raise ValueError(f"variant: expected 1 or 2 (curve road I or II), got {variant!r}")
    road = ArcLengthSpline(default if points is None else points)
    return road_scenario(
        road, profile, dt, meas_std, num_runs, generator, dtype, q=0.01, eta_std=0.002, window=12
    )

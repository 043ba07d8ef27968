"""Recorded flights as a benchmark: ADS-B positions as truth, seeded radar-like noise on top.

* :func:`load_flights`: flights of the ``traffic`` wheel's samples (default: the 24 calibration
  flights) in local east-north frames, thinned to a radar-like scan period, with the recorded
  positions as truth and the reported velocity where it agrees with the motion.
* :func:`noisy`: the same flights measured with Gaussian noise of a given standard deviation.
* :func:`split`: flights into a training and a test half.
* :func:`score`: position and velocity RMSE of an estimate against that truth.

The reported velocity (ground speed and track angle) is measured by the aircraft independently
of its position, so it is the natural truth for velocities, but in recorded samples it is not
always consistent with the positions: in 21 of the 24 calibration flights the track angle is
rotated by about 100° for much of the flight. A step's reported velocity is used as truth only
where it is within ``max(5 m/s, 10%)`` of the velocity the recorded positions imply (central
differences of the clean positions); :func:`score` reports how many steps that leaves, and also
scores against the position-derived velocity everywhere.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchsvs.datasets import RecordedTracks
from torchsvs.datasets.adsb import sample_files
from torchsvs.datasets.flights import flight_steps
from torchsvs.metrics import entries, pooled_rmse

#: Reported quantities carried per step (as recorded: ft, kt, deg, ft/min).
REPORTED = ("altitude_ft", "groundspeed_kt", "track_deg", "vertical_rate_fpm")


def flight_files(sets: str = "calibration") -> list[Path]:
    """Sample files of the named folders (comma-separated, e.g. ``"calibration,surveys"``) or
    of file paths."""
    files = []
    for name in sets.split(","):
        path = Path(name)
        if path.is_file():
            files.append(path)
            continue
        chosen = [p for p in sample_files() if p.parent.name == name]
        if not chosen:
            raise ValueError(f"flights: no sample folder or file named {name!r}")
        files += chosen
    return files


def _thin(times: np.ndarray, period: float) -> np.ndarray:
    """Indices of reports at least ``period`` apart (greedy, from the first)."""
    keep, last = [], -np.inf
    for i, t in enumerate(times):
        if t - last >= period - 1e-6:
            keep.append(i)
            last = t
    return np.asarray(keep, dtype=np.int64)


def load_flights(
    sets: str = "calibration", scan: float = 5.0, min_steps: int = 50
) -> RecordedTracks:
    """Flights as a truth batch (``z`` is the clean recorded position; see :func:`noisy`).

    Each flight keeps its reports at least ``scan`` seconds apart (a radar's scan period) where
    the position is recorded; flights shorter than ``min_steps`` are left out. ``truth`` is
    ``[B, T, 4]`` in the state layout ``(x, vx, y, vy)``: positions, and the reported velocity
    where it is consistent with the motion (NaN elsewhere); ``extra["vx_motion"]``,
    ``extra["vy_motion"]`` hold the position-derived velocity, and the :data:`REPORTED`
    quantities are there as recorded.
    """
    steps, _ = flight_steps(flight_files(sets))
    picked: list[int] = []
    step_index: list[np.ndarray] = []
    for k in range(steps.num_tracks):
        s, L = steps.start[k], steps.length[k]
        seen = np.isfinite(steps.position[s : s + L]).all(axis=1)
        index = np.flatnonzero(seen)
        keep = index[_thin(steps.time[s + index], scan)]
        if len(keep) >= min_steps:
            picked.append(k)
            step_index.append(s + keep)
    B, T = len(picked), max(len(i) for i in step_index)
    pos = np.full((B, T, 2), np.nan)
    vel = np.full((B, T, 2), np.nan)
    time = np.full((B, T), np.nan)
    reported = {k: np.full((B, T), np.nan) for k in REPORTED}
    for b, index in enumerate(step_index):
        pos[b, : len(index)] = steps.position[index]
        vel[b, : len(index)] = np.stack([steps.extra["ve"][index], steps.extra["vn"][index]], -1)
        time[b, : len(index)] = steps.time[index]
        for k in REPORTED:
            reported[k][b, : len(index)] = steps.extra[k][index]
    dt = np.diff(time, axis=1)
    first = np.nanmedian(dt, axis=1)
    dt = np.concatenate([first[:, None], dt], axis=1)
    dt = np.where(np.isfinite(dt), dt, first[:, None])
    motion = _motion_velocity(pos, time)
    speed = np.linalg.norm(motion, axis=-1, keepdims=True)
    agree = np.linalg.norm(vel - motion, axis=-1, keepdims=True) <= np.maximum(5.0, 0.1 * speed)
    vel = np.where(agree, vel, np.nan)
    lengths = torch.tensor([len(i) for i in step_index])
    t = torch.from_numpy
    truth = t(np.stack([pos[..., 0], vel[..., 0], pos[..., 1], vel[..., 1]], -1))
    return RecordedTracks(
        z=t(pos),
        dt=t(dt),
        time=t(time),
        lengths=lengths,
        ids=[steps.ids[k] for k in picked],
        extra={
            "vx_motion": t(motion[..., 0]),
            "vy_motion": t(motion[..., 1]),
            **{k: t(v) for k, v in reported.items()},
        },
        truth=truth,
    )


def _motion_velocity(pos: np.ndarray, time: np.ndarray) -> np.ndarray:
    """Central differences of the recorded positions (one-sided at the ends)."""
    v = np.full_like(pos, np.nan)
    dt2 = (time[:, 2:] - time[:, :-2])[..., None]
    v[:, 1:-1] = (pos[:, 2:] - pos[:, :-2]) / dt2
    v[:, 0] = (pos[:, 1] - pos[:, 0]) / (time[:, 1] - time[:, 0])[:, None]
    last = np.isfinite(time).sum(axis=1) - 1
    rows = np.arange(len(pos))
    v[rows, last] = (pos[rows, last] - pos[rows, last - 1]) / (
        time[rows, last] - time[rows, last - 1]
    )[:, None]
    return v


def noisy(flights: RecordedTracks, sigma: float, seed: int = 0) -> RecordedTracks:
    """The flights measured with white Gaussian noise of standard deviation ``sigma`` (m) per
    axis, seeded."""
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(flights.z.shape, generator=gen, dtype=torch.float64) * sigma
    return replace(flights, z=flights.z + noise)


def split(flights: RecordedTracks, seed: int = 0) -> tuple[RecordedTracks, RecordedTracks]:
    """A seeded half of the flights for training, the other half for testing."""
    order = torch.randperm(len(flights), generator=torch.Generator().manual_seed(seed))
    half = len(flights) // 2
    return flights.subset(order[:half].sort().values), flights.subset(order[half:].sort().values)


def score(mean: Tensor, flights: RecordedTracks) -> dict[str, float]:
    """Position RMSE per axis (the square root of the mean over both axes and all real steps),
    velocity RMSE against the consistent reported velocity and against the motion, and how much
    of the reported velocity was consistent."""
    real = flights.mask
    truth = flights.truth
    assert truth is not None
    reported = truth[..., [1, 3]]
    usable = entries(reported, real, known=True)
    motion = torch.stack([flights.extra["vx_motion"], flights.extra["vy_motion"]], -1)
    return {
        "position": float(pooled_rmse(mean[..., [0, 2]], truth[..., [0, 2]], real)),
        "velocity": float(pooled_rmse(mean[..., [1, 3]], reported, usable))
        if usable.any()
        else float("nan"),
        "velocity_motion": float(pooled_rmse(mean[..., [1, 3]], motion, real)),
        "velocity_coverage": float(usable.sum() / (2 * real.sum())),
    }

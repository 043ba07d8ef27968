"""Kinds of motion (torchsvs.fitting.q_kinds): each track's own ``q`` shrunk toward its kind's
curve, so that ships among aircraft keep a ship's ``q``."""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from torchsvs.fitting.q_kinds import NO_KIND, kind_table, kind_targets, track_kinds


def _turning(rng, count: int, steps: int, interval: float, speed: float, turn_deg: float):
    """``count`` tracks at ``speed`` reported every ``interval`` s, turning at up to
    ``turn_deg`` deg/s for stretches of 5-30 reports, straight between: ``[count, steps, 2]``."""
    paths = np.empty((count, steps, 2))
    for b in range(count):
        heading, rate, left = rng.uniform(0, 2 * np.pi), 0.0, 0
        point = rng.uniform(-5e4, 5e4, 2)
        for k in range(steps):
            if left == 0:
                rate = np.deg2rad(turn_deg) * rng.choice([-1.0, 0.0, 0.0, 1.0]) * rng.uniform()
                left = int(rng.integers(5, 30))
            left -= 1
            for _ in range(10):  # (ten substeps a report)
                heading += rate * interval / 10
                point = point + speed * interval / 10 * np.array([np.cos(heading), np.sin(heading)])
            paths[b, k] = point
    return paths


def _frame(paths: np.ndarray, interval: float, sigma: float, name: str, rng) -> pd.DataFrame:
    count, steps, _ = paths.shape
    noisy = paths + sigma * rng.standard_normal(paths.shape)
    return pd.DataFrame(
        {
            "id": np.repeat([f"{name}{b}" for b in range(count)], steps),
            "t": np.tile(np.arange(steps) * interval, count),
            "x": noisy[..., 0].reshape(-1),
            "y": noisy[..., 1].reshape(-1),
            "tx": paths[..., 0].reshape(-1),
            "ty": paths[..., 1].reshape(-1),
        }
    )


def _kinds_of(paths: np.ndarray, interval: float, sigma: float, rng) -> torch.Tensor:
    z = torch.tensor(paths + sigma * rng.standard_normal(paths.shape))
    return track_kinds(z, torch.full(z.shape[:2], interval, dtype=torch.float64))


def test_a_tracks_kind_is_its_interval_and_speed_whatever_its_noise_and_gaps() -> None:
    rng = np.random.default_rng(0)
    ships = _kinds_of(_turning(rng, 6, 60, 10.0, 2.0, 0.5), 10.0, 10.0, rng)
    aircraft = _kinds_of(_turning(rng, 6, 60, 5.0, 230.0, 3.0), 5.0, 50.0, rng)
    cars = _kinds_of(_turning(rng, 6, 60, 1.0, 15.0, 10.0), 1.0, 5.0, rng)
    parked = _kinds_of(np.zeros((6, 60, 2)), 1.0, 5.0, rng)  # noise alone: still
    for kinds in (ships, aircraft, cars, parked):
        assert len(kinds.unique()) == 1
    assert len({int(k[0]) for k in (ships, aircraft, cars, parked)}) == 4
    assert int(ships[0]) == 2 * (1 << 20) + 1  # 10 s (10^1), 2 m/s (10^0.3): bins 2 and 1
    # a track with positions missing (NaN) is of the kind it is without them
    z = torch.tensor(_turning(rng, 1, 80, 5.0, 230.0, 3.0))
    dt = torch.full((1, 80), 5.0, dtype=torch.float64)
    gappy = z.clone()
    gappy[0, 10:30:2] = float("nan")
    assert int(track_kinds(gappy, dt)[0]) == int(track_kinds(z, dt)[0]) == int(aircraft[0])
    # one position tells no kind; two do
    assert int(track_kinds(z[:, :1], dt[:, :1])[0]) == NO_KIND
    assert int(track_kinds(z[:, :2], dt[:, :2])[0]) == int(aircraft[0])


def test_each_track_is_shrunk_toward_its_kinds_curve_and_that_toward_the_files() -> None:
    risk = torch.tensor([[1.0, 3.0, 5.0], [2.0, 2.0, 6.0]], dtype=torch.float64)  # [F=2, B=3]
    counts = torch.tensor([100.0, 100.0, 200.0], dtype=torch.float64)
    assert kind_table(risk, counts, torch.tensor([7, 7, 7])) is None  # one kind: the file's
    table = kind_table(risk, counts, torch.tensor([7, 7, 9]))
    assert table == [[7.0, 200.0, 0.02, 0.02], [9.0, 200.0, 0.025, 0.03]]
    file_curve = torch.tensor([1.0, 2.0], dtype=torch.float64)
    targets = kind_targets(torch.tensor([9, NO_KIND, 8]), file_curve, table)
    weight = 200.0 / 600.0  # (SHRINK_KIND 400): the shapes mixed in logs, at the kind's level
    shape = weight * np.log([1.0, 1.2]) + (1 - weight) * np.log([1.0, 2.0])
    assert np.allclose(targets[:, 0].numpy(), 0.025 * np.exp(shape))
    assert torch.equal(targets[:, 1], file_curve) and torch.equal(targets[:, 2], file_curve)


def test_ships_among_aircraft_keep_a_ships_q(tmp_path) -> None:
    """Ships (2 m/s, 10 s reports, σ 10 m) in one file with aircraft (230 m/s, turning, 5 s,
    σ 50 m): shrunk toward the whole file's curve, the aircraft's, each ship kept the file's
    ``q`` and came out at 0.93 of the measurements' error (0.36 in a file of their own); shrunk
    toward their kind's, well below."""
    from torchsvs.datasets import Columns
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    rng = np.random.default_rng(1)
    ships = _frame(_turning(rng, 40, 100, 10.0, 2.0, 0.5), 10.0, 10.0, "ship", rng)
    aircraft = _frame(_turning(rng, 40, 100, 5.0, 230.0, 3.0), 5.0, 50.0, "air", rng)
    frame = pd.concat([ships, aircraft], ignore_index=True)
    source, target = tmp_path / "mixed.csv", tmp_path / "out.csv"
    frame[["id", "t", "x", "y"]].to_csv(source, index=False)
    run = track_file(
        source,
        target,
        Settings("ks"),
        columns=Columns(track_id="id", time="t"),
        progress=False,
    )
    assert run.settings.q_kinds is not None and len(run.settings.q_kinds) >= 2
    out = pd.read_csv(target)
    ship = frame["id"].str.startswith("ship").to_numpy()

    def rmse(x: np.ndarray, y: np.ndarray) -> float:
        return float(
            np.sqrt(((x - frame.tx.to_numpy()) ** 2 + (y - frame.ty.to_numpy()) ** 2)[ship].mean())
        )

    error, raw = (
        rmse(out.x.to_numpy(), out.y.to_numpy()),
        rmse(frame.x.to_numpy(), frame.y.to_numpy()),
    )
    assert error < 0.6 * raw

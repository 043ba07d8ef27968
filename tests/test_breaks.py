"""Breaks in a track (torchsvs.datasets.breaks): a jump to another path between two reports
(two tracks' ids swapped) splits the track; outliers, turns and noise do not."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa

from torchsvs.datasets.breaks import break_steps, split_at_breaks
from torchsvs.datasets.rows import Columns, parse_block
from torchsvs.datasets.steps import group_rows


def _paths(rng, count: int, steps: int, interval: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` cars at 10-30 m/s turning gently: times ``[count, steps]``, paths ``[count,
    steps, 2]``, each track's times offset by up to one interval."""
    times = np.arange(steps) * interval + rng.uniform(0, interval, (count, 1))
    heading = rng.uniform(0, 2 * np.pi, (count, 1)) + np.cumsum(
        rng.normal(0, 0.02, (count, steps)), 1
    )
    speed = rng.uniform(10, 30, (count, 1))
    step = speed[..., None] * interval * np.stack([np.cos(heading), np.sin(heading)], -1)
    return times, rng.uniform(-5e3, 5e3, (count, 1, 2)) + np.cumsum(step, 1)


def _steps(times: np.ndarray, z: np.ndarray):
    count, steps = times.shape
    table = pa.table(
        {
            "track_id": np.repeat([f"t{b}" for b in range(count)], steps),
            "time": times.reshape(-1),
            "x": z[..., 0].reshape(-1),
            "y": z[..., 1].reshape(-1),
        }
    )
    return group_rows(parse_block(table, Columns().resolve(table.column_names)))


def test_a_jump_to_another_path_is_a_break_and_outliers_turns_and_noise_are_not() -> None:
    rng = np.random.default_rng(0)
    times, paths = _paths(rng, 200, 300)
    z = paths + rng.normal(0, 10.0, paths.shape)
    assert len(break_steps(_steps(times, z))) == 0  # (60,000 reports of noise and turns)
    # track 0 joins another object's path at report 150 (its times 0.1 s after the last);
    # track 1 has one report 800 m off; track 2 two reports off together; track 3 turns 90°
    swapped = z.copy()
    swapped[0, 150:] += np.array([600.0, -900.0])
    times[0, 150:] -= times[0, 150] - times[0, 149] - 0.1
    swapped[1, 100] += 800.0
    swapped[2, 100:102] += 800.0
    rotated = np.diff(paths[3], axis=0)[100:] @ np.array([[0.0, -1.0], [1.0, 0.0]])
    turned = np.concatenate([paths[3, :101], paths[3, 100] + np.cumsum(rotated, 0)])
    swapped[3] = turned + rng.normal(0, 10.0, turned.shape)
    found = _steps(times, swapped)
    assert break_steps(found).tolist() == [found.start[0] + 150]
    split, count = split_at_breaks(found)
    assert count == 1 and split.num_tracks == found.num_tracks + 1
    assert split.ids[:2] == ["t0", "t0 (part 2)"] and split.length[:2].tolist() == [150, 150]
    assert (split.row_step == found.row_step).all()  # (the rows keep their steps)


def test_swapped_ids_leave_the_other_tracks_and_the_files_q_as_they_were(tmp_path) -> None:
    """Two pairs of 80 tracks swap ids halfway (jumps of 400-2,000 m): the file's q rose from
    0.16 to 1,381 and the clean tracks' error from 4.5 to 7.8 m; now the swapped tracks are
    split, counted, and every track is estimated as the file split by hand is."""
    from torchsvs.recipes import Settings
    from torchsvs.tracking import track_file

    rng = np.random.default_rng(1)
    times, paths = _paths(rng, 40, 200)
    z = paths + rng.normal(0, 10.0, paths.shape)
    ids = np.array([[f"t{b}"] * 200 for b in range(40)])
    parts = ids.copy()
    for a, b in ((0, 1), (2, 3)):  # halfway, each joins the other's path, moved off by a jump
        shift = rng.uniform(400, 2000, 2)
        z[[a, b], 100:] = z[[b, a], 100:] + np.array([shift, -shift])[:, None]
        paths[[a, b], 100:] = paths[[b, a], 100:] + np.array([shift, -shift])[:, None]
        times[[a, b], 100:] = times[[b, a], 100:]
        parts[[a, b], 100:] = np.char.add(parts[[a, b], 100:], "b")
    bad = times[:, 100] <= times[:, 99]  # (the other's report may come first: nudge it)
    times[bad, 100:] += times[bad, 99:100] - times[bad, 100:101] + 0.1

    def run(names: np.ndarray, name: str) -> tuple[float, object]:
        frame = pd.DataFrame(
            {
                "track_id": names.reshape(-1),
                "time": times.reshape(-1),
                "x": z[..., 0].reshape(-1),
                "y": z[..., 1].reshape(-1),
            }
        )
        frame.to_csv(tmp_path / f"{name}.csv", index=False)
        found = track_file(
            tmp_path / f"{name}.csv", tmp_path / f"{name}.out.csv", Settings("ks"), progress=False
        )
        out = pd.read_csv(tmp_path / f"{name}.out.csv")
        assert (out.track_id.astype(str).to_numpy() == names.reshape(-1)).all()  # (as read)
        error = np.sqrt(((out[["x", "y"]].to_numpy() - paths.reshape(-1, 2)) ** 2).sum(1).mean())
        return float(error), found

    swapped, found = run(ids, "swapped")
    by_hand, reference = run(parts, "split")
    assert found.report.notes["track_breaks"] == 4
    assert found.settings.q < 2.0 * reference.settings.q
    assert swapped < 1.05 * by_hand

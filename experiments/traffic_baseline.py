"""The ADS-B library ``traffic``'s two-pass smoother ``KalmanSmoother6D`` as a comparison baseline.

``traffic`` (PyPI ``traffic==2.13``) is not a dependency of torchsvs: its ``__init__`` pulls in a
large tree (cartes, onnxruntime, pyopensky, rs1090, ...). The smoother itself lives in
``traffic/algorithms/filters/kalman.py`` and needs only numpy, pandas, ``impunity`` (unit
rewriting of annotated variables), and, through ``filters/__init__.py``, ``pyproj``. Install::

    pip install --no-deps traffic==2.13
    pip install impunity pyproj          # pulls Pint, astor, flexcache, flexparser, ...

Loading: ``importlib.util.find_spec("traffic")`` locates the installed package without executing
``traffic/__init__.py``; ``algorithms/filters/__init__.py`` is then loaded as a synthetic package
(its own name, ``submodule_search_locations`` set to its folder, registered in ``sys.modules``
*before* it runs) and ``kalman.py`` as its submodule, so ``from . import FilterBase`` resolves.
The registration before execution matters: ``@impunity`` runs at class-definition time, reads
the method source with ``inspect.getsource`` and the module globals through
``sys.modules[func.__module__]``, then swaps in rewritten bytecode that converts kts -> m/s,
ft -> m, ft/min -> m/s in ``preprocess`` and back in ``postprocess``. ``_check_units`` verifies
after loading that the conversion really happens.

What the smoother assumes and does (traffic 2.13):

- ``dt = 1`` s is hard-coded, so :func:`smooth_flight` resamples to a 1 s grid and back.
- R (diagonal, all six states measured, H = I) is estimated from the data: the squared std of
  each state column's residual to its trailing 17-sample rolling mean. Q is diagonal
  0.1 * (.25, .25, .25, 1, 1, 1) * diag(R), plus half each velocity variance of Q on the
  matching position-velocity off-diagonals. A column without variation (noise-free synthetic
  data, a constant altitude) gives a singular R and ``numpy.linalg.LinAlgError``.
- Outliers: when the innovation's NIS exceeds ``reject_sigma**2 * 6`` the components whose
  ``(S^-1 nu) * nu`` exceeds ``reject_sigma**2`` are replaced by the prediction (and their H
  diagonal zeroed). NaN measurements are set to 1e24 so that this test rejects them, but the
  state is initialised from the first row as is: a NaN there makes every output row NaN, and a
  column with a NaN in every 17-row window gets a NaN R, which also makes every row NaN.
- The fusion of the forward and backward passes is misaligned by one sample: row k fuses the
  forward estimate at k with the backward estimate at k + 1. On a straight flight the output
  leads the truth by about half a second of travel mid-flight (a full second at the first row,
  none at the last) and the speed is biased high by ~1.5 %. :func:`smooth_flight` reports the
  smoother's output as it is.

    python -m experiments.traffic_baseline        # unit check, directions, timing, NaN inputs
"""

from __future__ import annotations

import functools
import importlib.util
import sys
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

KT_TO_MS = 1852.0 / 3600.0
FT_TO_M = 0.3048
INSTALL_HINT = "pip install --no-deps traffic==2.13 && pip install impunity pyproj pandas"
# the name of the synthetic package standing in for traffic.algorithms.filters
_PKG = "_torchsvs_traffic_filters"


def _filters_dir() -> Path:
    spec = importlib.util.find_spec("traffic")  # locates the package, does not run its __init__
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(f"traffic is not installed; {INSTALL_HINT}")
    folder = Path(next(iter(spec.submodule_search_locations))) / "algorithms" / "filters"
    if not (folder / "kalman.py").is_file():
        raise ImportError(f"{folder / 'kalman.py'} not found; this baseline needs traffic==2.13")
    return folder


def _exec_module(name: str, path: Path, package_dir: Path | None = None) -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        name,
        path,
        submodule_search_locations=None if package_dir is None else [str(package_dir)],
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # impunity looks the module up here while the class body runs
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


@functools.cache
def _kalman() -> ModuleType:
    """traffic's kalman.py, loaded without ``traffic/__init__.py``; cached."""
    missing = [
        m
        for m in ("pandas", "impunity", "pyproj")
        if m not in sys.modules and importlib.util.find_spec(m) is None
    ]
    if missing:
        raise ImportError(f"missing {', '.join(missing)} for the traffic baseline; {INSTALL_HINT}")
    folder = _filters_dir()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            _exec_module(_PKG, folder / "__init__.py", package_dir=folder)
            kalman = _exec_module(f"{_PKG}.kalman", folder / "kalman.py")
    except ModuleNotFoundError as e:  # e.g. impunity installed without its dependency pint
        sys.modules.pop(_PKG, None)
        raise ImportError(f"missing {e.name} for the traffic baseline; {INSTALL_HINT}") from e
    except BaseException:
        sys.modules.pop(_PKG, None)
        raise
    _check_units(kalman)
    return kalman


def _check_units(kalman: ModuleType) -> None:
    """Fails loudly if impunity's rewriting of preprocess/postprocess did not take place."""
    import pandas as pd

    smoother = kalman.KalmanSmoother6D()
    raw = pd.DataFrame(
        dict(
            x=[0.0],
            y=[0.0],
            altitude=[10000.0],
            groundspeed=[200.0],
            track=[0.0],
            vertical_rate=[1000.0],
        )
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        pre = smoother.preprocess(raw).iloc[0]
        post = smoother.postprocess(pre.to_frame().T)
    expected_si = dict(z=10000 * FT_TO_M, dx=0.0, dy=200 * KT_TO_MS, dz=1000 * FT_TO_M / 60)
    for key, value in expected_si.items():
        if not np.isclose(pre[key], value, rtol=1e-6, atol=1e-9):
            raise RuntimeError(
                f"traffic's impunity unit rewriting did not take place: preprocess gave "
                f"{key}={pre[key]!r}, expected {value!r} (SI)"
            )
    for key, value in dict(altitude=10000.0, groundspeed=200.0, vertical_rate=1000.0).items():
        if not np.isclose(post[key][0], value, rtol=1e-6):
            raise RuntimeError(
                f"traffic's impunity unit rewriting did not take place: postprocess gave "
                f"{key}={post[key][0]!r}, expected {value!r}"
            )


def available() -> bool:
    """Whether traffic's KalmanSmoother6D and its dependencies can be loaded."""
    try:
        _kalman()
    except ImportError:
        return False
    return True


def _unwrap_deg(angle: np.ndarray) -> np.ndarray:
    """Unwraps an angle in degrees over its finite entries (a NaN would poison np.unwrap)."""
    out = angle.astype(float).copy()
    ok = np.isfinite(out)
    out[ok] = np.unwrap(out[ok], period=360.0)
    return out


def _to_grid(grid: np.ndarray, t: np.ndarray, values: np.ndarray, fill_gaps: bool) -> np.ndarray:
    """Linear interpolation of one column to the 1 s grid, NaN samples handled per ``fill_gaps``.

    ``fill_gaps``: interpolate over the finite samples only, holding the first/last finite value
    beyond them (an all-NaN column stays NaN). Otherwise a grid time that falls on a NaN sample,
    or between two samples one of which is NaN, stays NaN for the smoother to deal with.
    """
    finite = np.isfinite(values)
    if not finite.any():
        return np.full(grid.shape, np.nan)
    out = np.interp(grid, t[finite], values[finite])
    if not fill_gaps:
        j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 1)
        k = np.minimum(j + 1, len(t) - 1)
        on_sample = t[j] == grid
        out[~finite[j] | (~on_sample & ~finite[k])] = np.nan
    return out


def _interp(t: np.ndarray, tp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """np.interp, extrapolating linearly after tp[-1] (the 1 s grid may stop short of t[-1])."""
    out = np.interp(t, tp, fp)
    after = t > tp[-1]
    if after.any() and len(tp) > 1:
        slope = (fp[-1] - fp[-2]) / (tp[-1] - tp[-2])
        out[after] = fp[-1] + slope * (t[after] - tp[-1])
    return out


def smooth_flight(
    time_s: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    altitude_ft: np.ndarray,
    groundspeed_kt: np.ndarray,
    track_deg: np.ndarray,
    vertical_rate_fpm: np.ndarray,
    reject_sigma: float = 3.0,
    fill_gaps: bool = True,
) -> dict[str, Any]:
    """Runs traffic's ``KalmanSmoother6D`` on one flight.

    Args:
        time_s: increasing sample times [s], possibly irregular.
        x, y: position [m] in a local plane, x east, y north.
        altitude_ft: altitude [ft]; groundspeed_kt: ground speed [kt]; track_deg: track angle
            [deg], clockwise from north; vertical_rate_fpm: vertical rate [ft/min].
        reject_sigma: the smoother's outlier gate (traffic's default 3).
        fill_gaps: how NaN samples reach the 1 s grid. True (default): each column is
            interpolated over its finite samples, as traffic's own ``Flight.resample("1s")``
            does before filtering (and, unlike it, leading NaNs take the first finite value).
            False: grid rows on or next to a NaN sample stay NaN and the smoother's own NaN
            handling applies; a NaN in the first grid row makes the whole output NaN.

    The inputs are linearly interpolated to a 1 s grid from ``time_s[0]`` (the track on its
    unwrapped angle), smoothed, and the output is interpolated back to ``time_s`` (extrapolated
    linearly past the last grid point, less than 1 s).

    Returns:
        ``x``, ``y`` [m], ``vx``, ``vy`` [m/s, east/north, from the output ground speed and
        track], ``altitude_ft``, plus ``groundspeed_kt``, ``track_deg``, ``vertical_rate_fpm``
        as output by the smoother, all at ``time_s``; ``points_processed``, the number of 1 s
        rows smoothed; ``seconds``, the wall time of the ``apply`` call alone.
    """
    import pandas as pd

    kalman = _kalman()
    t = np.asarray(time_s, dtype=float)
    if t.ndim != 1 or len(t) < 2 or not np.all(np.diff(t) > 0):
        raise ValueError("time_s must be a 1-D, strictly increasing array of at least 2 times")
    columns = dict(
        x=np.asarray(x, dtype=float),
        y=np.asarray(y, dtype=float),
        altitude=np.asarray(altitude_ft, dtype=float),
        groundspeed=np.asarray(groundspeed_kt, dtype=float),
        track=_unwrap_deg(np.asarray(track_deg, dtype=float)),
        vertical_rate=np.asarray(vertical_rate_fpm, dtype=float),
    )
    for name, values in columns.items():
        if values.shape != t.shape:
            raise ValueError(f"{name} has shape {values.shape}, time_s {t.shape}")

    grid = t[0] + np.arange(int(np.floor(t[-1] - t[0] + 1e-9)) + 1, dtype=float)
    frame = pd.DataFrame(
        {name: _to_grid(grid, t, values, fill_gaps) for name, values in columns.items()}
    )
    frame["track"] = np.mod(frame["track"], 360.0)

    smoother = kalman.KalmanSmoother6D(reject_sigma=reject_sigma)
    with warnings.catch_warnings():
        # traffic 2.13 predates numpy 2.4 / pandas 3; nothing it warns about changes the result.
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        start = time.perf_counter()
        try:
            out = smoother.apply(frame)
        except np.linalg.LinAlgError as e:
            e.add_note(
                "traffic's KalmanSmoother6D estimates R from each column's variation around a "
                "17-sample rolling mean; a column without variation makes R singular"
            )
            raise
        seconds = time.perf_counter() - start

    speed = out["groundspeed"].to_numpy(float) * KT_TO_MS
    track = np.radians(out["track"].to_numpy(float))
    smoothed = dict(
        x=out["x"].to_numpy(float),
        y=out["y"].to_numpy(float),
        vx=speed * np.sin(track),  # track is clockwise from north: east = sin, north = cos
        vy=speed * np.cos(track),
        altitude_ft=out["altitude"].to_numpy(float),
        groundspeed_kt=out["groundspeed"].to_numpy(float),
        track_deg=_unwrap_deg(out["track"].to_numpy(float)),
        vertical_rate_fpm=out["vertical_rate"].to_numpy(float),
    )
    result: dict[str, Any] = {key: _interp(t, grid, v) for key, v in smoothed.items()}
    result["track_deg"] = np.mod(result["track_deg"], 360.0)
    result["points_processed"] = len(grid)
    result["seconds"] = seconds
    return result


def straight_flight(
    track_deg: float,
    n: int = 200,
    groundspeed_kt: float = 200.0,
    noise: float = 1.0,
    seed: int = 0,
    irregular: bool = True,
) -> dict[str, np.ndarray]:
    """A level straight flight at constant speed, with measurement noise scaled by ``noise``.

    ``noise=0`` gives exact measurements, which the smoother cannot run on (singular R).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    if irregular:
        t = t + rng.uniform(-0.3, 0.3, n) * (np.arange(n) > 0)
    speed = groundspeed_kt * KT_TO_MS
    heading = np.radians(track_deg)

    def noisy(values: np.ndarray, sigma: float) -> np.ndarray:
        return values + noise * sigma * rng.standard_normal(n)

    return dict(
        time_s=t,
        x=noisy(speed * np.sin(heading) * t, 5.0),
        y=noisy(speed * np.cos(heading) * t, 5.0),
        altitude_ft=noisy(np.full(n, 10000.0), 25.0),
        groundspeed_kt=noisy(np.full(n, groundspeed_kt), 1.0),
        track_deg=np.mod(noisy(np.full(n, track_deg), 0.5), 360.0),
        vertical_rate_fpm=noisy(np.zeros(n), 64.0),
    )


def main() -> None:
    """Unit check, direction checks, timing and NaN behaviour, printed."""
    if not available():
        _kalman()  # raises the ImportError that says what is missing
    print(f"traffic loaded from {_filters_dir()} as {_PKG} (traffic/__init__ not run)")
    print("impunity unit check on preprocess/postprocess: passed")

    for heading in (90.0, 0.0, 225.0):
        flight = straight_flight(heading)
        res = smooth_flight(**flight)
        speed = 200 * KT_TO_MS
        t, mid = flight["time_s"], slice(20, -20)
        east, north = np.sin(np.radians(heading)), np.cos(np.radians(heading))
        along = (res["x"] - speed * east * t) * east + (res["y"] - speed * north * t) * north
        cross = (res["x"] - speed * east * t) * north - (res["y"] - speed * north * t) * east
        print(
            f"track {heading:5.1f} deg: vx, vy = {np.median(res['vx']):7.2f}, "
            f"{np.median(res['vy']):7.2f} m/s (truth {speed * east:7.2f}, {speed * north:7.2f}); "
            f"gs {np.median(res['groundspeed_kt']):6.2f} kt; along-track error mid-flight "
            f"{np.mean(along[mid]):6.2f} m (= {np.mean(along[mid]) / speed:.2f} s of travel), "
            f"cross-track rms {np.sqrt(np.mean(cross[mid] ** 2)):.2f} m, first/last row "
            f"along {along[0]:.1f}/{along[-1]:.1f} m"
        )

    try:
        smooth_flight(**straight_flight(90.0, noise=0.0, irregular=False))
    except np.linalg.LinAlgError as e:
        print(f"noise-free straight flight: LinAlgError: {e}")

    long_flight = straight_flight(45.0, n=3000, irregular=False)
    for run in (1, 2):
        res = smooth_flight(**long_flight)
        print(
            f"timing run {run}: {res['points_processed']} points in {res['seconds']:.2f} s, "
            f"{1000 * res['seconds'] / res['points_processed']:.3f} ms/point"
        )

    clean_flight = straight_flight(90.0, irregular=False)  # 1 s samples: grid rows = samples
    clean = smooth_flight(**clean_flight)

    def nan_case(label: str, column: str, rows: slice, fill_gaps: bool) -> None:
        flight = {key: value.copy() for key, value in clean_flight.items()}
        flight[column][rows] = np.nan
        res = smooth_flight(**flight, fill_gaps=fill_gaps)
        bad = ~np.isfinite(res["x"]) | ~np.isfinite(res["vx"])
        diff = np.abs(res["x"] - clean["x"])[~bad]
        print(
            f"NaN {label} (fill_gaps={fill_gaps}): {bad.sum()}/{len(bad)} output rows NaN; "
            f"max |x - x without NaN| elsewhere {diff.max() if len(diff) else float('nan'):.2f} m"
        )

    for fill_gaps in (False, True):
        nan_case("groundspeed, rows 50-59", "groundspeed_kt", slice(50, 60), fill_gaps)
        nan_case("groundspeed, every 3rd row", "groundspeed_kt", slice(1, None, 3), fill_gaps)
        nan_case("x, rows 50-59", "x", slice(50, 60), fill_gaps)
        nan_case("vertical rate, first row", "vertical_rate_fpm", slice(0, 1), fill_gaps)
        nan_case("groundspeed, whole flight", "groundspeed_kt", slice(None), fill_gaps)


if __name__ == "__main__":
    main()

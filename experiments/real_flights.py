"""Real flights: every applicable estimator on recorded ADS-B flights with radar-like noise.

The recorded positions of the ``traffic`` wheel's flights (default: the 24 calibration flights,
which circle and turn around navigation aids) are the truth; seeded Gaussian noise of
σ = 50, 100, 200 m per axis makes them radar-like measurements, at the flights' 5 s scan. A
seeded half of the flights is for training, the other half is held out. Each estimator runs with
parameters

* from the rules of thumb (R = σ², q read off the measurements, ψ = 5σ per component),
* from a grid (best on the training flights; the best on the held-out flights, which needs
  their truth, is the bound a tuning can reach),
* learned without truth on the training flights (``self_tune``: SURE with the known σ; and
  with σ unknown, innovation NLL first),
* learned on simulated maneuvers with truth (does simulated training transfer?),

beside the ``traffic`` library's own ``KalmanSmoother6D`` where it is installed, and
``torchsvs track --fit`` run on a CSV of the held-out flights themselves. Velocities are scored
against the reported velocity where it agrees with the motion, and against the motion itself.
The IMM of a CV and a coordinated-turn mode (``torchsvs track --estimator imm --lag 0``: its
filter; ``track`` smooths by default) has rows of its own and a section: its rank, and the study on the training flights its default settings
come from. Writes ``experiments/results/real_flights.md`` and PNGs.

    python -m experiments.real_flights [--flights calibration] [--seeds 2] [--quick]
    python -m experiments.real_flights --only-imm   # the IMM rows and section alone, merged

``--only-imm`` runs only the IMM's rows and section on the same flights, noise and split, and
merges them into the existing ``real_flights.md`` (its rows into the held-out table, its section
replaced or appended), leaving every other number of the file as it was: the whole run takes
tens of minutes, much of it in ``traffic``'s smoother and the fits.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from tqdm.auto import tqdm

from experiments import traffic_baseline
from experiments.common import RESULTS, render
from experiments.flight_data import load_flights, noisy, score, split
from torchsvs.datasets import RecordedTracks, padded_batch, with_prior
from torchsvs.datasets.flights import FlightReport, flight_steps
from torchsvs.datasets.rows import RowReport
from torchsvs.evaluation import markdown_table
from torchsvs.fitting.defaults import (
    IMM_QUIET,
    TURN_RATE_SCALE,
    complete_settings,
    imm_base_q,
    turn_settings,
    typical_speed,
)
from torchsvs.fitting.tuning import self_tune
from torchsvs.kernels import build, eager_loops
from torchsvs.metrics import pooled_rmse
from torchsvs.recipes import Settings, make_estimator, make_model, rule_of_thumb_psi
from torchsvs.runs import run_estimator
from torchsvs.step_estimates import centred

#: The IMM's rows in the held-out table start with this label.
IMM_LABEL = "IMM(CV, CT)"
#: The IMM rows are its filter (``torchsvs track --estimator imm --lag 0``; ``track`` smooths
#: by default): this report ranks it among the filters.
IMM_FILTER = 0
#: The SVSS lag of the learned rows (the lag study below shows why).
DEFAULT_SVSS_LAG = 5
SIGMAS = (50.0, 100.0, 200.0)
MAIN_SIGMA = 100.0


def estimate(settings: Settings, tracks: RecordedTracks) -> tuple[torch.Tensor, float]:
    """Estimates ``[B, T, 4]`` in the flights' frames and the seconds it took (float64)."""
    assert settings.meas_var is not None
    est = make_estimator(settings, make_model(settings)).double()
    moved, offset = centred(tracks)
    moved = with_prior(moved, torch.tensor(settings.meas_var, dtype=torch.float64).sqrt())
    start = time.perf_counter()
    mean, _ = run_estimator(est, moved)
    seconds = time.perf_counter() - start
    mean = mean.double().clone()
    mean[..., 0::2] += offset.unsqueeze(1)
    return mean, seconds


def evaluate(settings: Settings, tracks: RecordedTracks) -> dict[str, float]:
    mean, seconds = estimate(settings, tracks)
    result = score(mean, tracks)
    result["us_per_point"] = 1e6 * seconds / float(tracks.lengths.sum())
    return result


def rule_of_thumb(name: str, train: RecordedTracks, sigma: float, **kw: Any) -> Settings:
    return complete_settings(Settings(estimator=name, meas_var=[sigma**2] * 2, **kw), train)


# ------------------------------------------------------------------------------------------
# grids


Q_GRID = [10.0, 20.0, 40.0, 60.0, 80.0, 100.0, 130.0, 160.0, 200.0, 250.0, 320.0, 400.0, 600.0]
#: Limits of the SVSF family's variable boundary layer (``track``'s default since it replaced
#: the classic gain), in innovation standard deviations, shared by the axes.
PSI_LIMITS = [1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0]
SVSS_Q = [60.0, 120.0, 250.0]


def grid_ks(base: Settings, tracks: RecordedTracks) -> dict[float, float]:
    """Position RMSE for every q of :data:`Q_GRID`."""
    return {q: evaluate(replace(base, q=q), tracks)["position"] for q in Q_GRID}


def grid_svss(base: Settings, tracks: RecordedTracks) -> dict[tuple[float, float], float]:
    """Position RMSE for every (q, ψ limit) (γ as in ``base``), the limit shared by the axes."""
    m = len(base.meas_var or [])
    return {
        (q, limit): evaluate(replace(base, q=q, psi=[limit] * m), tracks)["position"]
        for q in SVSS_Q
        for limit in PSI_LIMITS
    }


# ------------------------------------------------------------------------------------------
# simulation-trained parameters


def train_on_simulation(name: str, sigma: float, lag: int, seconds: float) -> Settings:
    """An estimator's q (KS) or q, ψ, γ (SVSS) learned with truth on random maneuvers that look
    like the flights (5 s scan, 50-250 m/s, turns up to 4°/s, σ noise), via Lightning."""

    from torchsvs.scenarios import ManeuverRanges
    from torchsvs.training import EstimatorModule, ManeuveringTargetDataModule
    from torchsvs.training.quiet import quiet_lightning, tool_trainer

    ranges = ManeuverRanges(
        steps=150,
        dt=5.0,
        speed=(50.0, 250.0),
        segment_duration=(20.0, 200.0),
        turn_rate_deg=(0.5, 4.0),
        turn_accel_deg=(0.02, 0.2),
        accel=(0.2, 2.0),
        meas_std=(sigma, sigma),
    )
    interval = ranges.dt
    settings = Settings(
        estimator=name,
        meas_var=[sigma**2] * 2,
        q=50.0,
        lag=lag,
        interval=interval,
        # The SVSF family's rule of thumb (ψ per axis, in the units make_estimator reads).
        psi=None if name == "ks" else rule_of_thumb_psi(2),
    )
    model = make_model(settings, learn_q=True)
    est = make_estimator(settings, model)
    data = ManeuveringTargetDataModule(
        ranges,
        prior_std=(sigma, 2 * sigma / interval),
        batch_size=32,
        train_batches=12,
        val_batches=1,
        test_batches=1,
        seed=3,
    )
    module = EstimatorModule(est, loss="supervised", lr=0.1, seed=0)
    with quiet_lightning(), warnings.catch_warnings():
        trainer = tool_trainer(max_time={"seconds": seconds}, max_epochs=6)
        warnings.filterwarnings("ignore", message=".*LeafSpec.*|.*does not have many workers.*")
        trainer.fit(module, data)
    learned: dict[str, Any] = {"q": float(model.q().detach())}
    svsf = getattr(est, "filter", None)
    if svsf is not None and hasattr(svsf, "psi"):
        learned["psi"] = [float(p) for p in svsf.psi.detach().reshape(-1)]
        learned["gamma"] = float(svsf.gamma.detach())
    return replace(settings, **learned)


# ------------------------------------------------------------------------------------------
# traffic's smoother


def traffic_rows(
    tracks: RecordedTracks, velocity: str = "reported"
) -> tuple[torch.Tensor, float, int] | None:
    """``KalmanSmoother6D`` on every flight: estimates ``[B, T, 4]``, seconds, and 1 s points
    processed; ``None`` when traffic is not installed. Its design measures the velocity too:
    ``velocity="reported"`` gives it the recorded ground speed and track (inconsistent with the
    motion in most of these flights), ``"measured"`` the central differences of the noisy
    positions (the information every torchsvs estimator has)."""
    if not traffic_baseline.available():
        return None
    B, T = tracks.z.shape[:2]
    mean = torch.full((B, T, 4), float("nan"), dtype=torch.float64)
    seconds, points = 0.0, 0
    for b in tqdm(range(B), desc="traffic", leave=False):
        L = int(tracks.lengths[b])
        t = tracks.time[b, :L].numpy()
        x, y = tracks.z[b, :L, 0].numpy(), tracks.z[b, :L, 1].numpy()
        ex = {k: v[b, :L].numpy() for k, v in tracks.extra.items()}
        speed, heading = ex["groundspeed_kt"], ex["track_deg"]
        if velocity == "measured":
            vx, vy = np.gradient(x, t), np.gradient(y, t)
            speed = np.hypot(vx, vy) / traffic_baseline.KT_TO_MS
            heading = np.degrees(np.arctan2(vx, vy)) % 360.0
        start = time.perf_counter()
        out = traffic_baseline.smooth_flight(
            t - t[0], x, y, ex["altitude_ft"], speed, heading, ex["vertical_rate_fpm"]
        )
        seconds += time.perf_counter() - start
        points += out["points_processed"]
        mean[b, :L] = torch.from_numpy(np.stack([out["x"], out["vx"], out["y"], out["vy"]], -1))
    return mean, seconds, points


# ------------------------------------------------------------------------------------------
# the command line on a CSV of the held-out flights


def write_csv(tracks: RecordedTracks, path: Path) -> None:
    import pyarrow as pa
    import pyarrow.csv as pcsv

    ids, times, xs, ys = [], [], [], []
    for b in range(len(tracks)):
        L = int(tracks.lengths[b])
        ids += [tracks.ids[b]] * L
        times.append(tracks.time[b, :L].numpy())
        xs.append(tracks.z[b, :L, 0].numpy())
        ys.append(tracks.z[b, :L, 1].numpy())
    table = pa.table(
        {
            "track_id": ids,
            "time": np.concatenate(times),
            "x": np.concatenate(xs),
            "y": np.concatenate(ys),
        }
    )
    pcsv.write_csv(table, path)


def cli_fit(tracks: RecordedTracks, name: str, sigma: float, workdir: Path) -> dict[str, float]:
    """``torchsvs track IN -o OUT --estimator NAME --meas-std σ --fit`` on the held-out flights
    themselves; their position RMSE and the command's wall time."""
    import pyarrow.csv as pcsv

    source, target = workdir / "held_out.csv", workdir / f"{name}.csv"
    if not source.exists():
        write_csv(tracks, source)
    command = [
        sys.executable,
        "-m",
        "torchsvs.cli",
        "track",
        str(source),
        "-o",
        str(target),
        "--estimator",
        name,
        *(["--lag", str(IMM_FILTER)] if name == "imm" else []),
        "--meas-std",
        str(sigma),
        "--fit",
        "--quiet",
        "--double",
    ]
    start = time.perf_counter()
    subprocess.run(command, check=True)
    seconds = time.perf_counter() - start
    out = pcsv.read_csv(target).to_pandas()
    mean = torch.full((len(tracks), tracks.z.shape[1], 4), float("nan"), dtype=torch.float64)
    row = 0
    for b in range(len(tracks)):
        L = int(tracks.lengths[b])
        block = out.iloc[row : row + L]
        mean[b, :L] = torch.tensor(block[["x", "vx", "y", "vy"]].to_numpy())
        row += L
    return {**score(mean, tracks), "seconds": seconds}


# ------------------------------------------------------------------------------------------
# the report


def run(sets: str, seeds: int, quick: bool, progress: bool = True) -> str:
    """The whole study: compute each part, format it, write ``RESULTS/real_flights.md``."""
    torch.set_num_threads(1)
    RESULTS.mkdir(exist_ok=True)
    lines = [render("real_flights", "intro"), ""]
    lines += loader_lines(flight_steps()[1])
    lines += dirty_lines(dirty_study())
    flights = load_flights(sets)
    coverage = score(flights.truth, flights)["velocity_coverage"]  # type: ignore[arg-type]
    lines += flights_lines(sets, flights, coverage)
    data = noisy(flights, MAIN_SIGMA, seed=0)
    train, test = split(data)
    lines += main_table(train, test, quick, progress)
    if not quick:
        lines += why_lines(why_study(train, test, MAIN_SIGMA))
    lines += noise_lines(noise_study(flights, seeds, quick))
    report = "\n".join(lines)
    report = merge_imm(report, *imm_part(flights, train, test, quick, progress))
    (RESULTS / "real_flights.md").write_text(report + "\n")
    return report


def loader_lines(report: FlightReport) -> list[str]:
    """What the loader made of every sample file of the wheel (``flight_steps()``'s report)."""
    rows = report.rows
    table = markdown_table(
        ["rows", "reason", "count"],
        [["set aside", k, v] for k, v in sorted(rows.set_aside.items())]
        + [["note", k, v] for k, v in sorted(rows.notes.items())],
    )
    text = render(
        "real_flights",
        "loader",
        files=report.files,
        track_files=report.track_files,
        not_tracks=len(report.not_tracks),
        not_track_reasons="; ".join(f"`{k}`: {v}" for k, v in report.not_tracks.items()),
        tracks=rows.tracks,
        total=rows.total,
        measurements=rows.measurement,
        predictions=rows.prediction,
        aside=sum(rows.set_aside.values()),
        table=table,
    )
    return [text, ""]


class DirtyFile(NamedTuple):
    """One ``noisy/`` sample through the loader and the KS and SVSS."""

    name: str
    rows: RowReport  #: what the loader did with its rows
    finite: bool  #: every estimate at a placed row finite, for both estimators


def dirty_study() -> list[DirtyFile]:
    """The ``noisy/`` samples (spoofing, outliers, a time jump, ground and take-off noise)
    through the loader and the KS and SVSS, settings read off each file."""
    from torchsvs.datasets.adsb import sample_files

    files = []
    for path in [p for p in sample_files() if p.parent.name == "noisy"]:
        steps, report = flight_steps([path])
        tracks = padded_batch(steps, np.arange(steps.num_tracks), torch.float64)
        finite = []
        for name in ("ks", "svss"):
            settings = complete_settings(Settings(estimator=name), tracks)
            mean, _ = estimate(settings, tracks)
            finite.append(bool(torch.isfinite(mean[tracks.mask]).all()))
        files.append(DirtyFile(path.name, report.rows, all(finite)))
    return files


def dirty_lines(files: list[DirtyFile]) -> list[str]:
    """The dirty samples' table: rows placed, set aside, fixed up, and whether all is finite."""
    rows = []
    for f in files:
        r = f.rows
        notes = ", ".join(f"{k} {v}" for k, v in sorted({**r.notes, **r.set_aside}.items()))
        rows.append(
            [
                f.name,
                r.total,
                r.tracks,
                r.measurement,
                r.prediction,
                sum(r.set_aside.values()),
                notes,
                "yes" if f.finite else "NO",
            ]
        )
    table = markdown_table(
        [
            "file",
            "rows",
            "tracks",
            "measurements",
            "predictions",
            "set aside",
            "reasons and fix-ups",
            "finite",
        ],
        rows,
    )
    return [render("real_flights", "dirty", table=table), ""]


def flights_lines(sets: str, flights: RecordedTracks, coverage: float) -> list[str]:
    """The benchmark's flights: how many, their scans, the split, and the share of scans
    (``coverage``) where the reported velocity agrees with the motion."""
    text = render(
        "real_flights",
        "flights",
        sets=sets,
        flights=len(flights),
        scans=int(flights.lengths.sum()),
        dt=f"{float(flights.dt[flights.mask].median()):.0f}",
        train=len(flights) // 2,
        test=len(flights) - len(flights) // 2,
        coverage=f"{100 * coverage:.0f}",
    )
    return [text, ""]


def table_row(
    label: str, source: str, settings: Settings | None, result: dict[str, float]
) -> list[object]:
    """A row of the held-out table: accuracy, cost and the parameters used."""
    shown = ""
    if settings is not None:
        shown = f"q {settings.q:.0f}"
        if settings.psi is not None and settings.estimator not in ("kf", "ks"):
            shown += ", ψ " + "/".join(f"{p:.0f}" for p in settings.psi[:2])
            shown += f", γ {settings.gamma:.2f}"
        if settings.estimator == "imm":
            assert settings.turn_q is not None and settings.turn_rate_q is not None
            shown = f"CV q {settings.q:.1f}, turn q {settings.turn_q:.1f}" + (
                f", ω noise {math.degrees(math.sqrt(settings.turn_rate_q) * settings.interval):.2f}"
                "°/s per scan"
            )
    return [
        label,
        source,
        f"{result['position']:.1f}",
        f"{result['velocity']:.1f}",
        f"{result['velocity_motion']:.1f}",
        f"{result['us_per_point']:.2f}" if "us_per_point" in result else "",
        shown,
    ]


class Row(NamedTuple):
    """One estimator's scores on the held-out flights, and the settings it ran with."""

    label: str
    source: str
    settings: Settings | None
    result: dict[str, float]


@dataclass
class HeldOut:
    """The held-out study's numbers (:func:`held_out_study`), all that :func:`held_out_lines`
    formats."""

    sigma: float
    lag: int  #: the SVSS lag of the learned rows
    measurements: dict[str, float]  #: the scores of the measurements themselves
    rows: list[Row]
    fits: dict[str, Any]  #: label → the truth-free fit (``self_tune``'s result)
    ks_test: dict[float, float]  #: the KS's q grid on the held-out flights (needs their truth)
    sv_test: dict[tuple[float, float], float]  #: the SVSS's (q, ψ limit) grid, likewise
    clis: dict[str, dict[str, float]]  #: ``torchsvs track --fit`` per estimator
    #: traffic's smoother on the held-out flights (mean, seconds, points), where installed
    traffic: tuple[torch.Tensor, float, int] | None = None

    @property
    def results(self) -> dict[str, dict[str, float]]:
        """Each row's scores by ``"label, source"``."""
        return {f"{r.label}, {r.source}": r.result for r in self.rows}


def held_out_study(
    train: RecordedTracks, test: RecordedTracks, quick: bool, progress: bool
) -> HeldOut:
    """Every estimator on the held-out flights: rules of thumb, grids, truth-free fits on the
    training flights, training on simulation, traffic's smoother and ``torchsvs track --fit``."""
    sigma, lag = MAIN_SIGMA, DEFAULT_SVSS_LAG
    rows: list[Row] = []

    def add(label: str, source: str, settings: Settings | None, result: dict[str, float]) -> None:
        rows.append(Row(label, source, settings, result))

    measurements = score(
        torch.stack(
            [
                test.z[..., 0],
                torch.full_like(test.z[..., 0], math.nan),
                test.z[..., 1],
                torch.full_like(test.z[..., 0], math.nan),
            ],
            -1,
        ),
        test,
    )
    names = ["kf", "ks", "svsf", "svss", "svstps", "rstkf"]
    for name in tqdm(names, desc="rules of thumb", disable=not progress, leave=False):
        s = rule_of_thumb(name, train, sigma)
        add(name.upper(), "rules of thumb", s, evaluate(s, test))
    hplus = rule_of_thumb("svss", train, sigma, velocity=False, lag=1)
    add("SVSS lag 1, H⁺ mode (the paper's)", "rules of thumb", hplus, evaluate(hplus, test))

    # Grids: best on the training flights, applied to the held-out ones; and the held-out bound.
    ks_base = rule_of_thumb("ks", train, sigma)
    ks_train, ks_test = grid_ks(ks_base, train), grid_ks(ks_base, test)
    q_train = min(ks_train, key=ks_train.get)  # type: ignore[arg-type]
    chosen = replace(ks_base, q=q_train)
    add("KS", "grid (training)", chosen, evaluate(chosen, test))
    svss_base = rule_of_thumb("svss", train, sigma, lag=lag)
    sv_train = grid_svss(svss_base, train) if not quick else {}
    sv_test = grid_svss(svss_base, test) if not quick else {}
    if sv_train:
        q, limit = min(sv_train, key=sv_train.get)  # type: ignore[arg-type]
        chosen = replace(svss_base, q=q, psi=[limit, limit])
        add(f"SVSS lag {lag}", "grid (training)", chosen, evaluate(chosen, test))

    # Learned without truth on the training flights.
    fits: dict[str, Any] = {}
    learned_specs = [("ks", None), ("svsf", None), ("svss", 2), ("svss", lag), ("svstps", lag)]
    for name, lag_k in tqdm(
        learned_specs, desc="truth-free fits", disable=not progress, leave=False
    ):
        base = rule_of_thumb(name, train, sigma, **({} if lag_k is None else {"lag": lag_k}))
        fit = self_tune(base, train, known_noise=True)
        label = name.upper() + ("" if lag_k is None else f" lag {lag_k}")
        fits[f"{label}, learned, SURE (σ known)"] = fit
        add(label, "learned, SURE (σ known)", fit.settings, evaluate(fit.settings, test))
    for name, lag_k in [("ks", None), ("svss", lag)]:
        base = complete_settings(Settings(estimator=name, lag=lag_k), train)
        fit = self_tune(base, train, known_noise=False)
        label = name.upper() + ("" if lag_k is None else f" lag {lag_k}") + ", σ unknown"
        fits[f"{label}, learned, NLL then SURE"] = fit
        add(label, "learned, NLL then SURE", fit.settings, evaluate(fit.settings, test))

    # Learned with truth on simulated maneuvers.
    for name in ("ks", "svss"):
        s = train_on_simulation(name, sigma, lag, seconds=20.0 if quick else 60.0)
        add(
            name.upper() + ("" if name == "ks" else f" lag {lag}"),
            "learned on simulation",
            s,
            evaluate(s, test),
        )

    traffic = traffic_rows(test)
    if traffic is not None:
        for how, run_ in (("reported", traffic), ("measured", traffic_rows(test, "measured"))):
            assert run_ is not None
            mean, seconds, points = run_
            result = score(mean, test)
            result["us_per_point"] = 1e6 * seconds / float(test.lengths.sum())
            source = (
                "its own; velocity as reported"
                if how == "reported"
                else "its own; velocity from the noisy positions"
            )
            add("traffic KalmanSmoother6D", source, None, result)
    with tempfile.TemporaryDirectory() as workdir:
        clis = {name: cli_fit(test, name, sigma, Path(workdir)) for name in ("ks", "svss")}
    return HeldOut(sigma, lag, measurements, rows, fits, ks_test, sv_test, clis, traffic)


#: The held-out table's columns (:func:`merge_imm` adds the IMM's rows to it).
HELD_OUT_COLUMNS = (
    "estimator",
    "parameters",
    "position (m)",
    "velocity (m/s)",
    "vs motion",
    "µs/point",
    "values",
)


def held_out_lines(study: HeldOut) -> list[str]:
    """The held-out table, the truth-free fits and ``track --fit``, formatted (the prose in
    ``templates/real_flights.md``)."""
    rows: list[list[object]] = [
        ["measurements", "—", f"{study.measurements['position']:.1f}", "", "", "", ""]
    ]
    rows += [table_row(*row) for row in study.rows]
    held_out = markdown_table(list(HELD_OUT_COLUMNS), rows)
    cli_rows = []
    for name, r in study.clis.items():
        bound = (
            min(study.ks_test.values())
            if name == "ks"
            else min(study.sv_test.values(), default=math.nan)
        )
        cli_rows.append(
            [
                name.upper(),
                f"{r['position']:.2f}",
                f"{bound:.2f}",
                f"{r['position'] / bound:.3f}",
                f"{r['seconds']:.1f}",
            ]
        )
    cli = markdown_table(
        [
            "estimator",
            "position (m)",
            "best grid q / ψ on these flights (m)",
            "ratio",
            "wall time (s)",
        ],
        cli_rows,
    )
    fits = fit_section(study.fits, study.ks_test, study.sv_test, study.results, study.lag)
    return [
        render("real_flights", "held_out", sigma=f"{study.sigma:.0f}", table=held_out),
        "",
        *fits,
        render("real_flights", "track_fit", sigma=f"{study.sigma:.0f}", table=cli),
        "",
    ]


def main_table(
    train: RecordedTracks, test: RecordedTracks, quick: bool, progress: bool
) -> list[str]:
    """The held-out section: :func:`held_out_study`, then its lines, the speed section where
    traffic is installed and the map of the flight that turns most."""
    study = held_out_study(train, test, quick, progress)
    lines = held_out_lines(study)
    if study.traffic is not None:
        lines += speed_lines(speed_study(study.fits, study.traffic, test))
    shown = {
        "KS, learned": estimate(study.fits["KS, learned, SURE (σ known)"].settings, test)[0],
        f"SVSS lag {study.lag}, learned": estimate(
            study.fits[f"SVSS lag {study.lag}, learned, SURE (σ known)"].settings, test
        )[0],
    }
    if study.traffic is not None:
        shown["traffic"] = study.traffic[0]
    flight = map_figure(test, shown, RESULTS / "real_flights_map.png")
    return [*lines, render("real_flights", "map", flight=flight), ""]


def fit_section(
    fits: dict[str, Any],
    ks_test: dict[float, float],
    sv_test: dict[tuple[float, float], float],
    results: dict[str, dict[str, float]],
    lag: int,
) -> list[str]:
    """Learned against the best grid values on the held-out flights, and the time per fit."""
    ks_best = min(ks_test.values())
    rows = [
        [
            label,
            f"{fit.seconds:.1f}",
            f"{results[label]['position']:.2f}",
            "; ".join(fit.stages),
        ]
        for label, fit in fits.items()
    ]
    svss_best = svss_ratio = ""
    if sv_test:
        sv_best = min(sv_test.values())
        svss_best = render(
            "real_flights",
            "fits_svss_best",
            lag=lag,
            best=f"{sv_best:.2f}",
            at=min(sv_test, key=sv_test.__getitem__),
        )
        learned = results[f"SVSS lag {lag}, learned, SURE (σ known)"]["position"]
        svss_ratio = render(
            "real_flights", "fits_svss_ratio", lag=lag, ratio=f"{learned / sv_best:.3f}"
        )
    text = render(
        "real_flights",
        "fits",
        table=markdown_table(["fit", "seconds", "held-out position (m)", "what it learned"], rows),
        ks_best=f"{ks_best:.2f}",
        ks_q=f"{min(ks_test, key=ks_test.__getitem__):.0f}",
        svss_best=svss_best,
        ks_ratio=f"{results['KS, learned, SURE (σ known)']['position'] / ks_best:.3f}",
        svss_ratio=svss_ratio,
    )
    return [text, ""]


#: Calls per timing in the speed section; the best is kept.
SPEED_REPEATS = 5


class SpeedRow(NamedTuple):
    """µs per scan of one learned estimator (best of :data:`SPEED_REPEATS` calls)."""

    label: str
    float32: float
    float64: float
    batch: float  #: float32, every noise level and seed as one batch
    eager: float  #: float32 through the tensor loops


@dataclass
class Speed:
    """The speed study's numbers (:func:`speed_study`), all that :func:`speed_lines` formats."""

    points: int  #: one-second points traffic's smoother processed
    scans: int  #: scans of the held-out flights
    per_point: float  #: traffic's µs per scan
    realisations: int  #: noise draws in the batch column
    tracks: int  #: tracks in the batch column
    rows: list[SpeedRow]
    compiled: bool  #: the compiled loops are available
    build_seconds: float  #: the C++ build's time in this run (0: loaded from the cache)
    failure: str = ""  #: why the compiled loops are unavailable


def speed_study(
    fits: dict[str, Any], traffic: tuple[torch.Tensor, float, int], test: RecordedTracks
) -> Speed:
    """Per-scan cost of the learned estimators in float32 and float64 (best of five calls, all
    held-out flights at once), beside traffic's in the same run."""
    _, seconds, points = traffic
    scans = float(test.lengths.sum())
    per_point = 1e6 * seconds / scans
    assert test.truth is not None
    clean = replace(test, z=test.truth[..., [0, 2]])
    many = [noisy(clean, s, seed) for s in SIGMAS for seed in (0, 1)]
    monte_carlo = replace(
        test,
        z=torch.cat([t.z for t in many]),
        dt=test.dt.repeat(len(many), 1),
        lengths=test.lengths.repeat(len(many)),
        ids=test.ids * len(many),
        truth=None,
        extra={},
    )

    def cost(settings: Settings, tracks: RecordedTracks, dtype: torch.dtype) -> float:
        est = make_estimator(settings, make_model(settings)).to(dtype)
        moved, _ = centred(tracks)
        moved = with_prior(moved.to(dtype), torch.tensor(settings.meas_var, dtype=dtype).sqrt())
        best = math.inf
        for _ in range(SPEED_REPEATS):
            start = time.perf_counter()
            run_estimator(est, moved)
            best = min(best, time.perf_counter() - start)
        return 1e6 * best / float(tracks.lengths.sum())

    library = build.library()
    rows = []
    for label, fit in fits.items():
        if "σ unknown" in label:
            continue
        f32, f64 = (cost(fit.settings, test, d) for d in (torch.float32, torch.float64))
        batch = cost(fit.settings, monte_carlo, torch.float32)
        with eager_loops():
            eager = cost(fit.settings, test, torch.float32)
        rows.append(SpeedRow(label.split(",")[0], f32, f64, batch, eager))
    return Speed(
        points=points,
        scans=int(scans),
        per_point=per_point,
        realisations=len(many),
        tracks=len(many) * len(test),
        rows=rows,
        compiled=library is not None,
        build_seconds=float(build.BUILD["seconds"]),
        failure="" if library is not None else str(build.failure()),
    )


def speed_lines(speed: Speed) -> list[str]:
    """The speed study's table and what it ran on."""
    per_point = speed.per_point
    rows = [
        [
            r.label,
            f"{r.float32:.2f}",
            f"{per_point / r.float32:.0f}×",
            f"{r.float64:.2f}",
            f"{per_point / r.float64:.0f}×",
            f"{r.batch:.2f}",
            f"{per_point / r.batch:.0f}×",
            f"{r.eager:.2f}",
            f"{r.eager / r.float32:.0f}×",
        ]
        for r in speed.rows
    ]
    if not speed.compiled:
        built = render("real_flights", "built_unavailable", reason=speed.failure)
    elif speed.build_seconds > 0:
        built = render("real_flights", "built_now", seconds=f"{speed.build_seconds:.1f}")
    else:
        built = render("real_flights", "built_cached")
    table = markdown_table(
        [
            "estimator",
            "float32 µs/scan",
            "traffic ÷ this",
            "float64 µs/scan",
            "traffic ÷ this",
            f"float32, {speed.realisations} realisations at once",
            "traffic ÷ this",
            "float32, tensor loops",
            "tensor ÷ compiled loops",
        ],
        rows,
    )
    text = render(
        "real_flights",
        "speed",
        repeats=SPEED_REPEATS,
        points=speed.points,
        scans=speed.scans,
        per_point=f"{per_point:.0f}",
        table=table,
        built=built,
        tracks=speed.tracks,
    )
    return [text, ""]


@dataclass
class Noise:
    """The noise-level study's numbers (:func:`noise_study`), all that :func:`noise_lines`
    formats."""

    seeds: int
    lag: int  #: the SVSS and SVSTPS lag
    #: σ → row → held-out position RMSE per seed (traffic: seed 0 only, where installed)
    scores: dict[float, dict[str, list[float]]]
    gaps: dict[float, list[float]]  #: σ → SVSS minus KS per seed


def noise_study(flights: RecordedTracks, seeds: int, quick: bool) -> Noise:
    """Learned KS and SVSS (SURE on the training half) against traffic and the measurements at
    every noise level, over noise seeds: the held-out position RMSE of each."""
    lag = DEFAULT_SVSS_LAG
    table: dict[float, dict[str, list[float]]] = {}
    paired = []
    for sigma in SIGMAS:
        scores: dict[str, list[float]] = {
            "measurements": [],
            "KS": [],
            f"SVSS lag {lag}": [],
            f"SVSTPS lag {lag}": [],
            "traffic": [],
        }
        for seed in range(seeds):
            data = noisy(flights, sigma, seed=seed)
            train, test = split(data)
            scores["measurements"].append(
                float(pooled_rmse(test.z, test.truth[..., [0, 2]], test.mask))  # type: ignore[index]
            )
            ks = self_tune(rule_of_thumb("ks", train, sigma), train).settings
            svss = self_tune(rule_of_thumb("svss", train, sigma, lag=lag), train).settings
            svstps = self_tune(rule_of_thumb("svstps", train, sigma, lag=lag), train).settings
            scores["KS"].append(evaluate(ks, test)["position"])
            scores[f"SVSS lag {lag}"].append(evaluate(svss, test)["position"])
            scores[f"SVSTPS lag {lag}"].append(evaluate(svstps, test)["position"])
            paired.append((sigma, scores[f"SVSS lag {lag}"][-1] - scores["KS"][-1]))
            if seed == 0 and not quick:
                traffic = traffic_rows(test)
                if traffic is not None:
                    scores["traffic"].append(score(traffic[0], test)["position"])
        table[sigma] = scores
    gaps = {s: [d for sig, d in paired if sig == s] for s in SIGMAS}
    return Noise(seeds, lag, table, gaps)


def noise_lines(noise: Noise) -> list[str]:
    """The noise-level table (mean ± half the range over seeds) and SVSS minus KS per seed."""
    lag = noise.lag
    rows: list[list[object]] = [
        [f"{sigma:.0f}", *(_spread(values) for values in scores.values())]
        for sigma, scores in noise.scores.items()
    ]
    table = markdown_table(
        [
            "σ (m)",
            "measurements",
            "KS",
            f"SVSS lag {lag}",
            f"SVSTPS lag {lag}",
            "traffic (seed 0)",
        ],
        rows,
    )
    gaps = "; ".join(
        f"σ = {s:.0f}: " + ", ".join(f"{d:+.2f}" for d in ds) for s, ds in noise.gaps.items()
    )
    text = render("real_flights", "noise", seeds=noise.seeds, table=table, lag=lag, gaps=gaps)
    return [text, ""]


class WhyRow(NamedTuple):
    """One truth-free fit of the SVSF family or the KS, scored on the held-out flights."""

    estimator: str
    lag: object  #: the lag, or "full interval"
    result: dict[str, float]
    seconds: float  #: the fit's time


#: The optimiser comparison of the why section: Adam's learning rate and steps.
ADAM_LR, ADAM_STEPS = 0.05, 40


@dataclass
class Why:
    """What decides the SVSF family against the KS (:func:`why_study`)."""

    rows: list[WhyRow]
    adam_q: float  #: SURE's q for the KS from q = 1 by Adam
    adam_position: float
    lbfgs_q: float  #: the same by L-BFGS with the start search
    lbfgs_position: float
    lbfgs_seconds: float


def why_study(train: RecordedTracks, test: RecordedTracks, sigma: float) -> Why:
    """What decides the SVSF family against the KS: the lag, the velocity rule, the fit."""
    rows = []
    for name, lag in (
        [("ks", 1), ("ks", 2), ("ks", 5), ("ks", None)]
        + [("svss", k) for k in (1, 2, 3, 5, 10)]
        + [("svstps", k) for k in (1, 2, 5)]
    ):
        base = rule_of_thumb(name, train, sigma, **({"lag": lag} if lag else {}))
        fit = self_tune(base, train)
        result = evaluate(fit.settings, test)
        rows.append(
            WhyRow(name.upper(), "full interval" if lag is None else lag, result, fit.seconds)
        )
    hplus = self_tune(rule_of_thumb("svss", train, sigma, lag=5, velocity=False), train)
    rows.append(WhyRow("SVSS, H⁺ mode", 5, evaluate(hplus.settings, test), hplus.seconds))
    # The optimiser, not SURE, stalled before: Adam at 0.05 from q = 1 moves 5% per step.
    base = replace(rule_of_thumb("ks", train, sigma), q=1.0)
    adam = self_tune(base, train, optimizer="adam", lr=ADAM_LR, steps=ADAM_STEPS)
    lbfgs = self_tune(base, train)
    assert adam.settings.q is not None and lbfgs.settings.q is not None
    return Why(
        rows,
        adam.settings.q,
        evaluate(adam.settings, test)["position"],
        lbfgs.settings.q,
        evaluate(lbfgs.settings, test)["position"],
        lbfgs.seconds,
    )


def why_lines(why: Why) -> list[str]:
    """The why section: each fit's held-out scores, and Adam against L-BFGS."""
    rows = [
        [
            r.estimator,
            r.lag,
            f"{r.result['position']:.2f}",
            f"{r.result['velocity_motion']:.1f}",
            f"{r.seconds:.1f}",
        ]
        for r in why.rows
    ]
    table = markdown_table(
        ["estimator", "lag", "held-out position (m)", "velocity vs motion (m/s)", "fit (s)"],
        rows,
    )
    text = render(
        "real_flights",
        "why",
        table=table,
        lr=f"{ADAM_LR:g}",
        steps=ADAM_STEPS,
        adam_q=f"{why.adam_q:.1f}",
        adam_position=f"{why.adam_position:.2f}",
        lbfgs_q=f"{why.lbfgs_q:.1f}",
        lbfgs_position=f"{why.lbfgs_position:.2f}",
        lbfgs_seconds=f"{why.lbfgs_seconds:.1f}",
    )
    return [text, ""]


def map_figure(test: RecordedTracks, estimates: dict[str, torch.Tensor], path: Path) -> str:
    """The held-out flight that turns most: truth, measurements and estimates, and a zoom."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = test.truth
    assert truth is not None
    heading = torch.atan2(test.extra["vx_motion"], test.extra["vy_motion"])
    turning = torch.nan_to_num(
        torch.diff(heading, dim=1).remainder(2 * math.pi).sub(math.pi).abs().sub(math.pi).abs()
    )
    b = int(turning.sum(1).argmax())
    L = int(test.lengths[b])
    k0 = int(turning[b, : L - 1].unfold(0, 60, 1).sum(-1).argmax())  # the busiest 60 scans
    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    for ax, span in zip(axes, (slice(0, L), slice(k0, k0 + 60)), strict=True):
        ax.plot(
            test.z[b, span, 0] / 1e3,
            test.z[b, span, 1] / 1e3,
            ".",
            color="0.7",
            ms=3,
            label="measurements",
        )
        ax.plot(
            truth[b, span, 0] / 1e3, truth[b, span, 2] / 1e3, "k-", lw=1.5, label="recorded (truth)"
        )
        for (name, mean), style in zip(estimates.items(), ("-", "--", ":"), strict=False):
            ax.plot(mean[b, span, 0] / 1e3, mean[b, span, 2] / 1e3, style, lw=1.2, label=name)
        ax.set_aspect("equal")
        ax.set_xlabel("east (km)")
        ax.set_ylabel("north (km)")
    axes[0].set_title(f"{test.ids[b]}: whole flight")
    axes[1].set_title(f"the busiest 60 scans (5 min) from scan {k0}")
    axes[1].legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return test.ids[b]


def _spread(values: list[float]) -> str:
    if not values:
        return "—"
    mean = sum(values) / len(values)
    half = (max(values) - min(values)) / 2
    return f"{mean:.1f}" + (f" ± {half:.1f}" if len(values) > 1 else "")


# ------------------------------------------------------------------------------------------
# the IMM of a CV and a coordinated-turn mode

#: The study of the IMM's defaults (:func:`torchsvs.fitting.defaults.turn_settings`) on the training
#: flights: the CV mode's share of the data's q, and the turn-rate scale.
IMM_QUIET_GRID = (0.01, 0.03, 0.1, 0.3, 1.0)
IMM_RATE_GRID = (0.1, 0.3, 1.0)


@dataclass
class ImmDefaults:
    """The study of the IMM's defaults on the training flights (:func:`imm_defaults_study`)."""

    #: (CV mode's share of q, turn-rate scale) → (position, velocity vs motion) per σ
    scores: dict[tuple[float, float], list[tuple[float, float]]]
    sigmas: list[float]
    #: σ → the defaults' position RMSE over the grid's best (where the grid holds the defaults)
    ratios: dict[float, float]


@dataclass
class Imm:
    """The IMM's rows and section (:func:`imm_study`), all that :func:`imm_lines` formats."""

    rows: list[Row]
    fit: str  #: what ``--fit`` learned (the fit's summary)
    sigma: float
    cli: dict[str, float]  #: ``torchsvs track --estimator imm --fit`` on the held-out flights
    ks_cli: float  #: the KS's best grid q on the held-out flights (needs their truth)
    defaults: ImmDefaults


def imm_part(
    flights: RecordedTracks,
    train: RecordedTracks,
    test: RecordedTracks,
    quick: bool,
    progress: bool = True,
) -> tuple[list[list[object]], list[str]]:
    """The IMM's rows of the held-out table and its section (:func:`imm_study`, formatted by
    :func:`imm_lines`), as :func:`merge_imm` takes them."""
    return imm_lines(imm_study(flights, train, test, quick, progress))


def imm_study(
    flights: RecordedTracks,
    train: RecordedTracks,
    test: RecordedTracks,
    quick: bool,
    progress: bool = True,
) -> Imm:
    """The IMM on the held-out flights (σ = :data:`MAIN_SIGMA`: settings read off the
    training flights as ``torchsvs track`` reads them, and learned there by SURE), the study
    of its defaults on the training flights at every noise level, and ``torchsvs track
    --estimator imm --fit`` on the held-out flights."""
    sigma = MAIN_SIGMA
    base = rule_of_thumb("imm", train, sigma, lag=IMM_FILTER)
    rows = [Row(IMM_LABEL, "rules of thumb", base, evaluate(base, test))]
    fit = self_tune(base, train, known_noise=True)
    rows.append(
        Row(IMM_LABEL, "learned, SURE (σ known)", fit.settings, evaluate(fit.settings, test))
    )
    defaults = imm_defaults_study(flights, quick, progress)
    with tempfile.TemporaryDirectory() as workdir:
        cli = cli_fit(test, "imm", sigma, Path(workdir))
    ks_cli = min(grid_ks(rule_of_thumb("ks", train, sigma), test).values())
    return Imm(rows, fit.summary()[5:], sigma, cli, ks_cli, defaults)


def imm_lines(imm: Imm) -> tuple[list[list[object]], list[str]]:
    """The IMM's rows of the held-out table and its section's lines, with an ``IMM_RANKING``
    line where :func:`merge_imm` puts the ranking of the merged table."""
    section = render(
        "real_flights",
        "imm",
        label=IMM_LABEL,
        filter_lag=IMM_FILTER,
        quiet=f"{IMM_QUIET:g}",
        rate_scale=f"{TURN_RATE_SCALE:g}",
        fit=imm.fit,
        ranking="IMM_RANKING",
        sigma=f"{imm.sigma:.0f}",
        cli_position=f"{imm.cli['position']:.2f}",
        cli_seconds=f"{imm.cli['seconds']:.1f}",
        ks_cli=f"{imm.ks_cli:.2f}",
        defaults=imm_defaults_lines(imm.defaults),
    )
    return [table_row(*row) for row in imm.rows], [*section.split("\n"), ""]


def imm_defaults_study(flights: RecordedTracks, quick: bool, progress: bool) -> ImmDefaults:
    """Position RMSE and velocity RMSE against the motion on the training flights (the training
    half of each noise level's seed-0 draw, as in :func:`noise_study`) over the two factors of
    :func:`torchsvs.fitting.defaults.turn_settings`."""
    quiet_grid = IMM_QUIET_GRID if not quick else (IMM_QUIET, 1.0)
    rate_grid = IMM_RATE_GRID if not quick else (0.3,)
    scores: dict[tuple[float, float], list[tuple[float, float]]] = {
        (a, b): [] for a in quiet_grid for b in rate_grid
    }
    ratios: dict[float, float] = {}
    for sigma in tqdm(SIGMAS, desc="imm defaults", disable=not progress, leave=False):
        train, _ = split(noisy(flights, sigma, seed=0))
        base = rule_of_thumb("imm", train, sigma, lag=IMM_FILTER)
        q = imm_base_q(train, [sigma**2] * 2)
        speed = typical_speed(train)
        for a, b in scores:
            derived = turn_settings(q, [sigma**2] * 2, base.interval, speed, a, b)
            result = evaluate(replace(base, **derived), train)  # type: ignore[arg-type]
            scores[(a, b)].append((result["position"], result["velocity_motion"]))
        chosen = scores.get((IMM_QUIET, TURN_RATE_SCALE))
        if chosen is not None:
            ratios[sigma] = chosen[-1][0] / min(s[-1][0] for s in scores.values())
    return ImmDefaults(scores, list(SIGMAS), ratios)


def imm_defaults_lines(study: ImmDefaults) -> str:
    """The defaults study's table and how far the defaults are from the grid's best."""
    header = ["CV mode's share of q", "turn-rate scale"]
    for sigma in study.sigmas:
        header += [f"σ = {sigma:.0f}: position (m)", "velocity vs motion (m/s)"]
    rows = [
        [f"{a:g}", f"{b:g}", *(f"{v:.1f}" for pair in values for v in pair)]
        for (a, b), values in study.scores.items()
    ]
    return render(
        "real_flights",
        "imm_defaults",
        table=markdown_table(header, rows),
        quiet=f"{IMM_QUIET:g}",
        rate_scale=f"{TURN_RATE_SCALE:g}",
        ratios=", ".join(f"σ = {s:.0f}: {r:.3f}" for s, r in study.ratios.items()),
    )


def _table_span(lines: list[str]) -> tuple[int, int]:
    """First and one-past-last line of the held-out table (its header included)."""
    heading = next(i for i, line in enumerate(lines) if line.startswith("## Held-out flights"))
    start = next(i for i in range(heading, len(lines)) if lines[i].startswith("| estimator"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return start, end


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def merge_imm(report: str, rows: list[list[object]], section: list[str]) -> str:
    """``report`` with the IMM's ``rows`` in the held-out table (in place of any earlier IMM
    rows, before traffic's) and its ``section`` (with the ranking of the merged table) in place
    of any earlier one, or at the end. Nothing else changes."""
    lines = report.rstrip("\n").split("\n")
    start, end = _table_span(lines)
    body = [line for line in lines[start + 2 : end] if not _cells(line)[0].startswith(IMM_LABEL)]
    at = next(
        (i for i, line in enumerate(body) if _cells(line)[0].startswith("traffic")), len(body)
    )
    new = ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    body = body[:at] + new + body[at:]
    lines = lines[: start + 2] + body + lines[end:]
    heading = f"## {IMM_LABEL}"
    if any(line.startswith(heading) for line in lines):
        first = next(i for i, line in enumerate(lines) if line.startswith(heading))
        last = next(
            (i for i in range(first + 1, len(lines)) if lines[i].startswith("## ")), len(lines)
        )
        lines = lines[:first] + lines[last:]
        while lines and not lines[-1]:
            lines.pop()
    ranking = imm_ranking(body)
    section = [line for part in section for line in (ranking if part == "IMM_RANKING" else [part])]
    return "\n".join([*lines, "", *section]).rstrip("\n")


def imm_ranking(body: list[str]) -> list[str]:
    """The held-out table's rows ranked by position RMSE, and where the IMM's stand."""
    ranked = []
    for line in body:
        cells = _cells(line)
        if cells[0] == "measurements":
            continue
        ranked.append((float(cells[2]), cells))
    ranked.sort(key=lambda item: item[0])
    rows = [(k + 1, cells[0], cells[1], cells[2], cells[4]) for k, (_, cells) in enumerate(ranked)]
    learned = next(r for r in rows if r[1] == IMM_LABEL and r[2].startswith("learned"))
    ks = next(r for r in rows if r[1] == "KS" and r[2] == "learned, SURE (σ known)")
    family = [r for r in rows if r[1].split(" ")[0] in ("SVSF", "SVSS", "SVSTPS")]
    ahead = [r for r in family if r[0] < learned[0]]
    behind = [r for r in family if r[0] > learned[0]]
    svsf = ", ".join(str(r[3]) for r in behind if r[1] == "SVSF")
    filters = [r for r in rows if r[1] in ("KF", "SVSF", "RSTKF", IMM_LABEL)]
    text = render(
        "real_flights",
        "imm_ranking",
        rank=learned[0],
        rows=len(rows),
        position=learned[3],
        ks_rank=ks[0],
        ks_position=ks[3],
        ahead=len(ahead),
        family=len(family),
        best=ahead[0][1] if ahead else "—",
        best_position=ahead[0][3] if ahead else "—",
        behind=len(behind),
        svsf=render("real_flights", "imm_ranking_svsf", positions=svsf) if svsf else "",
        filters=", ".join(sorted({r[1] for r in filters})),
        filter_rank=1 + sum(r[0] < learned[0] for r in filters),
        filter_count=len(filters),
        table=markdown_table(
            ["rank", "estimator", "parameters", "position (m)", "vs motion (m/s)"],
            [list(r) for r in rows],
        ),
    )
    return text.split("\n")


def only_imm(sets: str, quick: bool, progress: bool = True) -> str:
    """The IMM's rows and section on the flights, noise and split of :func:`run`, merged into
    the existing ``real_flights.md``."""
    torch.set_num_threads(1)
    path = RESULTS / "real_flights.md"
    if not path.exists():
        raise SystemExit(f"--only-imm merges into {path}, which is missing: run the whole study")
    flights = load_flights(sets)
    train, test = split(noisy(flights, MAIN_SIGMA, seed=0))
    report = merge_imm(path.read_text(), *imm_part(flights, train, test, quick, progress))
    path.write_text(report + "\n")
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", default="calibration", help="sample folders or files")
    parser.add_argument("--seeds", type=int, default=2, help="noise seeds per level")
    parser.add_argument("--quick", action="store_true", help="fewer fits and grids")
    parser.add_argument(
        "--only-imm",
        action="store_true",
        help="run only the IMM's rows and section and merge them into the existing report",
    )
    args = parser.parse_args(argv)
    start = time.perf_counter()
    if args.only_imm:
        print(only_imm(args.flights, args.quick))
    else:
        print(run(args.flights, args.seeds, args.quick))
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()

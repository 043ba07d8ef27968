"""Bermúdez Ordoñez et al. 2020 (K-SVD, adaptive R): Examples 1 and 4 per covariance form.

Example 1 (Grewal & Andrews' ill-conditioned observational update, ``P0 = I3``,
``H = [[1, 1, 1], [1, 1, 1 + δ]]``, ``R = δ² I2``): δ from 1e-1 toward machine precision in
float64 and float32, for each covariance form the Kalman filter accepts, the correct digits of
``P`` against a 60-digit mpmath reference, whether ``P`` stays symmetric positive definite and
the smallest δ each form survives. Example 4 (DME-DME navigation, :func:`torchsvs.scenarios.
dme_scenario`): the EKF's position RMSE per covariance form, with the adaptive ``R`` of Eqs.
(29)-(30) (:class:`torchsvs.AdaptiveNoise`) against the fixed ``R``, on constant range noise and
on a station whose noise grows fivefold for a while. Also the adaptive ``R``'s recovery of a
step change of the noise. Writes ``experiments/results/ksvd_paper.md`` and its figures.

The covariance forms (``covariance_form=``: "joseph", "conventional", "sqrt", "ud", "svd") are
found by constructing the filters: the forms the installed torchsvs accepts run, the others
are listed as not available.

    python -m experiments.ksvd_paper [--runs 100] [--seed 0] [--quick] [--out experiments/results]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

import torchsvs as ts
from experiments import common
from experiments.common import RESULTS, template
from torchsvs.evaluation import markdown_table, save_figure
from torchsvs.scenarios import dme as dme_module

#: The covariance forms of the paper's comparison, in the order of the tables.
FORMS = ("joseph", "conventional", "sqrt", "ud", "svd")
#: Example 1's δ: 1e-1 down to 1e-16 (float64's unit round-off is 1.1e-16).
DELTAS = tuple(10.0**-k for k in range(1, 17))
#: Digits of the mpmath reference.
REFERENCE_DIGITS = 60
#: The adaptive R of Example 4: 30 samples (60 s) per segment; the paper gives no length.
WINDOW = 30
#: Example 4's degraded station: station 1's range noise × 5 from 1000 s to 2000 s.
DEGRADED = (0, 1000.0, 2000.0, 5.0)
#: Process noise spectral density of the DME filters (m²/s³): follows the 1.3 m/s² turn.
DME_Q = 1.0
#: Half-width (s) of the span around the baseline crossing in Example 4's table.
CROSSING_HALF_WIDTH = 100.0
#: Windows of the adaptive R tried on the degraded flights (samples).
SWEEP = (10, 30, 100)


def form_builder(cls: type, model: Any, **kwargs: Any) -> tuple[list[str], Callable[[str], Any]]:
    """The covariance forms ``cls`` accepts and a builder ``form -> cls(model, ...)``. Before
    ``covariance_form`` existed the filter's one form was the Joseph form."""
    try:
        cls(model, covariance_form="joseph", **kwargs)
    except TypeError:
        return ["joseph"], lambda form: cls(model, **kwargs)
    forms = []
    for form in FORMS:
        try:
            cls(model, covariance_form=form, **kwargs)
        except (TypeError, ValueError):
            continue
        forms.append(form)
    return forms, lambda form: cls(model, covariance_form=form, **kwargs)


# --- Example 1 ---------------------------------------------------------------------------------


@dataclass
class Update:
    """One observational update of Example 1."""

    digits: float  #: correct decimal digits of P (normwise, against the reference)
    symmetric: bool
    positive: bool  #: positive definite (the factor's, in a factored form; else P's eigenvalues)
    error: str = ""  #: the exception, if the update raised one

    @property
    def survives(self) -> bool:
        # Symmetry is reported, not required: the textbook form loses it at rounding level
        # long before its covariance is wrong.
        return not self.error and self.positive and self.digits >= 1.0


def _reference(H: Tensor, R: Tensor) -> list[list[Any]]:
    """``P⁺ = P − P Hᵀ (H P Hᵀ + R)⁻¹ H P`` with ``P = I3`` in mpmath, from the binary values of
    ``H`` and ``R`` as the filter holds them (the rounding of ``1 + δ`` is the problem's, the
    update's round-off is what is measured)."""
    import mpmath

    mpmath.mp.dps = REFERENCE_DIGITS
    Hm = mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in H.tolist()])
    Rm = mpmath.matrix([[mpmath.mpf(float(v)) for v in row] for row in R.tolist()])
    eye = mpmath.eye(3)
    S = Hm * Hm.T + Rm
    P = eye - Hm.T * mpmath.inverse(S) * Hm
    return [[P[i, j] for j in range(3)] for i in range(3)]


def representable(delta: float, dtype: torch.dtype) -> bool:
    """Whether ``1 + δ`` differs from 1 in ``dtype`` (else ``H`` has rank 1: another problem)."""
    one = torch.tensor(1.0, dtype=dtype)
    return bool(one + torch.tensor(delta, dtype=dtype) != one)


def example1_update(delta: float, dtype: torch.dtype, form: str) -> Update:
    """The observational update of Example 1 at ``δ`` with covariance form ``form``."""
    f64 = torch.float64
    H = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0 + delta]], dtype=f64)
    # Q tiny and positive (the model needs it SPD), so P⁻ = P0 = I3 exactly.
    model = ts.models.LinearGaussian(
        torch.eye(3, dtype=f64),
        H,
        1e-30 * torch.eye(3, dtype=f64),
        delta**2 * torch.eye(2, dtype=f64),
    ).to(dtype)
    _, build = form_builder(ts.KalmanFilter, model)
    kf = build(form)
    eps = torch.finfo(dtype).eps
    prior = kf.init(torch.zeros(1, 3, dtype=dtype), torch.eye(3, dtype=dtype))
    try:
        with torch.no_grad():
            state, out = kf.scan(prior, torch.zeros(1, 1, 2, dtype=dtype))
        P = out.cov[0, 0]
    except (RuntimeError, ValueError) as err:  # LinAlgError is a RuntimeError
        return Update(0.0, False, False, type(err).__name__)
    with torch.no_grad():
        reference = _reference(model.meas_matrix(), model.meas_cov())
    ref = torch.tensor([[float(v) for v in row] for row in reference], dtype=torch.float64)
    P64 = P.double()
    if not bool(torch.isfinite(P64).all()):
        return Update(0.0, False, False, "non-finite P")
    error = float((P64 - ref).abs().max() / ref.abs().max())
    digits = min(-math.log10(error), -math.log10(eps)) if error > 0 else -math.log10(eps)
    symmetric = float((P64 - P64.mT).abs().max()) <= eps * float(P64.abs().max())
    # A factored form's covariance is its factor: P formed from it rounds away eigenvalues
    # below eps (the exact P⁺ has one of about δ²/6), so its definiteness is the factor's.
    carried = getattr(state, "factor", None)
    if carried is not None:
        positive = bool(carried.factor.positive_definite().all())
    else:
        positive = bool(torch.linalg.eigvalsh(0.5 * (P64 + P64.mT)).min() > 0)
    return Update(max(digits, 0.0), symmetric, positive)


@dataclass
class Example1:
    forms: list[str]
    updates: dict[tuple[str, str, float], Update] = field(default_factory=dict)  # dtype, form, δ

    def deltas(self, dtype: str) -> list[float]:
        """The δ of the sweep for which ``1 + δ`` is representable in ``dtype``."""
        return [d for d in DELTAS if (dtype, self.forms[0], d) in self.updates]

    def smallest(self, dtype: str, form: str) -> float | None:
        """The smallest δ down to which every update survived (from 1e-1 on)."""
        last = None
        for delta in self.deltas(dtype):
            if not self.updates[dtype, form, delta].survives:
                break
            last = delta
        return last


def example1(progress: bool) -> Example1:
    probe = ts.models.LinearGaussian(torch.eye(3), torch.ones(2, 3), torch.eye(3), torch.eye(2))
    forms, _ = form_builder(ts.KalmanFilter, probe)
    res = Example1(forms)
    jobs = [
        (d, f, x)
        for d in (torch.float64, torch.float32)
        for f in forms
        for x in DELTAS
        if representable(x, d)
    ]
    for dtype, form, delta in tqdm(jobs, desc="Example 1", disable=not progress):
        res.updates[str(dtype).removeprefix("torch."), form, delta] = example1_update(
            delta, dtype, form
        )
    return res


# --- Example 4 ---------------------------------------------------------------------------------


@dataclass
class Run:
    """One filter on one DME case."""

    rmse: float  #: position RMSE over every run and step (m)
    degradation: float  #: during the degradation's time span (in both cases)
    crossing: float  #: within ±100 s of the baseline crossing
    turn: float  #: during the 270° turn
    seconds: float
    error_over_time: Tensor  #: [T] position RMSE over the runs at each step
    mean: Tensor  #: [B, T, 4] the estimates (float64)
    sigma: Tensor | None = None  #: [T, k] adaptive σ estimate, mean over the runs


@dataclass
class Example4:
    forms: list[str]
    cases: dict[str, ts.scenarios.DMEScenario]
    dtypes: tuple[str, ...]
    runs: dict[tuple[str, str, str, str], Run] = field(default_factory=dict)  # case, dtype, R, form
    windows: dict[int, Run] = field(default_factory=dict)  #: the window sweep (degraded, float64)
    crossing_time: float = 0.0


def dme_cases(runs: int, seed: int, names: tuple[str, ...]) -> dict[str, ts.scenarios.DMEScenario]:
    """The constant-noise and degraded-station flights (the same seed: the same paths)."""
    steps = round(dme_module.DURATION / dme_module.DT)
    t = (torch.arange(steps, dtype=torch.float64) + 1) * dme_module.DT
    station, start, stop, factor = DEGRADED
    std = torch.full((steps, 2), dme_module.RANGE_STD, dtype=torch.float64)
    std[(t >= start) & (t < stop), station] *= factor
    profiles = {"constant": dme_module.RANGE_STD, "degraded": std}
    return {
        name: ts.scenarios.dme_scenario(
            runs, torch.Generator().manual_seed(seed), range_std=profiles[name], q=DME_Q
        )
        for name in names
    }


def _dme_run(
    scenario: ts.scenarios.DMEScenario,
    dtype: torch.dtype,
    form: str,
    adaptive: ts.AdaptiveNoise | None,
    spans: dict[str, Tensor],
) -> Run:
    """The EKF (``covariance_form=form`` where the filter has it) on ``scenario`` in ``dtype``;
    the model is the scenario's (a filter computes in ``z``'s dtype)."""
    _, build = form_builder(ts.ExtendedKalmanFilter, scenario.model, adaptive_noise=adaptive)
    ekf = build(form)
    begin = time.perf_counter()
    with torch.no_grad():
        out = ekf(scenario.z.to(dtype), scenario.x0.to(dtype), scenario.P0.to(dtype))
    seconds = time.perf_counter() - begin
    d = out.mean[..., [0, 2]].double() - scenario.truth[..., [0, 2]].double()
    sq = d.square().sum(-1)  # [B, T] squared horizontal position errors
    sigma = None
    if adaptive is not None:
        sigma = out.meas_cov.diagonal(dim1=-2, dim2=-1).double().sqrt().mean(0)

    def rms(span: Tensor) -> float:
        return float(sq[:, span].mean().sqrt())

    return Run(
        float(sq.mean().sqrt()),
        rms(spans["degradation"]),
        rms(spans["crossing"]),
        rms(spans["turn"]),
        seconds,
        sq.mean(0).sqrt(),
        out.mean.double(),
        sigma,
    )


def example4(
    runs: int,
    seed: int,
    progress: bool,
    names: tuple[str, ...] = ("constant", "degraded"),
    dtypes: tuple[torch.dtype, ...] = (torch.float64, torch.float32),
    windows: tuple[int, ...] = SWEEP,
) -> Example4:
    cases = dme_cases(runs, seed, names)
    sc = next(iter(cases.values()))
    forms, _ = form_builder(ts.ExtendedKalmanFilter, sc.model)
    res = Example4(forms, cases, tuple(str(d).removeprefix("torch.") for d in dtypes))
    res.crossing_time = float(torch.tensor(dme_module.START).norm()) / dme_module.SPEED
    t = (torch.arange(sc.z.shape[1], dtype=torch.float64) + 1) * sc.dt
    spans = {
        "degradation": (t >= DEGRADED[1]) & (t < DEGRADED[2]),
        "crossing": (t - res.crossing_time).abs() <= CROSSING_HALF_WIDTH,
        "turn": t > sc.turn_start,
    }
    jobs = [
        (case, dtype, kind, form)
        for case in cases
        for dtype in dtypes
        for kind in ("fixed", "adaptive")
        for form in forms
    ]
    sweep = [w for w in windows if "degraded" in cases]
    bar = tqdm(desc="Example 4", total=len(jobs) + len(sweep), disable=not progress)
    for case, dtype, kind, form in jobs:
        adaptive = ts.AdaptiveNoise(WINDOW, floor=1.0) if kind == "adaptive" else None
        name = str(dtype).removeprefix("torch.")
        res.runs[case, name, kind, form] = _dme_run(cases[case], dtype, form, adaptive, spans)
        bar.update()
    for window in sweep:
        adaptive = ts.AdaptiveNoise(window, floor=1.0)
        res.windows[window] = _dme_run(cases["degraded"], torch.float64, forms[0], adaptive, spans)
        bar.update()
    bar.close()
    return res


# --- The adaptive R on a step change of the noise ----------------------------------------------


@dataclass
class Recovery:
    window: int
    before: tuple[float, float]  #: mean and largest relative error of σ̂ (true 1), window filled
    after: tuple[float, float]  #: the same after the change (true 5)
    tracks: int
    sigma: Tensor  #: [T] mean σ̂ over the tracks


def recovery(seed: int, tracks: int = 64, window: int = WINDOW) -> Recovery:
    """σ 1 → 5 at step 300 of 600 on a slow signal (a ramp and a 600-step sine), a KF with the
    adaptive R; σ̂ = √R_k averaged over the tracks."""
    T, change = 600, 300
    f64 = torch.float64
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=f64)
    signal = 100.0 * torch.sin(2 * math.pi * t / 600.0) + 2.0 * t
    std = torch.where(t < change, 1.0, 5.0)
    z = (signal + std * torch.randn(tracks, T, generator=g, dtype=f64)).unsqueeze(-1)
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=f64)
    model = ts.models.LinearGaussian(
        F, torch.tensor([[1.0, 0.0]]), torch.eye(2), 9.0 * torch.eye(1)
    )
    kf = ts.KalmanFilter(model.double(), adaptive_noise=ts.AdaptiveNoise(window))
    with torch.no_grad():
        out = kf(z, torch.zeros(2, dtype=f64), 100.0 * torch.eye(2, dtype=f64))
    sigma = out.meas_cov[..., 0, 0].sqrt().mean(0)
    before, after = sigma[window:change], sigma[change + window :]
    return Recovery(
        window,
        (float(before.mean()), float((before - 1.0).abs().max())),
        (float(after.mean()), float((after / 5.0 - 1.0).abs().max())),
        tracks,
        sigma,
    )


# --- Report ------------------------------------------------------------------------------------


@dataclass
class Results:
    ex1: Example1
    ex4: Example4
    rec: Recovery
    runs: int
    seconds: float
    quick: bool


def reproduce(runs: int, seed: int, quick: bool = False, progress: bool = True) -> Results:
    """Everything of the report; ``quick``: Example 4 on the degraded flights in float64 only,
    without the window sweep (a smoke test)."""
    begin = time.perf_counter()
    ex1 = example1(progress)
    if quick:
        ex4 = example4(runs, seed, progress, ("degraded",), (torch.float64,), ())
    else:
        ex4 = example4(runs, seed, progress)
    rec = recovery(seed)
    return Results(ex1, ex4, rec, runs, time.perf_counter() - begin, quick)


def _delta(x: float | None) -> str:
    return "none" if x is None else f"1e{round(math.log10(x))}"


def _cell(u: Update) -> str:
    if u.error:
        return f"fails ({u.error})"
    marks = ("" if u.symmetric else " asym") + ("" if u.positive else " not PD")
    return f"{u.digits:.1f}{marks}"


def _change(before: float, after: float) -> str:
    """``before → after`` in words: lowers/raises by how much."""
    word = "lowers" if after < before else "raises"
    return f"{word} it from {before:.1f} to {after:.1f} m ({100 * (after / before - 1):+.0f}%)"


def figures(res: Results, out_dir: Path) -> list[str]:
    """Example 1's digits against δ, Example 4's trajectory, errors and σ̂, the step change;
    returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names: list[str] = []

    def save(fig: Any, name: str) -> None:
        names.append(save_figure(fig, out_dir / name))

    ex1 = res.ex1
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, dtype in zip(axes, ("float64", "float32"), strict=True):
        deltas = ex1.deltas(dtype)
        for form in ex1.forms:
            digits = [ex1.updates[dtype, form, d].digits for d in deltas]
            ax.plot(deltas, digits, marker="o", label=form)
            bad = [d for d in deltas if not ex1.updates[dtype, form, d].survives]
            ax.plot(bad, [ex1.updates[dtype, form, d].digits for d in bad], "kx", ms=9)
        eps = torch.finfo(getattr(torch, dtype)).eps
        ax.axvline(math.sqrt(eps), color="gray", ls=":", label="δ² = eps")
        ax.set(xscale="log", xlabel="δ", title=f"Example 1, {dtype}")
        ax.invert_xaxis()
        ax.legend()
    axes[0].set_ylabel("correct digits of P⁺ (×: not surviving)")
    save(fig, "ksvd_example1_digits.png")

    ex4 = res.ex4
    form = ex4.forms[0]
    sc = ex4.cases["degraded"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 7), width_ratios=(1, 1.4))
    truth = sc.truth[0]
    stations = sc.model.stations
    for ax in axes:
        ax.plot(truth[:, 0] / 1e3, truth[:, 2] / 1e3, "k", lw=1, label="truth (run 1)")
        for kind, style in (("fixed", "C0"), ("adaptive", "C1")):
            est = ex4.runs["degraded", "float64", kind, form].mean[0]
            label = f"EKF, {kind} R ({form})"
            ax.plot(est[:, 0] / 1e3, est[:, 2] / 1e3, style, lw=0.8, label=label)
        ax.plot(stations[:, 0] / 1e3, stations[:, 1] / 1e3, "r^", ms=9, label="DME stations")
        ax.set(xlabel="x (km)", ylabel="y (km)")
        ax.set_aspect("equal")
    axes[0].set_title("Example 4: DME-DME, degraded station 1")
    axes[0].legend(loc="upper left", fontsize=8)
    crossing = int((truth[:-1, 2] > 0).logical_and(truth[1:, 2] <= 0).nonzero()[0])
    x_c = float(truth[crossing, 0]) / 1e3
    axes[1].set(
        xlim=(x_c - 2.5, x_c + 2.5),
        ylim=(-6, 6),
        title="the baseline crossing (station 1 degraded)",
    )
    save(fig, "ksvd_dme_trajectory.png")

    t = (torch.arange(sc.z.shape[1]) + 1) * sc.dt
    cases = list(ex4.cases)
    fig, axes = plt.subplots(len(cases) + 1, 1, figsize=(10, 3.4 * (len(cases) + 1)), sharex=True)
    for ax, case in zip(axes[:-1], cases, strict=True):
        for kind in ("fixed", "adaptive"):
            for f in ex4.forms:
                curve = ex4.runs[case, "float64", kind, f].error_over_time
                ax.plot(t, curve, lw=0.8, label=f"{kind} R, {f}")
        ax.axvline(ex4.crossing_time, color="gray", ls=":", label="baseline crossing")
        ax.axvline(sc.turn_start, color="gray", ls="--", label="turn")
        if case == "degraded":
            ax.axvspan(DEGRADED[1], DEGRADED[2], color="gray", alpha=0.15, label="degraded")
        ax.set(ylabel="position RMSE (m)", yscale="log", title=f"Example 4, {case} noise")
        ax.legend(fontsize=8)
    sigma = ex4.runs["degraded", "float64", "adaptive", form].sigma
    assert sigma is not None
    for i in range(sigma.shape[1]):
        axes[-1].plot(t, sigma[:, i], f"C{i}", label=f"σ̂ station {i + 1}")
        axes[-1].plot(t, sc.range_std[:, i], f"C{i}--", lw=0.8, label=f"true σ station {i + 1}")
    axes[-1].set(xlabel="time (s)", ylabel="range noise σ (m)", title="adaptive R, degraded")
    axes[-1].legend(fontsize=8)
    save(fig, "ksvd_dme_errors.png")

    rec = res.rec
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(rec.sigma, label=f"mean σ̂ over {rec.tracks} tracks (window {rec.window})")
    ax.plot([1.0] * 300 + [5.0] * 300, "k--", lw=0.8, label="true σ")
    ax.set(xlabel="step", ylabel="σ", title="adaptive R: a step change of the noise")
    ax.legend()
    save(fig, "ksvd_adaptive_step.png")
    return names


def report(res: Results, pngs: list[str]) -> str:
    """The results file: the prose of ``templates/ksvd_paper.md`` around the tables."""
    t = template("ksvd_paper")
    ex1, ex4, rec = res.ex1, res.ex4, res.rec
    missing = [f for f in FORMS if f not in ex1.forms]
    example1 = []
    for dtype in ("float64", "float32"):
        rows = [
            [_delta(d), *(_cell(ex1.updates[dtype, f, d]) for f in ex1.forms)]
            for d in ex1.deltas(dtype)
        ]
        table = markdown_table(["δ", *ex1.forms], rows)
        example1.append(t["example1_dtype"].substitute(dtype=dtype, table=table))
    smallest = [
        [f, *(_delta(ex1.smallest(dtype, f)) for dtype in ("float64", "float32"))]
        for f in ex1.forms
    ]

    deg = ex4.cases["degraded"]
    station, start, stop, factor = DEGRADED
    rows = []
    for case in ex4.cases:
        for dtype in ex4.dtypes:
            for kind in ("fixed", "adaptive"):
                for f in ex4.forms:
                    r = ex4.runs[case, dtype, kind, f]
                    rows.append(
                        [case, dtype, f"{kind} R", f]
                        + [f"{v:.1f}" for v in (r.rmse, r.degradation, r.crossing, r.turn)]
                        + [f"{r.seconds:.1f}"]
                    )
    header = ["noise", "dtype", "R", "form", "RMSE", f"{start:g}-{stop:g} s", "crossing ±100 s"]
    float32 = ""
    if "float32" in ex4.dtypes:
        gap = max(
            float((ex4.runs[k].mean - ex4.runs[(k[0], "float64", *k[2:])].mean).abs().max())
            for k in ex4.runs
            if k[1] == "float32"
        )
        float32 = t["float32"].substitute(gap=f"{gap:.2g}") + "\n\n"
    form = ex4.forms[0]

    def run(case: str, kind: str) -> Run:
        return ex4.runs[case, "float64", kind, form]

    steps = (torch.arange(deg.z.shape[1]) + 1) * deg.dt
    sigma = run("degraded", "adaptive").sigma
    assert sigma is not None
    inside = (steps >= start + WINDOW * deg.dt) & (steps < stop)
    before = (steps >= WINDOW * deg.dt) & (steps < start)
    fixed, adaptive = run("degraded", "fixed"), run("degraded", "adaptive")
    constant = ""
    if "constant" in ex4.cases:
        change = _change(run("constant", "fixed").rmse, run("constant", "adaptive").rmse)
        constant = t["constant"].substitute(change=change)
    windows = ""
    if ex4.windows:
        window_rows = [
            [str(w)] + [f"{v:.1f}" for v in (r.rmse, r.degradation, r.crossing, r.turn)]
            for w, r in ex4.windows.items()
        ]
        window_table = markdown_table(
            ["window", "RMSE", f"{start:g}-{stop:g} s", "crossing", "turn"], window_rows
        )
        windows = (
            t["windows"].substitute(
                form=form,
                fixed=f"{fixed.rmse:.1f} / {fixed.degradation:.1f} / {fixed.crossing:.1f} / "
                f"{fixed.turn:.1f}",
                table=window_table,
            )
            + "\n\n"
        )
    names = ", ".join(f"`{p}`" for p in pngs)
    return t["report"].substitute(
        seconds=f"{res.seconds:.0f}",
        runs=res.runs,
        quick=t["quick"].substitute() if res.quick else "",
        forms=", ".join(ex1.forms),
        missing=t["missing"].substitute(missing=", ".join(missing)) if missing else "",
        reference_digits=REFERENCE_DIGITS,
        example1="\n\n".join(example1),
        smallest=markdown_table(["form", "float64", "float32"], smallest),
        dt=f"{deg.dt:g}",
        steps=deg.z.shape[1],
        crossing=f"{ex4.crossing_time:.0f}",
        turn_start=f"{deg.turn_start:.0f}",
        station=station + 1,
        factor=f"{factor:g}",
        start=f"{start:g}",
        stop=f"{stop:g}",
        dme_q=f"{DME_Q:g}",
        window=WINDOW,
        example4=markdown_table([*header, "turn", "time (s)"], rows),
        float32=float32,
        form=form,
        degradation=_change(fixed.degradation, adaptive.degradation),
        crossing_change=_change(fixed.crossing, adaptive.crossing),
        overall=_change(fixed.rmse, adaptive.rmse),
        constant=constant,
        sigma_before=f"{float(sigma[before, station].mean()):.1f}",
        sigma_during=f"{float(sigma[inside, station].mean()):.1f}",
        true_during=f"{100 * factor:.0f}",
        other=2 - station,
        sigma_other=f"{float(sigma[WINDOW:, 1 - station].mean()):.1f}",
        windows=windows,
        tracks=rec.tracks,
        rec_window=rec.window,
        before=f"{rec.before[0]:.3f}",
        before_error=f"{100 * rec.before[1]:.1f}",
        after=f"{rec.after[0]:.3f}",
        after_error=f"{100 * rec.after[1]:.1f}",
        figures="\n" + t["figures"].substitute(names=names) + "\n" if pngs else "",
    )


def _quick(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke test: 4 runs, Example 4's degraded flights in float64, no window sweep",
    )


def main(argv: list[str] | None = None, out: Path = RESULTS) -> None:
    common.main(
        "ksvd_paper",
        __doc__,
        lambda args: reproduce(4 if args.quick else args.runs, args.seed, args.quick),
        figures,
        report,
        runs=100,
        runs_help="Example 4 runs",
        options=_quick,
        argv=argv,
        out=out,
    )


if __name__ == "__main__":
    main()

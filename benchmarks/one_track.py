"""`make bench` (part 5): one track, online and offline, against filterpy on the same data.

Online: the cost of one ``est.step`` call (B = 1, float64, no gradients; the whole step's
result, and keeping its moments only) beside filterpy's ``predict`` + ``update``, over 2,000
steps, and the tensor path's step (the compiled step turned off) for scale. Offline: one
recorded-length track (T = 1,000) and one long track (T = 100,000) through ``forward``,
beside filterpy's ``batch_filter`` (and ``rts_smoother``). Models: the constant-velocity
model of the papers, and a dense 3-state model (no per-axis structure).
Timings are the best of ``--repeats`` runs, alternating between the libraries, in one process;
ratios are filterpy ÷ torchsvs (> 1: torchsvs faster). Writes ``benchmarks/one_track.md``.

    python -m benchmarks.one_track [--repeats 5]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import torchsvs as ts
from benchmarks.timing import alternating_best
from torchsvs.evaluation import markdown_table
from torchsvs.kernels import eager_loops

RESULTS = Path(__file__).with_name("one_track.md")


class _Track:
    """One simulated track of ``model`` (prior 0, 100·I) and filterpy's filter of the same
    model and prior."""

    def __init__(self, model: ts.models.LinearModel, steps: int, seed: int) -> None:
        from filterpy.kalman import KalmanFilter

        n = model.state_dim
        self.x0 = torch.zeros(n, dtype=torch.float64)
        self.P0 = torch.eye(n, dtype=torch.float64) * 100.0
        _, z = model.simulate(self.x0.unsqueeze(0), steps, torch.Generator().manual_seed(seed))
        self.z, self.zn = z[0], z[0].numpy()
        self.F, H = model.transition().double().numpy(), model.meas_matrix().double().numpy()
        self.Q, R = model.process_noise().double().numpy(), model.meas_cov().double().numpy()
        self.filterpy = KalmanFilter(dim_x=n, dim_z=H.shape[0])
        self.filterpy.F, self.filterpy.H, self.filterpy.Q, self.filterpy.R = self.F, H, self.Q, R

    def restart_filterpy(self):  # noqa: ANN201
        f = self.filterpy
        f.x, f.P = self.x0.numpy().copy(), self.P0.numpy().copy()
        return f


def _online(label: str, est: torch.nn.Module, track: _Track, repeats: int) -> list[object]:
    """One ``est.step`` call at a time (compiled, and with the compiled step turned off)
    beside filterpy's ``predict`` + ``update``."""
    steps = len(track.zn)

    def torchsvs_steps(keep: str = "all") -> None:
        state = est.init(track.x0, track.P0)
        with torch.no_grad():
            for t in range(steps):
                state, _ = est.step(state, track.z[t], keep=keep)

    def tensor_path() -> None:
        with eager_loops():
            torchsvs_steps()

    def filterpy_steps() -> None:
        f = track.restart_filterpy()
        for t in range(steps):
            f.predict()
            f.update(track.zn[t])

    def moments() -> None:
        torchsvs_steps("moments")

    calls = {"fp": filterpy_steps, "ts": torchsvs_steps, "moments": moments, "tensor": tensor_path}
    best = alternating_best(calls, repeats)
    us = {k: 1e6 * v / steps for k, v in best.items()}
    return [
        f"online step, {label}",
        f"{us['fp']:.1f} µs",
        f"{us['ts']:.1f} µs; keep='moments' {us['moments']:.1f} µs (tensor path "
        f"{us['tensor']:.0f} µs)",
        f"{us['fp'] / us['ts']:.2f}×; {us['fp'] / us['moments']:.2f}×",
    ]


def _offline(
    label: str, est: torch.nn.Module, track: _Track, smooth: bool, repeats: int
) -> list[object]:
    """``forward`` on the whole track beside filterpy's ``batch_filter`` (and
    ``rts_smoother``)."""
    from filterpy.kalman import rts_smoother

    T = len(track.zn)

    def torchsvs_run() -> None:
        with torch.no_grad():
            est(track.z, track.x0, track.P0)

    def filterpy_run() -> None:
        mu, cov, _, _ = track.restart_filterpy().batch_filter(track.zn)
        if smooth:
            rts_smoother(mu, cov, [track.F] * T, [track.Q] * T)

    best = alternating_best({"fp": filterpy_run, "ts": torchsvs_run}, repeats)
    us = {k: 1e6 * v / T for k, v in best.items()}
    return [
        f"one track T = {T:,}, {label}",
        f"{us['fp']:.1f} µs/step",
        f"{us['ts']:.2f} µs/step",
        f"{us['fp'] / us['ts']:.1f}×",
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    torch.set_num_threads(1)  # what a small problem gets by default (threads_for) anyway
    cv = ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2).double()
    A = torch.tensor([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1], [0.0, -0.2, 0.95]], dtype=torch.float64)
    dense = ts.models.LinearGaussian(
        A,
        torch.tensor([[1.0, 0.5, 0.0], [0.0, 0.3, 1.0]], dtype=torch.float64),
        0.1 * torch.eye(3, dtype=torch.float64),
        torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64),
    )
    svsf = ts.SVSF(cv, psi=[800.0, 800.0], artificial=None, learn=False)
    online_repeats = max(1, args.repeats // 2)
    rows = [
        _online("KF, CV", ts.KalmanFilter(cv), _Track(cv, 2000, 0), online_repeats),
        _online("SVSF H⁺ mode, CV", svsf, _Track(cv, 2000, 0), online_repeats),
        _online(
            "KF, dense 3-state", ts.KalmanFilter(dense), _Track(dense, 2000, 0), online_repeats
        ),
    ]
    short = _Track(cv, 1000, 1)
    rows += [
        _offline("KF, CV", ts.KalmanFilter(cv), short, False, args.repeats),
        _offline("KF + RTS, CV", ts.RTSSmoother(ts.KalmanFilter(cv)), short, True, args.repeats),
        _offline(
            "SVSF (finite-difference velocity), CV",
            ts.SVSF(cv, psi=[800.0, 600.0] * 2),
            short,
            False,
            args.repeats,
        ),
        _offline(
            "KF, dense 3-state", ts.KalmanFilter(dense), _Track(dense, 1000, 1), False, args.repeats
        ),
    ]
    long = _Track(cv, 100_000, 1)
    rows += [
        _offline("KF, CV", ts.KalmanFilter(cv), long, False, 1),
        _offline("KF + RTS, CV", ts.RTSSmoother(ts.KalmanFilter(cv)), long, True, 1),
    ]

    table = markdown_table(["case", "filterpy", "torchsvs", "filterpy ÷ torchsvs"], rows)
    text = (
        "# One track: online steps and offline passes against filterpy\n\n"
        f"Generated by `python -m benchmarks.one_track --repeats {args.repeats}`: float64, one "
        "thread, no gradients, the same data for both libraries, best of the repeats "
        "(alternating). Online rows time `est.step` over 2,000 steps (filterpy: `predict` + "
        "`update`), returning the whole step's result, and with `keep='moments'` its mean and "
        "covariance (what filterpy's `x`, `P` hold); the compiled online step covers linear "
        "models (KF, EKF, the SVSF's H⁺ mode); the tensor path is the same step with it "
        "turned off. Offline rows time "
        "`forward` on one track (filterpy: `batch_filter`, `rts_smoother`); the CV model "
        "runs the per-axis compiled loops, the dense model the compiled dense steps.\n\n"
        f"{table}\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""`make bench` (part 5): one track, online and offline, against filterpy on the same data.

Online: the cost of one ``est.step`` call (B = 1, float64, no gradients) beside filterpy's
``predict`` + ``update``, over 2,000 steps, and the tensor path's step (the compiled step turned
off) for scale. Offline: one recorded-length track (T = 1,000) and one long track (T = 100,000)
through ``forward``, beside filterpy's ``batch_filter`` (and ``rts_smoother``). Models: the
constant-velocity model of the papers, and a dense 3-state model (the general path). Timings are
the best of ``--repeats`` runs, alternating between the libraries, in one process; ratios are
filterpy ÷ torchsvs (> 1: torchsvs faster). Writes ``benchmarks/one_track.md``.

    python -m benchmarks.one_track [--repeats 5]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import torchsvs as ts
from torchsvs.evaluation import markdown_table
from torchsvs.kernels import eager_loops

RESULTS = Path(__file__).with_name("one_track.md")


def _best(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Seconds per call, best of ``repeats``, the calls alternating."""
    best = {name: float("inf") for name in calls}
    for call in calls.values():
        call()  # warm-up (the compiled library, caches)
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            best[name] = min(best[name], time.perf_counter() - start)
    return best


def _filterpy(model: ts.models.LinearModel, x0: np.ndarray, P0: np.ndarray):  # noqa: ANN202
    from filterpy.kalman import KalmanFilter

    F, H = model.transition().double().numpy(), model.meas_matrix().double().numpy()
    Q, R = model.process_noise().double().numpy(), model.meas_cov().double().numpy()

    def make() -> KalmanFilter:
        f = KalmanFilter(dim_x=F.shape[0], dim_z=H.shape[0])
        f.x, f.P, f.F, f.H, f.Q, f.R = x0.copy(), P0.copy(), F, H, Q, R
        return f

    return make, F, Q


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    from filterpy.kalman import rts_smoother

    torch.set_num_threads(1)  # what a small problem gets by default (threads_for) anyway
    cv = ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2).double()
    A = torch.tensor([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1], [0.0, -0.2, 0.95]], dtype=torch.float64)
    dense = ts.models.LinearGaussian(
        A,
        torch.tensor([[1.0, 0.5, 0.0], [0.0, 0.3, 1.0]], dtype=torch.float64),
        0.1 * torch.eye(3, dtype=torch.float64),
        torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64),
    )
    rows: list[list[object]] = []

    # Online: one step call at a time.
    steps = 2000
    for label, model, est in (
        ("KF, CV", cv, ts.KalmanFilter(cv)),
        ("SVSF H⁺ mode, CV", cv, ts.SVSF(cv, psi=[800.0, 800.0], artificial=None, learn=False)),
        ("KF, dense 3-state", dense, ts.KalmanFilter(dense)),
    ):
        n = model.state_dim
        x0 = torch.zeros(n, dtype=torch.float64)
        P0 = torch.eye(n, dtype=torch.float64) * 100.0
        _, z = model.simulate(x0.unsqueeze(0), steps, torch.Generator().manual_seed(0))
        z = z[0]
        zn = z.numpy()
        make, _, _ = _filterpy(model, x0.numpy(), P0.numpy())

        def online(est: torch.nn.Module = est, x0: torch.Tensor = x0, P0=P0, z=z) -> None:  # noqa: ANN001
            state = est.init(x0, P0)
            with torch.no_grad():
                for t in range(steps):
                    state, _ = est.step(state, z[t])

        def tensor_path(online: Callable[[], None] = online) -> None:
            with eager_loops():
                online()

        def filterpy(make=make, zn=zn) -> None:  # noqa: ANN001
            f = make()
            for t in range(steps):
                f.predict()
                f.update(zn[t])

        best = _best(
            {"fp": filterpy, "ts": online, "tensor": tensor_path}, max(1, args.repeats // 2)
        )
        us = {k: 1e6 * v / steps for k, v in best.items()}
        rows.append(
            [
                f"online step, {label}",
                f"{us['fp']:.1f} µs",
                f"{us['ts']:.1f} µs (tensor path {us['tensor']:.0f} µs)",
                f"{us['fp'] / us['ts']:.2f}×",
            ]
        )

    # Offline: one track through forward.
    for T in (1000, 100_000):
        repeats = args.repeats if T <= 1000 else 1
        for label, model, est, smooth in (
            ("KF, CV", cv, ts.KalmanFilter(cv), False),
            ("KF + RTS, CV", cv, ts.RTSSmoother(ts.KalmanFilter(cv)), True),
            (
                "SVSF (finite-difference velocity), CV",
                cv,
                ts.SVSF(cv, psi=[800.0, 600.0] * 2),
                False,
            ),
            ("KF, dense 3-state", dense, ts.KalmanFilter(dense), False),
        ):
            if T > 1000 and label.startswith(("SVSF", "KF, dense")):
                continue
            n = model.state_dim
            x0 = torch.zeros(n, dtype=torch.float64)
            P0 = torch.eye(n, dtype=torch.float64) * 100.0
            _, z = model.simulate(x0.unsqueeze(0), T, torch.Generator().manual_seed(1))
            z = z[0]
            zn = z.numpy()
            make, F, Q = _filterpy(model, x0.numpy(), P0.numpy())

            def offline(est: torch.nn.Module = est, z=z, x0=x0, P0=P0) -> None:  # noqa: ANN001
                with torch.no_grad():
                    est(z, x0, P0)

            def filterpy(make=make, zn=zn, smooth=smooth, F=F, Q=Q) -> None:  # noqa: ANN001
                mu, cov, _, _ = make().batch_filter(zn)
                if smooth:
                    rts_smoother(mu, cov, [F] * len(zn), [Q] * len(zn))

            best = _best({"fp": filterpy, "ts": offline}, repeats)
            us = {k: 1e6 * v / T for k, v in best.items()}
            rows.append(
                [
                    f"one track T = {T:,}, {label}",
                    f"{us['fp']:.1f} µs/step",
                    f"{us['ts']:.2f} µs/step",
                    f"{us['fp'] / us['ts']:.1f}×",
                ]
            )

    table = markdown_table(["case", "filterpy", "torchsvs", "filterpy ÷ torchsvs"], rows)
    text = (
        "# One track: online steps and offline passes against filterpy\n\n"
        f"Generated by `python -m benchmarks.one_track --repeats {args.repeats}`: float64, one "
        "thread, no gradients, the same data for both libraries, best of the repeats "
        "(alternating). Online rows time `est.step` over 2,000 steps (filterpy: `predict` + "
        "`update`); the compiled online step covers linear models (KF, EKF, the SVSF's H⁺ "
        "mode); the tensor path is the same step with it turned off. Offline rows time "
        "`forward` on one track (filterpy: `batch_filter`, `rts_smoother`); the CV model "
        "runs the per-axis compiled loops, the dense model the general path.\n\n"
        f"{table}\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

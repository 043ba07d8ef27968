"""`make bench`: the cost of a training step, compiled (forward loops and their reverse modes in
C++) against the differentiable tensor loops, and its peak memory on long batches.

* One SURE step (the forward pass, SURE's second forward pass on perturbed measurements, the
  backward pass) of an SVSS (finite-difference velocities, lag 5) on 12 recorded flights ×
  400 scans (the ADS-B samples with 100 m noise; seeded random tracks when traffic is not
  installed), float64, compiled and tensor loops alternating in one process.
* Forward + backward ÷ forward of the same step on B = 256 × T = 1,000 tracks, float32.
* Peak resident memory of one such step on T = 10,000 × B = 256, float32 and float64, each in
  a fresh process (``ru_maxrss``), beside the memory before the step.

    python -m benchmarks.training [--repeats 5]

Writes ``benchmarks/training.md``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from benchmarks.timing import alternating_best
from torchsvs.evaluation import markdown_table
from torchsvs.kernels import eager_loops
from torchsvs.training.data import TrackBatch

RESULTS = Path(__file__).with_name("training.md")
SIGMA = 100.0  # m, noise added to the recorded positions


def _batch(B: int, T: int, dtype: torch.dtype, recorded: bool) -> tuple[TrackBatch, str]:
    """A training batch of ``B`` tracks × ``T`` steps with two-point priors rebuilt from ``z``
    (as SURE's second pass needs), and what it holds."""
    from torchsvs.datasets.priors import two_point_prior

    variance = torch.tensor([SIGMA**2, SIGMA**2], dtype=dtype)
    z = dt = None
    label = f"{B} seeded random tracks × {T} steps"
    if recorded:
        try:
            from experiments.flight_data import load_flights, noisy

            flights = noisy(load_flights(), SIGMA)
            longest = flights.lengths.argsort(descending=True)[:B]
            if len(longest) == B and int(flights.lengths[longest].min()) >= T:
                z, dt = flights.z[longest, :T].to(dtype), flights.dt[longest, :T].to(dtype)
                label = f"{B} recorded flights × {T} scans (ADS-B samples, {SIGMA:g} m noise)"
        except (ImportError, FileNotFoundError, ValueError):
            pass
    if z is None or dt is None:
        gen = torch.Generator().manual_seed(0)
        velocity = torch.randn(B, 1, 2, generator=gen, dtype=dtype) * 150
        steps = torch.arange(T, dtype=dtype)[None, :, None] * 5.0
        walk = torch.randn(B, T, 2, generator=gen, dtype=dtype).cumsum(1) * 20
        z = velocity * steps + walk + SIGMA * torch.randn(B, T, 2, generator=gen, dtype=dtype)
        z[:, 5::37] = float("nan")
        dt = torch.full((B, T), 5.0, dtype=dtype)
    prior = two_point_prior(z, dt, variance)
    batch = TrackBatch(z=z, truth=None, x0=prior.x0, P0=prior.P0, dt=dt, prior_var=variance)
    return batch, label


def _svss(dtype: torch.dtype) -> torch.nn.Module:
    from torchsvs.recipes import Settings, make_estimator, make_model

    settings = Settings(estimator="svss", meas_var=[SIGMA**2] * 2, q=1.0, lag=5, interval=5.0)
    return make_estimator(settings, make_model(settings)).to(dtype)


def _step(batch: TrackBatch, backward: bool = True) -> Callable[[], object]:
    """One SURE training step of an SVSS on ``batch`` (forward passes, and backward)."""
    from torchsvs.estimator import threads_for
    from torchsvs.training.module import batch_loss

    dtype = batch.z.dtype
    svss = _svss(dtype)
    meas_cov = torch.eye(2, dtype=dtype) * SIGMA**2
    probes = torch.Generator().manual_seed(0)

    def call() -> object:
        with threads_for(batch.z.shape[0], 4):
            loss, _ = batch_loss(svss, batch, "sure", meas_cov=meas_cov, generator=probes)
            if backward:
                loss.backward()
        return loss

    return call


def _eager(call: Callable[[], object]) -> Callable[[], object]:
    def run() -> object:
        with eager_loops():
            return call()

    return run


def memory_probe(B: int, T: int, dtype: str) -> dict[str, float]:
    """One SURE step in this (fresh) process: peak resident memory and its time."""
    batch, _ = _batch(B, T, getattr(torch, dtype), recorded=False)
    step = _step(batch)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    start = time.perf_counter()
    step()
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return {"before": before, "peak": peak, "seconds": seconds}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--memory-probe", nargs=3, metavar=("B", "T", "DTYPE"))
    args = parser.parse_args(argv)
    if args.memory_probe:
        B, T, dtype = args.memory_probe
        print(json.dumps(memory_probe(int(B), int(T), dtype)))
        return

    torch.set_num_threads(min(2, torch.get_num_threads()))
    small, label = _batch(12, 400, torch.float64, recorded=True)
    sure = alternating_best(
        {
            "compiled": _step(small),
            "compiled, forward only": _step(small, backward=False),
            "tensor loops": _eager(_step(small)),
            "tensor loops, forward only": _eager(_step(small, backward=False)),
        },
        args.repeats,
        progress="SURE step, 12 × 400",
    )
    large, _ = _batch(256, 1000, torch.float32, recorded=False)
    big = alternating_best(
        {"forward + backward": _step(large), "forward": _step(large, backward=False)},
        max(2, args.repeats // 2),
        progress="SURE step, 256 × 1,000",
    )
    memory = {}
    for dtype in ("float32", "float64"):
        command = [sys.executable, "-m", "benchmarks.training", "--memory-probe", "256", "10000"]
        done = subprocess.run([*command, dtype], capture_output=True, text=True, check=True)
        memory[dtype] = json.loads(done.stdout.strip().splitlines()[-1])

    rows = [
        ["SURE step, compiled", f"{sure['compiled'] * 1e3:.1f} ms", "target ≤ 200 ms"],
        ["SURE step, tensor loops", f"{sure['tensor loops'] * 1e3:.1f} ms", ""],
        [
            "tensor loops ÷ compiled",
            f"{sure['tensor loops'] / sure['compiled']:.1f}×",
            "",
        ],
        [
            "forward + backward ÷ forward (12 × 400, compiled)",
            f"{sure['compiled'] / sure['compiled, forward only']:.2f}",
            "target ≤ 3",
        ],
        [
            "forward + backward ÷ forward (12 × 400, tensor loops)",
            f"{sure['tensor loops'] / sure['tensor loops, forward only']:.2f}",
            "",
        ],
        [
            "forward + backward ÷ forward (256 × 1,000 float32, compiled)",
            f"{big['forward + backward'] / big['forward']:.2f}",
            f"{big['forward + backward']:.2f} s a step",
        ],
    ]
    for dtype, probe in memory.items():
        rows.append(
            [
                f"peak memory, T = 10,000 × B = 256, {dtype}",
                f"{probe['peak']:.2f} GB",
                f"{probe['before']:.2f} GB before the step; step {probe['seconds']:.1f} s"
                + (" (target < 4 GB)" if dtype == "float32" else ""),
            ]
        )
    table = markdown_table(["measure", "value", "note"], rows)
    text = (
        "# The cost of a training step\n\n"
        f"Generated by `python -m benchmarks.training --repeats {args.repeats}`. One SURE step "
        "of an SVSS (finite-difference velocities, lag 5): the forward pass, SURE's second "
        "forward pass on perturbed measurements and the backward pass. Small batch: "
        f"{label}, float64, best of {args.repeats} alternating rounds; compiled: the forward "
        "and smoother loops and their reverse modes in C++ (`torchsvs.kernels.fused_axes`); tensor "
        "loops: the same formulas as tensor operations (`torchsvs.kernels.eager_loops()`). "
        "Peak memory: `ru_maxrss` of a fresh process running one step on seeded random tracks.\n\n"
        f"{table}\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""`make bench` (part 7): the Gaussian filters' general step eager and through ``torch.compile``.

The EKF, UKF and SVSF on the ballistic re-entry model (Gadsden et al. 2012, Sec. 5.1: a
nonlinear model, so neither the per-axis kernel nor the dense C++ loops apply and every step is
the general Python step), ``B`` tracks of ``T`` steps, float32 and float64, forward only
(``torch.no_grad``) and forward + backward (gradients of a loss of the means and variances
with respect to the prior mean and the filter's parameters). For each case the compiled steps
(:func:`torchsvs.kernels.compiled_steps`, chunks of 4 steps) are compiled once, then eager
and compiled calls alternate round by round, best of ``--rounds``. Compile time = the first
compiled call minus the best warm one, with inductor's on-disk caches off (a later process with
them warm compiles faster). One intra-op thread throughout (``torch.set_num_threads(1)``; the
library picks one itself for these sizes, ``B·n² < 4096``). Writes
``benchmarks/compiled_steps.md``.

    python -m benchmarks.compiled_steps [--rounds 5] [--steps 300]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch._functorch.config
import torch._inductor.config

import torchsvs as ts
from benchmarks.timing import alternating_best
from torchsvs.evaluation import markdown_table
from torchsvs.kernels import COMPILED_STEPS, compiled, compiled_steps

RESULTS = Path(__file__).with_name("compiled_steps.md")
BATCHES = (1, 100)
DTYPES = {"float64": torch.float64, "float32": torch.float32}
MODES = ("forward", "forward+backward")


def _filters(model: ts.models.BallisticReentry) -> dict[str, torch.nn.Module]:
    return {
        "EKF": ts.ExtendedKalmanFilter(model),
        "UKF": ts.UnscentedKalmanFilter(model),
        "SVSF": ts.SVSF(model, psi=[400.0, 400.0], gamma=0.1),
    }


def _call(est: torch.nn.Module, z: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor, mode: str):
    """A zero-argument call of ``est``: a forward pass, or a forward and backward pass."""
    params = [p for p in est.parameters() if p.requires_grad]

    def forward() -> object:
        with torch.no_grad():
            return est(z, x0, P0)

    def backward() -> object:
        x = x0.clone().requires_grad_(True)
        out = est(z, x, P0)
        loss = out.mean.square().mean() + out.cov.diagonal(dim1=-2, dim2=-1).log().sum()
        return torch.autograd.grad(loss, [x, *params])

    return forward if mode == "forward" else backward


def _compiled(call: Callable[[], object]) -> Callable[[], object]:
    def run() -> object:
        with compiled_steps():
            return call()

    return run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--filters", default="EKF,UKF,SVSF")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch._inductor.config.fx_graph_cache = False  # compile times from scratch
    torch._functorch.config.enable_autograd_cache = False
    names = args.filters.split(",")
    T = args.steps
    rows, records = [], []
    for name in names:
        for dtype_name, dtype in DTYPES.items():
            for B in BATCHES:
                sc = ts.scenarios.ballistic_scenario(
                    B, torch.Generator().manual_seed(0), duration=T / 10, dtype=dtype
                )
                for mode in MODES:
                    est = _filters(sc.model)[name].to(dtype)
                    call = _call(est, sc.z, sc.x0, sc.P0, mode)
                    fast = _compiled(call)
                    start = time.perf_counter()
                    fast()
                    first = time.perf_counter() - start
                    best = alternating_best({"eager": call, "compiled": fast}, args.rounds)
                    compile_s = first - best["compiled"]
                    saved = best["eager"] - best["compiled"]
                    runs = f"{compile_s / saved:.0f}" if saved > 0 else "never"
                    ratio = best["compiled"] / best["eager"]
                    records.append((name, dtype_name, B, mode, ratio))
                    row = [
                        name,
                        dtype_name,
                        str(B),
                        mode,
                        f"{1e6 * best['eager'] / T:.0f}",
                        f"{1e6 * best['compiled'] / T:.0f}",
                        f"{ratio:.2f}×",
                        f"{compile_s:.1f}",
                        runs,
                    ]
                    rows.append(row)
                    print(" | ".join(row), flush=True)
    header = ["filter", "dtype", "B", "pass", "eager (µs/step)", "compiled (µs/step)"]
    header += ["ratio", "compile (s)", "runs to repay"]
    table = markdown_table(header, rows)
    paying = [r for r in records if r[4] < 0.9]
    text = (
        "# Compiled steps\n\n"
        f"Generated by `python -m benchmarks.compiled_steps --rounds {args.rounds} --steps {T}`: "
        "the general predict-correct step of each filter on the ballistic re-entry model, eager "
        "and through `torch.compile` (inductor, `ts.kernels.compiled_steps()`, "
        f"chunks of {COMPILED_STEPS['chunk']} steps per compiled call), {T} steps, eager and "
        f"compiled calls alternating, best of {args.rounds} rounds, one intra-op thread. "
        "Per-step times are a whole call divided by T. Compile time: the first compiled call "
        "minus a warm one, inductor's on-disk caches off; runs to repay: compile time ÷ time "
        "saved per call. Ratio = compiled ÷ eager.\n\n"
        f"{table}\n\n"
        f"Compiling pays (ratio < 0.9) in {len(paying)} of {len(records)} cases; "
        f"{compiled.STATS['compiles']} compilations took {compiled.STATS['seconds']:.0f} s "
        "in all (forward graphs; a backward graph compiles at the first backward pass).\n"
    )
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

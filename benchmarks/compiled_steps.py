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
from torchsvs.kernels import COMPILED_STEPS, compiled_steps

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


HEADER = ["filter", "dtype", "B", "pass", "eager (µs/step)", "compiled (µs/step)", "ratio"]
HEADER += ["compile (s)", "runs to repay"]


def _case(name: str, dtype: torch.dtype, B: int, mode: str, T: int, rounds: int) -> list[str]:
    """One table row: eager and compiled calls of one case, alternating."""
    sc = ts.scenarios.ballistic_scenario(
        B, torch.Generator().manual_seed(0), duration=T / 10, dtype=dtype
    )
    est = _filters(sc.model)[name].to(dtype)
    call = _call(est, sc.z, sc.x0, sc.P0, mode)
    fast = _compiled(call)
    start = time.perf_counter()
    fast()
    first = time.perf_counter() - start
    best = alternating_best({"eager": call, "compiled": fast}, rounds)
    compile_s = first - best["compiled"]
    saved = best["eager"] - best["compiled"]
    return [
        name,
        str(dtype).removeprefix("torch."),
        str(B),
        mode,
        f"{1e6 * best['eager'] / T:.0f}",
        f"{1e6 * best['compiled'] / T:.0f}",
        f"{best['compiled'] / best['eager']:.2f}×",
        f"{compile_s:.1f}",
        f"{compile_s / saved:.0f}" if saved > 0 else "never",
    ]


def _merged(logs: list[Path]) -> list[list[str]]:
    """The rows printed by earlier runs (a benchmark split over processes; a case measured
    twice: the later log's), in the table's order."""
    rows = {}
    for log in logs:
        for line in log.read_text().splitlines():
            cells = line.split(" | ")
            if len(cells) == len(HEADER) and cells[0] in ("EKF", "UKF", "SVSF"):
                rows[tuple(cells[:4])] = cells
    order = [
        (name, dtype, str(B), mode)
        for name in ("EKF", "UKF", "SVSF")
        for dtype in DTYPES
        for B in BATCHES
        for mode in MODES
    ]
    return [rows[case] for case in order if case in rows]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--filters", default="EKF,UKF,SVSF")
    parser.add_argument("--dtypes", default=",".join(DTYPES))
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--merge", type=Path, nargs="+", help="write the table of rows printed by earlier runs"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch._inductor.config.fx_graph_cache = False  # compile times from scratch
    torch._functorch.config.enable_autograd_cache = False
    T = args.steps
    command = f"python -m benchmarks.compiled_steps --rounds {args.rounds} --steps {T}"
    if args.merge:
        rows = _merged(args.merge)
        command = (
            f"{command} --filters NAMES`, one run per filter list, merged by "
            "`python -m benchmarks.compiled_steps --merge LOGS"
        )
    else:
        rows = []
        for name in args.filters.split(","):
            for dtype in (DTYPES[d] for d in args.dtypes.split(",")):
                for B in BATCHES:
                    for mode in MODES:
                        rows.append(_case(name, dtype, B, mode, T, args.rounds))
                        print(" | ".join(rows[-1]), flush=True)
    ratios = [float(row[6].rstrip("×")) for row in rows]
    compile_s = [float(row[7]) for row in rows]
    repay = [int(row[8]) for row in rows if row[8].isdigit()]
    measured = {tuple(row[:4]) for row in rows}
    missing = [
        f"{name} {dtype} B = {B} {mode}"
        for name in args.filters.split(",")
        for dtype in DTYPES
        for B in BATCHES
        for mode in MODES
        if (name, dtype, str(B), mode) not in measured
    ]
    text = (
        "# Compiled steps\n\n"
        f"Generated by `{command}`: the general predict-correct step of each filter on the "
        "ballistic re-entry model, eager and through `torch.compile` (inductor, "
        f"`ts.kernels.compiled_steps()`, chunks of {COMPILED_STEPS['chunk']} steps per compiled "
        f"call), {T} steps, eager and compiled calls alternating, best of {args.rounds} rounds, "
        "one intra-op thread. Per-step times are a whole call divided by T. Compile time: the "
        "first compiled call minus a warm one, inductor's on-disk caches off (forward and, for "
        "forward + backward, the backward graph compiled at the first backward pass); runs to "
        "repay: compile time ÷ time saved per call. Ratio = compiled ÷ eager. The machine "
        "(2 cores) is shared with other jobs: absolute times and compile times vary with its "
        "load (up to 2-4× here), the ratios of alternating calls much less.\n\n"
        f"{markdown_table(HEADER, rows)}\n\n"
        f"Compiled steps are faster in {sum(r < 1 for r in ratios)} of {len(rows)} cases "
        f"(ratio {min(ratios):.2f}-{max(ratios):.2f}×); a compilation takes "
        f"{min(compile_s):.0f}-{max(compile_s):.0f} s, repaid after "
        f"{min(repay)}-{max(repay)} runs of {T} steps.\n"
    )
    if missing:
        text += f"\nNot measured (the run was stopped): {'; '.join(missing)}.\n"
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""`make bench`: the covariance forms (``covariance_form=``) of the KF and the SVSF, their cost
and their agreement with the Joseph form.

Speed: nanoseconds per track-step of each form on the papers' 2-D constant-velocity problem
(:class:`benchmarks.common.CVProblem`, per-track priors ``P0 [B, 4, 4]``, no gradients, the
result's means and covariances kept), float32 and float64, beside the Joseph form measured in
the same run, alternating round by round: by default (its per-axis kernel and compiled loops)
and on the general step loop the factored forms run (``general_path()`` + ``eager_loops()``),
the ratio to which is the cost of the form itself. The largest differences from the Joseph
filter's means and covariances (its default path) are printed beside.

Robustness (the ill-conditioned example, δ swept) is ``experiments/ksvd_paper.py``'s.

    python -m benchmarks.covariance_forms [--tracks 1,100,10000] [--steps 1000,1000,10]

Writes ``benchmarks/covariance_forms.md``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import torch

import torchsvs as ts
from benchmarks.common import CVProblem
from benchmarks.timing import alternating_best
from torchsvs.evaluation import markdown_table
from torchsvs.kernels import eager_loops, general_path

RESULTS = Path(__file__).with_name("covariance_forms.md")
FORMS = ("conventional", "sqrt", "ud", "svd")
JOSEPH, GENERAL = "joseph (default path)", "joseph (general loop)"


def _filter(kind: str, model: torch.nn.Module, form: str) -> ts.filters.GaussianFilter:
    if kind == "KF":
        return ts.KalmanFilter(model, covariance_form=form)
    return ts.SVSF(model, psi=[800.0, 800.0], gamma=0.1, artificial=None, covariance_form=form)


def _timed_forms(
    kind: str, z: torch.Tensor, x0: torch.Tensor, P0: torch.Tensor, repeats: int
) -> tuple[dict[str, float], dict[str, ts.FilterResult]]:
    """Seconds per pass of every form of ``kind`` on ``z`` (alternating rounds) and the last
    result of each."""
    estimators = {
        name: _filter(kind, CVProblem.make_model(), "joseph" if name in (JOSEPH, GENERAL) else name)
        for name in (JOSEPH, GENERAL, *FORMS)
    }

    def call(name: str) -> Callable[[], ts.FilterResult]:
        est = estimators[name].to(z.dtype)

        def run() -> ts.FilterResult:
            with torch.no_grad():
                if name == GENERAL:
                    with general_path(), eager_loops():
                        return est(z, x0, P0, keep="moments")
                return est(z, x0, P0, keep="moments")

        return run

    outputs: dict[str, ts.FilterResult] = {}

    def inspect(name: str, out: object) -> None:
        outputs[name] = out  # type: ignore[assignment]

    timed = alternating_best({name: call(name) for name in estimators}, repeats, inspect=inspect)
    return timed, outputs


def speed_rows(B: int, T: int, repeats: int) -> list[list[object]]:
    """One row per filter, dtype and form at ``B`` tracks × ``T`` steps."""
    problem = CVProblem(B, T)
    rows: list[list[object]] = []
    for dtype in (torch.float32, torch.float64):
        z = problem.z_as(dtype)
        x0, P0 = problem.x0.to(dtype), problem.per_track_P0(dtype)
        for kind in ("KF", "SVSF"):
            timed, outputs = _timed_forms(kind, z, x0, P0, repeats)
            reference = outputs[JOSEPH]
            for name, seconds in timed.items():
                out = outputs[name]
                rows.append(
                    [
                        kind,
                        str(dtype).removeprefix("torch."),
                        f"{B:,} × {T:,}",
                        name,
                        f"{1e9 * seconds / (B * T):,.0f}",
                        f"{seconds / timed[JOSEPH]:.1f}×",
                        f"{seconds / timed[GENERAL]:.2f}×",
                        f"{(out.mean - reference.mean).abs().max().item():.1e}",
                        f"{(out.cov - reference.cov).abs().max().item():.1e}",
                    ]
                )
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", default="1,100,10000")
    parser.add_argument("--steps", default="1000,1000,10")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    sizes = list(
        zip(map(int, args.tracks.split(",")), map(int, args.steps.split(",")), strict=True)
    )

    header = [
        "filter",
        "dtype",
        "B × T",
        "form",
        "ns / track-step",
        "÷ joseph",
        "÷ joseph general",
        "max |Δ mean|",
        "max |Δ cov|",
    ]
    speed: list[list[object]] = []
    for B, T in sizes:
        print(f"B = {B}, T = {T}")
        speed += speed_rows(B, T, args.repeats)
    sizes_text = ", ".join(f"B = {B:,} × T = {T:,}" for B, T in sizes)
    text = (
        "# Covariance forms: cost and robustness\n\n"
        f"Generated by `python -m benchmarks.covariance_forms --tracks {args.tracks} --steps "
        f"{args.steps} --repeats {args.repeats}`: torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, a 2-core machine shared with other jobs; best of "
        "the rounds, the forms alternating. The constant-velocity problem of "
        f"`benchmarks/common.py` ({sizes_text}; the largest batch over fewer steps: the general "
        "step loop costs a tenth of a second or more per step there, and the run is kept "
        "to a few minutes), per-track priors, "
        "`keep='moments'`, no gradients. *÷ joseph*: time over the Joseph form's default path "
        "(the per-axis kernel's compiled loop for these models); *÷ joseph general*: over "
        "the Joseph form on the general step loop (`general_path()`, `eager_loops()`), the "
        "loop every other form runs, so the cost of the form itself. *max |Δ|*: largest "
        "difference from the Joseph filter's means and covariances (default path, same "
        "dtype; covariances of order 10⁴, means 10⁴-10⁵). The SVSF's means do not depend on "
        "the covariance; its conventional covariance is Eq. (28)'s printed right side, not "
        "the SVSF's covariance, hence its large Δ.\n\n"
        f"{markdown_table(header, speed)}\n\n"
        "Which form survives how ill-conditioned an update (the δ sweep of Example 1 of "
        "Bermúdez Ordoñez et al. 2020) is in `experiments/results/ksvd_paper.md` "
        "(`make ksvd`).\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

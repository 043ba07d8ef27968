"""`make bench` (part 4): the step protocol's cost, against the code before it, in one run.

Every filter's ``forward`` is ``init``, a loop of ``step`` and one stack since the step protocol
(issue 12). This benchmark extracts the last commit before it (:data:`BASELINE`) from git into
a temporary directory, imports it beside the current package and times the same forward
passes with both, alternating call by call (so a busy machine slows both alike), best of
``--rounds``. Cases run on the general (dense-matrix) path as tensor operations, where the
step loop is (no per-axis kernel, no compiled loops); the per-axis kernel row runs as the
estimators choose. Writes ``benchmarks/step_overhead.md``.

    python -m benchmarks.step_overhead [--rounds 15]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch

from benchmarks.timing import alternating_best

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).with_name("step_overhead.md")
#: The last commit before the step protocol: "Threads chosen by problem size".
BASELINE = "7da37d2"


def _cases(ts: ModuleType) -> dict[str, Callable[[], object]]:
    """name → a zero-argument forward pass, built with the torchsvs package ``ts``."""
    kernels = importlib.import_module(ts.__name__ + ".kernels")
    general_path, eager_loops = kernels.general_path, kernels.eager_loops
    gen = torch.Generator().manual_seed(0)
    cv = ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2)
    x0 = torch.tensor([-25000.0, 120.0, -10000.0, 0.0], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([1e4, 1e3, 1e4, 1e3], dtype=torch.float64))
    B, T = 64, 300
    states = [x0.expand(B, 4)]
    F = cv.transition()
    for _ in range(T):
        states.append(states[-1] @ F.mT + torch.randn(B, 4, generator=gen, dtype=torch.float64))
    truth = torch.stack(states[1:], 1)
    z = truth[..., [0, 2]] + 200.0 * torch.randn(B, T, 2, generator=gen, dtype=torch.float64)
    z[:, 50:60, 0] = float("nan")
    sc = ts.scenarios.ballistic_scenario(16, torch.Generator().manual_seed(0), duration=10.0)

    def general(est: torch.nn.Module, *args: object, **kwargs: object) -> Callable[[], object]:
        def call() -> object:
            with torch.no_grad(), general_path(), eager_loops():
                return est(*args, **kwargs)

        return call

    def chosen(est: torch.nn.Module, *args: object) -> Callable[[], object]:
        def call() -> object:
            with torch.no_grad():
                return est(*args)

        return call

    def seeded() -> dict[str, torch.Generator]:
        return {"generator": torch.Generator().manual_seed(1)}

    ballistic = (sc.z, sc.x0, sc.P0)
    svsf_fd = ts.SVSF(cv, psi=[800.0, 600.0, 800.0, 600.0])
    return {
        "KF, CV, B = 64, T = 300": general(ts.KalmanFilter(cv), z, x0, P0),
        "EKF, CV": general(ts.ExtendedKalmanFilter(cv), z, x0, P0),
        "UKF, CV": general(ts.UnscentedKalmanFilter(cv), z, x0, P0),
        "SVSF H⁺ mode, CV": general(ts.SVSF(cv, psi=[800.0, 800.0], artificial=None), z, x0, P0),
        "SVSF artificial velocity, CV": general(svsf_fd, z, x0, P0),
        "RSTKF, CV": general(ts.filters.RobustStudentTKalmanFilter(cv), z, x0, P0),
        "EKF, ballistic, B = 16, T = 100": general(ts.ExtendedKalmanFilter(sc.model), *ballistic),
        "SVSF, ballistic": general(ts.SVSF(sc.model, psi=[400.0, 400.0]), *ballistic),
        "PF 200 particles, ballistic": general(
            ts.ParticleFilter(sc.model, num_particles=200), *ballistic, **seeded()
        ),
        "SPVSF 200 particles, ballistic": general(
            ts.SPVSF(sc.model, psi=[400.0, 400.0], num_particles=200), *ballistic, **seeded()
        ),
        "KF per-axis kernel, CV, B = 64, T = 300": chosen(ts.KalmanFilter(cv), z, x0, P0),
    }


def _load_baseline(into: Path) -> ModuleType:
    """The torchsvs package of :data:`BASELINE`, extracted under ``into`` and imported beside
    the current one (its modules renamed ``torchsvs_baseline``)."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", BASELINE, "torchsvs"],
        check=True,
        capture_output=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    package = into / "torchsvs_baseline"
    (into / "torchsvs").rename(package)
    for source in package.rglob("*.py"):  # the package's absolute imports of itself
        text = source.read_text()
        for old in ("from torchsvs.", "from torchsvs import", "import torchsvs."):
            text = text.replace(old, old.replace("torchsvs", "torchsvs_baseline"))
        source.write_text(text)
    # Loaded from its folder by name (no sys.path edit): its submodules import through the
    # package's __path__.
    spec = importlib.util.spec_from_file_location(
        "torchsvs_baseline", package / "__init__.py", submodule_search_locations=[str(package)]
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["torchsvs_baseline"] = module
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    args = parser.parse_args(argv)
    import torchsvs
    from torchsvs.evaluation import markdown_table

    with tempfile.TemporaryDirectory() as tmp:
        try:
            baseline = _load_baseline(Path(tmp))
        except (OSError, subprocess.CalledProcessError) as err:
            print(f"step overhead: skipped, the baseline {BASELINE} needs a git clone ({err})")
            return
        versions = {"before": _cases(baseline), "now": _cases(torchsvs)}
        # Each case before and now in turn, so noise hits both alike.
        names = list(versions["now"])
        calls = {(label, name): versions[label][name] for name in names for label in versions}
        timed = alternating_best(calls, args.rounds, progress="rounds")
        best = {label: {name: timed[label, name] for name in names} for label in versions}
    rows = []
    for name, now in best["now"].items():
        old = best["before"][name]
        rows.append([name, f"{1e3 * old:.1f}", f"{1e3 * now:.1f}", f"{now / old:.2f}×"])
    ratios = [best["now"][n] / best["before"][n] for n in best["now"]]
    table = markdown_table(["forward pass", "before (ms)", "step protocol (ms)", "ratio"], rows)
    text = (
        "# The step protocol's cost\n\n"
        f"Generated by `python -m benchmarks.step_overhead --rounds {args.rounds}`: the same "
        f"forward passes with the code before the step protocol (commit {BASELINE}) and now, "
        "alternating call by call in one process, best of the rounds, float64, the estimators' "
        "default threads. Ratio = step protocol ÷ before (≤ 1.1 is the target).\n\n"
        f"{table}\n\nLargest ratio: {max(ratios):.2f}×; median "
        f"{sorted(ratios)[len(ratios) // 2]:.2f}×.\n"
    )
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""The ``torchsvs`` command line.

    torchsvs demo [--epochs 4] [--runs 500]           learn ψ, γ; track Chen et al. 2020's scenarios
    torchsvs reproduce svss [--runs 500] [--seed 0]   Tables 1-3, A2 and Figs 4-9 of that paper
    torchsvs reproduce spvsf [--runs 100]             Tables 1, 2, 4, 5, Figs 5-9 of Gadsden 2012
    torchsvs fit --config CONFIG.yaml                 train an estimator (LightningCLI)

The experiments are scripts of the source checkout (``experiments/``), not of the installed
library: the command runs them from the clone that ``pip install -e .`` installed.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

COMMANDS = {
    "demo": ("experiments.demo", "learn ψ, γ, then track the scenarios of Chen et al. 2020"),
    "reproduce svss": ("experiments.svss_paper", "Chen et al. 2020: Tables 1-3, A2, Figs 4-9"),
    "reproduce spvsf": (
        "experiments.spvsf_paper",
        "Gadsden et al. 2012: Tables 1, 2, 4, 5, Figs 5-9",
    ),
}


def _import_experiment(module: str) -> ModuleType:
    root = Path(__file__).resolve().parents[1]
    if not (root / "experiments" / "__init__.py").is_file():
        raise SystemExit(
            "torchsvs: the experiments are part of the source checkout (experiments/); "
            "install torchsvs from a clone with `pip install -e .` to run them"
        )
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module(module)


def main(argv: list[str] | None = None) -> None:
    """Dispatches ``torchsvs COMMAND [options]`` to the experiment's own ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["fit"]:
        from torchsvs.training.cli import main as fit

        fit(args[1:])
        return
    for words in sorted(COMMANDS, key=len, reverse=True):
        size = len(words.split())
        if args[:size] == words.split():
            _import_experiment(COMMANDS[words][0]).main(args[size:])
            return
    usage = "\n".join(f"  torchsvs {k:<16} {v[1]}" for k, v in COMMANDS.items())
    usage += "\n  torchsvs fit --config CONFIG.yaml   train an estimator (LightningCLI)"
    print(f"usage: torchsvs COMMAND [options]\n\ncommands:\n{usage}", file=sys.stderr)
    raise SystemExit(2)


if __name__ == "__main__":
    main()

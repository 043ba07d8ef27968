"""The ``torchsvs`` command line.

    torchsvs demo [--runs 500] [--seed 0]   the ATC comparison of Chen et al. 2020, Table 1

The experiments are scripts of the source checkout (``experiments/``), not of the installed
library: the command runs them from the clone that ``pip install -e .`` installed.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from types import ModuleType

COMMANDS = {"demo": ("experiments.demo", "the ATC scenario of Chen et al. 2020 beside Table 1")}


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
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="torchsvs", description="torchsvs experiments")
    parser.add_argument(
        "command",
        choices=sorted(COMMANDS),
        help="; ".join(f"{k}: {v[1]}" for k, v in COMMANDS.items()),
    )
    args, rest = parser.parse_known_args(argv)
    _import_experiment(COMMANDS[args.command][0]).main(rest)


if __name__ == "__main__":
    main()

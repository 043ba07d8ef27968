"""The ``torchsvs`` command line.

    torchsvs fit --config CONFIG.yaml                 train an estimator (LightningCLI)
    torchsvs track INPUT -o OUTPUT [--estimator svss] [--fit] [--processes 2] ...
                                                      estimate every track of a CSV/Parquet file

The demo and the papers' reproductions are scripts of the source checkout, not commands of the
installed library: ``make demo``, ``make reproduce`` or ``python -m experiments.NAME`` in a clone.
"""

from __future__ import annotations

import atexit
import os
import sys

#: The commands ``torchsvs`` lists: name → (arguments, what it does). Each runs from an installed
#: wheel alone (``tests/test_cli.py`` checks every one's ``--help`` without the checkout).
COMMANDS = {
    "fit": ("--config CONFIG.yaml", "train an estimator (LightningCLI)"),
    "track": ("INPUT -o OUTPUT", "estimate every track of a file"),
}


def usage() -> str:
    lines = [
        f"  torchsvs {f'{name} {words}':<28} {what}" for name, (words, what) in COMMANDS.items()
    ]
    return (
        "usage: torchsvs COMMAND [options]\n\ncommands:\n"
        + "\n".join(lines)
        + "\n\n`torchsvs COMMAND --help` lists a command's options.\nThe demo and the papers' "
        "reproductions run from a clone: make demo, make reproduce."
    )


def main(argv: list[str] | None = None) -> None:
    """Dispatches ``torchsvs COMMAND [options]`` to the command's own ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        print(usage(), file=sys.stderr)
        raise SystemExit(2)
    if args[:1] in (["-h"], ["--help"], ["help"]):
        print(usage())  # asked for: standard output, success
        return
    if args[:1] == ["fit"]:
        from torchsvs.training.cli import main as fit

        fit(args[1:])
        return
    if args[:1] == ["track"]:
        from torchsvs.track_command import track

        track(args[1:])
        return
    print(f"torchsvs: unknown command {args[0]!r}\n\n{usage()}", file=sys.stderr)
    raise SystemExit(2)


def command() -> None:
    """The ``torchsvs`` program: :func:`main`, then an exit that skips tearing down the
    interpreter's modules (torch, Lightning: about a second, paid by every process of a run)
    once the exit handlers have run and the output is flushed."""
    if sys.argv[1:2] == ["track"]:
        from torchsvs.track_command import set_up_process

        set_up_process()
    try:
        main()
        code = 0
    except SystemExit as stop:
        if stop.code is not None and not isinstance(stop.code, int):
            print(stop.code, file=sys.stderr)
        code = stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 1
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    command()

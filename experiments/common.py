"""What the experiments share: one command line (compute → figures → report) and the reports'
prose, which lives in markdown templates (``experiments/templates/NAME.md``), not in code.

An experiment computes its results, draws its figures from them and fills its template with
the numbers and tables it formats; :func:`main` runs those three steps behind the options
every experiment takes (``--runs`` with the experiment's default, ``--seed``, ``--out``).
"""

from __future__ import annotations

import argparse
import re
import string
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

#: Where ``python -m experiments.NAME`` writes its report: the tracked results of the checkout.
RESULTS = Path(__file__).parent / "results"
#: The reports' prose, one markdown file per experiment.
TEMPLATES = Path(__file__).parent / "templates"

#: A template file is split into sections by lines of this form; text before the first is
#: a comment for the reader of the template and is not rendered.
_SECTION = re.compile(r"^<!-- section: (\w+) -->\n", re.MULTILINE)

Results = TypeVar("Results")


def template(name: str) -> dict[str, string.Template]:
    """The sections of ``templates/NAME.md`` by name, each a :class:`string.Template`
    (placeholders ``$field`` or ``${field}``; ``$$`` is a dollar sign). A section runs from
    its ``<!-- section: KEY -->`` line to the next one; the newline that ends it is not its
    own (the code that joins sections says where lines break)."""
    path = TEMPLATES / f"{name}.md"
    if not path.is_file():
        raise ValueError(f"name: expected a template in {TEMPLATES}, found no {path.name}")
    parts = _SECTION.split(path.read_text())
    if len(parts) < 3:
        raise ValueError(f"name: {path} has no '<!-- section: KEY -->' line")
    keys, bodies = parts[1::2], parts[2::2]
    return {k: string.Template(b.removesuffix("\n")) for k, b in zip(keys, bodies, strict=True)}


def render(name: str, section: str, **fields: object) -> str:
    """Section ``section`` of ``templates/NAME.md`` with its placeholders filled; a missing
    field raises KeyError, so the prose and the code cannot drift apart silently."""
    return template(name)[section].substitute(fields)


def main(
    name: str,
    doc: str | None,
    compute: Callable[[argparse.Namespace], Results],
    figures: Callable[[Results, Path], list[str]],
    report: Callable[[Results, list[str]], str],
    *,
    runs: int,
    runs_help: str = "Monte Carlo runs",
    options: Callable[[argparse.ArgumentParser], object] | None = None,
    argv: Sequence[str] | None = None,
    out: Path = RESULTS,
) -> Results:
    """The command line of experiment ``name``: parses ``--runs`` (default ``runs``),
    ``--seed``, ``--out`` (default ``out``) and the experiment's own ``options``, then
    ``compute(args)`` → ``figures(results, out)`` (the PNGs' names) → ``report(results,
    pngs)``, writes the report to ``OUT/NAME.md`` and prints it and where it went."""
    import torch

    parser = argparse.ArgumentParser(
        prog=f"python -m experiments.{name}",
        description=(doc or name).splitlines()[0],
    )
    parser.add_argument("--runs", type=int, default=runs, help=f"{runs_help} (default {runs})")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--out", type=Path, default=out, help=f"where the report and figures go (default {out})"
    )
    if options is not None:
        options(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # small tensors in step loops; the machine is shared
    args.out.mkdir(parents=True, exist_ok=True)
    results = compute(args)
    pngs = figures(results, args.out)
    text = report(results, pngs)
    path = args.out / f"{name}.md"
    path.write_text(text)
    print(text)
    print(f"written: {path}" + (f" and {', '.join(pngs)}" if pngs else ""))
    return results

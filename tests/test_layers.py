"""The layers of tracking import each other one way only: recipes ← fitting, estimating ←
tracking ← training (issue 29, item 7). Read off the source (every ``import`` of ``torchsvs.*``,
at module level or inside a function), so a loop hidden in a function is caught too."""

from __future__ import annotations

import ast
import os
import pkgutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import torchsvs

#: The modules whose imports must form no loop (a name ending in ``.`` is a package's modules).
LAYERS = (
    "torchsvs.recipes",
    "torchsvs.estimating",
    "torchsvs.selection",
    "torchsvs.fitting",
    "torchsvs.track_run",
    "torchsvs.tracking",
)
LAYER_PACKAGES = ("torchsvs.fitting.", "torchsvs.training.")


def _modules(root: Path) -> dict[str, Path]:
    """Every module of the package at ``root`` (a package's ``__init__`` under its own name)."""
    found = {"torchsvs": root / "__init__.py"}
    folders = [(root, "torchsvs")]
    while folders:  # pkgutil.walk_packages would import the packages (of this checkout)
        folder, prefix = folders.pop()
        for info in pkgutil.iter_modules([str(folder)]):
            name = f"{prefix}.{info.name}"
            if info.ispkg:
                found[name] = folder / info.name / "__init__.py"
                folders.append((folder / info.name, name))
            else:
                found[name] = folder / f"{info.name}.py"
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imported(path: Path, name: str) -> list[tuple[str, list[str]]]:
    """What ``name``'s import statements name when it runs, at any depth but under ``if
    TYPE_CHECKING:`` (never run): ``(module, [])`` for ``import module``, ``(base, names)`` for
    ``from base import names`` (relative bases made absolute)."""
    tree = ast.parse(path.read_text(), str(path))
    skipped = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and _is_type_checking(node)
        for statement in node.body
        for inner in ast.walk(statement)
    }
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, list[str]]] = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found.append((base, [a.name for a in node.names]))
    return found


def _imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """The torchsvs modules ``name`` imports when it runs (:func:`_imported`); ``from a import
    b`` is ``a.b`` where that is a module, and a module's package counts as imported with it."""
    targets: set[str] = set()
    for base, names in _imported(path, name):
        targets.add(base)
        targets.update(f"{base}.{alias}" for alias in names)
    edges = set()
    for target in targets:
        # importing a.b.c runs a.b's __init__ too (the root package aside: everything is in it)
        while target.count("."):
            if target in modules and target != name:
                edges.add(target)
            target = target.rpartition(".")[0]
    return edges


def _in_layers(name: str) -> bool:
    return name in LAYERS or name.startswith(LAYER_PACKAGES) or name == "torchsvs.training"


def layer_loops(root: Path) -> list[list[str]]:
    """The loops of imports through a layer module of the package at ``root``, a module's
    package counted as imported with it (:func:`_imports`: what running the import runs)."""
    return [loop for loop in module_loops(root, _imports) if any(map(_in_layers, loop))]


def test_the_tracking_layers_import_one_way():
    # TORCHSVS_LAYERS_ROOT: check another tree's package (e.g. another checkout's torchsvs/)
    root = Path(os.environ.get("TORCHSVS_LAYERS_ROOT", Path(torchsvs.__file__).parent))
    loops = layer_loops(root)
    assert loops == [], f"import loops: {loops}"


def test_a_loop_inside_a_function_is_found(tmp_path):
    """The check can fail: a function-level import back up the layers is a loop."""
    package = tmp_path / "torchsvs"
    (package / "fitting").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "fitting" / "__init__.py").write_text('"""lazy"""\n')
    (package / "recipes.py").write_text("X = 1\n")
    (package / "fitting" / "tuning.py").write_text(
        "from torchsvs.recipes import X\n\ndef f():\n    from torchsvs.tracking import Y\n"
    )
    (package / "tracking.py").write_text("from torchsvs.fitting import tuning\nY = 2\n")
    assert layer_loops(package) == [["torchsvs.fitting.tuning", "torchsvs.tracking"]]
    (package / "fitting" / "tuning.py").write_text("from torchsvs.recipes import X\n")
    assert layer_loops(package) == []


def test_fitting_needs_no_lightning():
    """``torchsvs.fitting`` imports none of its parts eagerly and none of them Lightning: the
    truth-free fit of ``torchsvs track`` runs without it (~2 s of imports)."""
    code = (
        "import sys, torchsvs.fitting.noise; "
        "print('lightning' in sys.modules, 'torchsvs.fitting.tuning' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(torchsvs.__file__).parents[1],
    )
    assert out.stdout.split() == ["False", "False"]


def _direct_imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """The torchsvs modules ``name`` names in its imports, each the most specific one
    (``from a.b import c`` is ``a.b.c`` where that is a module, else ``a.b``): a package's
    ``__init__`` counts only where it is imported itself."""
    found: set[str] = set()
    for base, names in _imported(path, name):
        found.update(f"{base}.{a}" if f"{base}.{a}" in modules else base for a in names)
        if not names:
            found.add(base)
    return {target for target in found if target in modules and target != name}


Edges = Callable[[Path, str, dict[str, Path]], set[str]]


def module_loops(root: Path, edges: Edges | None = None) -> list[list[str]]:
    """Every set of modules of the package at ``root`` that import each other in a loop (the
    strongly connected components of more than one module, Tarjan's algorithm), by the import
    edges ``edges`` reads (default :func:`_direct_imports`)."""
    edges = edges or _direct_imports
    modules = _modules(root)
    graph = {name: edges(path, name, modules) for name, path in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    loops: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                loops.append(sorted(component))

    for name in sorted(graph):
        if name not in index:
            visit(name)
    return loops


def test_no_module_imports_itself_through_others():
    """No import loop anywhere in the package (issue 30), at module level or in a function."""
    assert module_loops(Path(torchsvs.__file__).parent) == []


def test_a_loop_between_two_modules_is_found(tmp_path):
    package = tmp_path / "torchsvs"
    (package / "kernels").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "kernels" / "__init__.py").write_text("")
    (package / "kernels" / "axes.py").write_text("def f():\n    from . import scan\n")
    (package / "kernels" / "scan.py").write_text("from torchsvs.kernels.axes import f\n")
    assert module_loops(package) == [["torchsvs.kernels.axes", "torchsvs.kernels.scan"]]
    (package / "kernels" / "axes.py").write_text("def f():\n    pass\n")
    assert module_loops(package) == []


#: The longest a Python file of the package may be (issue 30: one idea per file).
MAX_LINES = 600


def test_no_python_file_of_the_package_is_over_the_limit():
    root = Path(torchsvs.__file__).parent
    long = {
        str(path.relative_to(root)): lines
        for path in root.rglob("*.py")
        if (lines := len(path.read_text(encoding="utf-8").splitlines())) > MAX_LINES
    }
    assert not long, f"over {MAX_LINES} lines: {long}"

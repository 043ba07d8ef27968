"""The ``torchsvs`` command line: help, unknown commands, and every listed command runs from
the package alone (as from an installed wheel, without the checkout's experiments/)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchsvs import cli

ROOT = Path(__file__).resolve().parents[1]


def test_help_goes_to_standard_output_and_succeeds(capsys):
    for flag in ("--help", "-h", "help"):
        cli.main([flag])
        out, err = capsys.readouterr()
        assert out.startswith("usage: torchsvs COMMAND") and err == ""
        for command in ("fit", "track"):
            assert f"torchsvs {command} " in out
        # the checkout's scripts are not commands of the installed CLI
        assert "torchsvs demo" not in out and "torchsvs reproduce" not in out


def test_no_command_and_unknown_commands_fail_on_standard_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([])
    assert exit_info.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage:")
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["trak"])
    assert exit_info.value.code == 2
    assert "unknown command 'trak'" in capsys.readouterr().err


def _package_alone(tmp_path: Path) -> dict[str, str]:
    """An environment whose ``torchsvs`` is a copy of the package alone (no experiments/,
    benchmarks/, tests/ beside it), as a wheel installs it."""
    site = tmp_path / "site"
    shutil.copytree(
        ROOT / "torchsvs", site / "torchsvs", ignore=shutil.ignore_patterns("__pycache__")
    )
    return dict(os.environ, PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE="1")


#: Run in one interpreter (the imports of ``fit``, Lightning's, take most of the time): where
#: torchsvs comes from, whether ``experiments`` can be imported, and each listed command's exit
#: code and usage with ``--help``.
LISTED_COMMANDS_HELP = """
import contextlib, importlib.util, io, torchsvs
from torchsvs import cli
print(torchsvs.__file__)
print(importlib.util.find_spec("experiments"))
help = io.StringIO()
with contextlib.redirect_stdout(help):
    cli.main(["--help"])
for line in help.getvalue().splitlines():
    if line.startswith("  torchsvs "):
        name = line.split()[1]
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                cli.main([name, "--help"])
                code = 0
            except SystemExit as stop:
                code = stop.code
        print(name, code, out.getvalue().startswith("usage:") and "--help" in out.getvalue())
"""


def test_every_listed_command_runs_from_the_package_alone(tmp_path):
    """Each command ``torchsvs --help`` lists prints its own usage from a copy of the package
    run outside the checkout, where ``experiments`` cannot be imported (a command that needed
    the checkout, as ``demo`` and ``reproduce`` did, fails here)."""
    work = tmp_path / "elsewhere"
    work.mkdir()
    run = subprocess.run(
        [sys.executable, "-c", LISTED_COMMANDS_HELP],
        cwd=work,
        env=_package_alone(tmp_path),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    where, experiments, *commands = run.stdout.splitlines()
    assert where == str(tmp_path / "site" / "torchsvs" / "__init__.py")
    assert experiments == "None"
    assert commands == [f"{name} 0 True" for name in cli.COMMANDS]


def test_a_built_wheel_ships_the_fit_configs(tmp_path):
    """A non-editable install has the configs of `torchsvs fit --config NAME` (package data).
    The wheel is built from a copy of the package so the checkout gets no build/ or egg-info."""
    import zipfile

    from torchsvs.training import shipped_configs

    pytest.importorskip("setuptools", minversion="77")  # pyproject's build-system, no isolation
    root = Path(__file__).resolve().parents[1]
    src = tmp_path / "src"
    shutil.copytree(
        root / "torchsvs", src / "torchsvs", ignore=shutil.ignore_patterns("__pycache__")
    )
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(root / name, src / name)
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation"]
    command += ["--no-index", "--quiet", "-w", str(tmp_path / "dist"), str(src)]
    subprocess.run(command, check=True, timeout=120)
    (wheel,) = (tmp_path / "dist").glob("torchsvs-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert shipped_configs() == ["atc_svss", "complex_svss"]
    for config in shipped_configs():
        assert f"torchsvs/training/configs/{config}.yaml" in names


def test_track_threads_default_to_the_cores_shared_by_the_processes():
    from torchsvs.track_command import default_threads

    cores = len(os.sched_getaffinity(0))
    assert default_threads() == cores
    assert default_threads(2) == max(1, cores // 2)
    assert default_threads(10 * cores) == 1

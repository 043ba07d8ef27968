"""The ``torchsvs`` command line: help, unknown commands, subcommand usage, where reports go."""

from __future__ import annotations

from pathlib import Path

import pytest

from torchsvs import cli


def test_help_goes_to_standard_output_and_succeeds(capsys):
    for flag in ("--help", "-h", "help"):
        cli.main([flag])
        out, err = capsys.readouterr()
        assert out.startswith("usage: torchsvs COMMAND") and err == ""
        for command in ("demo", "reproduce svss", "reproduce spvsf", "fit", "track"):
            assert f"torchsvs {command}" in out


def test_no_command_and_unknown_commands_fail_on_standard_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([])
    assert exit_info.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage:")
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["reproduc"])
    assert exit_info.value.code == 2
    assert "unknown command 'reproduc'" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["demo", "reproduce svss", "reproduce spvsf"])
def test_subcommand_usage_names_the_subcommand_and_explains_options(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*command.split(), "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: torchsvs {command} ")
    assert "--seed SEED" in out and "random seed" in out
    assert "--runs RUNS" in out and "Monte Carlo runs" in out


def test_reproduce_writes_outside_the_checkout_by_default(monkeypatch, tmp_path):
    """Without --out the report goes to ./torchsvs-results/<paper>, never into the tracked
    experiments/results/ of the checkout."""
    seen = {}

    class Experiment:
        @staticmethod
        def main(argv, prog=None, out=None):
            seen.update(argv=argv, prog=prog, out=out)

    monkeypatch.setattr(cli, "_import_experiment", lambda module: Experiment)
    cli.main(["reproduce", "svss", "--runs", "3"])
    assert seen == {
        "argv": ["--runs", "3"],
        "prog": "torchsvs reproduce svss",
        "out": Path("torchsvs-results") / "svss",
    }
    from experiments import svss_paper

    assert svss_paper.RESULTS == Path(svss_paper.__file__).parent / "results"  # python -m


def test_an_installed_package_without_the_checkout_says_what_is_needed(monkeypatch, tmp_path):
    """A non-editable install has no experiments/: the experiment commands say so (checked by
    hand with `pip install --target`; `track`, `fit` and `--help` work there)."""
    package = tmp_path / "site-packages" / "torchsvs"
    package.mkdir(parents=True)
    monkeypatch.setattr(cli, "__file__", str(package / "cli.py"))
    with pytest.raises(
        SystemExit, match=r"experiments are part of the source checkout.*pip install -e"
    ):
        cli.main(["reproduce", "svss"])


def test_a_built_wheel_ships_the_fit_configs(tmp_path):
    """A non-editable install has the configs of `torchsvs fit --config NAME` (package data).
    The wheel is built from a copy of the package so the checkout gets no build/ or egg-info."""
    import shutil
    import subprocess
    import sys
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

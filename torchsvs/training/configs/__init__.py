"""The LightningCLI configs shipped with torchsvs (installed with the package, not only in a
checkout): ``torchsvs fit --config NAME`` with a name of :func:`shipped_configs`.

* ``atc_svss``: an SVSS (lag 1) for the ATC sensor of Chen et al. 2020, Sec 4.1.
* ``complex_svss``: an SVSS (lag 1) with artificial velocity for the complex-maneuver sensor of
  Chen et al. 2020, Sec 4.2.
"""

from __future__ import annotations

from pathlib import Path

CONFIGS = Path(__file__).resolve().parent


def shipped_configs() -> list[str]:
    """The names of the shipped configs (file names without ``.yaml``), sorted."""
    return sorted(path.stem for path in CONFIGS.glob("*.yaml"))


def config_path(name: str) -> Path:
    """The file of a shipped config, by name with or without ``.yaml``, e.g. ``"atc_svss"``.

    Raises:
        ValueError: ``name`` is not a shipped config (the message lists those that are).
    """
    stem = name.removesuffix(".yaml")
    if stem not in shipped_configs():
        raise ValueError(
            f"no shipped config named {name!r}; shipped configs: {', '.join(shipped_configs())}"
        )
    return CONFIGS / f"{stem}.yaml"

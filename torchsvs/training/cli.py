"""``torchsvs fit``: train an estimator with LightningCLI from a YAML config.

    torchsvs fit --config atc_svss [--trainer.max_epochs 10 ...]
    torchsvs fit --config path/to/my_config.yaml

``--config`` takes a file, or the name of a config shipped with torchsvs (with or without
``.yaml``; :func:`~torchsvs.training.shipped_configs`): ``atc_svss`` and ``complex_svss``, the
SVSS of Chen et al. 2020's ATC and complex-maneuver sensors (files in
``torchsvs/training/configs/``, :func:`~torchsvs.training.config_path`). An existing file wins
over a shipped name.

Seeds with ``seed_everything``; checkpoints, the progress bar and CSV/TensorBoard logs come from
the config's trainer section. Any torchsvs estimator (nested ``class_path``/``init_args``) can be
trained on the maneuvering-target data module.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import yaml
from jsonargparse import ActionConfigFile
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from torchsvs.training.configs import config_path, shipped_configs
from torchsvs.training.data import ManeuveringTargetDataModule
from torchsvs.training.module import EstimatorModule
from torchsvs.training.quiet import quiet_lightning, without_tips


def resolve_config(value: str) -> str:
    """What ``--config VALUE`` reads: an existing file as given, else a shipped config's file.

    A YAML/JSON mapping given inline (jsonargparse's ``--config '{trainer: ...}'``) passes through.

    Raises:
        TypeError: neither a file nor a shipped name (jsonargparse reports it as a usage error).
    """
    if Path(value).is_file():
        return value
    try:
        return str(config_path(value))
    except ValueError:
        pass
    try:
        inline = isinstance(yaml.safe_load(value), dict)
    except yaml.YAMLError:
        inline = False
    if inline:
        return value
    raise TypeError(
        f"--config: {value!r} is neither a file nor a shipped config; shipped configs: "
        f"{', '.join(shipped_configs())}"
    )


class _ConfigFile(ActionConfigFile):
    """``--config``: a path, or the name of a shipped config."""

    def __call__(self, parser: Any, cfg: Any, values: Any, option_string: Any = None) -> None:
        super().__call__(parser, cfg, resolve_config(values), option_string)


class _CLI(LightningCLI):
    def init_parser(self, **kwargs: Any) -> LightningArgumentParser:
        kwargs.setdefault("dump_header", [f"lightning.pytorch=={pl.__version__}"])
        parser = self.parser_class(**kwargs)
        parser.add_argument(
            "-c",
            "--config",
            action=_ConfigFile,
            help="Path to a configuration file in json or yaml format, or the name of a config "
            f"shipped with torchsvs: {', '.join(shipped_configs())}.",
        )
        return parser


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Builds the CLI; ``args`` as after ``torchsvs fit``, e.g. ``["--config", "atc_svss"]``."""
    # Lightning 2.6 on torch 2.13 warns about LeafSpec at every fit; third-party, harmless.
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    # A run keeps Lightning's lines but its tips; a CLI built without running (for the objects
    # it makes: experiments, tests) shows none of its Trainer's banners.
    with warnings.catch_warnings(), without_tips() if run else quiet_lightning():
        # Called from Python (experiments, tests) with explicit args, the caller's own sys.argv
        # is not meant for the CLI.
        warnings.filterwarnings(
            "ignore", message=".*args parameter is intended to run from within Python.*"
        )
        return _CLI(
            EstimatorModule,
            ManeuveringTargetDataModule,
            args=(["fit", *args] if run else args) if args is not None else None,
            run=run,
            seed_everything_default=0,
            save_config_kwargs={"overwrite": True},
        )


if __name__ == "__main__":
    main()

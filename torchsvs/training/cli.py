"""``torchsvs fit``: train an estimator with LightningCLI from a YAML config.

    torchsvs fit --config experiments/configs/atc_svss.yaml [--trainer.max_epochs 10 ...]

Seeds with ``seed_everything``; checkpoints, the progress bar and CSV/TensorBoard logs come from
the config's trainer section. Any torchsvs estimator (nested ``class_path``/``init_args``) can be
trained on the maneuvering-target data module.
"""

from __future__ import annotations

import warnings

from lightning.pytorch.cli import LightningCLI

from torchsvs.training.data import ManeuveringTargetDataModule
from torchsvs.training.module import EstimatorModule


def main(args: list[str] | None = None, run: bool = True) -> LightningCLI:
    """Builds the CLI; ``args`` as after ``torchsvs fit``, e.g. ``["--config", path]``."""
    # Lightning 2.6 on torch 2.13 warns about LeafSpec at every fit; third-party, harmless.
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    with warnings.catch_warnings():
        # Called from Python (experiments, tests) with explicit args, the caller's own sys.argv
        # is not meant for the CLI.
        warnings.filterwarnings(
            "ignore", message=".*args parameter is intended to run from within Python.*"
        )
        return LightningCLI(
            EstimatorModule,
            ManeuveringTargetDataModule,
            args=(["fit", *args] if run else args) if args is not None else None,
            run=run,
            seed_everything_default=0,
            save_config_kwargs={"overwrite": True},
        )


if __name__ == "__main__":
    main()

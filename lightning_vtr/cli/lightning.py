"""``lightning-vtr fit|validate|test``: config-driven runs through Lightning's ``LightningCLI``.

Any :class:`~lightning_vtr.models.base.VoxelReconstructionModule` subclass is a valid ``model``;
the data is :class:`~lightning_vtr.data.VTRDataModule`; the augmentation callback and its selector and
synthesizer are configured under ``trainer.callbacks`` (see ``configs/``)::

    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml
    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml --print_config
    lightning-vtr test --config configs/pix2vox_tiny_vtr.yaml --ckpt_path runs/.../last.ckpt
"""

from __future__ import annotations

from collections.abc import Sequence

from lightning.pytorch.cli import LightningCLI

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.base import VoxelReconstructionModule

__all__ = ["LIGHTNING_SUBCOMMANDS", "VTRLightningCLI", "run_lightning_cli"]

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test")


class VTRLightningCLI(LightningCLI):
    """``LightningCLI`` with the package's defaults: data reloaded every epoch (the callback needs it)."""


def run_lightning_cli(argv: Sequence[str] | None = None) -> int:
    """Run LightningCLI on ``argv`` (``None``: ``sys.argv[1:]``)."""
    VTRLightningCLI(
        VoxelReconstructionModule,
        VTRDataModule,
        subclass_mode_model=True,
        args=None if argv is None else list(argv),
        trainer_defaults={"reload_dataloaders_every_n_epochs": 1},
        save_config_kwargs={"overwrite": True},
        auto_configure_optimizers=False,
    )
    return 0

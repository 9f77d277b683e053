"""``lightning-vtr fit|validate|test|predict``: config-driven runs through Lightning's ``LightningCLI``.

Any :class:`~lightning_vtr.models.base.VoxelReconstructionModule` subclass is a valid ``model``;
the data is :class:`~lightning_vtr.data.VTRDataModule`; the augmentation callback and its selector and
synthesizer are configured under ``trainer.callbacks`` (see ``configs/``)::

    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml
    lightning-vtr fit --config configs/pix2vox_tiny_vtr.yaml --print_config
    lightning-vtr test --config configs/pix2vox_tiny_vtr.yaml --ckpt_path runs/.../last.ckpt
    lightning-vtr predict --config configs/pix2vox_tiny_vtr.yaml --ckpt_path runs/.../last.ckpt \\
        --trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter --trainer.callbacks.output_dir=predictions

``predict`` runs on the test split of every view set (the test loaders) when the datamodule has no
``predict_dataloader`` of its own; :class:`~lightning_vtr.export.VoxelPredictionWriter` writes the binvox
files, meshes, sheets and ``index.html``.

:class:`VTRLightningCLI` holds these defaults, so a script of one's own gets the same command line with
``VTRLightningCLI()``.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import MethodType
from typing import Any

from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.utilities.model_helpers import is_overridden

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.base import VoxelReconstructionModule

__all__ = ["LIGHTNING_SUBCOMMANDS", "TRAINER_DEFAULTS", "VTRLightningCLI", "run_lightning_cli"]

#: The ``LightningCLI`` sub-commands ``lightning-vtr`` passes on.
LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")
#: Trainer defaults of :class:`VTRLightningCLI`: the callback's samples reach the next epoch's loader only
#: when the dataloaders are rebuilt every epoch.
TRAINER_DEFAULTS: dict[str, Any] = {"reload_dataloaders_every_n_epochs": 1}


class VTRLightningCLI(LightningCLI):
    """``LightningCLI`` with the package's defaults.

    Compared with ``LightningCLI()``: the model is any
    :class:`~lightning_vtr.models.base.VoxelReconstructionModule` subclass (``subclass_mode_model``),
    the data :class:`~lightning_vtr.data.VTRDataModule`, the Trainer reloads its dataloaders every epoch
    (:data:`TRAINER_DEFAULTS`, which the callback needs), a re-run overwrites the saved ``config.yaml``,
    and the models' own ``configure_optimizers`` is kept (``auto_configure_optimizers=False``). Every
    argument of ``LightningCLI`` can still be given; ``trainer_defaults`` and ``save_config_kwargs``
    are merged over these defaults.

    Example::

        # my_cli.py: `python my_cli.py fit --config configs/pix2vox_tiny_vtr.yaml`
        from lightning_vtr.cli.lightning import VTRLightningCLI

        VTRLightningCLI()
    """

    def __init__(
        self,
        model_class: Any = VoxelReconstructionModule,
        datamodule_class: Any = VTRDataModule,
        *,
        subclass_mode_model: bool = True,
        trainer_defaults: dict[str, Any] | None = None,
        save_config_kwargs: dict[str, Any] | None = None,
        auto_configure_optimizers: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            model_class,
            datamodule_class,
            subclass_mode_model=subclass_mode_model,
            trainer_defaults={**TRAINER_DEFAULTS, **(trainer_defaults or {})},
            save_config_kwargs={"overwrite": True, **(save_config_kwargs or {})},
            auto_configure_optimizers=auto_configure_optimizers,
            **kwargs,
        )

    def before_predict(self) -> None:
        """Give a datamodule without ``predict_dataloader`` one: its test loaders (every view set's test split)."""
        dm = getattr(self, "datamodule", None)
        if dm is not None and not is_overridden("predict_dataloader", dm) and hasattr(dm, "test_dataloader"):
            dm.predict_dataloader = MethodType(_test_loaders, dm)


def _test_loaders(datamodule: Any) -> Any:
    return datamodule.test_dataloader()


def run_lightning_cli(argv: Sequence[str] | None = None) -> int:
    """Run :class:`VTRLightningCLI` on ``argv`` (``None``: ``sys.argv[1:]``); returns the exit status 0."""
    VTRLightningCLI(args=None if argv is None else list(argv))
    return 0

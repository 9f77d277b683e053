"""lightning_vtr: view transformation robustness for multi-view 3D object reconstruction.

The one-line use: ``Trainer(callbacks=[ErrorGuidedViewAugmentation()], reload_dataloaders_every_n_epochs=1)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.data.datamodule import VTRDataModule
    from lightning_vtr.protocol import (
        AugmentableDataModule,
        ReconstructionModel,
        check_augmentable_datamodule,
        check_reconstruction_model,
    )
    from lightning_vtr.selection.registry import SELECTORS
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.callback": ["ErrorGuidedViewAugmentation"],
            "lightning_vtr.data.datamodule": ["VTRDataModule"],
            "lightning_vtr.protocol": [
                "AugmentableDataModule",
                "ReconstructionModel",
                "check_augmentable_datamodule",
                "check_reconstruction_model",
            ],
            "lightning_vtr.selection.registry": ["SELECTORS"],
        },
    )

__version__ = "0.4.0"

__all__ = [
    "SELECTORS",
    "AugmentableDataModule",
    "ErrorGuidedViewAugmentation",
    "ReconstructionModel",
    "VTRDataModule",
    "__version__",
    "check_augmentable_datamodule",
    "check_reconstruction_model",
]

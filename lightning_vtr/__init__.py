"""lightning_vtr: view transformation robustness for multi-view 3D object reconstruction.

The one-line use: ``Trainer(callbacks=[ErrorGuidedViewAugmentation()], reload_dataloaders_every_n_epochs=1)``.
"""

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.protocol import ReconstructionModel, check_reconstruction_model

__version__ = "0.1.0"
__all__ = [
    "ErrorGuidedViewAugmentation",
    "ReconstructionModel",
    "VTRDataModule",
    "__version__",
    "check_reconstruction_model",
]

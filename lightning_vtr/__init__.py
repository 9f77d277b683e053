"""lightning_vtr: view transformation robustness for multi-view 3D object reconstruction.

The one-line use: ``Trainer(callbacks=[ErrorGuidedViewAugmentation()], reload_dataloaders_every_n_epochs=1)``.
Names are imported lazily so light entry points (dataset build workers, ``dataset-info``) skip Lightning.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Type checkers and IDEs read these imports; at run time they are skipped and __getattr__ resolves each name
# on first use, so `import lightning_vtr` stays light.
if TYPE_CHECKING:  # pragma: no cover
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.data.datamodule import VTRDataModule
    from lightning_vtr.protocol import (
        AugmentableDataModule,
        ReconstructionModel,
        check_augmentable_datamodule,
        check_reconstruction_model,
    )
    from lightning_vtr.selection.registry import SELECTORS

__version__ = "0.4.0"

#: Lazily exported name -> the module that defines it (keep in step with the TYPE_CHECKING imports above).
_EXPORTS = {
    "ErrorGuidedViewAugmentation": "lightning_vtr.callback",
    "VTRDataModule": "lightning_vtr.data.datamodule",
    "AugmentableDataModule": "lightning_vtr.protocol",
    "ReconstructionModel": "lightning_vtr.protocol",
    "check_augmentable_datamodule": "lightning_vtr.protocol",
    "check_reconstruction_model": "lightning_vtr.protocol",
    "SELECTORS": "lightning_vtr.selection.registry",
}
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


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr' has no attribute {name!r}")


def __dir__() -> list[str]:
    # the lazy names are not in globals() until first used; list them so dir() and completion show them
    return sorted({*globals(), *_EXPORTS})

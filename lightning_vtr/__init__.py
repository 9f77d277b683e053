"""lightning_vtr: view transformation robustness for multi-view 3D object reconstruction.

The one-line use: ``Trainer(callbacks=[ErrorGuidedViewAugmentation()], reload_dataloaders_every_n_epochs=1)``.
Names are imported lazily so light entry points (dataset build workers, ``dataset-info``) skip Lightning.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "ErrorGuidedViewAugmentation": "lightning_vtr.callback",
    "VTRDataModule": "lightning_vtr.data.datamodule",
    "ReconstructionModel": "lightning_vtr.protocol",
    "check_reconstruction_model": "lightning_vtr.protocol",
}
__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr' has no attribute {name!r}")

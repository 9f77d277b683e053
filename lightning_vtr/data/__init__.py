"""Data: the ShapeNet-VTR format and builder, the procedural dataset, readers, and the mutable DataModule.

Names are imported lazily so dataset build workers do not import Lightning.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "BuildReport": "lightning_vtr.data.builder",
    "build_dataset": "lightning_vtr.data.builder",
    "ensure_embedded_dataset": "lightning_vtr.data.builder",
    "VIEW_SETS": "lightning_vtr.data.datamodule",
    "VTRDataModule": "lightning_vtr.data.datamodule",
    "GeneratedSample": "lightning_vtr.data.dataset",
    "ImageTransform": "lightning_vtr.data.dataset",
    "DatasetFormatError": "lightning_vtr.data.format",
    "ObjectRecord": "lightning_vtr.data.format",
    "scan_dataset": "lightning_vtr.data.format",
    "ShapeNetRenderingSource": "lightning_vtr.data.shapenet_rendering",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr.data' has no attribute {name!r}")

"""Data: the ShapeNet-VTR format and builder, the procedural dataset, readers, image recipes and the mutable DataModule.

Names are imported lazily so dataset build workers do not import Lightning.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what IDEs and type checkers see; at runtime __getattr__ imports on first use
    from lightning_vtr.data.builder import BuildReport, build_dataset, ensure_embedded_dataset
    from lightning_vtr.data.datamodule import VTRDataModule
    from lightning_vtr.data.dataset import GeneratedSample
    from lightning_vtr.data.folder_test_set import FolderTestSet
    from lightning_vtr.data.format import DatasetFormatError, ObjectRecord, scan_dataset
    from lightning_vtr.data.pix3d import Pix3DDataset, Pix3DRecord, read_pix3d
    from lightning_vtr.data.shapenet_rendering import ShapeNetRenderingSource
    from lightning_vtr.data.transforms import IMAGE_RECIPES, ImageRecipe, ImageTransform
    from lightning_vtr.data.verify import VerifyReport, verify_dataset
    from lightning_vtr.protocol import VIEW_SETS

_EXPORTS = {
    "BuildReport": "lightning_vtr.data.builder",
    "build_dataset": "lightning_vtr.data.builder",
    "ensure_embedded_dataset": "lightning_vtr.data.builder",
    "VIEW_SETS": "lightning_vtr.protocol",
    "VTRDataModule": "lightning_vtr.data.datamodule",
    "GeneratedSample": "lightning_vtr.data.dataset",
    "DatasetFormatError": "lightning_vtr.data.format",
    "ObjectRecord": "lightning_vtr.data.format",
    "scan_dataset": "lightning_vtr.data.format",
    "ShapeNetRenderingSource": "lightning_vtr.data.shapenet_rendering",
    "FolderTestSet": "lightning_vtr.data.folder_test_set",
    "Pix3DDataset": "lightning_vtr.data.pix3d",
    "Pix3DRecord": "lightning_vtr.data.pix3d",
    "read_pix3d": "lightning_vtr.data.pix3d",
    "IMAGE_RECIPES": "lightning_vtr.data.transforms",
    "ImageRecipe": "lightning_vtr.data.transforms",
    "ImageTransform": "lightning_vtr.data.transforms",
    "VerifyReport": "lightning_vtr.data.verify",
    "verify_dataset": "lightning_vtr.data.verify",
}
__all__ = [
    "IMAGE_RECIPES",
    "VIEW_SETS",
    "BuildReport",
    "DatasetFormatError",
    "FolderTestSet",
    "GeneratedSample",
    "ImageRecipe",
    "ImageTransform",
    "ObjectRecord",
    "Pix3DDataset",
    "Pix3DRecord",
    "ShapeNetRenderingSource",
    "VTRDataModule",
    "VerifyReport",
    "build_dataset",
    "ensure_embedded_dataset",
    "read_pix3d",
    "scan_dataset",
    "verify_dataset",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr.data' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)

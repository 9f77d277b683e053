"""Data: the ShapeNet-VTR format and builder, the procedural dataset, readers, image recipes and the mutable DataModule."""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
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
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.data.builder": ["BuildReport", "build_dataset", "ensure_embedded_dataset"],
            "lightning_vtr.data.datamodule": ["VTRDataModule"],
            "lightning_vtr.data.dataset": ["GeneratedSample"],
            "lightning_vtr.data.folder_test_set": ["FolderTestSet"],
            "lightning_vtr.data.format": ["DatasetFormatError", "ObjectRecord", "scan_dataset"],
            "lightning_vtr.data.pix3d": ["Pix3DDataset", "Pix3DRecord", "read_pix3d"],
            "lightning_vtr.data.shapenet_rendering": ["ShapeNetRenderingSource"],
            "lightning_vtr.data.transforms": ["IMAGE_RECIPES", "ImageRecipe", "ImageTransform"],
            "lightning_vtr.data.verify": ["VerifyReport", "verify_dataset"],
            "lightning_vtr.protocol": ["VIEW_SETS"],
        },
    )

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

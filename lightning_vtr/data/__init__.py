"""Data: the ShapeNet-VTR format and builder, the procedural dataset, readers, and the mutable DataModule."""

from __future__ import annotations

from lightning_vtr.data.builder import BuildReport, build_dataset, ensure_embedded_dataset
from lightning_vtr.data.datamodule import VIEW_SETS, VTRDataModule
from lightning_vtr.data.dataset import GeneratedSample, ImageTransform
from lightning_vtr.data.format import DatasetFormatError, ObjectRecord, scan_dataset

__all__ = [
    "VIEW_SETS",
    "BuildReport",
    "DatasetFormatError",
    "GeneratedSample",
    "ImageTransform",
    "ObjectRecord",
    "VTRDataModule",
    "build_dataset",
    "ensure_embedded_dataset",
    "scan_dataset",
]

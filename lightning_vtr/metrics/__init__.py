"""Voxel reconstruction metrics: IoU at thresholds, best-threshold IoU and F-score@1 %.

Classes are torchmetrics ``Metric``s that sync across processes; the math lives in
:mod:`lightning_vtr.metrics.functional`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.metrics.functional import (
        DEFAULT_FSCORE_CONVENTION,
        DEFAULT_IOU_THRESHOLDS,
        DEFAULT_THRESHOLD,
        FSCORE_CONVENTIONS,
        voxel_fscore,
        voxel_iou,
        voxel_iou_best,
    )
    from lightning_vtr.metrics.voxel import VoxelFScore, VoxelIoU, VoxelIoUBest
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.metrics.functional": [
                "DEFAULT_FSCORE_CONVENTION",
                "DEFAULT_IOU_THRESHOLDS",
                "DEFAULT_THRESHOLD",
                "FSCORE_CONVENTIONS",
                "voxel_fscore",
                "voxel_iou",
                "voxel_iou_best",
            ],
            "lightning_vtr.metrics.voxel": ["VoxelFScore", "VoxelIoU", "VoxelIoUBest"],
        },
    )

__all__ = [
    "DEFAULT_FSCORE_CONVENTION",
    "DEFAULT_IOU_THRESHOLDS",
    "DEFAULT_THRESHOLD",
    "FSCORE_CONVENTIONS",
    "VoxelFScore",
    "VoxelIoU",
    "VoxelIoUBest",
    "voxel_fscore",
    "voxel_iou",
    "voxel_iou_best",
]

"""Voxel reconstruction metrics (DESIGN section 7): IoU at thresholds and F-score@1 %.

Classes are torchmetrics ``Metric``s that sync across processes; the math lives in
:mod:`lightning_vtr.metrics.functional`.
"""

from __future__ import annotations

from lightning_vtr.metrics.functional import DEFAULT_IOU_THRESHOLDS, voxel_fscore, voxel_iou
from lightning_vtr.metrics.voxel import VoxelFScore, VoxelIoU

__all__ = ["DEFAULT_IOU_THRESHOLDS", "VoxelFScore", "VoxelIoU", "voxel_fscore", "voxel_iou"]

"""Evaluation on Pix3D: the evaluation loop and the frame check of the Pix3D reader's conventions.

:func:`evaluate_pix3d` measures a model on :class:`~lightning_vtr.data.pix3d.Pix3DDataset` photographs (the
paper's Table 5 metrics). :func:`frame_check` tests the frames :mod:`lightning_vtr.data.pix3d` derives: it
projects a record's voxels with its ``rot_mat``, ``trans_mat`` and ``focal_length`` (perspective, as Pix3D's
``demo.py`` renders; the voxel cube's unknown size in model units is fitted so that the projection is as large
as the mask) and compares the silhouette with the mask, both cropped to their bounding boxes (padded to
squares) and resampled to the same grid. A swapped or mirrored voxel axis, a transposed rotation or a mirrored
image lowers the IoU; the turn about +Z into the package frame is a convention no photograph can check.
:func:`write_frame_check` and :func:`frame_check_summary` report it for many records::

    records = read_pix3d("~/data/Pix3D", categories=["chair"])
    print(frame_check_summary({r.key: frame_check(r) for r in records[:20]}))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
from PIL import Image

from lightning_vtr.data.pix3d import (
    BLENDER_TO_CAMERA,
    VOXEL_TO_MODEL,
    Pix3DDataset,
    Pix3DRecord,
    downsample_voxels,
    load_voxel_mat,
    read_pix3d_image,
    read_pix3d_mask,
)
from lightning_vtr.evaluation.dataset import evaluate_dataset
from lightning_vtr.utils.io import write_csv

__all__ = [
    "FRAME_CHECK_MIN_IOU",
    "evaluate_pix3d",
    "frame_check",
    "frame_check_summary",
    "frame_check_warning",
    "write_frame_check",
]

#: The mean frame-check IoU below which :func:`frame_check_warning` warns.
FRAME_CHECK_MIN_IOU = 0.8


def evaluate_pix3d(model: Any, dataset: Pix3DDataset, **kwargs: Any) -> dict[str, Any]:
    """:func:`~lightning_vtr.evaluation.dataset.evaluate_dataset` on Pix3D: per category and overall.

    Args:
        model: anything with ``predict_voxels(images (B, 1, 3, H, W)) -> (B, R, R, R)`` probabilities.
        dataset: the photographs, at the model's voxel resolution.
        **kwargs: passed to :func:`~lightning_vtr.evaluation.dataset.evaluate_dataset` (``batch_size``,
            ``device``, ``thresholds``, ``fscore_points``, ...).

    Returns:
        ``{"overall", "categories", "best_threshold"}``, as
        :func:`~lightning_vtr.evaluation.dataset.evaluate_dataset` returns them.

    Raises:
        ValueError: the dataset is empty, or the predictions' shape is not the voxels' (see
            :func:`~lightning_vtr.evaluation.dataset.evaluate_dataset`).

    Example::

        results = evaluate_pix3d(model, Pix3DDataset(read_pix3d("~/data/Pix3D"), resolution=32))
    """
    return evaluate_dataset(model, dataset, **kwargs)


# ---------------------------------------------------------------------------------------------- frame check
def _square_raster(rows: np.ndarray, cols: np.ndarray, size: int) -> np.ndarray:
    """Mark the pixels of an ``size x size`` grid hit by points, the grid spanning their bounding box padded to
    a centred square."""
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    side = max(r1 - r0, c1 - c0) or 1.0
    top, left = (r0 + r1) / 2.0 - side / 2.0, (c0 + c1) / 2.0 - side / 2.0
    r = np.clip(((rows - top) / side * size).astype(int), 0, size - 1)
    c = np.clip(((cols - left) / side * size).astype(int), 0, size - 1)
    out = np.zeros((size, size), bool)
    out[r, c] = True
    return out


def _mask_silhouette(mask: np.ndarray, size: int) -> np.ndarray:
    rows, cols = np.nonzero(mask > 127)
    if rows.size == 0:
        return np.zeros((size, size), bool)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    side = max(r1 - r0, c1 - c0)
    square = np.zeros((side, side), np.uint8)
    top, left = (side - (r1 - r0)) // 2, (side - (c1 - c0)) // 2
    square[top : top + r1 - r0, left : left + c1 - c0] = np.where(mask[r0:r1, c0:c1] > 127, 255, 0)
    resized = np.asarray(Image.fromarray(square).resize((size, size), Image.BOX))  # type: ignore[attr-defined]  # PIL sets the alias at runtime
    return resized >= 128


def _project(
    record: Pix3DRecord, voxel_to_model: np.ndarray, points: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Image ``(rows, cols)`` of voxel-frame points, up to a shift and a scale.

    With a focal length and the object in front of the camera: perspective, the voxel cube's size ``s`` (model
    units; unknown, as ``voxel.mat`` is normalised) fitted so that the projection's extent matches the mask's,
    starting from the para-perspective estimate. Otherwise orthographic along the optical axis.
    """
    rotated = (BLENDER_TO_CAMERA @ record.rotation @ voxel_to_model @ points.T).T  # camera frame, about the origin
    centre = BLENDER_TO_CAMERA @ record.translation
    depth = -centre[2]
    if record.focal_length is None or depth <= 0:
        return -rotated[:, 1], rotated[:, 0]
    focal = record.focal_length / 32.0 * mask.shape[1]  # pixels: demo.py's sensor is 32 mm wide
    rows, cols = np.nonzero(mask > 127)
    target = max(rows.max() - rows.min(), cols.max() - cols.min()) + 1.0
    ortho = max(np.ptp(rotated[:, 0]), np.ptp(rotated[:, 1]))
    scale = target * depth / (focal * ortho) if ortho > 0 else 1.0
    for _ in range(6):  # fixed point: scale the cube until its perspective image is as large as the mask
        camera = centre + scale * rotated
        z = np.maximum(-camera[:, 2], 1e-6 * depth)
        u, v = focal * camera[:, 0] / z, -focal * camera[:, 1] / z
        extent = max(np.ptp(u), np.ptp(v))
        if extent <= 0 or np.any(-camera[:, 2] <= 0):
            break
        scale *= target / extent
    camera = centre + scale * rotated
    if np.any(-camera[:, 2] <= 0):  # the fitted cube reaches behind the camera: fall back to para-perspective
        x = rotated[:, 0] + centre[0] / depth * rotated[:, 2]
        y = rotated[:, 1] + centre[1] / depth * rotated[:, 2]
        return -y, x
    z = -camera[:, 2]
    return -camera[:, 1] / z, camera[:, 0] / z


@overload
def frame_check(
    record: Pix3DRecord,
    *,
    voxel_to_model: np.ndarray = ...,
    grid: int = ...,
    size: int = ...,
    return_silhouettes: Literal[False] = ...,
) -> float: ...
@overload
def frame_check(
    record: Pix3DRecord,
    *,
    voxel_to_model: np.ndarray = ...,
    grid: int = ...,
    size: int = ...,
    return_silhouettes: Literal[True],
) -> tuple[float, np.ndarray, np.ndarray]: ...
@overload
def frame_check(
    record: Pix3DRecord,
    *,
    voxel_to_model: np.ndarray = ...,
    grid: int = ...,
    size: int = ...,
    return_silhouettes: bool = ...,
) -> float | tuple[float, np.ndarray, np.ndarray]: ...
def frame_check(
    record: Pix3DRecord,
    *,
    voxel_to_model: np.ndarray = VOXEL_TO_MODEL,
    grid: int = 64,
    size: int = 64,
    return_silhouettes: bool = False,
) -> float | tuple[float, np.ndarray, np.ndarray]:
    """IoU between the record's mask and its voxels projected with ``rot_mat`` (see the module docstring).

    The voxels (down-sampled to ``grid^3`` with ``pooling="max"``, ``fit=False``; the surface voxels, each
    sampled at 64 points reaching its faces) are mapped to the model frame with ``voxel_to_model``, rotated by
    ``rot_mat``, placed at ``trans_mat`` and projected with the record's focal length (demo.py's camera). The
    size of the voxel cube in model units is not in the data, so it is fitted to make the projection as large
    as the mask (a few fixed-point steps); without a focal length the projection is orthographic along the
    optical axis. The projection and the mask are each cropped to their bounding box, padded to a centred
    square and rasterised on ``size x size`` pixels.

    Args:
        record: a Pix3D photograph.
        voxel_to_model: the voxel -> model frame map under test (default the derived :data:`VOXEL_TO_MODEL`).
        grid: the voxel resolution of the projection.
        size: the silhouettes' side in pixels.
        return_silhouettes: also return the two ``(size, size)`` bool silhouettes (projection, mask).

    Returns:
        The IoU in ``[0, 1]`` (0 when the voxels or the mask are empty); above ~0.8 on an untruncated,
        unoccluded photograph means the frames agree. With ``return_silhouettes``: ``(iou, projection, mask)``,
        the two silhouettes ``(size, size)`` bool.

    Raises:
        ValueError: ``voxel_to_model`` is not 3x3.
        DatasetFormatError: ``voxel.mat`` is unreadable or not a cubic grid, or the mask's size is not the
            photograph's.
        OSError: the photograph or the mask cannot be read.

    Example::

        from lightning_vtr.data import read_pix3d
        from lightning_vtr.evaluation import frame_check

        record = read_pix3d("~/data/Pix3D", categories=["chair"])[0]
        iou, projection, mask = frame_check(record, return_silhouettes=True)  # projection, mask: (64, 64) bool
    """
    voxel_to_model = np.asarray(voxel_to_model, dtype=np.float64)
    if voxel_to_model.shape != (3, 3):
        raise ValueError(f"`voxel_to_model` must be 3x3, got shape {voxel_to_model.shape}")
    raw = load_voxel_mat(record.voxel_path)
    image = read_pix3d_image(record.image_path)
    mask = read_pix3d_mask(record.mask_path, image.shape[:2], record.image_path)
    silhouette = _mask_silhouette(mask, size)
    small = downsample_voxels(raw, min(grid, raw.shape[0]), fit=False, pooling="max")
    padded = np.pad(small, 1)
    inner = padded[1:-1, 1:-1, 1:-1]
    for axis in range(3):  # a voxel with all six neighbours occupied cannot change the silhouette
        for shift in (-1, 1):
            inner = inner & np.roll(padded, shift, axis)[1:-1, 1:-1, 1:-1]
    cells = np.argwhere(small & ~inner)
    if cells.size == 0 or not silhouette.any():
        empty = np.zeros((size, size), bool)
        return (0.0, empty, silhouette) if return_silhouettes else 0.0
    n = small.shape[0]
    steps = np.array([-0.5, -1.0 / 6.0, 1.0 / 6.0, 0.5])  # faces and thirds: no gaps, the true extent
    offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3)
    points = ((cells[:, None, :] + 0.5 + offsets[None]) / n - 0.5).reshape(-1, 3)  # voxel frame
    rows, cols = _project(record, voxel_to_model, points, mask)
    projection = _square_raster(rows, cols, size)
    union = np.logical_or(projection, silhouette).sum()
    iou = float(np.logical_and(projection, silhouette).sum() / union) if union else 0.0
    return (iou, projection, silhouette) if return_silhouettes else iou


def frame_check_summary(ious: Mapping[str, float]) -> str:
    """One line: count, mean and minimum of frame-check IoUs, and the worst record.

    Args:
        ious: record key -> :func:`frame_check` IoU.

    Returns:
        The summary line (``"frame check: no records"`` when ``ious`` is empty).

    Example:
        >>> frame_check_summary({"chair/0001": 0.91, "chair/0002": 0.84})
        'frame check on 2 record(s): mean IoU 0.875, min 0.840 (chair/0002)'
    """
    if not ious:
        return "frame check: no records"
    worst = min(ious, key=lambda key: ious[key])
    values = np.fromiter(ious.values(), float)
    return f"frame check on {len(values)} record(s): mean IoU {values.mean():.3f}, min {values.min():.3f} ({worst})"


def write_frame_check(out: str | Path, records: Sequence[Pix3DRecord]) -> dict[str, float]:
    """Frame-check ``records`` and write ``frame_check.csv`` (``photograph,iou``) into ``out``.

    Args:
        out: the output folder (created when missing).
        records: the photographs to check.

    Returns:
        Record key -> :func:`frame_check` IoU, in the records' order.

    Example::

        ious = write_frame_check("pix3d_eval", read_pix3d("~/data/Pix3D")[:20])
        print(frame_check_summary(ious))
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ious = {record.key: frame_check(record) for record in records}
    write_csv(out / "frame_check.csv", ([key, f"{iou:.4f}"] for key, iou in ious.items()), ["photograph", "iou"])
    return ious


def frame_check_warning(ious: Mapping[str, float]) -> str | None:
    """A warning when the mean frame-check IoU is below :data:`FRAME_CHECK_MIN_IOU`, else ``None``.

    Args:
        ious: record key -> :func:`frame_check` IoU.

    Returns:
        One line saying that the projected voxels do not match the masks, or ``None``.

    Example:
        >>> frame_check_warning({"img/chair/0001.png": 0.95}) is None
        True
    """
    if not ious or sum(ious.values()) / len(ious) >= FRAME_CHECK_MIN_IOU:
        return None
    return (
        "warning: the voxels projected with the photographs' poses do not match the masks well "
        "(mean IoU < 0.8); see frame_check.csv and lightning_vtr.data.pix3d"
    )

"""Evaluating a model on a test set: the metrics overall and per category, and the tables that print them.

:func:`evaluate_dataset` runs any model with ``predict_voxels`` over a dataset of ``VTRDataset``'s batch
dictionaries (:class:`~lightning_vtr.data.FolderTestSet`, :class:`~lightning_vtr.data.Pix3DDataset`,
``VTRDataset``) and returns the package's metrics overall and per category; :func:`evaluate_folder` does it for
a folder test set. :func:`format_evaluation_table` prints results in the paper's Table 5 layout
(``Method | mIoU | F-score``), :func:`evaluation_rows` gives them as CSV rows, and :func:`write_evaluation`
writes ``table.md``, ``results.csv`` and ``results.json``::

    results = {"Ours (Pix2Vox++)": evaluate_folder(model, "VTR_test/Spherical", "ShapeNetVox32", num_views=3)}
    print(format_evaluation_table(results))
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence, Sized
from pathlib import Path
from typing import Any, cast

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from lightning_vtr.data.folder_test_set import FolderTestSet
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation.tables import format_cell
from lightning_vtr.metrics.functional import DEFAULT_FSCORE_CONVENTION, DEFAULT_IOU_THRESHOLDS, threshold_key
from lightning_vtr.metrics.voxel import VoxelFScore, VoxelIoU
from lightning_vtr.utils.io import atomic_write, write_csv
from lightning_vtr.utils.validation import check_int

__all__ = [
    "evaluate_dataset",
    "evaluate_folder",
    "evaluation_notes",
    "evaluation_rows",
    "format_evaluation_table",
    "write_evaluation",
]


# ---------------------------------------------------------------------------------------------- evaluation
def evaluate_dataset(
    model: Any,
    dataset: Dataset,
    *,
    batch_size: int = 8,
    device: str | torch.device = "cpu",
    thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
    fscore_threshold: float = 0.4,
    fscore_points: int = 8192,
    fscore_convention: str = DEFAULT_FSCORE_CONVENTION,
    num_workers: int = 0,
) -> dict[str, Any]:
    """Run ``model.predict_voxels`` over ``dataset`` and measure IoU and F-score, overall and per category.

    The metrics are the package's (:class:`~lightning_vtr.metrics.VoxelIoU`,
    :class:`~lightning_vtr.metrics.VoxelFScore`, community F-score convention by default), i.e. what a model's
    ``test_step`` logs. ``iou_best`` is the best-threshold mIoU VTR's test script prints: the largest of the
    overall per-threshold means; each category's ``iou_best`` is its mean at that same threshold.

    Args:
        model: anything with ``predict_voxels(images (B, V, 3, H, W)) -> (B, R, R, R)`` probabilities (moved to
            ``device`` and put in eval mode when it has ``to`` / ``eval``).
        dataset: items with ``images``, ``voxels`` and ``category`` (:class:`~lightning_vtr.data.FolderTestSet`,
            :class:`~lightning_vtr.data.pix3d.Pix3DDataset`, ``VTRDataset``).
        batch_size: objects per forward pass.
        device: where the forward passes run.
        num_workers: data-loading worker processes.
        thresholds: the IoU thresholds (each gives ``iou@<t>``).
        fscore_threshold: as in :class:`~lightning_vtr.metrics.VoxelFScore`.
        fscore_points: as in :class:`~lightning_vtr.metrics.VoxelFScore`.
        fscore_convention: as in :class:`~lightning_vtr.metrics.VoxelFScore`.

    Returns:
        ``{"overall": {...}, "categories": {category: {...}}, "best_threshold": t}``, each inner dict holding
        ``count``, ``iou@<t>`` for every threshold, ``iou_best`` and ``fscore`` (fractions in ``[0, 1]``).

    Raises:
        TypeError: ``batch_size`` is not an int.
        ValueError: the dataset is empty, ``batch_size`` is below 1, or a prediction's shape is not the ground
            truth's (names both).

    Example:
        >>> from types import SimpleNamespace
        >>> cube = torch.zeros(8, 8, 8)
        >>> cube[2:6, 2:6, 2:6] = 1
        >>> items = [{"images": torch.zeros(1, 3, 32, 32), "voxels": cube, "category": "chair"}] * 2
        >>> oracle = SimpleNamespace(predict_voxels=lambda images: cube.expand(len(images), 8, 8, 8))
        >>> result = evaluate_dataset(oracle, items, fscore_points=512)
        >>> overall = result["overall"]
        >>> overall["count"], overall["iou@0.4"], result["best_threshold"]
        (2, 1.0, 0.2)
    """
    if len(cast(Sized, dataset)) == 0:  # a map-style dataset
        raise ValueError("`dataset` must hold at least one item, got an empty dataset")
    batch_size = check_int("batch_size", batch_size, minimum=1)
    device = torch.device(device)
    iou = VoxelIoU(thresholds)
    fscore = VoxelFScore(threshold=fscore_threshold, num_points=fscore_points, convention=fscore_convention)
    if hasattr(model, "to"):
        model = model.to(device)
    if hasattr(model, "eval"):
        model.eval()
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers)
    with torch.no_grad():
        for batch in loader:
            predicted: Tensor = model.predict_voxels(batch["images"].to(device)).float().cpu()
            target = batch["voxels"].float()
            if predicted.shape != target.shape:
                raise ValueError(
                    f"the model's predictions must have the ground truth's shape {tuple(target.shape)}, got "
                    f"{tuple(predicted.shape)}: choose a dataset `resolution` equal to the model's voxel_resolution"
                )
            categories = list(batch["category"])
            iou.update(predicted, target, categories)
            fscore.update(predicted, target, categories)
    overall_iou = iou.compute().reshape(-1)
    best = int(torch.argmax(overall_iou))  # the lowest threshold on ties, like np.argmax
    counts = dict(zip(iou.categories, iou.category_count.tolist()))

    def entry(values: Tensor, f: Tensor, count: float) -> dict[str, float]:
        values = values.reshape(-1)
        out: dict[str, float] = {"count": int(count)}
        out.update({threshold_key(t): float(v) for t, v in zip(iou.thresholds, values)})
        out["iou_best"] = float(values[best])
        out["fscore"] = float(f)
        return out

    per_f = fscore.compute_per_category()
    return {
        "overall": entry(overall_iou, fscore.compute(), float(iou.count)),
        "categories": {c: entry(v, per_f[c], counts[c]) for c, v in iou.compute_per_category().items()},
        "best_threshold": iou.thresholds[best],
    }


def evaluate_folder(
    model: Any,
    image_root: str | Path,
    voxel_root: str | Path,
    *,
    num_views: int | None = None,
    transform: Any = None,
    batch_size: int = 8,
    device: str | torch.device = "cpu",
    **dataset_kwargs: Any,
) -> dict[str, Any]:
    """Evaluate ``model`` on a folder test set: :class:`~lightning_vtr.data.FolderTestSet` + :func:`evaluate_dataset`.

    ``num_views`` defaults to ``model.num_views`` and ``transform`` to the plain transform at
    ``model.image_size`` (pass the one the model was validated with, e.g.
    ``lightning_vtr.evaluation.predict.make_datamodule(ckpt, model).transform``); other keyword arguments go to
    :class:`~lightning_vtr.data.FolderTestSet`.

    Args:
        model: anything with ``predict_voxels(images (B, V, 3, H, W)) -> (B, R, R, R)`` probabilities, as in
            :func:`evaluate_dataset`.
        image_root: the set's folder, ``<image_root>/<taxonomy>/<model>/NN.png``.
        voxel_root: ``<voxel_root>/<taxonomy>/<model>/model.binvox`` (ShapeNetVox32).
        num_views: pictures per object; ``None``: ``model.num_views`` (1 when the model has none).
        transform: RGBA uint8 pictures -> model input; ``None``: the plain
            :class:`~lightning_vtr.data.ImageTransform` at ``model.image_size`` (224 when the model has none).
        batch_size: objects per forward pass.
        device: where the forward passes run.
        **dataset_kwargs: further arguments of :class:`~lightning_vtr.data.FolderTestSet` (e.g.
            ``view_choice``, ``categories``, ``split_file``).

    Returns:
        The dict :func:`evaluate_dataset` returns: ``{"overall": {...}, "categories": {...}, "best_threshold": t}``.

    Raises:
        FileNotFoundError: a root is not a directory (see :class:`~lightning_vtr.data.FolderTestSet`).
        ValueError: the folders hold no usable object, an object has fewer than ``num_views`` pictures, or a
            prediction's shape is not the ground truth's.

    Example::

        results = evaluate_folder(model, "VTR_test/Spherical", "ShapeNetVox32", num_views=3)
        print(format_evaluation_table({"Ours (Pix2Vox++)": results}))
    """
    dataset = FolderTestSet(
        image_root,
        voxel_root,
        num_views=int(num_views if num_views is not None else getattr(model, "num_views", 1)),
        transform=transform if transform is not None else ImageTransform(int(getattr(model, "image_size", 224))),
        **dataset_kwargs,
    )
    return evaluate_dataset(model, dataset, batch_size=batch_size, device=device)


# ---------------------------------------------------------------------------------------------- tables
def format_evaluation_table(
    results: Mapping[str, Mapping[str, Any]],
    *,
    categories: Sequence[str] | None = None,
    metric: str = "iou@0.4",
    digits: int = 2,
) -> str:
    """The paper's Table 5 layout: ``| Method | mIoU | F-score |``, one row per method, values in %.

    Args:
        results: method name -> the dict :func:`evaluate_dataset` returns.
        categories: also print ``<category> mIoU | <category> F-score`` columns for these (a category a
            method has no objects of prints ``-``).
        metric: the IoU column's key (``iou@0.4``, the paper's, by default; ``iou_best`` for VTR's script's).
        digits: decimals of the percentages.

    Returns:
        A Markdown table, one line per row, values in % (``-`` for a missing value).

    Example:
        >>> r = {"overall": {"iou@0.4": 0.1624, "fscore": 0.0776}, "categories": {}}
        >>> print(format_evaluation_table({"Pix2Vox++": r}))
        | Method | mIoU | F-score |
        |---|---|---|
        | Pix2Vox++ | 16.24 | 7.76 |
    """
    title = "mIoU" if metric == "iou@0.4" else ("best mIoU" if metric == "iou_best" else f"mIoU@{metric[4:]}")
    header = ["Method", title, "F-score"]
    for category in categories or ():
        header += [f"{category} {title}", f"{category} F-score"]
    rows = []
    for method, result in results.items():
        groups = [result.get("overall", {})] + [result.get("categories", {}).get(c, {}) for c in categories or ()]
        cells = [format_cell(g.get(key), digits=digits) for g in groups for key in (metric, "fscore")]
        rows.append([method, *cells])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def evaluation_rows(results: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Long-form rows for a CSV: one per method and group (``category`` is ``"all"`` for the overall row).

    Args:
        results: method name -> the dict :func:`evaluate_dataset` returns.

    Returns:
        One dict per method and group, in order: ``method``, ``category``, then the group's ``count``, every
        ``iou@<t>``, ``iou_best`` and ``fscore`` as fractions (NaN values left out).

    Example:
        >>> group = {"count": 2, "iou@0.4": 0.5, "iou_best": 0.52, "fscore": 0.3}
        >>> r = {"overall": group, "categories": {"chair": group}, "best_threshold": 0.3}
        >>> for row in evaluation_rows({"Ours": r}):
        ...     print(row["method"], row["category"], row["count"], row["iou@0.4"])
        Ours all 2 0.5
        Ours chair 2 0.5
    """
    rows = []
    for method, result in results.items():
        groups = {"all": result.get("overall", {}), **result.get("categories", {})}
        for category, values in groups.items():
            row: dict[str, Any] = {"method": method, "category": category}
            row.update({k: v for k, v in values.items() if not (isinstance(v, float) and math.isnan(v))})
            rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------- files
def evaluation_notes(results: Mapping[str, Mapping[str, Any]], what: str) -> list[str]:
    """The notes under an evaluation table: what was measured, then each method's object counts.

    Args:
        results: method name -> the dict :func:`evaluate_dataset` returns.
        what: the test set in words (e.g. ``"Pix3D (~/data/Pix3D), 2894 photographs, one view each"``).

    Returns:
        One line for the set and the metrics, then one per method (its objects per category and its
        best-threshold mIoU).

    Raises:
        KeyError: a result lacks ``overall``, ``categories``, ``best_threshold`` or a group's ``count`` /
            ``iou_best``.

    Example:
        >>> group = {"count": 2, "iou@0.4": 0.5, "iou_best": 0.52, "fscore": 0.3}
        >>> r = {"overall": group, "categories": {"chair": group}, "best_threshold": 0.3}
        >>> evaluation_notes({"Ours": r}, "Pix3D chairs")[1]
        'Ours: 2 objects (chair 2); best-threshold mIoU 52.00 at 0.3'
    """
    notes = [
        f"{what}; mIoU: mean IoU over objects at threshold 0.4 (the paper's); F-score@1 % (community convention, "
        "binarised at 0.4); values in %.",
    ]
    for name, result in results.items():
        counts = ", ".join(f"{c} {v['count']}" for c, v in sorted(result["categories"].items()))
        notes.append(
            f"{name}: {result['overall']['count']} objects ({counts}); best-threshold mIoU "
            f"{100 * result['overall']['iou_best']:.2f} at {result['best_threshold']:g}"
        )
    return notes


def write_evaluation(
    out: str | Path,
    results: Mapping[str, Mapping[str, Any]],
    *,
    title: str,
    notes: Sequence[str],
    per_category: bool,
) -> str:
    """Write ``table.md``, ``results.csv`` and ``results.json`` into ``out`` (created when missing).

    Args:
        out: the output folder.
        results: method name -> the dict :func:`evaluate_dataset` returns.
        title: the table's heading.
        notes: lines listed under the table (e.g. :func:`evaluation_notes`).
        per_category: add each category's columns to the table.

    Returns:
        The table, as :func:`format_evaluation_table` prints it.

    Example::

        table = write_evaluation("eval", results, title="Pix3D", notes=evaluation_notes(results, "Pix3D"),
                                 per_category=False)
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    categories = sorted({c for r in results.values() for c in r["categories"]}) if per_category else None
    table = format_evaluation_table(results, categories=categories)
    atomic_write(out / "table.md", f"# {title}\n\n{table}\n\n" + "".join(f"* {n}\n" for n in notes))
    rows = evaluation_rows(results)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    write_csv(out / "results.csv", rows, fields)
    atomic_write(out / "results.json", json.dumps(results, indent=1))
    return table

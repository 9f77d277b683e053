"""Test sets that are folders of images plus voxels, without camera metadata, and the evaluation loop they share.

The VTR authors released their test sets in the 3D-R2N2 / Pix2Vox layout without ``rendering_metadata.txt``::

    <image_root>/<taxonomy>/<model>/00.png, 01.png, ...   # <image_root> is one set, e.g. .../Spherical
    <voxel_root>/<taxonomy>/<model>/model.binvox          # ShapeNetVox32: 32^3, made in ShapeNet's +Y-up frame

:class:`FolderTestSet` serves it as the batch dictionaries of :class:`~lightning_vtr.data.dataset.VTRDataset`
(``images`` ``(V, 3, H, W)``, ``voxels`` ``(R, R, R)``, ``viewpoints``, ``category``, ``object_id``,
``view_set``), so a model's ``test_step`` and :func:`evaluate_dataset` take it as they take ShapeNet-VTR.
The viewpoints are unknown there and are served as NaN.

Which ``num_views`` of an object's pictures an item uses (``view_choice``):

* ``"first"`` (default): the ``num_views`` lowest-numbered files, as Pix2Vox(++)'s test loader (which VTR's test
  script inherits) takes views ``0 .. n - 1``.
* ``"spread"``: evenly spaced over the sorted files, ``floor(i * N / n)`` for ``i = 0 .. n - 1`` (24 files, 3
  views: 00, 08, 16).
* ``"random"``: ``numpy.random.default_rng([seed, crc32("<taxonomy>/<model>")])`` draws ``n`` distinct files,
  so the choice depends only on the object and the seed, not on the order, the workers or the other objects.

Files are sorted by the number in their name (``2.png`` before ``10.png``); names without a number come after,
alphabetically. Voxels are read with :func:`lightning_vtr.data.dataset.load_voxels` from
:class:`~lightning_vtr.data.format.ObjectRecord` s that carry ``voxel_up_axis="y"``, exactly as
:class:`~lightning_vtr.data.shapenet_rendering.ShapeNetRenderingSource` reads ShapeNetVox32, so both readers put
the same file in the same package-frame grid (+Z up, ``V[i, j, k]`` with ``(x, y, z)`` indices).

:func:`evaluate_dataset` runs any model with ``predict_voxels`` over such a dataset (this one, Pix3D's or
``VTRDataset``) and returns the package's metrics overall and per category; :func:`format_evaluation_table`
prints them in the paper's Table 5 layout (``Method | mIoU | F-score``).
"""

from __future__ import annotations

import math
import re
import warnings
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from lightning_vtr.data.dataset import _transform, load_rgba, load_voxels
from lightning_vtr.data.format import SHAPENET_SYNSETS, SPLITS, ObjectRecord
from lightning_vtr.data.shapenet_rendering import _load_split_file
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation.tables import format_cell
from lightning_vtr.metrics.functional import DEFAULT_FSCORE_CONVENTION, DEFAULT_IOU_THRESHOLDS
from lightning_vtr.metrics.voxel import VoxelFScore, VoxelIoU
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = [
    "IMAGE_SUFFIXES",
    "VIEW_CHOICES",
    "FolderTestSet",
    "choose_views",
    "evaluate_dataset",
    "evaluate_folder",
    "evaluation_rows",
    "format_evaluation_table",
]

#: How :class:`FolderTestSet` picks an object's views (see the module docstring).
VIEW_CHOICES = ("first", "spread", "random")
#: Picture files of an object folder (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_NUMBER = re.compile(r"\d+")


def _picture_order(path: Path) -> tuple[int, int, str]:
    match = _NUMBER.search(path.stem)
    return (0, int(match.group()), path.name) if match else (1, 0, path.name)


def choose_views(count: int, num_views: int, rule: str = "first", key: Sequence[int] = (0,)) -> np.ndarray:
    """Indices of the ``num_views`` views an object with ``count`` sorted pictures uses (see the module docstring).

    Args:
        count: the object's number of pictures ``N``.
        num_views: how many to pick, at most ``N``.
        rule: one of :data:`VIEW_CHOICES`.
        key: the random generator's seed for ``"random"`` (the dataset passes ``(seed, crc32(object key))``).

    Example:
        >>> choose_views(24, 3, "first").tolist(), choose_views(24, 3, "spread").tolist()
        ([0, 1, 2], [0, 8, 16])
    """
    check_choice("view_choice", rule, VIEW_CHOICES)
    count = check_int("count", count, minimum=1)
    num_views = check_int("num_views", num_views, minimum=1, maximum=count)
    if rule == "first":
        return np.arange(num_views)
    if rule == "spread":
        return (np.arange(num_views) * count) // num_views
    return np.random.default_rng([int(k) for k in key]).choice(count, size=num_views, replace=False)


class FolderTestSet(Dataset):
    """Objects of a folder test set, one item each: ``num_views`` of its pictures and its voxels.

    Args:
        image_root: the set's folder, ``<image_root>/<taxonomy>/<model>/NN.png``.
        voxel_root: ``<voxel_root>/<taxonomy>/<model>/<voxel_name>`` (ShapeNetVox32).
        num_views: pictures per item.
        view_choice: one of :data:`VIEW_CHOICES` (see the module docstring).
        transform: RGBA uint8 pictures -> model input (default: the plain :class:`ImageTransform` at
            ``image_size``); use the transform the model was validated with.
        image_size: the default transform's output size.
        view_set: the ``view_set`` name items carry (a model's ``test_step`` logs under it); ``None``: the
            image root's folder name when it is one of :data:`~lightning_vtr.protocol.VIEW_SETS`
            (case-insensitive, so ``.../Spherical`` gives ``"spherical"``), else ``"aligned"``.
        seed: seeds ``view_choice="random"``.
        categories: keep only these taxonomies (ids such as ``03001627`` or names such as ``chair``).
        split_file: a Pix2Vox-style split JSON; only the models it lists under ``split`` are kept.
        split: the split of ``split_file`` to keep.
        voxel_up_axis: the up axis the voxel files were made in (``"y"`` for ShapeNetVox32, ``"z"`` for files
            this package writes).
        voxel_name: the voxel file in each model folder.
        missing: a model folder without its voxel file: ``"warn"`` (skip it, warn once with the count),
            ``"skip"`` or ``"error"``.

    Raises:
        FileNotFoundError: a root is not a directory, or (``missing="error"``) a voxel file is absent.
        ValueError: no object is left, or an object has fewer than ``num_views`` pictures (names the folder).
    """

    def __init__(
        self,
        image_root: str | Path,
        voxel_root: str | Path,
        *,
        num_views: int = 1,
        view_choice: str = "first",
        transform: Any = None,
        image_size: int = 224,
        view_set: str | None = None,
        seed: int = 0,
        categories: Sequence[str] | None = None,
        split_file: str | Path | None = None,
        split: str = "test",
        voxel_up_axis: str = "y",
        voxel_name: str = "model.binvox",
        missing: str = "warn",
    ) -> None:
        self.image_root = Path(image_root).expanduser()
        self.voxel_root = Path(voxel_root).expanduser()
        for name, path in (("image_root", self.image_root), ("voxel_root", self.voxel_root)):
            if not path.is_dir():
                raise FileNotFoundError(f"`{name}` must be a directory, got {str(path)!r}")
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.view_choice = check_choice("view_choice", view_choice, VIEW_CHOICES)
        check_choice("split", split, SPLITS)
        check_choice("voxel_up_axis", voxel_up_axis, ("y", "z"))
        check_choice("missing", missing, ("warn", "skip", "error"))
        self.transform = transform if transform is not None else ImageTransform(image_size)
        self.seed = int(seed)
        if view_set is None:
            folder = self.image_root.resolve().name.lower()
            view_set = folder if folder in VIEW_SETS else "aligned"
        self.view_set = view_set
        listed = self._listed(Path(split_file).expanduser(), split) if split_file is not None else None
        self.records = self._scan(categories, listed, voxel_up_axis, voxel_name, missing)

    @staticmethod
    def _listed(split_file: Path, split: str) -> set[tuple[str, str]]:
        if not split_file.is_file():
            raise FileNotFoundError(f"`split_file` {str(split_file)!r} does not exist")
        return {(str(e["taxonomy_id"]), str(m)) for e in _load_split_file(split_file) for m in e.get(split, [])}

    def _scan(
        self,
        categories: Sequence[str] | None,
        listed: set[tuple[str, str]] | None,
        up_axis: str,
        voxel_name: str,
        missing: str,
    ) -> list[ObjectRecord]:
        taxonomies = sorted(p for p in self.image_root.iterdir() if p.is_dir())
        if categories is not None:
            wanted = {str(c) for c in categories}
            known = {t.name for t in taxonomies} | {SHAPENET_SYNSETS.get(t.name, t.name) for t in taxonomies}
            unknown = sorted(wanted - known)
            if unknown:
                raise ValueError(
                    f"`categories` must name taxonomies of {str(self.image_root)!r} (ids or names: {sorted(known)}), "
                    f"got unknown {unknown}"
                )
            taxonomies = [t for t in taxonomies if {t.name, SHAPENET_SYNSETS.get(t.name, t.name)} & wanted]
        records, skipped = [], []
        for taxonomy in taxonomies:
            category = SHAPENET_SYNSETS.get(taxonomy.name, taxonomy.name)
            for model_dir in sorted(p for p in taxonomy.iterdir() if p.is_dir()):
                if listed is not None and (taxonomy.name, model_dir.name) not in listed:
                    continue
                pictures = sorted(
                    (p for p in model_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                    key=_picture_order,
                )
                if len(pictures) < self.num_views:
                    raise ValueError(
                        f"`num_views` must be at most the number of pictures of every object, got {self.num_views}; "
                        f"{str(model_dir)!r} has {len(pictures)}"
                    )
                voxel_path = self.voxel_root / taxonomy.name / model_dir.name / voxel_name
                if not voxel_path.is_file():
                    if missing == "error":
                        raise FileNotFoundError(f"{str(model_dir)!r} has no voxels: {str(voxel_path)!r} does not exist")
                    skipped.append(str(voxel_path))
                    continue
                viewpoints = np.full((len(pictures), 2), np.nan)
                records.append(
                    ObjectRecord(
                        category=category,
                        object_id=model_dir.name,
                        split="test",
                        voxel_path=voxel_path,
                        mesh_path=None,
                        views={self.view_set: (pictures, viewpoints)},
                        voxel_up_axis=up_axis,
                    )
                )
        if skipped and missing == "warn":
            warnings.warn(
                f"Skipped {len(skipped)} object(s) of {str(self.image_root)!r} without voxels, e.g. {skipped[0]}",
                stacklevel=3,
            )
        if not records:
            raise ValueError(
                f"no objects in {str(self.image_root)!r}: expected <taxonomy>/<model>/NN.png folders with voxels "
                f"at {str(self.voxel_root)!r}/<taxonomy>/<model>/{voxel_name}"
            )
        return records

    def __len__(self) -> int:
        return len(self.records)

    def view_indices(self, index: int) -> np.ndarray:
        """Positions (in the sorted pictures of object ``index``) of the views its item uses."""
        record = self.records[index]
        count = len(record.views[self.view_set][0])
        key = (self.seed, zlib.crc32(f"{Path(record.voxel_path).parent.parent.name}/{record.object_id}".encode()))
        return choose_views(count, self.num_views, self.view_choice, key)

    def view_paths(self, index: int) -> list[Path]:
        """The picture files item ``index`` uses, in order."""
        paths = self.records[index].views[self.view_set][0]
        return [paths[i] for i in self.view_indices(index)]

    def __getitem__(self, index: int) -> dict:
        record = self.records[index]
        images = np.stack([load_rgba(p) for p in self.view_paths(index)])
        return {
            "images": _transform(self.transform, images, (self.seed, 0, index)),
            "voxels": load_voxels(record),
            "viewpoints": torch.full((self.num_views, 2), float("nan")),
            "category": record.category,
            "object_id": record.object_id,
            "view_set": self.view_set,
        }


# ---------------------------------------------------------------------------------------------- evaluation
def _metric_key(threshold: float) -> str:
    return f"iou@{threshold:g}"


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
        dataset: items with ``images``, ``voxels`` and ``category`` (:class:`FolderTestSet`,
            :class:`~lightning_vtr.data.pix3d.Pix3DDataset`, ``VTRDataset``).
        batch_size, device, num_workers: of the forward passes.
        thresholds: the IoU thresholds (each gives ``iou@<t>``).
        fscore_threshold, fscore_points, fscore_convention: of :class:`~lightning_vtr.metrics.VoxelFScore`.

    Returns:
        ``{"overall": {...}, "categories": {category: {...}}, "best_threshold": t}``, each inner dict holding
        ``count``, ``iou@<t>`` for every threshold, ``iou_best`` and ``fscore`` (fractions in ``[0, 1]``).

    Raises:
        ValueError: the dataset is empty, or a prediction's shape is not the ground truth's (names both).
    """
    if len(dataset) == 0:
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
        out.update({_metric_key(t): float(v) for t, v in zip(iou.thresholds, values)})
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
    """Evaluate ``model`` on a folder test set: :class:`FolderTestSet` + :func:`evaluate_dataset`.

    ``num_views`` defaults to ``model.num_views`` and ``transform`` to the plain transform at
    ``model.image_size`` (pass the one the model was validated with, e.g.
    ``lightning_vtr.cli.predict.make_datamodule(ckpt, model).transform``); other keyword arguments go to
    :class:`FolderTestSet`.

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
    """Long-form rows for a CSV: one per method and group (``category`` is ``"all"`` for the overall row),
    with ``count``, every ``iou@<t>``, ``iou_best`` and ``fscore`` as fractions."""
    rows = []
    for method, result in results.items():
        groups = {"all": result.get("overall", {}), **result.get("categories", {})}
        for category, values in groups.items():
            row: dict[str, Any] = {"method": method, "category": category}
            row.update({k: v for k, v in values.items() if not (isinstance(v, float) and math.isnan(v))})
            rows.append(row)
    return rows

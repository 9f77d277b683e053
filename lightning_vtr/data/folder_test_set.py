"""Test sets that are folders of images plus voxels, without camera metadata.

The VTR authors released their test sets in the 3D-R2N2 / Pix2Vox layout without ``rendering_metadata.txt``::

    <image_root>/<taxonomy>/<model>/00.png, 01.png, ...   # <image_root> is one set, e.g. .../Spherical
    <voxel_root>/<taxonomy>/<model>/model.binvox          # ShapeNetVox32: 32^3, made in ShapeNet's +Y-up frame

:class:`FolderTestSet` serves it as the batch dictionaries of :class:`~lightning_vtr.data.dataset.VTRDataset`
(``images`` ``(V, 3, H, W)``, ``voxels`` ``(R, R, R)``, ``viewpoints``, ``category``, ``object_id``,
``view_set``), so a model's ``test_step`` and :func:`~lightning_vtr.evaluation.dataset.evaluate_dataset` take
it as they take ShapeNet-VTR. The viewpoints are unknown there and are served as NaN.

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

Pictures are the files ending in one of :data:`~lightning_vtr.data.format.IMAGE_SUFFIXES` (any case).
:func:`lightning_vtr.evaluation.dataset.evaluate_folder` evaluates a model on such a set.
"""

from __future__ import annotations

import re
import warnings
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from lightning_vtr.data.dataset import apply_image_transform, load_rgba, load_voxels
from lightning_vtr.data.format import IMAGE_SUFFIXES, SHAPENET_SYNSETS, SPLITS, ObjectRecord
from lightning_vtr.data.shapenet_rendering import read_split_file
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.paths import check_name, check_no_case_collisions
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = ["VIEW_CHOICES", "FolderTestSet", "choose_views"]

#: How :class:`FolderTestSet` picks an object's views (see the module docstring).
VIEW_CHOICES = ("first", "spread", "random")
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
        FileNotFoundError: a root is not a directory, ``split_file`` does not exist, or (``missing="error"``) a
            voxel file is absent.
        TypeError: ``num_views`` is not an int.
        ValueError: no object is left, an object has fewer than ``num_views`` pictures (names the folder),
            ``categories`` names a taxonomy the image root lacks, or ``num_views``, ``view_choice``, ``split``,
            ``voxel_up_axis`` or ``missing`` is out of range.

    Example::

        from lightning_vtr.data import FolderTestSet

        test_set = FolderTestSet("VTR/Spherical", "ShapeNetVox32", num_views=3, view_choice="spread")
        item = test_set[0]  # item["images"]: (3, 3, 224, 224), item["voxels"]: (32, 32, 32), view_set "spherical"
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
        return {(str(e["taxonomy_id"]), str(m)) for e in read_split_file(split_file) for m in e.get(split, [])}

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
            # Folder names become the names of the outputs written for them.
            check_name(taxonomy.name, source=self.image_root, entry="taxonomy folder")
            models = sorted(p for p in taxonomy.iterdir() if p.is_dir())
            for model_dir in models:
                check_name(model_dir.name, source=taxonomy, entry="model folder")
            check_no_case_collisions([p.name for p in models], source=taxonomy, entry="model folder")
            for model_dir in models:
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
            "images": apply_image_transform(self.transform, images, (self.seed, 0, index)),
            "voxels": load_voxels(record),
            "viewpoints": torch.full((self.num_views, 2), float("nan")),
            "category": record.category,
            "object_id": record.object_id,
            "view_set": self.view_set,
        }

"""Torch datasets over a ShapeNet-VTR directory and over generated (synthesized) view sets.

Both yield the batch dictionaries described in :mod:`lightning_vtr.protocol`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from torch.utils.data import Dataset

from lightning_vtr.data.binvox import read_binvox
from lightning_vtr.data.format import ObjectRecord
from lightning_vtr.data.transforms import IMAGENET_MEAN, IMAGENET_STD, ImageTransform
from lightning_vtr.errors import DataError
from lightning_vtr.utils.io import atomic_open, atomic_write
from lightning_vtr.utils.limits import image_side_limit, open_image
from lightning_vtr.utils.paths import check_name, join_under
from lightning_vtr.utils.validation import check_int

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "GeneratedDataset",
    "GeneratedSample",
    "ImageTransform",
    "VTRDataset",
    "apply_image_transform",
    "load_rgba",
    "load_voxels",
    "write_generated_sample",
]

# The last entry of a generated sample's augmentation key, which keeps it apart from the training objects' keys.
_GENERATED_STREAM = 1


def apply_image_transform(transform: Callable[..., Tensor], images: np.ndarray, key: tuple[int, ...]) -> Tensor:
    """``transform(images, key=key)`` for an :class:`ImageTransform`, ``transform(images)`` for any other callable.

    The datasets call every transform through this, so a user's one-argument callable keeps working while the
    package's transform draws its random parameters from ``key`` (``(seed, epoch, index)``).
    """
    return transform(images, key=key) if isinstance(transform, ImageTransform) else transform(images)


def load_rgba(path: str | Path, image_size: int | None = None, *, root: str | Path | None = None) -> np.ndarray:
    """Read an image file as ``(H, W, 4)`` uint8 RGBA (opaque alpha for RGB files).

    Args:
        path: the picture.
        image_size: the side of the dataset's images, where known: a picture whose header states more than
            :func:`~lightning_vtr.utils.limits.image_side_limit` of it per side is refused before decoding.
        root: the dataset's folder (``ObjectRecord.root``), where known: a picture whose resolved path is not
            inside it (a symlink leading out of the dataset) is refused.

    Raises:
        DataError: the picture is larger than the limit (names the file, its size and the limit); it is not a
            regular file (a FIFO, a device, a folder) or leads out of ``root``
            (:func:`~lightning_vtr.utils.limits.check_regular_file`).
        OSError: it cannot be read or decoded.
    """
    try:
        with open_image(path, image_side_limit(image_size), root=root) as img:
            return np.asarray(img.convert("RGBA"))
    except DataError:
        raise
    except (OSError, ValueError) as err:
        raise OSError(f"Cannot read image {path}: {err}") from err


def load_voxels(record: ObjectRecord) -> Tensor:
    """``(R, R, R)`` float occupancy of an object, in the package frame whatever its file's up axis; a file of
    another resolution than the record's dataset states is refused before its grid is allocated, and so is one
    leading out of the record's dataset folder (``record.root``) or that is not a regular file."""
    up_axis: Literal["y", "z"] = getattr(record, "voxel_up_axis", "z")  # read_binvox checks it
    resolution = getattr(record, "resolution", None)
    root = getattr(record, "root", None)
    voxels = read_binvox(record.voxel_path, up_axis=up_axis, resolution=resolution, root=root)
    return torch.from_numpy(voxels.astype(np.float32))


class VTRDataset(Dataset):
    """One item per object: ``num_views`` images of one view set, the object's voxels and viewpoints.

    In training the views are drawn afresh every epoch as a function of ``(seed, epoch, index)`` (call
    :meth:`set_epoch` before building each epoch's loader), so a resumed run and every DDP rank draw exactly
    the views an uninterrupted single-process run would; in evaluation (``train=False``) they are a fixed
    function of ``(seed, index)``. A random ``transform`` (a training recipe) is called with the key
    ``(seed, epoch, index)`` too, so its augmentation follows the same rule.

    In evaluation ``repeats > 1`` serves every object ``repeats`` times in a row (item ``i`` is object
    ``i // repeats``), each time with another fixed choice of views: more view sets per object cut the
    variance of a test mean at the cost of more forward passes, without more objects. The first choice of
    an object is the one ``repeats=1`` makes; the others are distinct from it and from each other whenever
    the object has enough views to make them so.

    Args:
        records: the objects, one item each (``repeats`` items each in evaluation).
        view_set: the view set the images are drawn from.
        num_views: images per item (at most the number of views of every object).
        transform: RGBA uint8 images -> model input (default :class:`ImageTransform`); an
            :class:`ImageTransform` gets the key ``(seed, epoch, index)``, any other callable the images only.
        train: draw views afresh every epoch (else a fixed choice per item).
        seed: seeds the view choice and the augmentation.
        repeats: items per object, each with its own fixed view choice; must be 1 in training.
    """

    def __init__(
        self,
        records: Sequence[ObjectRecord],
        view_set: str,
        *,
        num_views: int = 3,
        transform: ImageTransform | None = None,
        train: bool = False,
        seed: int = 0,
        repeats: int = 1,
    ) -> None:
        self.records = list(records)
        self.view_set = view_set
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.transform = transform or ImageTransform()
        self.train = train
        self.seed = int(seed)
        self.repeats = check_int("repeats", repeats, minimum=1)
        if train and self.repeats != 1:
            raise ValueError(
                f"`repeats` must be 1 in training (views are drawn afresh every epoch there), got {self.repeats}"
            )
        self.epoch = 0
        for rec in self.records:
            if view_set not in rec.views:
                raise KeyError(
                    f"Object {rec.category}/{rec.object_id} has no view set {view_set!r}; "
                    f"available: {sorted(rec.views)}"
                )
            available = len(rec.views[view_set][0])
            if available < self.num_views:
                raise ValueError(
                    f"`num_views` must be at most the number of views of each object, got {self.num_views}; "
                    f"object {rec.category}/{rec.object_id} has {available} in {view_set!r}"
                )

    def __len__(self) -> int:
        return len(self.records) * self.repeats

    def set_epoch(self, epoch: int) -> None:
        """Draw the training views and augmentations of ``epoch`` from now on (also the ``epoch`` attribute)."""
        self.epoch = check_int("epoch", epoch, minimum=0)

    def view_indices(self, index: int) -> np.ndarray:
        """Which of the object's views item ``index`` uses (fixed in evaluation)."""
        obj, repeat = divmod(index, self.repeats)
        available = len(self.records[obj].views[self.view_set][0])
        if self.train:
            return np.random.default_rng([self.seed, self.epoch, obj]).choice(available, self.num_views, replace=False)
        return self._eval_choices(obj, available)[repeat]

    def _eval_choices(self, obj: int, available: int) -> list[np.ndarray]:
        """The ``repeats`` fixed view choices of object ``obj``: the first keyed ``(seed, obj)`` as with one
        repeat, the others ``(seed, obj, r)``, redrawn while they repeat an earlier set of views (when the
        object has enough views for ``repeats`` distinct sets)."""
        distinct = math.comb(available, self.num_views) >= self.repeats
        choices: list[np.ndarray] = []
        seen: set[tuple[int, ...]] = set()
        for repeat in range(self.repeats):
            attempt = 0
            while True:
                key = [self.seed, obj] if repeat == 0 else [self.seed, obj, repeat, attempt]
                chosen = np.random.default_rng(key).choice(available, size=self.num_views, replace=False)
                views = tuple(sorted(chosen.tolist()))
                if not distinct or views not in seen:
                    break
                attempt += 1
            seen.add(views)
            choices.append(chosen)
        return choices

    def __getitem__(self, index: int) -> dict:
        rec = self.records[index // self.repeats]
        paths, viewpoints = rec.views[self.view_set]
        chosen = self.view_indices(index)
        images = np.stack([load_rgba(paths[i], rec.image_size, root=getattr(rec, "root", None)) for i in chosen])
        return {
            "images": apply_image_transform(self.transform, images, (self.seed, self.epoch, index)),
            "voxels": load_voxels(rec),
            "viewpoints": torch.as_tensor(np.asarray(viewpoints)[chosen], dtype=torch.float32),
            "category": rec.category,
            "object_id": rec.object_id,
            "view_set": self.view_set,
        }


@dataclass
class GeneratedSample:
    """A synthesized view set for one training object.

    Attributes:
        category: the object's category.
        object_id: the object's id.
        images: ``(T, H, W, 4)`` uint8 RGBA.
        viewpoints: ``(T, 2)`` (yaw, pitch) in degrees.
        epoch: the training epoch whose end produced it.

    Example:
        >>> images = np.zeros((3, 64, 64, 4), np.uint8)  # three RGBA views
        >>> viewpoints = np.array([[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]])  # (yaw, pitch) in degrees
        >>> sample = GeneratedSample("chair", "chair_0001", images, viewpoints, epoch=4)
        >>> sample.images.shape, sample.viewpoints.shape
        ((3, 64, 64, 4), (3, 2))
    """

    category: str
    object_id: str
    images: np.ndarray
    viewpoints: np.ndarray
    epoch: int = 0


def _atomic_save_png(image: np.ndarray, path: Path) -> None:
    with atomic_open(path, "wb") as f:
        Image.fromarray(image).save(f, format="PNG")


def write_generated_sample(sample: GeneratedSample, directory: Path) -> dict:
    """Write one sample's images (atomically, idempotently) into ``directory``; return its index entry."""
    directory.mkdir(parents=True, exist_ok=True)
    images = np.asarray(sample.images)
    viewpoints = np.asarray(sample.viewpoints, dtype=np.float64)
    if images.ndim != 4 or images.shape[-1] != 4 or images.dtype != np.uint8:
        raise ValueError(
            f"`images` of generated sample {sample.category}/{sample.object_id} must be (T, H, W, 4) uint8, "
            f"got {images.shape} {images.dtype}"
        )
    if viewpoints.shape != (images.shape[0], 2):
        raise ValueError(
            f"`viewpoints` of generated sample {sample.category}/{sample.object_id} must be ({images.shape[0]}, 2), "
            f"got {viewpoints.shape}"
        )
    names = [f"{i:02d}.png" for i in range(images.shape[0])]
    for image, name in zip(images, names):
        _atomic_save_png(image, join_under(directory, name, replace_link=True))
    return {
        "category": sample.category,
        "object_id": sample.object_id,
        "epoch": int(sample.epoch),
        "dir": directory.name,
        "images": names,
        "viewpoints": viewpoints.tolist(),
    }


class GeneratedDataset(Dataset):
    """Serves generated view sets (index entries from :func:`write_generated_sample`) as training items.

    A random ``transform`` draws a sample's augmentation from ``(seed, epoch, id, 1)``, ``id`` being the
    entry's stable sample id (its position when the entry has none), so it does not change when older
    samples are dropped and never coincides with a training object's key ``(seed, epoch, index)``.
    An entry's images are read from ``<entry["root"]>/<entry["dir"]>``, or ``<directory>/<entry["dir"]>`` when
    it has no ``"root"``.
    """

    def __init__(
        self,
        entries: Sequence[dict],
        directory: Path,
        records: dict[tuple[str, str], ObjectRecord],
        transform: ImageTransform | None = None,
        *,
        seed: int = 0,
        epoch: int = 0,
    ) -> None:
        self.entries = list(entries)
        self.directory = Path(directory)
        # The entries may come from a checkpoint made elsewhere: their names must stay inside `directory`.
        source = self.directory / "index.json"
        for entry in self.entries:
            check_name(entry["dir"], source=source, entry="generated sample dir")
            for name in entry["images"]:
                check_name(name, source=source, entry=f"image of sample {entry['dir']!r}")
        self.records = records
        self.transform = transform or ImageTransform()
        self.seed = int(seed)
        self.epoch = check_int("epoch", epoch, minimum=0)

    def __len__(self) -> int:
        return len(self.entries)

    def set_epoch(self, epoch: int) -> None:
        """Draw the augmentations of ``epoch`` from now on."""
        self.epoch = check_int("epoch", epoch, minimum=0)

    def __getitem__(self, index: int) -> dict:
        entry = self.entries[index]
        sample_dir = Path(entry.get("root", self.directory)) / entry["dir"]  # "root": the folder it was written to
        images = np.stack([load_rgba(sample_dir / name) for name in entry["images"]])
        key = (self.seed, self.epoch, int(entry.get("id", index)), _GENERATED_STREAM)
        return {
            "images": apply_image_transform(self.transform, images, key),
            "voxels": load_voxels(self.records[(entry["category"], entry["object_id"])]),
            "viewpoints": torch.as_tensor(entry["viewpoints"], dtype=torch.float32),
            "category": entry["category"],
            "object_id": entry["object_id"],
            "view_set": "generated",
        }


def dump_index(entries: Sequence[dict], path: Path) -> None:
    """Write the generated-sample index as JSON, atomically (for inspection; the checkpoint is authoritative)."""
    atomic_write(path, json.dumps(list(entries), indent=1))

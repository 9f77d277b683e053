"""``VTRDataModule``: the ShapeNet-VTR protocol (train on Aligned, test on all three view sets) as a
mutable LightningDataModule that accepts generated samples between epochs.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping, Sequence, Sized
from pathlib import Path
from typing import Any, cast

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_warn
from PIL import Image
from torch.utils.data import ConcatDataset, DataLoader, DistributedSampler

from lightning_vtr.data.dataset import (
    GeneratedDataset,
    GeneratedSample,
    VTRDataset,
    dump_index,
    load_rgba,
    load_voxels,
    write_generated_sample,
)
from lightning_vtr.data.format import ObjectRecord
from lightning_vtr.data.transforms import IMAGE_RECIPES, BackgroundFolder, ImageRecipe, ImageTransform
from lightning_vtr.protocol import VIEW_SETS, check_model_matches_data
from lightning_vtr.utils.paths import check_name, join_under
from lightning_vtr.utils.validation import check_choice, check_int, check_type

__all__ = ["VIEW_SETS", "VTRDataModule"]

_STATE_VERSION = 1
_SHAPENET_RENDERING_KEYS = ("rendering_root", "split_file", "voxel_root")


class _EpochSeededSampler(torch.utils.data.Sampler[int]):
    """A random permutation that depends only on ``seed``: the same order at every ``iter()``."""

    def __init__(self, length: int, seed: int) -> None:
        self.length = length
        self.seed = seed

    def __len__(self) -> int:
        return self.length

    def __iter__(self):
        return iter(torch.randperm(self.length, generator=torch.Generator().manual_seed(self.seed)).tolist())


class _UnpaddedShardSampler(DistributedSampler):
    """Rank ``r`` of ``n`` gets items ``r, r + n, r + 2n, ...`` of the dataset, in order, and nothing else.

    Lightning's default :class:`~torch.utils.data.DistributedSampler` repeats the first items until the
    dataset divides evenly among the ranks, so a test mean would count them twice. Shards here differ in
    length by at most one, which evaluation allows: no gradients are synced, and the metrics are synced once
    at the epoch's end. Being a ``DistributedSampler``, Lightning keeps it instead of injecting its own.
    """

    def __init__(self, dataset: torch.utils.data.Dataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)
        self.total_size = len(cast(Sized, dataset))  # the datasets served here are map-style, with a length
        self.num_samples = len(range(rank, self.total_size, num_replicas))

    def __iter__(self):
        return iter(range(self.rank, self.total_size, self.num_replicas))


class VTRDataModule(L.LightningDataModule):
    """Serves a ShapeNet-VTR dataset to Lightning: training, validation and one test dataloader per view set.

    Aligned/train for training, Aligned/val for validation (another view set with ``train_view_set``), and the
    test split of every view set as named test dataloaders (in ``test_view_sets`` order).

    Generated view sets enter through :meth:`add_samples`; they are written to ``generated_dir`` and
    appear from the next ``train_dataloader()`` call on (use ``reload_dataloaders_every_n_epochs=1``).
    The list of generated samples is part of :meth:`state_dict`, so a resumed run sees exactly the
    samples it had.

    Args:
        root: a directory written by ``lightning-vtr build-dataset``. ``None`` builds (once, cached) and
            uses the embedded procedural dataset, with ``embedded`` as build options.
        shapenet_rendering: instead of ``root``, a dict ``{"rendering_root", "voxel_root", "split_file"}``
            for the 3D-R2N2 / Pix2Vox layout (one view set, served as "aligned").
        num_views: images per sample. A model's declared ``num_views`` must equal it when training.
        image_size: side of the model input in pixels: images are resized to it. ``None`` takes the dataset's
            rendered size (``metadata.json``'s ``image_size``; with ``shapenet_rendering`` the side of the first
            object's first image), so nothing is resized. A model's declared ``image_size`` must equal it.
        background: RGB compositing background (in training too, unless ``background_range`` is given); or
            ``"folder:PATH"``: training views are composited over random crops of the images under ``PATH``
            (``.png``/``.jpg``/``.jpeg``, recursive; e.g. SUN backgrounds for the Pix3D protocol), one image
            and crop per view drawn from ``(seed, epoch, index)``; validation and test keep the recipe's
            background (white for ``"plain"``). It combines with any ``recipe``, whose colour range it replaces.
        normalize: ``"imagenet"``, ``"pm1"`` (``x * 2 - 1``, the same as mean = std = 0.5) or ``None``.
        background_range: training only: a per-sample random background, each channel an int in
            ``(low, high)`` inclusive (a pair for all channels, or three pairs); validation and test keep
            ``background``. ``None``: ``background`` in training too.
        recipe: the image recipe (see :data:`~lightning_vtr.data.transforms.IMAGE_RECIPES`): ``"plain"`` (the
            default; built from ``background``, ``normalize`` and ``background_range``), ``"pix2vox"`` or
            ``"lrgt"`` (the published recipes of Pix2Vox++ and LRGT), or an
            :class:`~lightning_vtr.data.transforms.ImageRecipe` (or a dict of its fields; the hyperparameters
            hold it as one, so ``hparams.yaml`` stays loadable). A recipe other than ``"plain"`` sets the
            background and normalisation itself: leave those three arguments at their defaults, or pass
            ``dataclasses.replace(IMAGE_RECIPES["pix2vox"], normalize="imagenet")`` to change one. Random
            training ops are drawn per ``(seed, epoch, index)``; use ``reload_dataloaders_every_n_epochs=1`` so
            every epoch draws its own.
        batch_size: per-process batch size.
        num_workers: dataloader workers.
        test_view_sets: view sets served by ``test_dataloader`` (one loader each, in this order).
        categories: restrict to these categories (``None``: all).
        generated_dir: where generated samples are written (default ``<trainer log dir>/vtr_generated``).
        max_generated: removed; must be ``None``. The cap on generated samples belongs to the caller of
            :meth:`add_samples` (its ``max_total``): ``ErrorGuidedViewAugmentation(max_samples=...)``.
        seed: fixes evaluation view choices.
        test_repeats: items per test object, each with its own fixed choice of ``num_views`` views (the same
            for every model tested with this ``seed``); test metrics average over all of them, every object
            weighing the same. More repeats cut the variance of a test mean without more objects.
        embedded: build options for the embedded dataset (see ``lightning_vtr.data.builder.build_dataset``).
        verify: at :meth:`setup`, read every image and voxel file of the dataset once
            (:func:`~lightning_vtr.data.verify.verify_dataset`) and raise one
            :class:`~lightning_vtr.data.format.DatasetFormatError` listing every missing, unreadable or
            inconsistent file, instead of failing at the first epoch that draws one. Under a distributed
            Trainer global rank 0 reads the files and every process raises. ShapeNet-VTR directories only (not
            ``shapenet_rendering``); ``lightning-vtr dataset-info ROOT --verify`` is the same check by hand.
        train_view_set: the view set of the train and validation splits: ``"aligned"`` (the paper's protocol),
            or ``"pix3d"`` for a dataset built with ``lightning-vtr build-dataset --protocol pix3d``.
        test_split: the split ``test_dataloader`` serves (``"test"``); ``"val"`` tests on the validation
            objects' view sets, with ``test_repeats`` items each, to choose among models without touching the
            test split.

    At :meth:`setup` under a Trainer, the Trainer's model is checked against the datamodule with
    :func:`~lightning_vtr.protocol.check_model_matches_data`: its declared ``image_size`` and
    ``voxel_resolution`` (and ``num_views`` when fitting) must equal :attr:`image_size`,
    :attr:`voxel_resolution` and ``num_views``; a model without these attributes is not checked.

    Raises:
        DatasetFormatError: at :meth:`setup`, with ``verify=True``, when the dataset has problems.
        ValueError: on invalid arguments, and for any ``max_generated`` but ``None`` (naming its replacement);
            at :meth:`setup`, when the Trainer's model declares another ``image_size``, ``voxel_resolution`` or
            (when fitting) ``num_views`` (one line naming both values).

    Example:
        >>> dm = VTRDataModule(num_views=3, batch_size=8)  # doctest: +SKIP
        >>> trainer.fit(model, datamodule=dm)  # doctest: +SKIP
        >>> dm = VTRDataModule(recipe="pix2vox", image_size=224)  # doctest: +SKIP
    """

    def __init__(
        self,
        root: str | None = None,
        *,
        shapenet_rendering: dict[str, str] | None = None,
        num_views: int = 3,
        image_size: int | None = None,
        background: tuple[int, int, int] | str = (255, 255, 255),
        normalize: str | None = "imagenet",
        batch_size: int = 32,
        num_workers: int = 0,
        test_view_sets: Sequence[str] = VIEW_SETS,
        categories: Sequence[str] | None = None,
        generated_dir: str | None = None,
        max_generated: int | None = None,
        seed: int = 0,
        test_repeats: int = 1,
        embedded: dict[str, Any] | None = None,
        background_range: Sequence[int] | Sequence[Sequence[int]] | None = None,
        recipe: ImageRecipe | str | Mapping[str, Any] = "plain",
        verify: bool = False,
        train_view_set: str = "aligned",
        test_split: str = "test",
    ) -> None:
        super().__init__()
        if root is not None and shapenet_rendering is not None:
            raise ValueError(
                "`shapenet_rendering` must be None when `root` (a ShapeNet-VTR directory) is given, "
                f"got {shapenet_rendering!r}"
            )
        check_int("num_views", num_views, minimum=1)
        if image_size is not None:
            check_int("image_size", image_size, minimum=1)
        check_int("batch_size", batch_size, minimum=1)
        check_int("num_workers", num_workers, minimum=0)
        check_int("test_repeats", test_repeats, minimum=1)
        if max_generated is not None:
            raise ValueError(
                f"`max_generated` must be None (the datamodule no longer caps generated samples), got "
                f"{max_generated!r}; cap them with `ErrorGuidedViewAugmentation(max_samples=...)`, or "
                "`add_samples(samples, max_total=...)` when adding samples yourself"
            )
        if shapenet_rendering is not None:
            check_type("shapenet_rendering", shapenet_rendering, Mapping, "dict")
            missing = set(_SHAPENET_RENDERING_KEYS) - set(shapenet_rendering)
            if missing:
                raise ValueError(
                    f"`shapenet_rendering` must have the keys {list(_SHAPENET_RENDERING_KEYS)}, "
                    f"got {shapenet_rendering!r} (missing {sorted(missing)})"
                )
        check_type("verify", verify, bool, "bool")
        check_type("train_view_set", train_view_set, str, "str")
        check_choice("test_split", test_split, ("test", "val"))
        if verify and shapenet_rendering is not None:
            raise ValueError(
                "`verify` must be False with `shapenet_rendering` (it checks ShapeNet-VTR directories), "
                f"got verify={verify!r}"
            )
        self.save_hyperparameters(ignore=["max_generated"])
        if isinstance(recipe, ImageRecipe):
            self.hparams["recipe"] = dataclasses.asdict(recipe)
        self.root = Path(root).expanduser() if root is not None else None
        self.shapenet_rendering = shapenet_rendering
        self.num_views = int(num_views)
        colour, background_folder = _split_background(background, background_range)
        self.recipe = _resolve_recipe(recipe, colour, normalize, background_range)
        if background_folder is not None:
            self.recipe = dataclasses.replace(self.recipe, background_folder=background_folder)
        self._image_size = None if image_size is None else int(image_size)
        self._dataset_sizes: dict[str, int] | None = None  # the dataset's image size and voxel resolution, once read
        self._transforms: tuple[ImageTransform, ImageTransform] | None = None  # (eval, train), once the size is known
        if image_size is not None:
            self._transforms = self._build_transforms(int(image_size))
        elif self.recipe.background_folder is not None:
            BackgroundFolder(self.recipe.background_folder)  # a missing or empty folder fails here, as with a size
        self.batch_size = int(batch_size)
        self.num_workers = int(num_workers)
        self.test_view_sets = tuple(test_view_sets)
        self._category_filter = tuple(categories) if categories is not None else None
        self.seed = int(seed)
        self.test_repeats = int(test_repeats)
        self.embedded = dict(embedded or {})
        self._generated_dir_arg = generated_dir
        self._write_dir: Path | None = None  # where this run writes new samples, resolved at first use
        self.verify = verify
        self.train_view_set = train_view_set
        self.test_split = test_split
        self._records: list[ObjectRecord] | None = None
        self._generated: list[dict] = []
        self._next_sample_id = 0

    # ------------------------------------------------------------------ data discovery
    def prepare_data(self) -> None:
        if self.root is None and self.shapenet_rendering is None:
            from lightning_vtr.data.builder import ensure_embedded_dataset

            ensure_embedded_dataset(**self.embedded)

    def _resolve_root(self) -> Path | None:
        if self.root is None and self.shapenet_rendering is None:
            from lightning_vtr.data.builder import ensure_embedded_dataset

            self.root = Path(ensure_embedded_dataset(**self.embedded))
        return self.root

    def setup(self, stage: str | None = None) -> None:
        """Read the dataset (once), then check the Trainer's model against it (every call under a Trainer).

        Raises:
            ValueError: the Trainer's model declares another ``image_size``, ``voxel_resolution`` or, when
                ``stage`` is ``"fit"``, ``num_views`` than this datamodule serves
                (:func:`~lightning_vtr.protocol.check_model_matches_data`).
        """
        self._load_records()
        model = self.trainer.lightning_module if self.trainer is not None else None
        if model is not None:
            check_model_matches_data(model, self, training=stage in (None, "fit"))

    def _load_records(self) -> None:
        if self._records is not None:
            return
        root = self._resolve_root()
        if self.shapenet_rendering is not None:
            from lightning_vtr.data.shapenet_rendering import ShapeNetRenderingSource

            records = list(ShapeNetRenderingSource(**self.shapenet_rendering))
        else:
            from lightning_vtr.data.format import scan_dataset

            assert root is not None, "_resolve_root sets a root when there is no shapenet_rendering"
            if self.verify:
                self._verify(root)
            records = scan_dataset(root)
        if self._category_filter is not None:
            unknown = set(self._category_filter) - {r.category for r in records}
            if unknown:
                raise ValueError(
                    f"`categories` must be categories of the dataset at {root}, got unknown {sorted(unknown)}"
                )
            records = [r for r in records if r.category in self._category_filter]
        # A fixed order makes every process (and every resumed run) index objects identically.
        self._records = sorted(records, key=lambda r: (r.category, r.object_id))
        self._by_key = {(r.category, r.object_id): r for r in self._records}

    def _verify(self, root: Path) -> None:
        """Raise one :class:`DatasetFormatError` listing every problem of the dataset at ``root``.

        Under a distributed Trainer global rank 0 reads the files and every process raises its message, so a
        node's processes do not each read the whole dataset.
        """
        from lightning_vtr.data.format import DatasetFormatError
        from lightning_vtr.data.verify import verify_dataset

        trainer = self.trainer
        distributed = trainer is not None and trainer.world_size > 1
        message = None
        if trainer is None or not distributed or trainer.is_global_zero:
            report = verify_dataset(root, progress=trainer is None or trainer.is_global_zero)
            message = None if report.ok else report.error_message()
        if trainer is not None and distributed:
            message = trainer.strategy.broadcast(message, src=0)
        if message:
            raise DatasetFormatError(message)

    @property
    def records(self) -> list[ObjectRecord]:
        self._load_records()
        assert self._records is not None, "setup sets the records"
        return self._records

    def split_records(self, split: str) -> list[ObjectRecord]:
        """Objects of one split (``"train"``, ``"val"`` or ``"test"``), in a fixed order."""
        return [r for r in self.records if r.split == split]

    @property
    def categories(self) -> list[str]:
        """The dataset's category names, sorted (the vocabulary models use for per-category metrics)."""
        return sorted({r.category for r in self.records})

    # ------------------------------------------------------------------ sizes and transforms
    @property
    def image_size(self) -> int:
        """Side in pixels of the images served: ``image_size`` if given, else the dataset's rendered size.

        Raises:
            ValueError: with ``shapenet_rendering``, the first image is not square or there are no objects.
        """
        if self._image_size is not None:
            return self._image_size
        return self._read_dataset_sizes()["image_size"]

    @property
    def voxel_resolution(self) -> int:
        """``R`` of the ``(R, R, R)`` voxel grids served: the dataset's (``metadata.json``'s ``resolution``; with
        ``shapenet_rendering`` the first object's grid)."""
        return self._read_dataset_sizes()["resolution"]

    @property
    def transform(self) -> ImageTransform:
        """The validation/test (and the callback's) transform, at :attr:`image_size`: RGBA uint8
        ``(T, H, W, 4)`` -> ``(T, 3, S, S)`` float."""
        return self._transform_pair()[0]

    @property
    def train_transform(self) -> ImageTransform:
        """The training transform: :attr:`transform` plus the recipe's random ops (the same object without any)."""
        return self._transform_pair()[1]

    def _build_transforms(self, image_size: int) -> tuple[ImageTransform, ImageTransform]:
        evaluation = self.recipe.eval_transform(image_size)
        differs = self.recipe.is_random or self.recipe.background_range is not None
        return evaluation, (self.recipe.train_transform(image_size) if differs else evaluation)

    def _transform_pair(self) -> tuple[ImageTransform, ImageTransform]:
        if self._transforms is None:
            self._transforms = self._build_transforms(self.image_size)
        return self._transforms

    def _read_dataset_sizes(self) -> dict[str, int]:
        """``{"image_size", "resolution"}`` of the dataset, read once."""
        if self._dataset_sizes is not None:
            return self._dataset_sizes
        if self.shapenet_rendering is None:
            from lightning_vtr.data.format import load_metadata

            root = self._resolve_root()
            assert root is not None, "_resolve_root sets a root when there is no shapenet_rendering"
            meta = load_metadata(root)
            sizes = {"image_size": int(meta["image_size"]), "resolution": int(meta["resolution"])}
        else:
            if not self.records:
                raise ValueError(
                    f"`shapenet_rendering` {self.shapenet_rendering!r} has no objects to read the image size from"
                    + (f" (categories={list(self._category_filter)})" if self._category_filter else "")
                    + "; pass `image_size`"
                )
            first = self.records[0]
            path = next(iter(first.views.values()))[0][0]
            with Image.open(path) as image:
                width, height = image.size
            if width != height:
                raise ValueError(
                    f"`image_size` must be given for `shapenet_rendering` images that are not square: {path} is "
                    f"{width}x{height} pixels"
                )
            sizes = {"image_size": int(width), "resolution": int(load_voxels(first).shape[0])}
        self._dataset_sizes = sizes
        return sizes

    @property
    def generated_dir(self) -> Path:
        """Where this run writes new generated samples: ``generated_dir`` if given, else the running Trainer's
        ``<log dir>/vtr_generated`` (``<root>/generated/vtr_generated`` without a Trainer), so a shared, read-only
        dataset is never written to and a resumed run never writes into the run it resumes. Fixed once first
        resolved. Samples restored from a checkpoint are read from the folder their entry names (``"root"``)."""
        if self._write_dir is None:
            if self._generated_dir_arg is not None:
                base = Path(self._generated_dir_arg).expanduser()
            elif self.trainer is not None:  # `log_dir` is a collective under DDP: every rank resolves it
                base = Path(self.trainer.log_dir or self.trainer.default_root_dir) / "vtr_generated"
            else:
                base = Path(self.root if self.root is not None else ".") / "generated" / "vtr_generated"
            self._write_dir = base.absolute()
        return self._write_dir

    # ------------------------------------------------------------------ loaders
    def _dataset(self, split: str, view_set: str, train: bool, repeats: int = 1) -> VTRDataset:
        return VTRDataset(
            self.split_records(split),
            view_set,
            num_views=self.num_views,
            transform=self.train_transform if train else self.transform,
            train=train,
            seed=self.seed,
            repeats=repeats,
        )

    def _epoch(self) -> int:
        return int(self.trainer.current_epoch) if self.trainer is not None else 0

    def train_dataset(self) -> torch.utils.data.Dataset:
        base = self._dataset("train", self.train_view_set, train=True)
        base.set_epoch(self._epoch())
        if not self._generated:
            return base
        generated = GeneratedDataset(
            self._generated, self.generated_dir, self._by_key, self.train_transform, seed=self.seed, epoch=self._epoch()
        )
        return ConcatDataset([base, generated])

    def _loader(self, dataset: torch.utils.data.Dataset, shuffle: bool) -> DataLoader:
        # Shuffling seeded by (seed, epoch) afresh at every iter(): the data order is a function of the epoch
        # alone, however often Lightning iterates the loader, so a resumed run trains on exactly the batches
        # an uninterrupted run would. (Under DDP Lightning swaps in a DistributedSampler, seeded likewise.)
        # The datasets served here are map-style, with a length.
        sampler = (
            _EpochSeededSampler(len(cast(Sized, dataset)), self.seed * 100_003 + self._epoch()) if shuffle else None
        )
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
            persistent_workers=False,
            drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        reload = getattr(self.trainer, "reload_dataloaders_every_n_epochs", 1) if self.trainer is not None else 1
        if self.train_transform.is_random and reload != 1:
            rank_zero_warn(
                f"VTRDataModule: the recipe's random image ops are drawn per (seed, epoch, index) when the train "
                f"loader is built; with `reload_dataloaders_every_n_epochs={reload}` some epochs reuse an earlier "
                "epoch's augmentations. Set it to 1 for fresh ones every epoch."
            )
        return self._loader(self.train_dataset(), shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("val", self.train_view_set, train=False), shuffle=False)

    def test_dataloader(self) -> list[DataLoader]:
        """One loader per view set of ``test_view_sets``. Under a distributed Trainer each process gets its own
        shard, without the repeated items Lightning's sampler pads with, so every test object counts once."""
        loaders = []
        for name in self.test_view_sets:
            dataset = self._dataset(self.test_split, name, train=False, repeats=self.test_repeats)
            shards = self.trainer.distributed_sampler_kwargs if self.trainer is not None else None
            if shards and shards.get("num_replicas", 1) > 1:
                sampler = _UnpaddedShardSampler(dataset, shards["num_replicas"], shards["rank"])
                loaders.append(
                    DataLoader(dataset, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers)
                )
            else:
                loaders.append(self._loader(dataset, shuffle=False))
        return loaders

    def predict_dataloader(self) -> list[DataLoader]:
        """The test split of every view set in ``test_view_sets`` (``Trainer.predict``, ``lightning-vtr predict``)."""
        return self.test_dataloader()

    # ------------------------------------------------------------------ what the callback uses
    def object_views(
        self, record: ObjectRecord, view_set: str = "aligned", indices: Sequence[int] | np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(images (V, H, W, 4) uint8, viewpoints (V, 2) degrees)`` of one object's view set."""
        paths, viewpoints = record.views[view_set]
        idx = list(range(len(paths))) if indices is None else list(indices)
        images = [
            load_rgba(paths[i], getattr(record, "image_size", None), root=getattr(record, "root", None)) for i in idx
        ]
        return np.stack(images), np.asarray(viewpoints, dtype=np.float64)[idx]

    def object_voxels(self, record: ObjectRecord) -> torch.Tensor:
        """``(R, R, R)`` float occupancy of one object."""
        return load_voxels(record)

    def eval_item(self, record: ObjectRecord, view_set: str = "aligned", seed: int = 0) -> dict:
        """A model-ready item of ``num_views`` views of ``record`` chosen as a fixed function of ``seed``."""
        paths, _ = record.views[view_set]
        rng = np.random.default_rng([self.seed, seed, int(hashlib.sha1(record.object_id.encode()).hexdigest()[:8], 16)])
        chosen = rng.choice(len(paths), size=self.num_views, replace=False)
        images, viewpoints = self.object_views(record, view_set, chosen)
        return {
            "images": self.transform(images),
            "voxels": self.object_voxels(record),
            "viewpoints": torch.as_tensor(viewpoints, dtype=torch.float32),
            "category": record.category,
            "object_id": record.object_id,
        }

    def record(self, category: str, object_id: str) -> ObjectRecord:
        """The record of one object.

        Raises:
            KeyError: no such object (after the ``categories`` filter).
        """
        return self._by_key[(category, object_id)]

    @property
    def generated_samples(self) -> list[dict]:
        """Index entries of the generated samples currently served (a copy)."""
        return [dict(e) for e in self._generated]

    def add_samples(self, samples: Sequence[GeneratedSample], *, max_total: int | None = None) -> list[dict]:
        """Persist generated view sets and serve them from the next ``train_dataloader()`` on.

        Every process must call this with the same samples in the same order (the callback does), so
        every rank's dataset stays identical. Writing is atomic and idempotent per file, so processes
        sharing a filesystem may write the same sample concurrently.

        Args:
            samples: the new samples, in the order they get ids.
            max_total: after adding, keep only the newest ``max_total`` generated samples (the oldest are no
                longer served; their files stay); ``None``: keep all.

        Returns:
            The new index entries (those of samples dropped at once by ``max_total`` included).

        Raises:
            KeyError: a sample of an object the datamodule does not have.
            ValueError: ``max_total`` is negative.

        Example:
            >>> dm.add_samples(samples, max_total=100)  # doctest: +SKIP
        """
        if max_total is not None:
            check_int("max_total", max_total, minimum=0)
        self._load_records()
        directory = self.generated_dir
        if not getattr(self, "_stale_removed", False):  # a killed run's half-written files, once per run
            from lightning_vtr.utils.io import remove_stale_temporaries

            remove_stale_temporaries(directory)
            self._stale_removed = True
        new = []
        for sample in samples:
            if (sample.category, sample.object_id) not in self._by_key:
                raise KeyError(f"add_samples: unknown object {sample.category}/{sample.object_id}")
            sample_dir = join_under(directory, f"{self._next_sample_id:07d}_{sample.category}_{sample.object_id}")
            entry = write_generated_sample(sample, sample_dir)
            entry["root"] = str(directory)
            entry["id"] = self._next_sample_id
            self._next_sample_id += 1
            new.append(entry)
        self._generated.extend(new)
        if max_total is not None and len(self._generated) > max_total:
            self._generated = self._generated[len(self._generated) - max_total :]
        if new and (self.trainer is None or self.trainer.is_global_zero):
            dump_index(self._generated, directory / "index.json")
        return new

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": _STATE_VERSION,
            "generated": [dict(e) for e in self._generated],
            "next_sample_id": self._next_sample_id,
            "generated_dir": str(self.generated_dir) if self._generated else None,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        version = state_dict.get("version", 1)
        if version > _STATE_VERSION:
            raise ValueError(
                f"This checkpoint's VTRDataModule state has version {version}; this lightning_vtr reads <= {_STATE_VERSION}"
            )
        self._generated = [dict(e) for e in state_dict.get("generated", [])]
        self._next_sample_id = int(state_dict.get("next_sample_id", len(self._generated)))
        saved_dir = state_dict.get("generated_dir")  # version 1 entries have no "root": they lived here
        for entry in self._generated:  # a checkpoint from elsewhere names folders under generated_dir
            check_name(entry["dir"], source="the checkpoint's VTRDataModule state", entry="generated sample dir")
            root = entry.get("root") or saved_dir or str(self.generated_dir)
            # moved since: found under the `generated_dir` given
            if self._generated_dir_arg is not None and not (Path(root) / entry["dir"]).is_dir():
                root = str(Path(self._generated_dir_arg).expanduser().absolute())
            entry["root"] = root
        missing = [
            str(Path(e["root"]) / e["dir"]) for e in self._generated if not (Path(e["root"]) / e["dir"]).is_dir()
        ]
        if missing:
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            raise FileNotFoundError(
                f"The checkpoint lists {len(missing)} generated samples whose folders are missing: "
                f"{', '.join(missing[:5])}{more}. Pass `generated_dir` pointing at the folder that now holds the "
                "checkpointed run's generated samples."
            )


_FOLDER_PREFIX = "folder:"


def _split_background(background: Sequence[int] | str, background_range: Any) -> tuple[Sequence[int], str | None]:
    """``(colour, folder)``: an RGB ``background`` as is, or ``"folder:PATH"`` as the plain colour and ``PATH``."""
    if not isinstance(background, str):
        return background, None
    folder = background[len(_FOLDER_PREFIX) :].strip() if background.startswith(_FOLDER_PREFIX) else ""
    if not folder:
        raise ValueError(f"`background` must be three ints (R, G, B) or 'folder:PATH', got {background!r}")
    if background_range is not None:
        raise ValueError(
            f"`background_range` must be None with `background={background!r}` (the folder's crops are the "
            f"training background), got {background_range!r}"
        )
    return IMAGE_RECIPES["plain"].background, folder


def _resolve_recipe(
    recipe: ImageRecipe | str | Mapping[str, Any],
    background: Sequence[int],
    normalize: str | None,
    background_range: Sequence[int] | Sequence[Sequence[int]] | None,
) -> ImageRecipe:
    """The datamodule's image recipe: ``"plain"`` from the three arguments, else the named or given recipe,
    which must not meet a non-default background or normalisation it would silently override."""
    if isinstance(recipe, str):
        check_choice("recipe", recipe, tuple(IMAGE_RECIPES))
        if recipe == "plain":
            # ImageRecipe.__post_init__ checks the given sequences and stores them as its tuple fields.
            return ImageRecipe(
                background=cast("tuple[int, int, int]", background),
                background_range=cast("tuple[tuple[int, int], ...] | None", background_range),
                normalize=normalize,
            )
        resolved = IMAGE_RECIPES[recipe]
    elif isinstance(recipe, Mapping):
        resolved = ImageRecipe(**recipe)
    else:
        resolved = check_type("recipe", recipe, ImageRecipe, "a recipe name, an ImageRecipe or a dict of its fields")
    given = {"background": background, "normalize": normalize, "background_range": background_range}
    for name, value in given.items():
        default = getattr(IMAGE_RECIPES["plain"], name)
        if value is None or default is None or isinstance(value, str):
            is_default = value == default
        else:
            is_default = tuple(value) == tuple(default)
        if not is_default:
            raise ValueError(
                f"`{name}` must be left at its default {default!r} with `recipe={recipe!r}`, which sets it "
                f"({getattr(resolved, name)!r}), got {value!r}; pass "
                f"`recipe=dataclasses.replace(<recipe>, {name}=...)` to change it"
            )
    return resolved

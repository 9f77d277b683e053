"""The shared LightningModule base of the package's reconstruction models.

:class:`VoxelReconstructionModule` satisfies :class:`~lightning_vtr.protocol.ReconstructionModel`
and holds everything that does not depend on the network: input checks, the training /
validation / test steps, and IoU / F-score logging per view set and per category. A model
(the package's Pix2Vox++ and LRGT, or a user's own) subclasses it and implements three things:

* ``reconstruct(images)``: the network. ``images`` ``(B, V, 3, H, W)`` (already checked) ->
  a dict of outputs that holds at least ``"voxels"``, the final occupancy probabilities
  ``(B, R, R, R)``; other entries (coarse volumes, logits, ...) are for the loss.
* ``loss(outputs, target)``: scalar training loss from that dict and the ground truth
  ``(B, R, R, R)``.
* ``configure_optimizers()``: as in any LightningModule.

and calls ``super().__init__(image_size=..., num_views=..., voxel_resolution=...)``. The base then
provides ``forward(images) -> dict`` (checks, then ``reconstruct``), ``predict_voxels(images) ->
(B, R, R, R)``, and the steps. Logged keys:

* ``train/loss``; ``val/loss``, ``val/iou@0.2`` ... ``val/iou@0.5``, ``val/fscore`` (validation
  loaders hold Aligned views);
* ``test/<set>/iou@<t>``, ``test/<set>/fscore``, ``test/<set>/<category>/iou@<t>``,
  ``test/<set>/<category>/fscore`` for each view set ``<set>`` in ``aligned`` / ``hemispherical``
  / ``spherical`` present in the test batches (``batch["view_set"]``, one name per sample;
  a batch without it counts as Aligned).

Metrics are accumulated in torchmetrics objects (one per view set, created up front) and synced
across processes at epoch end. Under DDP every test object counts once: ``VTRDataModule`` shards the test
set without padding, and :meth:`test_step` drops the repeats a padding ``DistributedSampler`` (Lightning's
default for other loaders) adds, so test means equal one process's. Per-category results need the
category vocabulary to be identical on every process under DDP: pass ``categories`` or let :meth:`setup`
take ``datamodule.categories``.
:func:`lightning_vtr.evaluation.tables.results_from_test_output` turns ``trainer.test(...)`` output into
the nested dict the paper-style table takes.

:meth:`VoxelReconstructionModule.load_from_checkpoint` builds the model inside
:func:`~lightning_vtr.models.weights.restoring_checkpoint`: a model reads no pretrained weight file
then (its hyperparameters still name the file), because the checkpoint's state dict holds every weight.
A checkpoint therefore loads on a machine without that file.
"""

from __future__ import annotations

import abc
import math
import os
import warnings
from collections.abc import Iterable, Sequence, Sized
from typing import IO, TYPE_CHECKING, Any, ClassVar, TypeVar, cast

import lightning as L
import torch
from torch import Tensor, nn
from torch.utils.data import DistributedSampler

from lightning_vtr.metrics import VoxelFScore, VoxelIoU
from lightning_vtr.metrics.functional import DEFAULT_IOU_THRESHOLDS, threshold_key
from lightning_vtr.models.weights import restoring_checkpoint
from lightning_vtr.protocol import DEFAULT_THRESHOLD, VIEW_SETS
from lightning_vtr.utils.validation import check_choice, check_int, check_type

try:  # Lightning's classmethod that refuses to be called on an instance (whose result would be dropped)
    from lightning.pytorch.utilities.model_helpers import _restricted_classmethod
except ImportError:  # pragma: no cover - depends on the Lightning version
    _restricted_classmethod = classmethod  # type: ignore[misc]  # the stand-in for older Lightning

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self needs Python 3.11

__all__ = ["VIEW_SETS", "VoxelReconstructionModule", "build_adam"]


#: Devices whose Adam and AdamW have a fused kernel in every torch release the package supports.
_FUSED_ADAM_DEVICES = ("cpu", "cuda")

_AdamT = TypeVar("_AdamT", torch.optim.Adam, torch.optim.AdamW)


def build_adam(optimizer_class: type[_AdamT], params: Iterable[Any], **kwargs: Any) -> _AdamT:
    """``optimizer_class(params, **kwargs)`` (``torch.optim.Adam`` or ``AdamW``), with torch's fused step where
    every parameter allows it.

    The fused step updates all parameters in one kernel per device; the default one loops over the parameters
    in Python on the CPU. It is the same update up to
    rounding, and needs floating-point parameters on the CPU or CUDA (otherwise the optimizer is torch's
    default). The fused kernel reads a gradient in its parameter's memory layout: a gradient in another layout
    (autograd never makes one; code that assigns ``.grad`` can) would be updated element by element against the
    wrong weights, so before each step such a gradient is copied into its parameter's layout.

    Args:
        optimizer_class: ``torch.optim.Adam`` or ``torch.optim.AdamW``.
        params: parameters or parameter groups, as the optimizer takes them.
        kwargs: the optimizer's other arguments (not ``fused``).

    Example:
        >>> build_adam(torch.optim.Adam, [nn.Parameter(torch.zeros(3))], lr=1e-3).defaults["fused"]
        True
    """
    items = list(params)
    tensors = [t for item in items for t in (item["params"] if isinstance(item, dict) else [item])]
    fused = bool(tensors) and all(t.is_floating_point() and t.device.type in _FUSED_ADAM_DEVICES for t in tensors)
    optimizer = optimizer_class(items, fused=fused or None, **kwargs)
    if fused:
        optimizer.register_step_pre_hook(_gradients_in_parameter_layout)
    return optimizer


def _gradients_in_parameter_layout(optimizer: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
    for group in optimizer.param_groups:
        for p in group["params"]:
            if p.grad is not None and p.grad.stride() != p.stride():
                p.grad = torch.empty_like(p).copy_(p.grad)


def _metric_group(group: nn.Module) -> dict[str, VoxelIoU | VoxelFScore]:
    """The metrics of a group ``{"iou": VoxelIoU, "fscore": VoxelFScore}`` (``nn.ModuleDict`` types them ``Module``)."""
    return cast("dict[str, VoxelIoU | VoxelFScore]", dict(cast(nn.ModuleDict, group).items()))


class VoxelReconstructionModule(L.LightningModule, abc.ABC):
    """Base LightningModule for multi-view voxel reconstruction (see the module docstring).

    Args:
        image_size: square input size ``H = W`` in pixels.
        num_views: number of input views per sample during training (any number works at test time).
        voxel_resolution: ``R`` of the ``(B, R, R, R)`` output.
        iou_thresholds: thresholds of the logged IoU.
        fscore_threshold: binarisation threshold of the F-score.
        fscore_points: points sampled per surface for the F-score.
        validation_fscore: also compute the F-score during validation (it samples surface points per object).
        categories: category vocabulary for per-category test metrics; ``None`` takes
            ``trainer.datamodule.categories`` at setup when it exists, else grows as names are seen
            (fine on one process; under DDP give it explicitly).
        log_sheets: objects of the first validation batch whose sheets (input views | prediction | ground
            truth | error | error projection, :func:`lightning_vtr.visualize.log_validation_sheets`) are logged
            every validation epoch, to any logger (PNG files for CSV); 0 (the default) logs none.

    Raises:
        TypeError: if a size or ``log_sheets`` is not an int.
        ValueError: if a size is not positive, or ``log_sheets`` is negative.

    Example:
        >>> class MeanShape(VoxelReconstructionModule):  # one learned shape for every input
        ...     def __init__(self):
        ...         super().__init__(image_size=32, num_views=2, voxel_resolution=8)
        ...         self.logits = nn.Parameter(torch.zeros(8, 8, 8))
        ...
        ...     def reconstruct(self, images):
        ...         return {"voxels": torch.sigmoid(self.logits).expand(len(images), 8, 8, 8)}
        ...
        ...     def loss(self, outputs, target):
        ...         return nn.functional.binary_cross_entropy(outputs["voxels"], target)
        ...
        ...     def configure_optimizers(self):
        ...         return torch.optim.Adam(self.parameters(), lr=1e-3)
        >>> MeanShape().predict_voxels(torch.zeros(4, 2, 3, 32, 32)).shape
        torch.Size([4, 8, 8, 8])
    """

    #: The model's published training-image recipe, a name of :data:`lightning_vtr.data.IMAGE_RECIPES`
    #: (``VTRDataModule(recipe=type(model).image_recipe)``; ``ExperimentConfig(recipe="reference")``).
    image_recipe: ClassVar[str] = "plain"

    def __init__(
        self,
        image_size: int,
        num_views: int,
        voxel_resolution: int = 32,
        *,
        iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
        fscore_threshold: float = DEFAULT_THRESHOLD,
        fscore_points: int = 8192,
        validation_fscore: bool = True,
        categories: Sequence[str] | None = None,
        log_sheets: int = 0,
    ) -> None:
        super().__init__()
        self.image_size = check_int("image_size", image_size, minimum=1)
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.voxel_resolution = check_int("voxel_resolution", voxel_resolution, minimum=1)
        self.iou_thresholds = tuple(float(t) for t in iou_thresholds)
        self.validation_fscore = validation_fscore
        self.log_sheets = check_int("log_sheets", log_sheets, minimum=0)
        self._sheet_batch: tuple[dict[str, Any], Tensor] | None = None
        cats = list(categories) if categories is not None else None

        def metrics() -> nn.ModuleDict:
            return nn.ModuleDict(
                {
                    "iou": VoxelIoU(self.iou_thresholds, categories=cats),
                    "fscore": VoxelFScore(threshold=fscore_threshold, num_points=fscore_points, categories=cats),
                }
            )

        self.val_metrics = metrics()
        self.test_metrics = nn.ModuleDict({name: metrics() for name in VIEW_SETS})
        #: "val" / "test" -> dataloader index -> items of it this process has been given so far in the epoch
        self._items_seen: dict[str, dict[int, int]] = {"val": {}, "test": {}}

    @_restricted_classmethod
    def load_from_checkpoint(
        cls,
        checkpoint_path: str | os.PathLike | IO,
        map_location: Any = None,
        hparams_file: str | os.PathLike | None = None,
        strict: bool | None = None,
        weights_only: bool | None = True,
        **kwargs: Any,
    ) -> Self:
        """Lightning's ``load_from_checkpoint``, with the model built inside
        :func:`~lightning_vtr.models.weights.restoring_checkpoint`.

        Pretrained weight files named by the hyperparameters (``backbone_weights``, ...) are not read:
        the checkpoint's state dict replaces every weight anyway, and the file may not exist on this
        machine. Arguments are Lightning's (``weights_only`` needs Lightning >= 2.4), except that ``weights_only``
        defaults to ``True``: the file is read as tensors and plain containers, never as a full pickle (which can
        run code in it), whatever ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD`` says; pass ``weights_only=False`` only for a
        file you trust.

        Raises:
            ValueError: ``checkpoint_path`` is a local checkpoint of another model class (e.g. an LRGT checkpoint
                given to ``Pix2VoxPlusPlus``); the message names both classes and the path.
        """
        cls._refuse_another_models_checkpoint(checkpoint_path)
        with restoring_checkpoint():
            return super().load_from_checkpoint(
                checkpoint_path,  # type: ignore[arg-type]  # Lightning takes any PathLike
                map_location=map_location,
                hparams_file=hparams_file,  # type: ignore[arg-type]  # likewise
                strict=strict,
                weights_only=weights_only,
                **kwargs,
            )

    @classmethod
    def _refuse_another_models_checkpoint(cls, checkpoint_path: str | os.PathLike | IO) -> None:
        """Raise ``ValueError`` when a local checkpoint file was saved from another model class.

        The class is the one a LightningCLI checkpoint names (``_class_path``), else the package's model class
        whose ``__init__`` takes every stored hyperparameter when ``cls`` does not (a hyperparameter ``cls`` lacks
        alone may be an older release's name, so that is no proof). Streams, remote paths and files
        ``torch.load(weights_only=True)`` cannot read are left to Lightning, as is a checkpoint of no known class.
        A ``_class_path`` outside ``lightning_vtr`` is never imported (only one already imported is looked up).
        """
        import importlib
        import inspect
        import pickle
        import sys

        if not isinstance(checkpoint_path, (str, os.PathLike)) or not os.path.isfile(checkpoint_path):
            return
        try:  # memory-mapped: the tensors are not read
            checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=True, mmap=True)
        except (OSError, RuntimeError, ValueError, EOFError, AttributeError, pickle.UnpicklingError):
            return
        hparams = checkpoint.get("hyper_parameters") if isinstance(checkpoint, dict) else None
        if not isinstance(hparams, dict):
            return

        def takes_all(model_cls: type[object]) -> bool:
            params = inspect.signature(model_cls.__init__).parameters.values()
            if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
                return True
            return {k for k in hparams if not str(k).startswith("_")} <= {p.name for p in params}

        def subclasses(base: type[object]) -> list[type]:
            found: list[type] = []
            for sub in base.__subclasses__():
                found += [sub, *subclasses(sub)]
            return found

        from lightning_vtr.models.registry import is_package_class_path  # the registry imports this module

        saved: type | str | None = None
        class_path = hparams.get("_class_path")
        if isinstance(class_path, str):
            module, _, name = class_path.rpartition(".")
            saved = class_path  # a checkpoint never makes us import a module outside lightning_vtr
            try:
                if is_package_class_path(class_path):
                    saved = getattr(importlib.import_module(module), name)
                elif module in sys.modules:  # imported already: nothing runs
                    saved = getattr(sys.modules[module], name)
            except (ImportError, AttributeError, ValueError):
                saved = class_path
            if saved == f"{cls.__module__}.{cls.__qualname__}":
                return
        elif not takes_all(cls):
            importlib.import_module("lightning_vtr.models")  # the package's models are candidates once imported
            candidates = [c for c in dict.fromkeys(subclasses(VoxelReconstructionModule)) if not inspect.isabstract(c)]
            candidates.sort(key=lambda c: (not c.__module__.startswith("lightning_vtr."), c.__module__, c.__qualname__))
            saved = next((c for c in candidates if takes_all(c) and not issubclass(c, cls)), None)
        if saved is None or (isinstance(saved, type) and issubclass(saved, cls)):
            return
        name = saved.__name__ if isinstance(saved, type) else saved.rpartition(".")[2]
        where = f"{saved.__module__}.{saved.__qualname__}" if isinstance(saved, type) else saved
        raise ValueError(
            f"{str(checkpoint_path)!r} is a checkpoint of {name} ({where}), not of {cls.__name__}: "
            f"{cls.__name__}.load_from_checkpoint cannot load it. Use {name}.load_from_checkpoint(...) "
            f"(`lightning-vtr predict --model {where}`)."
        )

    # ------------------------------------------------------------------ what subclasses implement
    @abc.abstractmethod
    def reconstruct(self, images: Tensor) -> dict[str, Tensor]:
        """Run the network on checked images ``(B, V, 3, H, W)``.

        Returns:
            a dict holding at least ``"voxels"``: occupancy probabilities ``(B, R, R, R)``.
        """

    @abc.abstractmethod
    def loss(self, outputs: dict[str, Tensor], target: Tensor) -> Tensor:
        """Scalar training loss from :meth:`reconstruct`'s outputs and ground truth ``(B, R, R, R)``."""

    # ------------------------------------------------------------------ protocol and checks
    def check_images(self, images: Tensor) -> None:
        """Raise ``ValueError`` naming expected vs actual if ``images`` is not valid model input (``TypeError``
        if it is not a tensor)."""
        check_type("images", images, Tensor, "torch.Tensor of shape (B, V, 3, H, W)")
        s = self.image_size
        if images.ndim != 5:
            raise ValueError(f"`images` must have shape (B, V, 3, {s}, {s}) (5 dimensions), got {tuple(images.shape)}")
        b, v, c, h, w = images.shape
        if c != 3:
            raise ValueError(f"`images` must have 3 (RGB) channels in dim 2, got {c} (shape {tuple(images.shape)})")
        if (h, w) != (s, s):
            raise ValueError(f"`images` must be {s}x{s} pixels (H, W), got {h}x{w} (shape {tuple(images.shape)})")
        if b < 1 or v < 1:
            raise ValueError(f"`images` must have at least one sample and one view, got shape {tuple(images.shape)}")
        if not images.is_floating_point():
            raise ValueError(f"`images` must be a floating-point tensor, got {images.dtype}")
        # A finite sum means every pixel is finite (a NaN or infinity makes it NaN or infinite); only a sum that
        # is not (an overflow, or a bad pixel) needs the elementwise test. The sum reads the batch once.
        if not torch.isfinite(images.sum()) and not torch.isfinite(images).all():
            raise ValueError("`images` must be finite normalised pixels, got NaN or infinite values")

    def check_voxels(self, voxels: Tensor, batch_size: int | None = None) -> None:
        """Raise ``ValueError`` if ``voxels`` is not a ``(B, R, R, R)`` target for this model."""
        r = self.voxel_resolution
        expected = (batch_size if batch_size is not None else "B", r, r, r)
        if (
            not isinstance(voxels, Tensor)
            or voxels.ndim != 4
            or tuple(voxels.shape[1:]) != (r, r, r)
            or (batch_size is not None and voxels.shape[0] != batch_size)
        ):
            actual = tuple(voxels.shape) if isinstance(voxels, Tensor) else type(voxels).__name__
            raise ValueError(f"`voxels` must have shape {expected}, got {actual}")

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        """Check ``images`` ``(B, V, 3, H, W)`` and return :meth:`reconstruct`'s outputs."""
        self.check_images(images)
        return self.reconstruct(images)

    def predict_voxels(self, images: Tensor) -> Tensor:
        """Occupancy probabilities ``(B, R, R, R)`` for images ``(B, V, 3, H, W)``.

        Half-precision outputs (``bfloat16`` / ``float16``, e.g. under the autocast of ``precision="bf16-mixed"``
        or ``"16-mixed"``) are returned as ``float32``; other dtypes as the network gives them. Gradients are
        tracked as usual: wrap the call in ``torch.no_grad()`` for inference.
        """
        voxels = self(images)["voxels"]
        return voxels.float() if voxels.dtype in (torch.bfloat16, torch.float16) else voxels

    def predict_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> Tensor:
        return self.predict_voxels(batch["images"])

    # ------------------------------------------------------------------ steps
    def setup(self, stage: str) -> None:
        if self.trainer is None:
            return
        datamodule = self.trainer.datamodule  # type: ignore[attr-defined]  # set by Lightning's data connector
        categories = getattr(datamodule, "categories", None) if datamodule else None
        if categories:
            for group in (self.val_metrics, *self.test_metrics.values()):
                for metric in _metric_group(group).values():
                    metric.add_categories(list(categories))

    def _batch(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor]:
        images, voxels = batch["images"], batch["voxels"]
        self.check_voxels(voxels, batch_size=images.shape[0] if isinstance(images, Tensor) else None)
        return images, voxels

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor:
        images, voxels = self._batch(batch)
        loss = self.loss(self(images), voxels)
        self.log("train/loss", loss, prog_bar=True, batch_size=images.shape[0])
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> None:
        images, voxels = self._batch(batch)
        # The whole batch goes forward (under DDP every process runs the same forwards as before); the repeats a
        # padding sampler appends are left out of the loss and the metrics, so every object counts once.
        outputs = self(images)
        if self.log_sheets and batch_idx == 0 and dataloader_idx == 0:
            self._sheet_batch = (batch, outputs["voxels"].detach())
        n = images.shape[0]
        keep = self._unpadded_items("val", n, batch_idx, dataloader_idx)
        categories = batch.get("category")
        if keep < n:
            outputs = {k: v[:keep] if isinstance(v, Tensor) and v.shape[:1] == (n,) else v for k, v in outputs.items()}
            voxels = voxels[:keep]
            categories = categories[:keep] if categories is not None else None
        if keep == 0:
            return
        self.log("val/loss", self.loss(outputs, voxels), batch_size=keep, add_dataloader_idx=False)
        probs = outputs["voxels"].detach()
        cast(VoxelIoU, self.val_metrics["iou"]).update(probs, voxels, categories)
        if self.validation_fscore:
            cast(VoxelFScore, self.val_metrics["fscore"]).update(probs, voxels, categories)

    def on_validation_epoch_start(self) -> None:
        # As in ``on_test_epoch_start``: own states in this process's memory (``ddp_spawn`` shares them).
        for metric in _metric_group(self.val_metrics).values():
            metric.reset()
        self._items_seen["val"] = {}

    def on_validation_epoch_end(self) -> None:
        self._log_metrics(self.val_metrics, "val", per_category=False)
        if self._sheet_batch is not None:
            from lightning_vtr.visualize import log_validation_sheets  # rendering stack only when asked

            log_validation_sheets(self, *self._sheet_batch, max_objects=self.log_sheets)
            self._sheet_batch = None

    def test_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> None:
        images, voxels = self._batch(batch)
        view_sets = batch.get("view_set") or ["aligned"] * images.shape[0]
        if isinstance(view_sets, str) or len(view_sets) != images.shape[0]:
            raise ValueError(
                f"`batch['view_set']` must list one view-set name per sample ({images.shape[0]}), got {view_sets!r}"
            )
        categories = batch.get("category")
        keep = self._unpadded_items("test", images.shape[0], batch_idx, dataloader_idx)
        if keep == 0:
            return
        if keep < images.shape[0]:
            images, voxels, view_sets = images[:keep], voxels[:keep], view_sets[:keep]
            categories = categories[:keep] if categories is not None else None
        probs = self(images)["voxels"].detach()
        for name in dict.fromkeys(view_sets):
            check_choice("batch['view_set']", name, VIEW_SETS)
            index = [i for i, s in enumerate(view_sets) if s == name]
            sel = torch.tensor(index, device=probs.device)
            cats = [categories[i] for i in index] if categories is not None else None
            for metric in _metric_group(self.test_metrics[name]).values():
                metric.update(probs.index_select(0, sel), voxels.index_select(0, sel), cats)

    def on_test_epoch_start(self) -> None:
        # Start from zero in this process's own memory: under ``ddp_spawn`` on CPU the processes receive the
        # metric states in shared memory, so in-place updates would add every process's objects (and a later
        # test in the launching process would start from their sum).
        for group in self.test_metrics.values():
            for metric in _metric_group(group).values():
                metric.reset()
        self._items_seen["test"] = {}

    def _unpadded_items(self, stage: str, batch_size: int, batch_idx: int, dataloader_idx: int) -> int:
        """How many leading items of a ``stage`` (``"val"`` / ``"test"``) batch are this process's share of the
        dataset, not padding.

        Under DDP Lightning's default :class:`~torch.utils.data.DistributedSampler` (``drop_last=False``) appends
        repeats of the first items to its index list until it divides among the ``n`` processes, and hands
        position ``p`` of the list to rank ``p % n``. The repeats therefore are the last items of each shard:
        rank ``r`` owns only the first ``len(range(r, N, n))`` of its items. Counting them keeps every object once
        in the means whatever loader the model is evaluated with (``VTRDataModule``'s test loaders do not pad at
        all; its validation loader keeps Lightning's padding sampler, so every process runs as many batches).
        """
        seen_by_loader = self._items_seen[stage]
        seen = 0 if batch_idx == 0 else seen_by_loader.get(dataloader_idx, 0)
        seen_by_loader[dataloader_idx] = seen + batch_size
        sampler = self._eval_sampler(stage, dataloader_idx)
        if sampler is None or sampler.total_size <= len(cast(Sized, sampler.dataset)):
            return batch_size  # no padding: one process, an unpadded sampler, or drop_last
        owned = len(range(sampler.rank, len(cast(Sized, sampler.dataset)), sampler.num_replicas))
        return max(0, min(batch_size, owned - seen))

    def _eval_sampler(self, stage: str, dataloader_idx: int) -> DistributedSampler | None:
        """The distributed sampler of ``stage`` (``"val"`` / ``"test"``) dataloader ``dataloader_idx``, if any."""
        if self._trainer is None:  # a step called by hand (Lightning's own properties test `_trainer` likewise)
            return None
        loaders = self.trainer.val_dataloaders if stage == "val" else self.trainer.test_dataloaders
        if isinstance(loaders, dict):
            loaders = list(loaders.values())
        elif not isinstance(loaders, (list, tuple)):
            loaders = [loaders]
        if dataloader_idx >= len(loaders):
            return None
        sampler = getattr(loaders[dataloader_idx], "sampler", None)
        return sampler if isinstance(sampler, DistributedSampler) else None

    def on_test_epoch_end(self) -> None:
        for name, group in self.test_metrics.items():
            self._log_metrics(group, f"test/{name}", per_category=True)

    def _log_metrics(self, group: nn.Module, prefix: str, per_category: bool) -> None:
        """Compute (synced), log and reset a group of IoU / F-score metrics; skip empty ones.

        Every process computes every metric, updated or not, because computing is a collective
        under DDP; a metric without objects on any process yields NaN and is not logged.
        """
        metrics = _metric_group(group)
        iou, fscore = metrics["iou"], metrics["fscore"]
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*compute.*before.*update.*")
            values = self._flatten(iou.compute().reshape(-1), fscore.compute())
            if per_category:
                f_cat = fscore.compute_per_category()
                for cat, iou_cat in iou.compute_per_category().items():
                    for key, val in self._flatten(iou_cat.reshape(-1), f_cat.get(cat)).items():
                        values[f"{cat}/{key}"] = val
        for key, val in values.items():
            if not math.isnan(val):
                self.log(f"{prefix}/{key}", val, add_dataloader_idx=False)
        iou.reset()
        fscore.reset()

    def _flatten(self, iou: Tensor, fscore: Tensor | None) -> dict[str, float]:
        out = {threshold_key(t): float(v) for t, v in zip(self.iou_thresholds, iou)}
        if fscore is not None:
            out["fscore"] = float(fscore)
        return out

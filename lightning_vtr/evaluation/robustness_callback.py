"""A Lightning callback that measures the viewpoint robustness map during training and logs it.

:class:`RobustnessMapLogger` runs :func:`~lightning_vtr.evaluation.robustness.robustness_map` every
``every_n_epochs`` validation epochs on a fixed subset of the datamodule's objects (:class:`ObjectSubset`: the
same objects and, with the same ``seed``, the same view sets every time), logs the equal-area picture
(:func:`~lightning_vtr.evaluation.robustness_plot.plot_map`) through
:func:`~lightning_vtr.utils.image_logging.log_image` as ``robustness/map`` and the area-weighted mean IoU
(:meth:`~lightning_vtr.evaluation.robustness.RobustnessMap.overall`) as the scalar ``robustness/mean_iou``.

Example::

    trainer = L.Trainer(callbacks=[RobustnessMapLogger(every_n_epochs=5, k=30, objects=16)])
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np

from lightning_vtr.evaluation.robustness import RobustnessMap, robustness_map
from lightning_vtr.geometry import check_bin_interval
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = ["ObjectSubset", "RobustnessMapLogger", "spread_over_categories"]


def spread_over_categories(records: Sequence[Any], count: int | None) -> list[Any]:
    """At most ``count`` records taken round-robin over the categories (first of each, then second, ...).

    Categories come in sorted order and objects in the order of ``records``; ``None`` keeps every record, in
    that order. The choice depends on nothing else, so every model measured on it gets the same objects.

    Example:
        >>> from types import SimpleNamespace as R
        >>> rs = [R(category=c, object_id=i) for c, i in [("b", "1"), ("b", "2"), ("a", "3")]]
        >>> [r.object_id for r in spread_over_categories(rs, 2)]
        ['3', '1']
    """
    if count is None:
        return list(records)
    count = check_int("count", count, minimum=1)
    rank: dict[str, int] = {}
    keyed = []
    for position, record in enumerate(records):
        keyed.append((rank.setdefault(record.category, 0), record.category, position, record))
        rank[record.category] += 1
    return [item[-1] for item in sorted(keyed, key=lambda item: item[:3])[:count]]


class ObjectSubset:
    """Some of a datamodule's objects, served as the datamodule serves them.

    :func:`~lightning_vtr.evaluation.robustness.robustness_map` takes it in place of the datamodule:
    ``split_records`` gives the chosen records (whatever split is asked), ``transform``, ``object_voxels`` and
    ``eval_item`` are the datamodule's.

    Args:
        datamodule: a :class:`~lightning_vtr.data.VTRDataModule` (or anything with ``transform``,
            ``object_voxels`` and ``eval_item``).
        records: the objects to serve.

    Example::

        subset = ObjectSubset.spread(dm, "test", 16)
        rmap = robustness_map(model, subset)
    """

    def __init__(self, datamodule: Any, records: Sequence[Any]) -> None:
        self.datamodule = datamodule
        self.records = list(records)

    @classmethod
    def spread(cls, datamodule: Any, split: str, count: int | None) -> ObjectSubset:
        """``count`` objects of ``split`` spread over the categories (:func:`spread_over_categories`)."""
        return cls(datamodule, spread_over_categories(datamodule.split_records(split), count))

    def split_records(self, split: str) -> list[Any]:
        """The chosen records (``split`` is ignored: they were chosen from one)."""
        return list(self.records)

    @property
    def transform(self) -> Any:
        """The datamodule's evaluation transform."""
        return self.datamodule.transform

    def object_voxels(self, record: Any) -> Any:
        """The datamodule's voxels of ``record``."""
        return self.datamodule.object_voxels(record)

    def eval_item(self, record: Any, view_set: str = "aligned", seed: int = 0) -> dict:
        """The datamodule's model-ready item of ``record``."""
        return self.datamodule.eval_item(record, view_set, seed=seed)


def map_picture(rmap: RobustnessMap, title: str | None = None, **kwargs: Any) -> np.ndarray:
    """The picture :func:`~lightning_vtr.evaluation.robustness_plot.plot_map` draws, as ``(H, W, 3)`` uint8."""
    from PIL import Image

    from lightning_vtr.evaluation.robustness_plot import plot_map

    with tempfile.TemporaryDirectory(prefix="robustness_map_") as folder:
        path = plot_map(rmap, Path(folder) / "map.png", title=title, **kwargs)
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))


class RobustnessMapLogger(L.Callback):
    """Log the robustness map of the model being trained every ``every_n_epochs`` validation epochs.

    At the end of validation epochs ``every_n_epochs - 1, 2 * every_n_epochs - 1, ...`` (not during the sanity
    check), global rank 0 measures :func:`~lightning_vtr.evaluation.robustness.robustness_map` of the
    LightningModule on ``objects`` objects of the datamodule's ``split`` (chosen once, round-robin over the
    categories, :class:`ObjectSubset`), with the datamodule's evaluation transform, under inference mode and with
    the model in eval mode (its mode is restored). It logs

    * ``robustness/mean_iou``: the area-weighted mean IoU over the sphere
      (:meth:`~lightning_vtr.evaluation.robustness.RobustnessMap.overall`), through ``pl_module.log``
      (``rank_zero_only``, so it cannot be monitored by checkpointing or early stopping under DDP);
    * ``robustness/map``: the equal-area picture on a fixed ``[0, 1]`` colour scale (one colour is one IoU in
      every epoch) through :func:`~lightning_vtr.utils.image_logging.log_image` (TensorBoard, W&B, MLflow,
      Comet; a PNG under the run directory for a CSV logger).

    The last map measured is kept as :attr:`last_map`.

    Args:
        every_n_epochs: measure every this many epochs.
        k: bin interval in degrees (divides 180); 30 gives 72 bins.
        objects: objects measured (fewer when the split holds fewer).
        split: the datamodule split the objects come from.
        seed: seeds the view sets (the same sets every time).
        sets_per_bin: view sets per bin and object.
        synthesizer: renders the views; ``None``: ``RenderSynthesizer(image_size=model.image_size)`` (the objects
            need meshes).

    Raises:
        ValueError: a bad ``k``, a count below 1 or an unknown split.

    Example::

        trainer = L.Trainer(callbacks=[RobustnessMapLogger(every_n_epochs=5, k=30, objects=16, split="val")])
    """

    def __init__(
        self,
        every_n_epochs: int = 5,
        k: int = 30,
        objects: int = 16,
        split: str = "val",
        seed: int = 0,
        sets_per_bin: int = 1,
        synthesizer: Any = None,
    ) -> None:
        self.every_n_epochs = check_int("every_n_epochs", every_n_epochs, minimum=1)
        self.k = check_bin_interval(k)
        self.objects = check_int("objects", objects, minimum=1)
        self.split = check_choice("split", split, ("train", "val", "test"))
        self.seed = int(seed)
        self.sets_per_bin = check_int("sets_per_bin", sets_per_bin, minimum=1)
        self.synthesizer = synthesizer
        self.last_map: RobustnessMap | None = None
        self._subset: ObjectSubset | None = None

    def _due(self, trainer: L.Trainer) -> bool:
        return not trainer.sanity_checking and (trainer.current_epoch + 1) % self.every_n_epochs == 0

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Measure and log the map when this epoch is due (global rank 0 only)."""
        if not self._due(trainer) or not trainer.is_global_zero:
            return
        datamodule = getattr(trainer, "datamodule", None)
        if datamodule is None or not hasattr(datamodule, "split_records"):
            raise ValueError(
                "RobustnessMapLogger needs a datamodule with `split_records` (a VTRDataModule) given to the "
                f"Trainer, got {type(datamodule).__name__}"
            )
        if self._subset is None or self._subset.datamodule is not datamodule:
            self._subset = ObjectSubset.spread(datamodule, self.split, self.objects)
        if not self._subset.records:
            from lightning.pytorch.utilities import rank_zero_warn

            rank_zero_warn(f"RobustnessMapLogger: the {self.split!r} split has no objects; nothing measured.")
            return
        rmap = robustness_map(
            pl_module,
            self._subset,
            k=self.k,
            sets_per_bin=self.sets_per_bin,
            seed=self.seed,
            synthesizer=self.synthesizer,
            split=self.split,
            progress=False,
        )
        self.last_map = rmap
        pl_module.log("robustness/mean_iou", rmap.overall(), rank_zero_only=True, on_epoch=True, batch_size=1)
        if trainer.loggers:
            from lightning_vtr.utils.image_logging import log_image

            title = (
                f"epoch {trainer.current_epoch}: IoU over the sphere {rmap.overall():.3f}, {rmap.num_objects} objects"
            )
            log_image(trainer, "robustness/map", map_picture(rmap, title=title), step=trainer.global_step)

"""The contracts of the view-augmentation callback: with the model it trains and the datamodule it feeds.

Any ``LightningModule`` that has the attributes and method of :class:`ReconstructionModel` can be trained
with :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`; the package's own Pix2Vox++ and LRGT
implement it, and a user's model can too (no inheritance needed). Likewise any ``LightningDataModule`` with
the members of :class:`AugmentableDataModule` can serve it; :class:`~lightning_vtr.data.VTRDataModule` does.

Batches (what :class:`~lightning_vtr.data.VTRDataModule` yields) are dictionaries:

* ``"images"``: ``(B, V, 3, H, W)`` float32, already transformed (resized, composited on the
  background, normalised) by the datamodule.
* ``"voxels"``: ``(B, R, R, R)`` float32 in {0, 1}, indexed per :mod:`lightning_vtr.geometry`.
* ``"viewpoints"``: ``(B, V, 2)`` float32 (yaw, pitch) in degrees of each input image.
* ``"category"``: list of ``B`` category names; ``"object_id"``: list of ``B`` object ids.
* ``"view_set"``: list of ``B`` view-set names (``"aligned"``, ...; ``"generated"`` for a sample the callback
  generated).

:func:`check_model_matches_data` compares a model's declared ``image_size``, ``num_views`` and
``voxel_resolution`` with the datamodule's; :class:`~lightning_vtr.data.VTRDataModule` calls it in ``setup``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:  # this module stays light: dataset build workers import VIEW_SETS without torch
    import numpy as np
    from torch import Tensor

__all__ = [
    "DEFAULT_THRESHOLD",
    "VIEW_SETS",
    "AugmentableDataModule",
    "ReconstructionModel",
    "check_augmentable_datamodule",
    "check_model_matches_data",
    "check_reconstruction_model",
]

VIEW_SETS: tuple[str, ...] = ("aligned", "hemispherical", "spherical")
"""The paper's three view sets, in table order: training views (a fixed elevation) and the two test sets."""

DEFAULT_THRESHOLD: float = 0.4
"""The occupancy threshold: a voxel predicted with probability ``>= DEFAULT_THRESHOLD`` is occupied. The
default binarisation of error volumes, selections, IoU/F-score, exports and figures (the paper's tables use it)."""


@runtime_checkable
class ReconstructionModel(Protocol):
    """What the callback needs from a multi-view voxel reconstruction model.

    Each attribute states what the model takes or gives; :func:`check_model_matches_data` refuses a datamodule that
    serves something else, when a Trainer sets the datamodule up.

    Attributes:
        image_size: the square input size ``H = W`` the model expects, in pixels. Must equal the datamodule's
            ``image_size`` (the side of the images it serves). Synthesizers built for a model render at it.
        num_views: the number of input views per sample it is trained with. Must equal the datamodule's
            ``num_views`` when training (evaluation may serve any number); the callback warns when its selector
            returns another number of views.
        voxel_resolution: ``R`` of its ``(B, R, R, R)`` output. Must equal the datamodule's ``voxel_resolution``
            (the dataset's voxel grids); the callback also checks one prediction's shape at fit start.

    Example:
        >>> class Constant:  # no base class needed
        ...     image_size, num_views, voxel_resolution = 224, 3, 32
        ...     def predict_voxels(self, images):
        ...         return images.new_full((len(images), 32, 32, 32), 0.5)
        >>> isinstance(Constant(), ReconstructionModel)
        True
        >>> isinstance(object(), ReconstructionModel)
        False
    """

    image_size: int
    num_views: int
    voxel_resolution: int

    def predict_voxels(self, images: Tensor) -> Tensor:
        """Occupancy probabilities ``(B, R, R, R)`` in ``[0, 1]`` for images ``(B, V, 3, H, W)``."""
        ...


def check_reconstruction_model(model: object) -> None:
    """Raise ``TypeError`` naming what is missing if ``model`` does not satisfy :class:`ReconstructionModel`.

    Args:
        model: the model to check (normally a ``LightningModule``).

    Raises:
        TypeError: naming every missing attribute at once, and ``predict_voxels`` when it is missing or not
            callable.

    Example:
        >>> check_reconstruction_model(object())  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        TypeError: object does not satisfy lightning_vtr.ReconstructionModel: missing image_size, num_views, ...
    """
    missing = [name for name in ("image_size", "num_views", "voxel_resolution") if not hasattr(model, name)]
    if not callable(getattr(model, "predict_voxels", None)):
        missing.append("predict_voxels(images) -> (B, R, R, R)")
    if missing:
        raise TypeError(
            f"{type(model).__name__} does not satisfy lightning_vtr.ReconstructionModel: missing {', '.join(missing)}. "
            "Add these attributes and method (see lightning_vtr.protocol)."
        )


#: The attributes :func:`check_model_matches_data` compares, with what to change when one disagrees.
_MATCHED_ATTRIBUTES: dict[str, str] = {
    "image_size": "the datamodule serves {data} px images: pass image_size={model} to the datamodule, or build the "
    "model for {data} px",
    "num_views": "the datamodule serves {data} views per training sample: pass num_views={model} to the datamodule, "
    "or build the model with num_views={data}",
    "voxel_resolution": "the dataset's voxel grids are {data}^3: build the model with voxel_resolution={data}, or use "
    "a dataset built at resolution {model}",
}


def check_model_matches_data(model: object, datamodule: object, *, training: bool = True) -> None:
    """Raise ``ValueError`` when ``model``'s declared sizes disagree with what ``datamodule`` serves.

    Compares ``image_size``, ``voxel_resolution`` and, when ``training``, ``num_views`` (a model may be evaluated
    on another number of views). An attribute that either side lacks, or that is ``None``, is not compared: a
    plain ``LightningModule`` without these attributes passes. Reading the datamodule's attributes may read the
    dataset (:class:`~lightning_vtr.data.VTRDataModule` takes its ``image_size`` and ``voxel_resolution`` from
    ``metadata.json``).

    Args:
        model: the model (normally a :class:`ReconstructionModel`).
        datamodule: the datamodule (normally a :class:`~lightning_vtr.data.VTRDataModule`).
        training: also compare ``num_views``.

    Raises:
        ValueError: one line naming every disagreeing attribute with both values and what to change.

    Example:
        >>> from types import SimpleNamespace
        >>> model = SimpleNamespace(image_size=128, num_views=3, voxel_resolution=32)
        >>> check_model_matches_data(model, SimpleNamespace(image_size=128, num_views=1), training=False)
        >>> check_model_matches_data(model, SimpleNamespace(image_size=64, num_views=3))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: SimpleNamespace.image_size is 128 but SimpleNamespace.image_size is 64: the datamodule serves 64 px ...
    """
    names = [name for name in _MATCHED_ATTRIBUTES if training or name != "num_views"]
    mismatches = []
    for name in names:
        declared = getattr(model, name, None)
        served = getattr(datamodule, name, None)
        if declared is None or served is None or declared == served:
            continue
        hint = _MATCHED_ATTRIBUTES[name].format(model=declared, data=served)
        mismatches.append(
            f"{type(model).__name__}.{name} is {declared!r} but {type(datamodule).__name__}.{name} is {served!r}: {hint}"
        )
    if mismatches:
        raise ValueError("; ".join(mismatches))


@runtime_checkable
class AugmentableDataModule(Protocol):
    """What :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` reads, writes and calls on a datamodule.

    The callback only calls these members; it never assigns an attribute of the datamodule. Records are
    objects with ``category``, ``object_id``, ``mesh_path`` (``None`` without a mesh) and ``views``, a mapping
    from view-set name to ``(image paths, (V, 2) viewpoints in degrees)``, as
    :class:`~lightning_vtr.data.format.ObjectRecord` has.

    Attributes:
        transform: turns ``(T, H, W, 4)`` uint8 RGBA images into model input ``(T, 3, H, W)`` float (the
            evaluation transform). An optional ``transform.normalize`` names its normalisation for figures.
        generated_samples: index entries (dicts with ``"category"``, ``"object_id"``, ``"epoch"``, ...) of
            the generated samples served now; read for the ``vtr/samples_total`` value.

    Example:
        >>> from lightning_vtr.protocol import AugmentableDataModule, check_augmentable_datamodule
        >>> check_augmentable_datamodule(object())  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        TypeError: object does not satisfy lightning_vtr.AugmentableDataModule: missing split_records(split), ...
    """

    @property
    def transform(self) -> Callable[..., Any]:
        """RGBA uint8 images ``(T, H, W, 4)`` -> model input ``(T, 3, H, W)`` float (the evaluation transform)."""
        ...

    @property
    def generated_samples(self) -> list[dict]:
        """Index entries of the generated samples served now."""
        ...

    def split_records(self, split: str) -> Sequence[Any]:
        """The records of one split (``"train"``), in an order that is the same on every process and run."""
        ...

    def record(self, category: str, object_id: str) -> Any:
        """The record of one object."""
        ...

    def eval_item(self, record: Any, view_set: str = "aligned", seed: int = 0) -> dict:
        """A model-ready item of ``record``: ``{"images": (V, 3, H, W), "voxels": (R, R, R), "viewpoints": (V, 2),
        "category", "object_id"}``, its views a fixed function of ``seed``."""
        ...

    def object_views(
        self, record: Any, view_set: str = "aligned", indices: Sequence[int] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(images (V, H, W, 4) uint8, viewpoints (V, 2) degrees)`` of one object's view set."""
        ...

    def add_samples(self, samples: Sequence[Any], *, max_total: int | None = None) -> list[dict]:
        """Store generated samples, serve them from the next train loader on, keep at most ``max_total``
        (the newest; ``None``: all). Called with the same samples in the same order on every process."""
        ...


#: The members :func:`check_augmentable_datamodule` looks for, as its message names them.
_DATAMODULE_MEMBERS: dict[str, str] = {
    "split_records": "split_records(split)",
    "record": "record(category, object_id)",
    "eval_item": "eval_item(record, view_set, seed)",
    "object_views": "object_views(record, view_set, indices)",
    "add_samples": "add_samples(samples, *, max_total)",
    "transform": "transform",
    "generated_samples": "generated_samples",
}
_DATAMODULE_METHODS = ("split_records", "record", "eval_item", "object_views", "add_samples", "transform")


def check_augmentable_datamodule(datamodule: object) -> None:
    """Check that ``datamodule`` has every member of :class:`AugmentableDataModule`.

    Args:
        datamodule: the datamodule to check.

    Raises:
        TypeError: naming every missing (or non-callable) member at once, and ``add_samples`` when it takes
            no ``max_total`` keyword.

    Example:
        >>> from lightning_vtr.data import VTRDataModule  # doctest: +SKIP
        >>> check_augmentable_datamodule(VTRDataModule())  # doctest: +SKIP
    """
    missing = []
    for name, shown in _DATAMODULE_MEMBERS.items():
        value = getattr(datamodule, name, None)
        if value is None or (name in _DATAMODULE_METHODS and not callable(value)):
            missing.append(shown)
        elif name == "add_samples" and not _accepts_keyword(value, "max_total"):
            missing.append(f"{shown} (its add_samples takes no max_total)")
    if missing:
        raise TypeError(
            f"{type(datamodule).__name__} does not satisfy lightning_vtr.AugmentableDataModule: missing "
            f"{', '.join(missing)}. Use lightning_vtr.data.VTRDataModule or add these members "
            "(see lightning_vtr.protocol.AugmentableDataModule)."
        )


def _accepts_keyword(function: Callable[..., Any], name: str) -> bool:
    try:
        parameters = inspect.signature(function).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin): assume it does
        return True
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters)

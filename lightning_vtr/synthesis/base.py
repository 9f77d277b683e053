"""The ``Synthesizer`` interface: images of an object at requested viewpoints."""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

__all__ = ["SynthesisRequest", "Synthesizer", "record_location"]

#: The two ways out when a synthesizer cannot serve a dataset, quoted by every refusal.
FIX_HINT = (
    "Use a synthesizer that needs only images (lightning_vtr.synthesis.Zero123Synthesizer, e.g. "
    "`Zero123Synthesizer.from_pretrained(<local weights dir>)`), or build a dataset with meshes "
    "(`lightning-vtr build-dataset OUT --source <ShapeNetCore or mesh folder>`, then `VTRDataModule(OUT)`)."
)


def record_location(record: Any) -> str:
    """Where an object's files are, for error messages: ``"<category>/<object_id> (<its images' folder>)"``."""
    name = f"{getattr(record, 'category', '?')}/{getattr(record, 'object_id', '?')}"
    for paths, _ in (getattr(record, "views", None) or {}).values():
        if len(paths):
            return f"{name} (images in {Path(paths[0]).parent})"
    voxel_path = getattr(record, "voxel_path", None)
    return f"{name} (voxels {voxel_path})" if voxel_path is not None else name


@dataclass
class SynthesisRequest:
    """One object's request.

    Attributes:
        object_id: the object's id in its dataset.
        category: its category name.
        source_images: ``(S, H, W, 4)`` uint8 RGBA views of the object that are already known.
        source_viewpoints: ``(S, 2)`` (yaw, pitch) in degrees of ``source_images``.
        target_viewpoints: ``(T, 2)`` (yaw, pitch) in degrees to synthesize.
        mesh_path: the object's normalised mesh, when the dataset has one (the render synthesizer needs it).
        extra: free-form data about the object for a custom synthesizer; the package's synthesizers do not read
            it (:class:`~lightning_vtr.synthesis.cache.CachedSynthesizer` passes it on to the one it wraps).

    Example:
        >>> import torch
        >>> request = SynthesisRequest(
        ...     object_id="0001",
        ...     category="chair",
        ...     source_images=np.zeros((1, 64, 64, 4), np.uint8),
        ...     source_viewpoints=torch.tensor([[0.0, 30.0]]),
        ...     target_viewpoints=torch.tensor([[90.0, 30.0], [180.0, 30.0]]),
        ... )
        >>> request.target_viewpoints.shape, request.mesh_path
        (torch.Size([2, 2]), None)
    """

    object_id: str
    category: str
    source_images: np.ndarray
    source_viewpoints: Tensor
    target_viewpoints: Tensor
    mesh_path: Path | None = None
    extra: dict = field(default_factory=dict)


class Synthesizer(abc.ABC):
    """Turns :class:`SynthesisRequest` s into images.

    Subclasses implement :meth:`synthesize`. Outputs are ``(T, H, W, 4)`` uint8 RGBA arrays at
    ``image_size`` (alpha 255 where the synthesizer cannot tell the object from the background). A subclass
    whose output depends on settings returns them in :meth:`config_key`, so cached views of other settings
    are not reused.

    Example:
        A synthesizer that returns blank images:

        >>> class Blank(Synthesizer):
        ...     image_size = 32
        ...     needs_source_images = False
        ...     def synthesize(self, requests):
        ...         return [np.zeros((len(r.target_viewpoints), 32, 32, 4), np.uint8) for r in requests]
        >>> import torch
        >>> request = SynthesisRequest("0001", "chair", np.zeros((0, 32, 32, 4), np.uint8),
        ...                            torch.zeros(0, 2), torch.tensor([[0.0, 30.0], [90.0, 30.0]]))
        >>> images = Blank().synthesize([request])
        >>> len(images), images[0].shape
        (1, (2, 32, 32, 4))
        >>> Blank().config_key()
        'Blank'
    """

    image_size: int = 256
    #: Whether ``synthesize`` reads ``SynthesisRequest.source_images``. Callers skip decoding the source views
    #: when it does not (the render synthesizer works from the mesh alone).
    needs_source_images: bool = True

    @abc.abstractmethod
    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        """Return one ``(T_i, H, W, 4)`` uint8 array per request, in request order."""

    def config_key(self) -> str:
        """A string identifying everything that changes the output (used for caching)."""
        return type(self).__name__

    def check_serves(self, records: Sequence[Any], *, view_set: str | None = None) -> None:
        """Refuse objects this synthesizer cannot make views of, before any training is spent on them.

        ``ErrorGuidedViewAugmentation.setup`` calls it with the training objects
        (:class:`~lightning_vtr.data.format.ObjectRecord` s) and the view set its source views come from.
        The default: a wrapper that keeps the synthesizer it wraps as ``self.synthesizer`` (as
        :class:`~lightning_vtr.synthesis.cache.CachedSynthesizer` does) defers to it; otherwise a synthesizer
        that reads source images (:attr:`needs_source_images`, e.g. Zero-1-to-3) needs at least one image per
        object in ``view_set`` (any view set when ``None``), and one that does not needs nothing. Subclasses
        with other needs override it (:class:`~lightning_vtr.synthesis.render.RenderSynthesizer`: a mesh
        per object).

        Raises:
            ValueError: naming the synthesizer, how many objects it cannot serve, the first of them (and
                where its files are) and the fix.
        """
        wrapped = getattr(self, "synthesizer", None)
        if isinstance(wrapped, Synthesizer) and wrapped is not self:
            wrapped.check_serves(records, view_set=view_set)
            return
        if not self.needs_source_images:
            return

        def has_images(record: Any) -> bool:
            views = getattr(record, "views", None)
            if views is None:  # not an ObjectRecord (a user's datamodule): nothing to tell from
                return True
            if view_set is None:
                return any(len(paths) > 0 for paths, _ in views.values())
            return view_set in views and len(views[view_set][0]) > 0

        lacking = [r for r in records if not has_images(r)]
        if lacking:
            where = f"view set {view_set!r}" if view_set is not None else "any view set"
            raise ValueError(
                f"{type(self).__name__} synthesizes from an object's source images, but {len(lacking)} of "
                f"{len(records)} training objects have no image in {where} (first: {record_location(lacking[0])}). "
                "Pass the view set the dataset has (the callback's `source_view_set`) or a dataset with images."
            )

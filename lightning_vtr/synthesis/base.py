"""The ``Synthesizer`` interface: images of an object at requested viewpoints."""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

__all__ = ["SynthesisRequest", "Synthesizer"]


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
    ``image_size`` (alpha 255 where the synthesizer cannot tell the object from the background).
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

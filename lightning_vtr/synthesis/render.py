"""``RenderSynthesizer``: new views by rendering the object's mesh (the fallback without diffusion weights)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from lightning_vtr.synthesis.base import FIX_HINT, SynthesisRequest, Synthesizer, record_location
from lightning_vtr.utils.validation import check_int

__all__ = ["RenderSynthesizer"]


class RenderSynthesizer(Synthesizer):
    """Renders each request's mesh (``SynthesisRequest.mesh_path``) at the target viewpoints.

    It uses the package renderer with the dataset builder's camera defaults, so a synthesized view
    looks like a dataset view taken from the same viewpoint. Meshes are kept in a small LRU cache.

    Args:
        image_size: output side in pixels (the datamodule resizes to the model input anyway).
        max_cached_meshes: how many loaded meshes to keep in memory.
        renderer_kwargs: passed to :func:`lightning_vtr.renderer.get_renderer` (camera type, fov, distance).

    Raises:
        TypeError: ``image_size`` or ``max_cached_meshes`` is not an int.
        ValueError: ``image_size < 1`` or ``max_cached_meshes < 0``; in :meth:`check_serves` (the callback's
            ``setup``), for a dataset whose objects have no mesh; at synthesis time, for a request without a
            mesh path (naming the object).

    Example::

        synthesizer = RenderSynthesizer(image_size=128)
        request = SynthesisRequest(
            object_id="0001",
            category="chair",
            source_images=np.zeros((0, 128, 128, 4), np.uint8),  # not read: the mesh is enough
            source_viewpoints=torch.zeros(0, 2),
            target_viewpoints=torch.tensor([[45.0, 30.0], [-135.0, 30.0]]),  # degrees
            mesh_path=record.mesh_path,  # the dataset's normalised mesh of the object
        )
        images = synthesizer.synthesize([request])  # [(2, 128, 128, 4) uint8 RGBA]
    """

    needs_source_images = False

    def __init__(self, image_size: int = 128, max_cached_meshes: int = 64, **renderer_kwargs: Any) -> None:
        self.image_size = check_int("image_size", image_size, minimum=1)
        self.max_cached_meshes = check_int("max_cached_meshes", max_cached_meshes, minimum=0)
        self.renderer_kwargs = dict(renderer_kwargs)
        self._meshes: OrderedDict[str, trimesh.Trimesh] = OrderedDict()

    def _mesh(self, path: Path) -> trimesh.Trimesh:
        from lightning_vtr.data.mesh import load_mesh

        key = str(path)
        if key in self._meshes:
            self._meshes.move_to_end(key)
            return self._meshes[key]
        # Dataset meshes are stored normalised in the package frame already.
        mesh = load_mesh(path, up_axis="z", normalize=False)
        self._meshes[key] = mesh
        while len(self._meshes) > self.max_cached_meshes:
            self._meshes.popitem(last=False)
        return mesh

    def check_serves(self, records: Sequence[Any], *, view_set: str | None = None) -> None:
        """Refuse objects without a mesh (``record.mesh_path is None``), e.g. every object of the
        ShapeNetRendering layout, which has images and voxels only; the message names the first and the fix."""
        lacking = [r for r in records if getattr(r, "mesh_path", None) is None]
        if lacking:
            raise ValueError(
                f"{type(self).__name__} renders each object's mesh, but {len(lacking)} of {len(records)} training "
                f"objects have none (first: {record_location(lacking[0])}); datasets in the ShapeNetRendering "
                f"layout have images and voxels only. {FIX_HINT}"
            )

    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        from lightning_vtr.renderer import get_renderer

        renderer = get_renderer(self.image_size, **self.renderer_kwargs)
        out = []
        for req in requests:
            if req.mesh_path is None:
                raise ValueError(
                    f"RenderSynthesizer needs a mesh for {req.category}/{req.object_id}, but the dataset has none "
                    "(e.g. the ShapeNetRendering layout). Use Zero123Synthesizer, which needs only images."
                )
            out.append(renderer.render(self._mesh(Path(req.mesh_path)), np.asarray(req.target_viewpoints)))
        return out

    def config_key(self) -> str:
        items = ",".join(f"{k}={v}" for k, v in sorted(self.renderer_kwargs.items()))
        return f"RenderSynthesizer(image_size={self.image_size},{items})"

"""What a selection round hands to the synthesizer and to the selectors that query the model."""

from __future__ import annotations

from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lightning_vtr.protocol import AugmentableDataModule
from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer

__all__ = ["selection_context", "synthesis_request"]


def synthesis_request(
    dm: AugmentableDataModule,
    record: Any,
    synthesizer: Synthesizer,
    source_view_set: str,
    targets: Tensor | np.ndarray | None = None,
) -> SynthesisRequest:
    """The request for images of ``record`` at ``targets``.

    Source images are decoded only for a synthesizer that reads them (:attr:`Synthesizer.needs_source_images`);
    mesh rendering gets an empty ``(0, 0, 0, 4)`` array.

    Args:
        dm: the datamodule (its ``object_views``).
        record: the object's record (``category``, ``object_id``, ``mesh_path``, ``views``).
        synthesizer: the synthesizer the request is for.
        source_view_set: the view set of the source images.
        targets: ``(n, 2)`` target viewpoints in degrees; ``None``: none (a selector's context).

    Returns:
        A :class:`~lightning_vtr.synthesis.base.SynthesisRequest`.

    Example::

        request = synthesis_request(dm, record, RenderSynthesizer(), "aligned", torch.tensor([[30.0, 10.0]]))
    """
    if synthesizer.needs_source_images:
        images, viewpoints = dm.object_views(record, source_view_set)
    else:  # e.g. mesh rendering: skip decoding every source image of the object
        _, viewpoints = record.views[source_view_set]
        images = np.zeros((0, 0, 0, 4), np.uint8)
    return SynthesisRequest(
        object_id=record.object_id,
        category=record.category,
        source_images=images,
        source_viewpoints=torch.as_tensor(viewpoints, dtype=torch.float32),
        target_viewpoints=torch.zeros(0, 2) if targets is None else torch.as_tensor(targets, dtype=torch.float32),
        mesh_path=record.mesh_path,
    )


def _voxel_bce(pred: Tensor, target: Tensor) -> Tensor:
    """Per-object binary cross-entropy ``(B,)`` of occupancy probabilities ``(B, R, R, R)``."""
    return F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), target, reduction="none").flatten(1).mean(1)


def selection_context(
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    synthesizer: Synthesizer,
    requests: list[SynthesisRequest],
) -> SelectionContext:
    """The context of a selector that queries the model (:attr:`ViewSelector.needs_context`).

    Args:
        pl_module: the model (in eval mode while the selector runs).
        dm: the datamodule (its evaluation ``transform``).
        synthesizer: renders the views the selector tries.
        requests: one request per object, as :func:`synthesis_request` builds them.

    Returns:
        A :class:`~lightning_vtr.selection.base.SelectionContext` whose loss is a per-object voxel BCE.

    Example::

        context = selection_context(model, dm, synthesizer, [synthesis_request(dm, r, synthesizer, "aligned")])
    """
    return SelectionContext(
        model=pl_module,
        synthesizer=synthesizer,
        requests=requests,
        transform=dm.transform,
        loss_fn=_voxel_bce,
        device=pl_module.device,
    )

"""The model's occupancy probabilities for a selection round, with the checks that catch a model breaking the
protocol (logits, another batch size, non-finite values)."""

from __future__ import annotations

from typing import cast

import lightning as L
import torch
from torch import Tensor

from lightning_vtr.protocol import ReconstructionModel
from lightning_vtr.utils.validation import check_probabilities

__all__ = ["PROBABILITIES_HINT", "predict_probabilities"]

PROBABILITIES_HINT = (
    "did predict_voxels return logits? apply torch.sigmoid to them (the callback thresholds occupancy "
    "probabilities); non-finite values mean the model diverged"
)
"""The hint of the error for a model that returns anything but probabilities (logits are the usual cause)."""


@torch.no_grad()
def predict_probabilities(pl_module: L.LightningModule, images: list[Tensor], batch_size: int) -> Tensor:
    """``predict_voxels`` over ``images`` (each ``(V, 3, H, W)``) in batches: ``(N, R, R, R)`` float32 probabilities.

    The model runs as it is (the caller sets eval mode) in its Trainer's precision context, as in validation
    (autocast under ``bf16-mixed`` / ``16-mixed``); its output is cast to float32, so error volumes and view
    selection are in float32.

    Args:
        pl_module: a model satisfying :class:`~lightning_vtr.protocol.ReconstructionModel`, attached to a Trainer.
        images: the objects' input views, each ``(V, 3, H, W)`` float.
        batch_size: objects per ``predict_voxels`` call.

    Returns:
        ``(N, R, R, R)`` float32 on the CPU; ``N = len(images)``.

    Raises:
        ValueError: the model returned another shape than ``(B, R, R, R)``, or anything but finite values in
            ``[0, 1]`` (the message gives the observed range and the count of non-finite values).

    Example::

        predicted = predict_probabilities(model, [item["images"] for item in items], batch_size=16)
    """
    name = f"{type(pl_module).__name__}.predict_voxels"
    preds = []
    for start in range(0, len(images), batch_size):
        batch = torch.stack(images[start : start + batch_size]).to(pl_module.device)
        with pl_module.trainer.precision_plugin.forward_context():
            out = cast(ReconstructionModel, pl_module).predict_voxels(batch)
        if not isinstance(out, Tensor) or out.ndim != 4 or out.shape[0] != batch.shape[0]:
            found = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"`{name}` must return occupancy probabilities of shape (B, R, R, R) for images of shape "
                f"{tuple(batch.shape)}, got {found}"
            )
        preds.append(check_probabilities(name, out.detach().float().cpu(), PROBABILITIES_HINT))
    return torch.cat(preds) if preds else torch.empty(0)

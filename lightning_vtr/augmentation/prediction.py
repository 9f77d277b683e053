"""The model's occupancy probabilities for a selection round, with the checks that catch a model breaking the
protocol (logits, another batch size, non-finite values)."""

from __future__ import annotations

from typing import Any, cast

import lightning as L
import torch
from lightning.pytorch.utilities.seed import isolate_rng
from torch import Tensor

from lightning_vtr.protocol import AugmentableDataModule, ReconstructionModel
from lightning_vtr.utils.validation import check_probabilities

__all__ = ["PROBABILITIES_HINT", "predict_in_eval", "predict_probabilities", "voxel_grid_mismatch"]

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


def predict_in_eval(pl_module: L.LightningModule, images: list[Tensor], batch_size: int, *, isolated: bool) -> Tensor:
    """:func:`predict_probabilities` with the model in eval mode, its mode restored after.

    Args:
        pl_module: the model, attached to a Trainer.
        images: the objects' input views, each ``(V, 3, H, W)`` float.
        batch_size: objects per ``predict_voxels`` call.
        isolated: restore every random number generator after (a model that draws random numbers while
            predicting must not shift the training's stream).

    Returns:
        ``(N, R, R, R)`` float32 on the CPU.

    Example::

        predicted = predict_in_eval(model, [item["images"]], batch_size=16, isolated=True)
    """
    was_training = pl_module.training
    pl_module.eval()
    try:
        if not isolated:
            return predict_probabilities(pl_module, images, batch_size)
        with isolate_rng():
            return predict_probabilities(pl_module, images, batch_size)
    finally:
        pl_module.train(was_training)


def voxel_grid_mismatch(pl_module: L.LightningModule, dm: AugmentableDataModule, source_view_set: str) -> str | None:
    """Predict the first training object once; say how the prediction's grid differs from the dataset's voxels.

    The model's mode and the random number generators are left as they were.

    Args:
        pl_module: the model, attached to a Trainer and on its device.
        dm: the datamodule.
        source_view_set: the view set the model's input views come from.

    Returns:
        A message naming both shapes and what to change, or ``None`` when they agree (or there are no training
        objects).

    Raises:
        ValueError: anything :func:`predict_probabilities` refuses (values outside ``[0, 1]``, another batch size).

    Example::

        message = voxel_grid_mismatch(model, trainer.datamodule, "aligned")
    """
    records = dm.split_records("train")
    if not records:
        return None
    item: dict[str, Any] = dm.eval_item(records[0], source_view_set, seed=0)
    predicted = predict_in_eval(pl_module, [item["images"]], 1, isolated=True)
    expected = tuple(item["voxels"].shape)
    if tuple(predicted.shape[1:]) == expected:
        return None
    return (
        f"ErrorGuidedViewAugmentation compares predictions with the dataset's voxels, but "
        f"{type(pl_module).__name__}.predict_voxels returned shape {tuple(predicted.shape)} for one training "
        f"item ({item['category']}/{item['object_id']}, images {tuple(item['images'].shape)}) and the "
        f"dataset's voxels have shape {expected}: use a model whose voxel_resolution is {expected[0]} or a "
        f"dataset built at the model's resolution."
    )

"""Input checks of voxel grids and the reconstruction error volume the error-guided scores project."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lightning_vtr.utils.validation import check_choice, check_float

__all__ = ["check_grid_shape", "check_tensor_ndim", "check_volume_pair", "check_volumes", "error_volume"]


def check_grid_shape(volumes: Tensor, name: str) -> None:
    """Raise unless ``volumes`` is a tensor of cubic grids ``(B, R, R, R)`` with ``R >= 1`` (``name`` in the message)."""
    if not isinstance(volumes, Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor, got {type(volumes).__name__}")
    if volumes.ndim != 4 or not (volumes.shape[1] == volumes.shape[2] == volumes.shape[3]):
        raise ValueError(f"`{name}` must have shape (B, R, R, R), got {tuple(volumes.shape)}")
    if volumes.shape[1] == 0:
        raise ValueError(f"`{name}` must be a non-empty grid (R >= 1), got shape {tuple(volumes.shape)}")


def check_tensor_ndim(value: Tensor, name: str, ndim: int, shape: str) -> None:
    """Raise unless ``value`` is a tensor with ``ndim`` dimensions (``shape``, e.g. ``"(B, V)"``, in the message)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape {shape}, got {type(value).__name__}")
    if value.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape}, got {tuple(value.shape)}")


def check_volumes(volumes: Tensor, name: str = "volumes") -> Tensor:
    """Check a batch of cubic voxel grids ``(B, R, R, R)``, ``R >= 1``; returns it as a float tensor.

    A bool tensor is converted to the default float dtype; a float tensor is returned as is.

    Args:
        volumes: ``(B, R, R, R)`` grids, floating-point or bool.
        name: the argument's name in error messages.

    Returns:
        ``volumes`` itself if floating-point, else a copy in the default float dtype.

    Raises:
        TypeError: ``volumes`` is not a tensor, or is neither floating-point nor bool.
        ValueError: another shape, or an empty grid (``R = 0``).

    Example:
        >>> check_volumes(torch.ones(1, 2, 2, 2, dtype=torch.bool)).dtype
        torch.float32
    """
    check_grid_shape(volumes, name)
    if volumes.dtype == torch.bool:
        return volumes.to(torch.get_default_dtype())
    if not volumes.is_floating_point():
        raise TypeError(f"`{name}` must be a floating-point (or bool) tensor, got dtype {volumes.dtype}")
    return volumes


def check_volume_pair(predicted: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Check what every :class:`~lightning_vtr.selection.base.ViewSelector` receives: two batches of grids.

    ``predicted`` and ``target`` must be ``(B, R, R, R)`` tensors of the same shape (see
    :func:`check_volumes`); a custom selector can call this first to fail with the package's messages.

    Args:
        predicted: ``(B, R, R, R)`` predicted occupancy, floating-point or bool.
        target: ``(B, R, R, R)`` ground-truth occupancy, floating-point or bool.

    Returns:
        ``(predicted, target)`` as float tensors (bool grids converted to the default float dtype).

    Raises:
        TypeError: either is not a tensor, or is neither floating-point nor bool.
        ValueError: the shapes differ (the message names both) or are not ``(B, R, R, R)`` with ``R >= 1``.

    Example:
        >>> predicted, target = check_volume_pair(torch.rand(2, 4, 4, 4), torch.zeros(2, 4, 4, 4, dtype=torch.bool))
        >>> target.dtype, tuple(target.shape)
        (torch.float32, (2, 4, 4, 4))
    """
    if not isinstance(predicted, Tensor) or not isinstance(target, Tensor):
        raise TypeError(
            f"`predicted` and `target` must be torch.Tensors, got {type(predicted).__name__} and {type(target).__name__}"
        )
    if predicted.shape != target.shape:
        raise ValueError(
            f"`predicted` and `target` must have the same shape (B, R, R, R), got predicted "
            f"{tuple(predicted.shape)} and target {tuple(target.shape)}"
        )
    return check_volumes(predicted, "predicted"), check_volumes(target, "target")


def error_volume(
    predicted: Tensor,
    target: Tensor,
    *,
    threshold: float = 0.4,
    mode: Literal["binary", "soft"] = "binary",
    mask: Literal[None, "gt"] = None,
) -> Tensor:
    """Reconstruction error ``E = |V - V_gt|`` of a batch of voxel grids.

    Args:
        predicted: ``(B, R, R, R)`` occupancy probabilities in ``[0, 1]``.
        target: ``(B, R, R, R)`` ground-truth occupancy in ``{0, 1}`` (binarised at 0.5).
        threshold: ``mode="binary"`` binarises the prediction as ``predicted >= threshold`` (the IoU
            convention), so ``E`` is in ``{0, 1}`` (the paper's definition, threshold 0.4).
        mode: ``"binary"`` (paper) or ``"soft"`` (``|predicted - target|`` of the continuous output).
        mask: ``"gt"`` keeps only errors inside ground-truth voxels (missed parts, as the released code
            does); ``None`` keeps every error.

    Returns:
        ``(B, R, R, R)`` error in ``[0, 1]``, dtype of ``predicted``.

    Raises:
        ValueError: on mismatched shapes (naming both) or a bad ``threshold`` / ``mode`` / ``mask``.
        TypeError: a non-tensor input or a non-number ``threshold``.

    Example:
        >>> predicted = torch.full((1, 2, 2, 2), 0.9)  # all occupied
        >>> target = torch.ones(1, 2, 2, 2)
        >>> target[0, 0] = 0  # half of the truth is empty: 4 false positives
        >>> error_volume(predicted, target).sum()
        tensor(4.)
        >>> error_volume(predicted, target, mask="gt").sum()  # only errors inside the truth
        tensor(0.)
    """
    predicted, target = check_volume_pair(predicted, target)
    check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    check_choice("mode", mode, ("binary", "soft"))
    check_choice("mask", mask, (None, "gt"))
    gt = target >= 0.5
    if mode == "binary":
        err = ((predicted >= threshold) != gt).to(predicted.dtype)
    else:
        err = (predicted - target.to(predicted.dtype)).abs()
    if mask == "gt":
        err.masked_fill_(~gt, 0.0)  # err is a fresh tensor in both modes
    return err

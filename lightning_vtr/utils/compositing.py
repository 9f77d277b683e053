"""Alpha compositing of straight-alpha RGBA images over a background, for numpy arrays and torch tensors."""

from __future__ import annotations

from typing import Any, TypeVar, cast

import numpy as np
import torch

__all__ = ["alpha_composite"]

ArrayOrTensor = TypeVar("ArrayOrTensor", np.ndarray, torch.Tensor)


def alpha_composite(rgba: ArrayOrTensor, background: Any = None, *, channels_first: bool = False) -> ArrayOrTensor:
    """Composite straight-alpha RGBA images over a background: ``rgb * a + background * (1 - a)``.

    The value range follows the dtype of ``rgba``:

    * ``uint8``: channels and ``background`` in ``0..255``, ``a = alpha / 255``; the blend runs in float32
      and is rounded to the nearest integer (ties to even) as ``uint8``.
    * floating point: channels, alpha and ``background`` in ``[0, 1]``; the blend runs in the dtype of
      ``rgba``, unrounded and unclamped.

    Args:
        rgba: a numpy array or torch tensor, ``(..., H, W, 4)``, or ``(..., 4, H, W)`` with ``channels_first``.
        background: ``None`` for white (255 or 1.0); a scalar grey level; an RGB colour ``(3,)`` or one colour
            per image ``(..., 3)``, its leading dimensions broadcast against those of ``rgba``; or background
            images with as many dimensions as ``rgba`` and 3 channels in the same layout (``(..., H, W, 3)`` or
            ``(..., 3, H, W)``). Any array-like; for a tensor ``rgba`` it is moved to its dtype and device.
        channels_first: the channel dimension of ``rgba``, the result and background images is ``-3``
            instead of ``-1``.

    Returns:
        The RGB images ``(..., H, W, 3)`` (``(..., 3, H, W)`` with ``channels_first``), of the same kind
        (array or tensor, device) as ``rgba``: ``uint8`` for ``uint8`` input, else the dtype of ``rgba``.

    Raises:
        TypeError: if ``rgba`` is not a numpy array or torch tensor of ``uint8`` or floating-point values.
        ValueError: if ``rgba`` has no 4 channels in its channel dimension, or ``background`` none of the
            shapes above.

    Example:
        >>> pixel = np.array([[[200, 100, 0, 128]]], dtype=np.uint8)  # (H, W, 4) = (1, 1, 4)
        >>> alpha_composite(pixel)[0, 0].tolist()
        [227, 177, 127]
        >>> half = torch.full((4, 1, 1), 0.5)  # (4, H, W): grey at half opacity
        >>> alpha_composite(half, (0.0, 0.0, 1.0), channels_first=True)[:, 0, 0].tolist()
        [0.25, 0.25, 0.75]
    """
    # 1. check inputs
    is_tensor = isinstance(rgba, torch.Tensor)
    if not is_tensor and not isinstance(rgba, np.ndarray):
        raise TypeError(f"`rgba` must be a numpy array or torch tensor, got {type(rgba).__name__}")
    axis = -3 if channels_first else -1
    layout = "(..., 4, H, W)" if channels_first else "(..., H, W, 4)"
    if rgba.ndim < 3 or rgba.shape[axis] != 4:
        raise ValueError(f"`rgba` must be {layout}, got shape {tuple(rgba.shape)}")
    if isinstance(rgba, torch.Tensor):
        integer, floating = rgba.dtype == torch.uint8, rgba.is_floating_point()
    else:
        integer, floating = rgba.dtype == np.uint8, np.issubdtype(rgba.dtype, np.floating)
    if not (integer or floating):
        raise TypeError(f"`rgba` must hold uint8 or floating-point values, got {rgba.dtype}")

    # 2. split the channels, in the range of the blend
    x = (rgba.float() if isinstance(rgba, torch.Tensor) else rgba.astype(np.float32)) if integer else rgba
    if channels_first:
        rgb, alpha = x[..., :3, :, :], x[..., 3:, :, :]
    else:
        rgb, alpha = x[..., :3], x[..., 3:]
    if integer:
        alpha = alpha / 255.0
    if background is None:
        background = 255.0 if integer else 1.0
    bg = _as_background(background, rgb, axis, channels_first)

    # 3. blend
    out = rgb * alpha + bg * (1.0 - alpha)
    if not integer:
        return out
    # (the cast: checking the numpy case, mypy also follows the isinstance-Tensor branch of `x` above)
    return cast(
        ArrayOrTensor,
        torch.round(out).to(torch.uint8) if isinstance(out, torch.Tensor) else np.rint(out).astype(np.uint8),
    )


def _as_background(background: Any, rgb: ArrayOrTensor, axis: int, channels_first: bool) -> ArrayOrTensor:
    """``background`` in the dtype (and device) of ``rgb``, shaped to broadcast against it."""
    if isinstance(rgb, torch.Tensor):
        bg = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
    else:
        bg = np.asarray(background, dtype=rgb.dtype)
    if bg.ndim == 0:
        return bg
    if bg.ndim == rgb.ndim and bg.shape[axis] == 3:  # background images
        return bg
    if bg.ndim < rgb.ndim and bg.shape[-1] == 3:  # colours: one per image
        return bg[..., :, None, None] if channels_first else bg[..., None, None, :]
    images = "(..., 3, H, W)" if channels_first else "(..., H, W, 3)"
    raise ValueError(
        f"`background` must be (..., 3) RGB colours, a scalar or {rgb.ndim}-d images {images}, "
        f"got shape {tuple(bg.shape)}"
    )

"""Layers shared by the reconstruction models, written for fast CPU training.

The models' 3-D activations travel in the ``channels_last_3d`` layout, where oneDNN, PyTorch's CPU convolution
backend, runs the tiny presets' few-channel 3-D convolutions about as fast as in the default layout or faster.
Two operations are slow there and get helpers that keep the models' math and parameters (checkpoints load
unchanged): a convolution with one output channel and a ``1^3`` kernel, which has no fast kernel in either
layout (:class:`VolumeHead`, a weighted sum over channels), and CPU batch normalisation of fewer than 8
channels, which is fast only in the default layout (:class:`BatchNorm3d`).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["BatchNorm3d", "VolumeHead", "VolumeHeadTransposed", "channels_last_3d"]


def channels_last_3d(x: Tensor) -> Tensor:
    """``x (N, C, D, H, W)`` in the ``channels_last_3d`` memory layout (a copy only if it is not already).

    Example:
        >>> channels_last_3d(torch.zeros(2, 4, 8, 8, 8)).stride()
        (2048, 1, 256, 32, 4)
    """
    return x.contiguous(memory_format=torch.channels_last_3d)


_FEW_CHANNELS = 8  # below this, CPU batch normalisation is fast only in the default layout


class BatchNorm3d(nn.BatchNorm3d):
    """``nn.BatchNorm3d`` that normalises volumes with fewer than 8 channels on the CPU in the default layout.

    Same parameters, buffers and math as ``nn.BatchNorm3d``; a ``channels_last_3d`` input with few channels
    is copied to the default layout first (PyTorch's CPU kernel is several times slower on such inputs in
    ``channels_last_3d``, and less accurate), and the output stays in the default layout.

    Example:
        >>> bn = BatchNorm3d(4)
        >>> bn(channels_last_3d(torch.randn(2, 4, 8, 8, 8))).is_contiguous()
        True
    """

    def forward(self, x: Tensor) -> Tensor:
        if x.device.type == "cpu" and x.shape[1] < _FEW_CHANNELS:
            x = x.contiguous()
        return super().forward(x)


def _weighted_channel_sum(x: Tensor, weight: Tensor) -> Tensor:
    """``(N, C, D, H, W)`` -> ``(N, 1, D, H, W)``: the sum over channels weighted by ``weight (C,)``.

    A broadcast product and a sum in the default layout, whose backward is about twice as fast as that of a
    contraction (``einsum`` turns the input's gradient into a batched product with an inner size of one); a
    contraction in ``channels_last_3d``, where the product's sum over channels is the slow one.
    """
    if x.is_contiguous():
        return (x * weight.to(x.dtype).view(1, -1, 1, 1, 1)).sum(dim=1, keepdim=True)  # x's dtype, as autocast
    return torch.einsum("ncdhw,c->ndhw", x, weight).unsqueeze(1)


class VolumeHead(nn.Conv3d):
    """``nn.Conv3d(in_channels, 1, kernel_size=1, bias=False)``, computed as a weighted sum over channels.

    Same parameter (``weight (1, C, 1, 1, 1)``) and output ``(N, 1, D, H, W)`` as the convolution it
    replaces, without oneDNN's slow one-output kernel.

    Example:
        >>> head = VolumeHead(4)
        >>> head(torch.zeros(2, 4, 8, 8, 8)).shape
        torch.Size([2, 1, 8, 8, 8])
    """

    def __init__(self, in_channels: int) -> None:
        super().__init__(in_channels, 1, kernel_size=1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return _weighted_channel_sum(x, self.weight.reshape(-1))


class VolumeHeadTransposed(nn.ConvTranspose3d):
    """``nn.ConvTranspose3d(in_channels, 1, kernel_size=1, bias=False)``, as a weighted sum over channels.

    Same parameter (``weight (C, 1, 1, 1, 1)``) and output ``(N, 1, D, H, W)`` as the transposed
    convolution it replaces (a ``1^3`` transposed convolution is the same map as a ``1^3`` convolution).

    Example:
        >>> head = VolumeHeadTransposed(3)
        >>> head(torch.zeros(2, 3, 8, 8, 8)).shape
        torch.Size([2, 1, 8, 8, 8])
    """

    def __init__(self, in_channels: int) -> None:
        super().__init__(in_channels, 1, kernel_size=1, bias=False)

    def forward(self, x: Tensor) -> Tensor:  # type: ignore[override]  # no output_size: the map is 1^3
        return _weighted_channel_sum(x, self.weight.reshape(-1))

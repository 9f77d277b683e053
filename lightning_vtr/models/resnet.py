"""ResNet-50 up to ``layer2`` in plain torch, loadable from a torchvision-format state dict.

Pix2Vox++ encodes each view with an ImageNet ResNet-50 truncated after ``layer2`` (512 channels at
stride 8). No torchvision build is usable here, so the module is written out with torchvision's
module names (``conv1``, ``bn1``, ``layer1.0.conv1``, ``layer1.0.downsample.0``, ...) and
:func:`load_torchvision_resnet50` reads a full ``resnet50`` state dict from a local file, a URL or
``"imagenet"`` (torchvision's ImageNet weights, through torch.hub's cache).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from torch import Tensor, nn

from lightning_vtr.models.weights import load_weights
from lightning_vtr.utils.validation import check_type

__all__ = ["Bottleneck", "ResNet50Stem", "load_torchvision_resnet50"]

#: Prefixes of a full torchvision ResNet-50 state dict that the truncated network does not have.
_DROPPED_PREFIXES = ("layer3.", "layer4.", "fc.")


class Bottleneck(nn.Module):
    """torchvision's ResNet v1.5 bottleneck: 1x1 -> 3x3 (carries the stride) -> 1x1, x4 expansion.

    Args:
        in_channels: input channels.
        planes: width of the inner convolutions; the output has ``4 * planes`` channels.
        stride: stride of the 3x3 convolution (and of the projection shortcut).
    """

    expansion = 4

    def __init__(self, in_channels: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        out_channels = planes * self.expansion
        self.conv1 = nn.Conv2d(in_channels, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, out_channels, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_channels)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False), nn.BatchNorm2d(out_channels)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


def _make_layer(in_channels: int, planes: int, blocks: int, stride: int) -> nn.Sequential:
    layers = [Bottleneck(in_channels, planes, stride)]
    layers += [Bottleneck(planes * Bottleneck.expansion, planes) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class ResNet50Stem(nn.Module):
    """ResNet-50 ``conv1 .. layer2``: ``(N, 3, H, W)`` -> ``(N, 512, H / 8, W / 8)``.

    At 224 px the output is ``(N, 512, 28, 28)``, the feature map Pix2Vox++ builds on. It takes no arguments;
    fill it with :func:`load_torchvision_resnet50`.

    Example:
        >>> import torch
        >>> ResNet50Stem().eval()(torch.zeros(1, 3, 64, 64)).shape
        torch.Size([1, 512, 8, 8])
    """

    out_channels = 512
    stride = 8

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = _make_layer(64, 64, blocks=3, stride=1)
        self.layer2 = _make_layer(256, 128, blocks=4, stride=2)

    def forward(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer2(self.layer1(x))


def load_torchvision_resnet50(
    module: ResNet50Stem, source: str | os.PathLike | Mapping[str, Tensor], *, progress: bool = True
) -> None:
    """Load a torchvision-format ResNet-50 state dict into ``module`` (in place).

    ``layer3``, ``layer4`` and ``fc`` entries are ignored; every other key must match exactly
    in name and shape.

    Args:
        module: the truncated ResNet-50.
        source: a local file saved with ``torch.save(resnet50().state_dict(), path)`` (optionally
            wrapped as ``{"state_dict": ...}``), an ``http(s)://`` or ``file://`` URL (downloaded once
            into torch.hub's cache), ``"imagenet"`` (torchvision's ``IMAGENET1K_V1`` weights), or the
            state dict itself. See :func:`~lightning_vtr.models.weights.load_weights`.
        progress: show a progress bar while downloading.

    Raises:
        TypeError: if ``source`` is neither a path, a URL nor a mapping.
        FileNotFoundError: if ``source`` is a path that does not exist.
        ~lightning_vtr.models.weights.WeightsDownloadError: if a download fails (the message names the
            URL and the cache path).
        ValueError: naming the missing / unexpected keys or mismatched shapes.

    Example:
        >>> stem = ResNet50Stem()
        >>> load_torchvision_resnet50(stem, ResNet50Stem().state_dict())  # or "imagenet", a path or a URL
    """
    check_type("source", source, (str, os.PathLike, Mapping), "path, a URL, 'imagenet' or a state dict")
    name = "state dict" if isinstance(source, Mapping) else os.fspath(source)
    source = load_weights(source, kind="resnet50", progress=progress)
    state = {k: v for k, v in source.items() if not k.startswith(_DROPPED_PREFIXES)}
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong_shape = [
        f"{k}: expected {tuple(own[k].shape)}, found {tuple(state[k].shape)}"
        for k in sorted(set(own) & set(state))
        if tuple(own[k].shape) != tuple(state[k].shape)
    ]
    if missing or unexpected or wrong_shape:
        raise ValueError(
            f"{name} is not a torchvision ResNet-50 state dict: missing keys {missing}, "
            f"unexpected keys {unexpected}, shape mismatches {wrong_shape}"
        )
    module.load_state_dict(state, strict=True)

"""Pix2Vox++/A as a LightningModule: per-view encoder-decoder, context-aware merger, refiner.

The ``paper`` preset is the published model (ResNet-50 to ``layer2``, about 96.3 M parameters,
224 px input); the ``tiny`` preset keeps the structure with a small convolutional backbone and
narrow layers so it trains on a laptop CPU (64 px input). :meth:`Pix2VoxPlusPlus.from_official_checkpoint`
reads the checkpoints the Pix2Vox++ authors released.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import pickle
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lightning_vtr.metrics.functional import DEFAULT_IOU_THRESHOLDS
from lightning_vtr.models.base import VoxelReconstructionModule, build_adam
from lightning_vtr.models.layers import BatchNorm3d, VolumeHead, channels_last_3d
from lightning_vtr.models.resnet import ResNet50Stem, load_torchvision_resnet50
from lightning_vtr.models.weights import fetch_weights, is_restoring_checkpoint, restoring_checkpoint
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.utils.validation import check_choice, check_int, check_type

if TYPE_CHECKING:
    from lightning.pytorch.utilities.parsing import AttributeDict
    from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

__all__ = ["PIX2VOX_PRESETS", "Pix2VoxPlusPlus", "Pix2VoxSpec", "reference_init_"]


@dataclass(frozen=True)
class Pix2VoxSpec:
    """Layer sizes of one Pix2Vox++ variant.

    Attributes:
        image_size: input size in pixels.
        backbone: ``"resnet50"`` (to ``layer2``) or ``"small"`` (strided 3x3 convs).
        small_backbone_channels: widths of the small backbone's stride-2 convs.
        encoder_channels: the three 3x3 conv widths after the backbone (the last two are followed
            by a 2x2 max-pool).
        decoder_channels: ConvTranspose3d widths, one per doubling from 2^3 to 32^3; the last is
            the raw feature width (8 in the paper), merged with the volume into ``last + 1``.
        refiner_channels: 3D U-Net widths at 16^3, 8^3, 4^3.
        refiner_hidden: width of the refiner's bottleneck fully-connected layer.
        merger_stride: the merger scores views on a grid this many times coarser than the volume
            (average-pooled features, nearest-upsampled scores). 1 in the paper; the tiny preset
            uses 4 (an 8^3 grid).
        init: initialisation of every layer but a ResNet-50 backbone: ``"reference"`` (Pix2Vox++'s:
            convolutions Kaiming-normal, BatchNorm weight 1 / bias 0, Linear N(0, 0.01), biases 0) or
            ``"torch"`` (PyTorch's defaults).
        two_stage_loss: the default loss: ``True`` for Pix2Vox++'s pretraining loss
            ``10 * (BCE(coarse) + BCE(refined))``, ``False`` for ``BCE(refined)``.

    Example:
        >>> spec = Pix2VoxSpec(
        ...     image_size=128,
        ...     backbone="resnet50",
        ...     encoder_channels=(512, 256, 256),
        ...     decoder_channels=(512, 128, 32, 8),
        ...     refiner_channels=(32, 64, 128),
        ...     refiner_hidden=2048,
        ... )
        >>> spec.backbone_channels, spec.feature_size
        (512, 4)
    """

    image_size: int
    backbone: str
    encoder_channels: tuple[int, int, int]
    decoder_channels: tuple[int, int, int, int]
    refiner_channels: tuple[int, int, int]
    refiner_hidden: int
    small_backbone_channels: tuple[int, ...] = ()
    merger_stride: int = 1
    init: str = "reference"
    two_stage_loss: bool = True

    @property
    def backbone_channels(self) -> int:
        """Channels of the backbone's feature map (512 for ``"resnet50"``)."""
        return ResNet50Stem.out_channels if self.backbone == "resnet50" else self.small_backbone_channels[-1]

    @property
    def backbone_stride(self) -> int:
        """Downsampling factor of the backbone (8 for ``"resnet50"``)."""
        return ResNet50Stem.stride if self.backbone == "resnet50" else 2 ** len(self.small_backbone_channels)

    @property
    def feature_size(self) -> int:
        """Side of the per-view feature map after the encoder (7 at 224 px for the paper)."""
        return self.image_size // (self.backbone_stride * 4)


PIX2VOX_PRESETS: dict[str, Pix2VoxSpec] = {
    "paper": Pix2VoxSpec(
        image_size=224,
        backbone="resnet50",
        encoder_channels=(512, 256, 256),
        decoder_channels=(512, 128, 32, 8),
        refiner_channels=(32, 64, 128),
        refiner_hidden=2048,
    ),
    "tiny": Pix2VoxSpec(
        image_size=64,
        backbone="small",
        small_backbone_channels=(16, 32),
        encoder_channels=(32, 32, 32),
        decoder_channels=(32, 16, 8, 4),
        refiner_channels=(4, 8, 16),
        refiner_hidden=256,
        merger_stride=4,
        init="torch",
        two_stage_loss=False,
    ),
}
"""The named presets. ``paper``: the published model, with Pix2Vox++'s initialisation and pretraining loss.
``tiny``: 64 px, about 0.76 M parameters. The tiny preset is ours, not published: it keeps PyTorch's
initialisation and ``BCE(refined)``, and its merger scores the views on an 8^3 grid (``merger_stride=4``; a checkpoint that does not record
its stride loads with the one it was trained with, see :class:`Pix2VoxPlusPlus`)."""

_LEGACY_MERGER_STRIDES = {"paper": 1, "tiny": 2}
"""Each preset's merger stride in checkpoints that do not record ``merger_stride`` (the stride they were trained with)."""

_RESOLUTION = 32  # four doublings from the 2^3 seed volume
_INITS = ("reference", "torch")


def _check_merger_stride(stride: object) -> int:
    value = check_int("merger_stride", stride, minimum=1)
    if _RESOLUTION % value:
        raise ValueError(f"`merger_stride` must divide the volume side {_RESOLUTION}, got {value}")
    return value


def _conv_bn_relu(c_in: int, c_out: int, pool: bool) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
    if pool:
        layers.append(nn.MaxPool2d(2))
    return nn.Sequential(*layers)


class _Encoder(nn.Module):
    """``(N, 3, H, W)`` -> ``(N, C, H / (4 s), W / (4 s))`` per view (``s`` the backbone stride)."""

    def __init__(self, spec: Pix2VoxSpec) -> None:
        super().__init__()
        if spec.backbone == "resnet50":
            self.backbone: nn.Module = ResNet50Stem()
        else:
            layers: list[nn.Module] = []
            c_in = 3
            for c in spec.small_backbone_channels:
                layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.BatchNorm2d(c), nn.ReLU(inplace=True)]
                c_in = c
            self.backbone = nn.Sequential(*layers)
        c1, c2, c3 = spec.encoder_channels
        self.layer1 = _conv_bn_relu(spec.backbone_channels, c1, pool=False)
        self.layer2 = _conv_bn_relu(c1, c2, pool=True)
        self.layer3 = _conv_bn_relu(c2, c3, pool=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.layer3(self.layer2(self.layer1(self.backbone(x))))


def _tconv3d(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.ConvTranspose3d(c_in, c_out, 4, stride=2, padding=1, bias=False),
        BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
    )


class _Decoder(nn.Module):
    """Feature ``(N, C, 2, 2, 2)`` -> features ``(N, c, 32, 32, 32)`` and a volume ``(N, 32, 32, 32)`` in [0, 1]."""

    def __init__(self, in_channels: int, channels: Sequence[int]) -> None:
        super().__init__()
        widths = [in_channels, *channels]
        self.layers = nn.Sequential(*[_tconv3d(a, b) for a, b in itertools.pairwise(widths)])
        self.to_volume = VolumeHead(channels[-1])

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        features = self.layers(channels_last_3d(x))
        return features, torch.sigmoid(self.to_volume(features)).squeeze(1)

    def reference_init_(self) -> None:
        """Pix2Vox++'s initialisation (:func:`reference_init_`), with the volume head's as released.

        The released head is ``ConvTranspose3d(C, 1, 1)``, whose Kaiming ``fan_in`` is its one output
        channel (std ``sqrt(2)``); ours is the same map as ``Conv3d(C, 1, 1)``, drawn through the transposed
        view to match.
        """
        reference_init_(self)
        nn.init.kaiming_normal_(self.to_volume.weight.transpose(0, 1))


def _conv3d_bn_lrelu(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(c_in, c_out, 3, padding=1), BatchNorm3d(c_out), nn.LeakyReLU(0.2))


class _ContextAwareMerger(nn.Module):
    """Scores each view's volume per voxel and fuses the views with a softmax over views.

    Works for any number of views: features ``(B V, C - 1, R, R, R)`` and volumes ``(B, V, R, R, R)`` ->
    ``(B, R, R, R)``. The scores see each view's features with its volume as the last channel.
    """

    def __init__(self, channels: int, stride: int = 1) -> None:
        super().__init__()
        self.stride = stride
        self.context = nn.ModuleList([_conv3d_bn_lrelu(channels, channels) for _ in range(4)])
        self.score = nn.Sequential(_conv3d_bn_lrelu(4 * channels, channels), _conv3d_bn_lrelu(channels, 1))

    def forward(self, features: Tensor, volumes: Tensor) -> Tensor:
        b, v = volumes.shape[:2]
        parts = [features, volumes.flatten(0, 1).unsqueeze(1)]
        if self.stride > 1:  # pooled apart and then joined: the same values, and the join is smaller
            parts = [F.avg_pool3d(part, self.stride) for part in parts]
        x = torch.cat(parts, dim=1)
        stages = []
        for layer in self.context:
            x = layer(x)
            stages.append(x)
        scores = self.score(channels_last_3d(torch.cat(stages, dim=1)))
        if self.stride > 1:
            scores = F.interpolate(scores, scale_factor=self.stride, mode="nearest")
        scores = scores.view(b, v, *volumes.shape[2:])
        weights = torch.softmax(scores, dim=1)
        return (volumes * weights).sum(dim=1).clamp(0, 1)


class _Refiner(nn.Module):
    """3D U-Net with a fully-connected bottleneck; returns ``(coarse + refined) / 2``."""

    def __init__(self, channels: Sequence[int], hidden: int) -> None:
        super().__init__()
        c1, c2, c3 = channels

        def down(a: int, b: int) -> nn.Sequential:
            # k4 / pad 2 grows the side by one; the pool then halves it exactly (32 -> 33 -> 16).
            return nn.Sequential(nn.Conv3d(a, b, 4, padding=2), BatchNorm3d(b), nn.LeakyReLU(0.2), nn.MaxPool3d(2))

        self.down1, self.down2, self.down3 = down(1, c1), down(c1, c2), down(c2, c3)
        self._bottleneck = (c3, 4, 4, 4)
        flat = c3 * 64
        self.fc = nn.Sequential(
            nn.Linear(flat, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, flat), nn.ReLU(inplace=True)
        )
        self.up1, self.up2 = _tconv3d(c3, c2), _tconv3d(c2, c1)
        self.up3 = nn.Sequential(nn.ConvTranspose3d(c1, 1, 4, stride=2, padding=1, bias=False), nn.Sigmoid())

    def forward(self, coarse: Tensor) -> Tensor:
        d1 = self.down1(channels_last_3d(coarse.unsqueeze(1)))
        d2 = self.down2(d1)
        d3 = self.down3(d2)
        x = d3 + self.fc(d3.flatten(1)).view(-1, *self._bottleneck)
        x = d2 + self.up1(x)
        x = d1 + self.up2(x)
        return (coarse + self.up3(x).squeeze(1)) * 0.5


def reference_init_(module: nn.Module) -> None:
    """Pix2Vox++'s initialisation of every layer of ``module``, in place.

    Conv2d / Conv3d / ConvTranspose3d weights Kaiming-normal with PyTorch's defaults (``a = 0``,
    ``mode="fan_in"``: std ``sqrt(2 / fan_in)``, where PyTorch takes ``fan_in`` from a weight's dim 1, i.e. the
    *output* channels of a transposed convolution); their biases 0. BatchNorm weight 1, bias 0 (running
    statistics untouched). Linear weight N(0, 0.01), bias 0.
    """
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.ConvTranspose3d)):
            nn.init.kaiming_normal_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d)):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, 0.01)
            nn.init.zeros_(m.bias)


# ---------------------------------------------------------------------- the released checkpoint layout
_OFFICIAL_PARTS = ("encoder", "decoder", "merger", "refiner")
# The released ResNet-50 is nn.Sequential(conv1, bn1, relu, maxpool, layer1, layer2, ...)[:6].
_OFFICIAL_RESNET = {"resnet.0.": "conv1.", "resnet.1.": "bn1.", "resnet.4.": "layer1.", "resnet.5.": "layer2."}
_OFFICIAL_VOLUME_HEAD = "decoder.to_volume.weight"


def _official_prefixes(spec: Pix2VoxSpec) -> dict[str, dict[str, str]]:
    """Per released part: released name prefix -> our name prefix (below the part's module)."""
    if spec.backbone == "resnet50":
        backbone = {old: f"backbone.{new}" for old, new in _OFFICIAL_RESNET.items()}
    else:  # no released counterpart; a Sequential in the released position keeps its indices
        backbone = {f"resnet.{i}.": f"backbone.{i}." for i in range(3 * len(spec.small_backbone_channels))}
    n = len(spec.decoder_channels)
    return {
        "encoder": {**backbone, "layer1.": "layer1.", "layer2.": "layer2.", "layer3.": "layer3."},
        "decoder": {**{f"layer{i + 1}.": f"layers.{i}." for i in range(n)}, f"layer{n + 1}.0.": "to_volume."},
        "merger": {
            **{f"layer{i + 1}.": f"context.{i}." for i in range(4)},
            "layer5.": "score.0.",
            "layer6.": "score.1.",
        },
        "refiner": {
            "layer1.": "down1.",
            "layer2.": "down2.",
            "layer3.": "down3.",
            "layer4.0.": "fc.0.",
            "layer5.0.": "fc.2.",
            "layer6.": "up1.",
            "layer7.": "up2.",
            "layer8.": "up3.",
        },
    }


def _read_official(checkpoint: str | os.PathLike | Mapping[str, Any]) -> tuple[str, Mapping[str, Any]]:
    check_type("checkpoint", checkpoint, (str, os.PathLike, Mapping), "path or a loaded checkpoint (a mapping)")
    if isinstance(checkpoint, Mapping):
        return "checkpoint", checkpoint
    name = os.fspath(checkpoint)
    if not os.path.isfile(name):
        raise FileNotFoundError(f"Pix2Vox++ checkpoint not found: {name}")
    # The released files also hold solver states and the best IoU, pickled as a NumPy scalar.
    safe_globals = getattr(torch.serialization, "safe_globals", None)  # torch >= 2.5
    try:
        with safe_globals(_numpy_scalar_globals()) if safe_globals else contextlib.nullcontext():
            loaded = torch.load(name, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise ValueError(
            f"{name} holds objects that weights-only loading refuses ({err}). If you trust the file, load it with "
            "torch.load(path, map_location='cpu', weights_only=False) and pass the resulting dict instead."
        ) from err
    if not isinstance(loaded, Mapping):
        raise ValueError(f"{name} must hold a dict with {_layout_keys()}, got {type(loaded).__name__}")
    return name, loaded


def _numpy_scalar_globals() -> list[Any]:
    """What ``weights_only`` loading needs for NumPy scalars pickled by NumPy 1 or 2."""
    try:
        from numpy._core.multiarray import scalar
    except ImportError:  # pragma: no cover - NumPy 1
        from numpy.core.multiarray import scalar  # type: ignore[no-redef]  # NumPy 1's location
    dtypes = getattr(np, "dtypes", None)
    classes = [getattr(dtypes, t) for t in ("Float64DType", "Float32DType", "Int64DType")] if dtypes else []
    return [(scalar, "numpy.core.multiarray.scalar"), (scalar, "numpy._core.multiarray.scalar"), np.dtype, *classes]


def _layout_keys() -> str:
    return ", ".join(f"'{p}_state_dict'" for p in _OFFICIAL_PARTS)


def _map_official(name: str, checkpoint: Mapping[str, Any], spec: Pix2VoxSpec) -> dict[str, Tensor]:
    """The released ``{encoder,decoder,merger,refiner}_state_dict`` as one state dict in our names."""
    absent = [f"{p}_state_dict" for p in _OFFICIAL_PARTS if not isinstance(checkpoint.get(f"{p}_state_dict"), Mapping)]
    if absent:
        raise ValueError(
            f"{name} is not a released Pix2Vox++ checkpoint: it must hold {_layout_keys()}; missing {absent}, "
            f"found keys {sorted(map(str, checkpoint))}"
        )
    prefixes = _official_prefixes(spec)
    state: dict[str, Tensor] = {}
    unknown: list[str] = []
    for part in _OFFICIAL_PARTS:
        rules = sorted(prefixes[part].items(), key=lambda rule: -len(rule[0]))
        for key, value in checkpoint[f"{part}_state_dict"].items():
            bare = key[len("module.") :] if key.startswith("module.") else key  # DataParallel / DDP wrapper
            rule = next(((old, new) for old, new in rules if bare.startswith(old)), None)
            if rule is None:
                unknown.append(f"{part}_state_dict: {key}")
                continue
            state[f"{part}.{rule[1]}{bare[len(rule[0]) :]}"] = value
    if _OFFICIAL_VOLUME_HEAD in state:
        # Released: ConvTranspose3d(C, 1, 1), weight (C, 1, 1, 1, 1); ours: the same map as Conv3d(C, 1, 1).
        state[_OFFICIAL_VOLUME_HEAD] = state[_OFFICIAL_VOLUME_HEAD].transpose(0, 1)
    if unknown:
        raise ValueError(f"{name}: keys without a counterpart in Pix2VoxPlusPlus: {unknown[:10]} ({len(unknown)} keys)")
    return state


class Pix2VoxPlusPlus(VoxelReconstructionModule):
    """Pix2Vox++/A multi-view voxel reconstruction (Xie et al. 2020), as used by the VTR paper.

    Each view is encoded to a ``(C, 2, 2, 2)`` seed and decoded to a coarse ``32^3`` volume with raw
    features; the context-aware merger fuses any number of views; the refiner corrects the fused
    volume. Outputs of :meth:`reconstruct`: ``"voxels"`` (refined, ``(B, 32, 32, 32)``),
    ``"coarse_voxels"`` (merged) and ``"view_voxels"`` (``(B, V, 32, 32, 32)``).

    Recipe defaults come from the preset (:class:`Pix2VoxSpec`): the ``paper`` preset uses Pix2Vox++'s
    initialisation and pretraining loss ``10 * (BCE(coarse) + BCE(refined))``; the ``tiny`` preset (ours, not
    published) keeps PyTorch's initialisation and ``BCE(refined)``.
    The loss is computed in float32 with autocast off (BCE refuses half precision under CUDA autocast).

    Args:
        preset: ``"paper"`` (224 px, ResNet-50 to layer2, ~96.3 M parameters) or ``"tiny"`` (64 px).
        num_views: views per training sample (the merger accepts any number at test time).
        lr: Adam learning rate of encoder, decoder and refiner (published: 1e-3).
        merger_lr: Adam learning rate of the merger (published: 1e-4).
        betas: Adam betas.
        milestones: epochs at which MultiStepLR multiplies the learning rates by ``gamma``.
        gamma: MultiStepLR factor (published: 0.5).
        two_stage_loss: ``True``: Pix2Vox++'s pretraining loss ``10 * (BCE(coarse) + BCE(refined))``;
            ``False``: ``BCE(refined)``, what VTR fine-tunes with; ``None``: the preset's
            (``paper``: ``True``, ``tiny``: ``False``). Fine-tuning a ``paper`` model as VTR does: ``False``.
        backbone_weights: torchvision ResNet-50 weights for the ``paper`` preset: a local file, an
            ``http(s)://`` / ``file://`` URL (downloaded once into torch.hub's cache) or ``"imagenet"``
            (torchvision's ``IMAGENET1K_V1``); see :func:`~lightning_vtr.models.weights.load_weights`.
            Not read by :meth:`load_from_checkpoint`, whose state dict holds the weights.
        freeze_backbone: keep the ResNet-50 (or the tiny preset's small backbone) fixed. Pix2Vox++
            trains it, so the default is ``False``. ``None`` (deprecated) freezes it exactly when
            ``backbone_weights`` is given.
        init: initialisation of every layer but a ResNet-50 backbone: ``"reference"`` (Pix2Vox++'s,
            see :func:`reference_init_`), ``"torch"`` (PyTorch's defaults) or ``None``: the preset's
            (``paper``: ``"reference"``, ``tiny``: ``"torch"``).
        iou_thresholds: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        fscore_threshold: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        fscore_points: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        validation_fscore: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        categories: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        log_sheets: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        merger_stride: the merger's scoring grid is this many times coarser than the volume; ``None``: the
            preset's (``paper``: 1, ``tiny``: 4). A divisor of 32. It has no parameters, so a model saved with
            one stride loads into another. A checkpoint brings the stride it was trained with (resuming a fit
            included) unless :meth:`load_from_checkpoint` is given ``merger_stride=``; one that does not record it loads
            with the stride its preset was trained with (``paper``: 1, ``tiny``: 2).

    Raises:
        ValueError: on an unknown preset or init, weights for a preset without ResNet-50, or bad sizes.
        FileNotFoundError, ~lightning_vtr.models.weights.WeightsDownloadError: if ``backbone_weights``
            cannot be read or downloaded.

    Example:
        >>> model = Pix2VoxPlusPlus(preset="tiny")
        >>> model.predict_voxels(torch.zeros(2, 5, 3, 64, 64)).shape
        torch.Size([2, 32, 32, 32])
    """

    image_recipe: ClassVar[str] = "pix2vox"

    def __init__(
        self,
        preset: str = "tiny",
        num_views: int = 3,
        lr: float = 1e-3,
        merger_lr: float = 1e-4,
        betas: tuple[float, float] = (0.9, 0.999),
        milestones: tuple[int, ...] = (150,),
        gamma: float = 0.5,
        two_stage_loss: bool | None = None,
        backbone_weights: str | None = None,
        freeze_backbone: bool | None = False,
        init: str | None = None,
        iou_thresholds: tuple[float, ...] = DEFAULT_IOU_THRESHOLDS,
        fscore_threshold: float = DEFAULT_THRESHOLD,
        fscore_points: int = 8192,
        validation_fscore: bool = True,
        log_sheets: int = 0,
        categories: tuple[str, ...] | None = None,
        merger_stride: int | None = None,
    ) -> None:
        # 1. resolve the preset's defaults first: save_hyperparameters() records the values in effect
        check_choice("preset", preset, PIX2VOX_PRESETS)
        spec = PIX2VOX_PRESETS[preset]
        init = spec.init if init is None else check_choice("init", init, _INITS)
        merger_stride = spec.merger_stride if merger_stride is None else _check_merger_stride(merger_stride)
        if merger_stride != spec.merger_stride:
            spec = dataclasses.replace(spec, merger_stride=merger_stride)
        two_stage_loss = spec.two_stage_loss if two_stage_loss is None else bool(two_stage_loss)
        if backbone_weights is not None and spec.backbone != "resnet50":
            raise ValueError(
                f"`backbone_weights` must be None for preset {preset!r}, which has no ResNet-50 backbone "
                f"(preset 'paper' has one), got {backbone_weights!r}"
            )
        if freeze_backbone is None:
            warnings.warn(
                "`freeze_backbone=None` (freeze exactly when `backbone_weights` is given) is deprecated and will be "
                "removed in 0.4; Pix2Vox++ trains its backbone. Pass freeze_backbone=True to keep it fixed.",
                DeprecationWarning,
                stacklevel=2,
            )
            freeze_backbone = backbone_weights is not None
        # Resolved (downloaded, or found missing) before the network is built; a restored checkpoint brings its own.
        weights_file = None
        if backbone_weights is not None and not is_restoring_checkpoint():
            weights_file = fetch_weights(backbone_weights, kind="resnet50")
        super().__init__(
            image_size=spec.image_size,
            num_views=num_views,
            voxel_resolution=_RESOLUTION,
            iou_thresholds=iou_thresholds,
            fscore_threshold=fscore_threshold,
            fscore_points=fscore_points,
            validation_fscore=validation_fscore,
            categories=categories,
            log_sheets=log_sheets,
        )
        self.save_hyperparameters()
        self.preset = preset
        self.spec = spec

        # 2. build the network
        self.encoder = _Encoder(spec)
        seed_channels = spec.encoder_channels[-1] * spec.feature_size**2
        if seed_channels % 8:
            raise ValueError(
                f"preset {preset!r}: encoder output {seed_channels} values cannot be reshaped to (C, 2, 2, 2)"
            )
        self.decoder = _Decoder(seed_channels // 8, spec.decoder_channels)
        self.merger = _ContextAwareMerger(spec.decoder_channels[-1] + 1, spec.merger_stride)
        self.refiner = _Refiner(spec.refiner_channels, spec.refiner_hidden)

        # 3. initialise: the reference recipe leaves a ResNet-50 as torchvision (or its weights) made it
        if init == "reference":
            for name, child in self.encoder.named_children():
                if name != "backbone" or spec.backbone != "resnet50":
                    reference_init_(child)
            self.decoder.reference_init_()
            reference_init_(self.merger)
            reference_init_(self.refiner)

        # 4. pretrained backbone weights
        if weights_file is not None:
            load_torchvision_resnet50(cast(ResNet50Stem, self.encoder.backbone), weights_file)
        self.encoder.backbone.requires_grad_(not freeze_backbone)

        # 5. the 3-D layers' weights in the layout of their activations (see lightning_vtr.models.layers): a weight
        #    in PyTorch's default layout sends a one-channel input (the refiner's) down the slow path
        for part in (self.decoder, self.merger, self.refiner):
            part.to(memory_format=torch.channels_last_3d)  # type: ignore[call-overload]  # Module.to takes it; stub lacks it

    @classmethod
    def from_official_checkpoint(
        cls, checkpoint: str | os.PathLike | Mapping[str, Any], *, preset: str = "paper", **kwargs: Any
    ) -> Pix2VoxPlusPlus:
        """A model holding the weights of a checkpoint released by the Pix2Vox++ authors.

        The released layout is ``{"encoder_state_dict", "decoder_state_dict", "merger_state_dict",
        "refiner_state_dict"}`` (plus solver states, ignored), with the ``module.`` prefix of
        ``DataParallel`` / ``DistributedDataParallel`` (optional here). Names map onto ours part by part
        (the ResNet-50 ``resnet.0/1/4/5`` -> ``backbone.conv1/bn1/layer1/layer2``, decoder ``layer1-4`` ->
        ``layers.0-3``, merger ``layer1-6`` -> ``context.0-3`` / ``score.0-1``, refiner ``layer1-8`` ->
        ``down1-3`` / ``fc.0,2`` / ``up1-3``); the decoder's 1x1x1 transposed-convolution volume head is
        transposed into our equivalent convolution. BatchNorm ``num_batches_tracked`` may be absent (files
        from PyTorch < 0.4.1). Inputs must be preprocessed as the reference does (224 px, RGB normalised
        with mean = std = 0.5).

        Args:
            checkpoint: the released ``.pth`` file (read with ``weights_only=True``), or its loaded dict.
            preset: the architecture; the released checkpoints are ``"paper"`` models.
            **kwargs: other arguments of :class:`Pix2VoxPlusPlus` (``lr``, ``two_stage_loss``, ...);
                ``backbone_weights`` is not read.

        Returns:
            the model, in training mode (call ``.eval()`` for inference).

        Raises:
            FileNotFoundError: if the file does not exist.
            ValueError: naming the file and the keys, if it lacks a part, holds a key we have no
                counterpart for, misses one of ours, or a shape differs.
        """
        name, loaded = _read_official(checkpoint)
        with restoring_checkpoint():
            model = cls(preset=preset, **kwargs)
        state = _map_official(name, loaded, model.spec)
        own = model.state_dict()
        for key, value in own.items():
            if key.endswith("num_batches_tracked"):
                state.setdefault(key, value)
        missing = sorted(set(own) - set(state))
        unexpected = sorted(set(state) - set(own))
        wrong = [
            f"{k}: expected {tuple(own[k].shape)}, found {tuple(state[k].shape)}"
            for k in sorted(set(own) & set(state))
            if own[k].shape != state[k].shape
        ]
        if missing or unexpected or wrong:
            raise ValueError(
                f"{name} does not match Pix2VoxPlusPlus(preset={preset!r}): missing keys {missing[:10]} "
                f"({len(missing)}), unexpected keys {unexpected[:10]} ({len(unexpected)}), shape mismatches "
                f"{wrong[:10]} ({len(wrong)})"
            )
        model.load_state_dict(state, strict=True)
        return model

    def reconstruct(self, images: Tensor) -> dict[str, Tensor]:
        """The network's outputs for checked images ``(B, V, 3, H, W)``.

        Returns:
            ``{"voxels", "coarse_voxels": (B, R, R, R), "view_voxels": (B, V, R, R, R)}``.
        """
        b, v = images.shape[:2]
        features = self.encoder(images.flatten(0, 1))  # (B V, C, h, w)
        features, volumes = self.decoder(features.reshape(b * v, -1, 2, 2, 2))  # (B V, c, R, R, R), (B V, R, R, R)
        volumes = volumes.view(b, v, *volumes.shape[1:])
        coarse = self.merger(features, volumes)
        return {"voxels": self.refiner(coarse), "coarse_voxels": coarse, "view_voxels": volumes}

    def loss(self, outputs: dict[str, Tensor], target: Tensor) -> Tensor:
        """BCE of the refined volume, or Pix2Vox++'s ``10 * (BCE(coarse) + BCE(refined))`` (``two_stage_loss``).

        Computed in float32 with autocast off (probabilities and target cast to float32):
        ``binary_cross_entropy`` refuses to run under CUDA autocast, where it is unsafe in float16.
        """
        refined = outputs["voxels"]
        with torch.autocast(device_type=refined.device.type, enabled=False):
            target = target.float()
            loss = F.binary_cross_entropy(refined.float(), target)
            if cast("AttributeDict", self.hparams).two_stage_loss:
                loss = 10 * (F.binary_cross_entropy(outputs["coarse_voxels"].float(), target) + loss)
        return loss

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        hp = cast("AttributeDict", self.hparams)
        groups = [
            {"params": [p for p in module.parameters() if p.requires_grad], "lr": lr}
            for module, lr in (
                (self.encoder, hp.lr),
                (self.decoder, hp.lr),
                (self.merger, hp.merger_lr),
                (self.refiner, hp.lr),
            )
        ]
        optimizer = build_adam(torch.optim.Adam, [g for g in groups if g["params"]], betas=tuple(hp.betas))
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=list(hp.milestones), gamma=hp.gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # Stored outside "hyper_parameters", which load_from_checkpoint(..., preset=...) overwrites.
        checkpoint["pix2vox_preset"] = self.preset

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        hparams = checkpoint.get("hyper_parameters", {})
        found = checkpoint.get("pix2vox_preset", hparams.get("preset"))
        if found is not None and found != self.preset:
            raise ValueError(
                f"checkpoint was saved from a Pix2VoxPlusPlus with preset {found!r}; this model has preset "
                f"{self.preset!r} (expected {self.preset!r}). Build the model with preset={found!r} or use "
                "Pix2VoxPlusPlus.load_from_checkpoint(path) without overriding `preset`."
            )
        # The stride the weights were trained with (no parameters depend on it); a checkpoint without it was
        # trained with _LEGACY_MERGER_STRIDES. load_from_checkpoint(path, merger_stride=...) records its override there first.
        # None (what LightningCLI records for the argument's default) is the preset's stride, which the model has.
        stride = hparams.get("merger_stride", _LEGACY_MERGER_STRIDES[self.preset])
        if stride is not None and stride != self.merger.stride:
            self._set_merger_stride(stride)

    def _set_merger_stride(self, stride: int) -> None:
        """Score the views on a grid ``stride`` times coarser than the volume (recorded in ``hparams``)."""
        stride = _check_merger_stride(stride)
        self.merger.stride = stride
        self.spec = dataclasses.replace(self.spec, merger_stride=stride)
        self.hparams["merger_stride"] = stride

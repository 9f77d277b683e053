"""Pix2Vox++/A as a LightningModule: per-view encoder-decoder, context-aware merger, refiner.

The ``paper`` preset follows DESIGN section 5 (ResNet-50 to ``layer2``, about 96.3 M parameters,
224 px input); the ``tiny`` preset keeps the structure with a small convolutional backbone and
narrow layers so it trains on a laptop CPU (64 px input).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lightning_vtr.metrics.functional import DEFAULT_IOU_THRESHOLDS
from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.resnet import ResNet50Stem, load_torchvision_resnet50
from lightning_vtr.utils.validation import check_choice

__all__ = ["PIX2VOX_PRESETS", "Pix2VoxPlusPlus", "Pix2VoxSpec"]


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
            uses 2 because scoring 32^3 voxels per view dominates a CPU training step.
    """

    image_size: int
    backbone: str
    encoder_channels: tuple[int, int, int]
    decoder_channels: tuple[int, int, int, int]
    refiner_channels: tuple[int, int, int]
    refiner_hidden: int
    small_backbone_channels: tuple[int, ...] = ()
    merger_stride: int = 1

    @property
    def backbone_channels(self) -> int:
        return ResNet50Stem.out_channels if self.backbone == "resnet50" else self.small_backbone_channels[-1]

    @property
    def backbone_stride(self) -> int:
        return ResNet50Stem.stride if self.backbone == "resnet50" else 2 ** len(self.small_backbone_channels)

    @property
    def feature_size(self) -> int:
        """Side of the per-view feature map after the encoder (7 at 224 px for the paper)."""
        return self.image_size // (self.backbone_stride * 4)


#: The named presets. ``paper``: DESIGN section 5. ``tiny``: 64 px, about 0.2 M parameters.
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
        merger_stride=2,
    ),
}

_RESOLUTION = 32  # four doublings from the 2^3 seed volume


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
        nn.BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
    )


class _Decoder(nn.Module):
    """Feature ``(N, C, 2, 2, 2)`` -> raw features ``(N, c + 1, 32, 32, 32)`` (last channel: volume)."""

    def __init__(self, in_channels: int, channels: Sequence[int]) -> None:
        super().__init__()
        widths = [in_channels, *channels]
        self.layers = nn.Sequential(*[_tconv3d(a, b) for a, b in zip(widths[:-1], widths[1:])])
        self.to_volume = nn.Conv3d(channels[-1], 1, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        features = self.layers(x)
        return torch.cat([features, torch.sigmoid(self.to_volume(features))], dim=1)


def _conv3d_bn_lrelu(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(c_in, c_out, 3, padding=1), nn.BatchNorm3d(c_out), nn.LeakyReLU(0.2))


class _ContextAwareMerger(nn.Module):
    """Scores each view's volume per voxel and fuses the views with a softmax over views.

    Works for any number of views: ``raw (B, V, C, R, R, R)`` -> ``(B, R, R, R)``.
    """

    def __init__(self, channels: int, stride: int = 1) -> None:
        super().__init__()
        self.stride = stride
        self.context = nn.ModuleList([_conv3d_bn_lrelu(channels, channels) for _ in range(4)])
        self.score = nn.Sequential(_conv3d_bn_lrelu(4 * channels, channels), _conv3d_bn_lrelu(channels, 1))

    def forward(self, raw: Tensor) -> Tensor:
        b, v = raw.shape[:2]
        x = raw.flatten(0, 1)
        if self.stride > 1:
            x = F.avg_pool3d(x, self.stride)
        stages = []
        for layer in self.context:
            x = layer(x)
            stages.append(x)
        scores = self.score(torch.cat(stages, dim=1))
        if self.stride > 1:
            scores = F.interpolate(scores, scale_factor=self.stride, mode="nearest")
        scores = scores.view(b, v, *raw.shape[3:])
        weights = torch.softmax(scores, dim=1)
        return (raw[:, :, -1] * weights).sum(dim=1).clamp(0, 1)


class _Refiner(nn.Module):
    """3D U-Net with a fully-connected bottleneck; returns ``(coarse + refined) / 2``."""

    def __init__(self, channels: Sequence[int], hidden: int) -> None:
        super().__init__()
        c1, c2, c3 = channels

        def down(a: int, b: int) -> nn.Sequential:
            # k4 / pad 2 grows the side by one; the pool then halves it exactly (32 -> 33 -> 16).
            return nn.Sequential(nn.Conv3d(a, b, 4, padding=2), nn.BatchNorm3d(b), nn.LeakyReLU(0.2), nn.MaxPool3d(2))

        self.down1, self.down2, self.down3 = down(1, c1), down(c1, c2), down(c2, c3)
        self._bottleneck = (c3, 4, 4, 4)
        flat = c3 * 64
        self.fc = nn.Sequential(
            nn.Linear(flat, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, flat), nn.ReLU(inplace=True)
        )
        self.up1, self.up2 = _tconv3d(c3, c2), _tconv3d(c2, c1)
        self.up3 = nn.Sequential(nn.ConvTranspose3d(c1, 1, 4, stride=2, padding=1, bias=False), nn.Sigmoid())

    def forward(self, coarse: Tensor) -> Tensor:
        d1 = self.down1(coarse.unsqueeze(1))
        d2 = self.down2(d1)
        d3 = self.down3(d2)
        x = d3 + self.fc(d3.flatten(1)).view(-1, *self._bottleneck)
        x = d2 + self.up1(x)
        x = d1 + self.up2(x)
        return (coarse + self.up3(x).squeeze(1)) * 0.5


class Pix2VoxPlusPlus(VoxelReconstructionModule):
    """Pix2Vox++/A multi-view voxel reconstruction (Xie et al. 2020), as used by the VTR paper.

    Each view is encoded to a ``(C, 2, 2, 2)`` seed and decoded to a coarse ``32^3`` volume with raw
    features; the context-aware merger fuses any number of views; the refiner corrects the fused
    volume. Outputs of :meth:`reconstruct`: ``"voxels"`` (refined, ``(B, 32, 32, 32)``),
    ``"coarse_voxels"`` (merged) and ``"view_voxels"`` (``(B, V, 32, 32, 32)``).

    Args:
        preset: ``"paper"`` (224 px, ResNet-50 to layer2, ~96.3 M parameters) or ``"tiny"`` (64 px).
        num_views: views per training sample (the merger accepts any number at test time).
        lr: Adam learning rate of encoder, decoder and refiner (published: 1e-3).
        merger_lr: Adam learning rate of the merger (published: 1e-4).
        betas: Adam betas.
        milestones: epochs at which MultiStepLR multiplies the learning rates by ``gamma``.
        gamma: MultiStepLR factor (published: 0.5).
        two_stage_loss: use the original loss ``10 * (BCE(coarse) + BCE(refined))`` instead of
            ``BCE(refined)``.
        backbone_weights: path to a torchvision ResNet-50 state dict (``paper`` preset only).
        freeze_backbone: keep the ResNet-50 fixed, as published; ``None`` freezes it exactly when
            ``backbone_weights`` is given (a random backbone must train).
        iou_thresholds, fscore_threshold, fscore_points, validation_fscore, categories: see
            :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.

    Raises:
        ValueError: on an unknown preset, weights for a preset without ResNet-50, or bad sizes.

    Example:
        >>> model = Pix2VoxPlusPlus(preset="tiny")
        >>> model.predict_voxels(torch.zeros(2, 5, 3, 64, 64)).shape
        torch.Size([2, 32, 32, 32])
    """

    def __init__(
        self,
        preset: str = "tiny",
        num_views: int = 3,
        lr: float = 1e-3,
        merger_lr: float = 1e-4,
        betas: tuple[float, float] = (0.9, 0.999),
        milestones: tuple[int, ...] = (150,),
        gamma: float = 0.5,
        two_stage_loss: bool = False,
        backbone_weights: str | None = None,
        freeze_backbone: bool | None = None,
        iou_thresholds: tuple[float, ...] = DEFAULT_IOU_THRESHOLDS,
        fscore_threshold: float = 0.4,
        fscore_points: int = 8192,
        validation_fscore: bool = True,
        categories: tuple[str, ...] | None = None,
    ) -> None:
        check_choice("preset", preset, PIX2VOX_PRESETS)
        spec = PIX2VOX_PRESETS[preset]
        super().__init__(
            image_size=spec.image_size,
            num_views=num_views,
            voxel_resolution=_RESOLUTION,
            iou_thresholds=iou_thresholds,
            fscore_threshold=fscore_threshold,
            fscore_points=fscore_points,
            validation_fscore=validation_fscore,
            categories=categories,
        )
        self.save_hyperparameters()
        self.preset = preset
        self.spec = spec
        self.encoder = _Encoder(spec)
        seed_channels = spec.encoder_channels[-1] * spec.feature_size**2
        if seed_channels % 8:
            raise ValueError(
                f"preset {preset!r}: encoder output {seed_channels} values cannot be reshaped to (C, 2, 2, 2)"
            )
        self.decoder = _Decoder(seed_channels // 8, spec.decoder_channels)
        self.merger = _ContextAwareMerger(spec.decoder_channels[-1] + 1, spec.merger_stride)
        self.refiner = _Refiner(spec.refiner_channels, spec.refiner_hidden)
        if backbone_weights is not None:
            if spec.backbone != "resnet50":
                raise ValueError(
                    f"`backbone_weights` must be None for preset {preset!r}, which has no ResNet-50 backbone "
                    f"(preset 'paper' has one), got {backbone_weights!r}"
                )
            load_torchvision_resnet50(self.encoder.backbone, backbone_weights)
        freeze = backbone_weights is not None if freeze_backbone is None else freeze_backbone
        self.encoder.backbone.requires_grad_(not freeze)

    def reconstruct(self, images: Tensor) -> dict[str, Tensor]:
        """``images (B, V, 3, H, W)`` -> ``{"voxels", "coarse_voxels": (B, R, R, R), "view_voxels": (B, V, R, R, R)}``."""
        b, v = images.shape[:2]
        features = self.encoder(images.flatten(0, 1))  # (B V, C, h, w)
        raw = self.decoder(features.reshape(b * v, -1, 2, 2, 2))  # (B V, c + 1, R, R, R)
        raw = raw.view(b, v, *raw.shape[1:])
        coarse = self.merger(raw)
        return {"voxels": self.refiner(coarse), "coarse_voxels": coarse, "view_voxels": raw[:, :, -1]}

    def loss(self, outputs: dict[str, Tensor], target: Tensor) -> Tensor:
        """BCE of the refined volume, or the published ``10 * (BCE(coarse) + BCE(refined))``."""
        target = target.to(outputs["voxels"].dtype)
        refined = F.binary_cross_entropy(outputs["voxels"], target)
        if not self.hparams.two_stage_loss:
            return refined
        return 10 * (F.binary_cross_entropy(outputs["coarse_voxels"], target) + refined)

    def configure_optimizers(self) -> dict[str, Any]:
        hp = self.hparams
        groups = [
            {"params": [p for p in module.parameters() if p.requires_grad], "lr": lr}
            for module, lr in (
                (self.encoder, hp.lr),
                (self.decoder, hp.lr),
                (self.merger, hp.merger_lr),
                (self.refiner, hp.lr),
            )
        ]
        optimizer = torch.optim.Adam([g for g in groups if g["params"]], betas=tuple(hp.betas))
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=list(hp.milestones), gamma=hp.gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # Stored outside "hyper_parameters", which load_from_checkpoint(..., preset=...) overwrites.
        checkpoint["pix2vox_preset"] = self.preset

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        found = checkpoint.get("pix2vox_preset", checkpoint.get("hyper_parameters", {}).get("preset"))
        if found is not None and found != self.preset:
            raise ValueError(
                f"checkpoint was saved from a Pix2VoxPlusPlus with preset {found!r}; this model has preset "
                f"{self.preset!r} (expected {self.preset!r}). Build the model with preset={found!r} or use "
                "Pix2VoxPlusPlus.load_from_checkpoint(path) without overriding `preset`."
            )

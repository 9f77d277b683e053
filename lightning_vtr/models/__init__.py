"""Reconstruction models: the shared LightningModule base, Pix2Vox++ and LRGT with their specs, and backbones.

Every model satisfies :class:`~lightning_vtr.protocol.ReconstructionModel`. ``Pix2VoxSpec`` and ``LRGTSpec``
are the frozen architecture descriptions the presets hold (``PIX2VOX_PRESETS``, ``LRGT_PRESETS``) and each
model's ``spec`` attribute. :func:`load_weights` reads pretrained weights from a path, a URL or ``"imagenet"``.
:data:`MODELS` names the model classes and :func:`load_model` loads a trained model from a Lightning checkpoint
(:mod:`lightning_vtr.models.registry`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.models.base import VoxelReconstructionModule
    from lightning_vtr.models.lrgt import LRGT, LRGT_PRESETS, LRGTSpec
    from lightning_vtr.models.pix2vox import PIX2VOX_PRESETS, Pix2VoxPlusPlus, Pix2VoxSpec
    from lightning_vtr.models.registry import MODELS, check_checkpoint, load_model
    from lightning_vtr.models.resnet import ResNet50Stem, load_torchvision_resnet50
    from lightning_vtr.models.vit import DistilledVisionTransformer, load_timm_deit
    from lightning_vtr.models.weights import IMAGENET_WEIGHTS, WeightsDownloadError, load_weights
    from lightning_vtr.protocol import VIEW_SETS
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.models.base": ["VoxelReconstructionModule"],
            "lightning_vtr.models.lrgt": ["LRGT", "LRGT_PRESETS", "LRGTSpec"],
            "lightning_vtr.models.pix2vox": ["PIX2VOX_PRESETS", "Pix2VoxPlusPlus", "Pix2VoxSpec"],
            "lightning_vtr.models.registry": ["MODELS", "check_checkpoint", "load_model"],
            "lightning_vtr.models.resnet": ["ResNet50Stem", "load_torchvision_resnet50"],
            "lightning_vtr.models.vit": ["DistilledVisionTransformer", "load_timm_deit"],
            "lightning_vtr.models.weights": ["IMAGENET_WEIGHTS", "WeightsDownloadError", "load_weights"],
            "lightning_vtr.protocol": ["VIEW_SETS"],
        },
    )

__all__ = [
    "IMAGENET_WEIGHTS",
    "LRGT",
    "LRGT_PRESETS",
    "MODELS",
    "PIX2VOX_PRESETS",
    "VIEW_SETS",
    "DistilledVisionTransformer",
    "LRGTSpec",
    "Pix2VoxPlusPlus",
    "Pix2VoxSpec",
    "ResNet50Stem",
    "VoxelReconstructionModule",
    "WeightsDownloadError",
    "check_checkpoint",
    "load_model",
    "load_timm_deit",
    "load_torchvision_resnet50",
    "load_weights",
]

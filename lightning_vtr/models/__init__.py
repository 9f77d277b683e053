"""Reconstruction models: the shared LightningModule base, Pix2Vox++, and backbones."""

from lightning_vtr.models.base import VIEW_SETS, VoxelReconstructionModule
from lightning_vtr.models.pix2vox import PIX2VOX_PRESETS, Pix2VoxPlusPlus
from lightning_vtr.models.resnet import ResNet50Stem, load_torchvision_resnet50

__all__ = [
    "PIX2VOX_PRESETS",
    "Pix2VoxPlusPlus",
    "ResNet50Stem",
    "VIEW_SETS",
    "VoxelReconstructionModule",
    "load_torchvision_resnet50",
]

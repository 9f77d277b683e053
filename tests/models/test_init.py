"""``lightning_vtr.models``: both models, their spec classes and presets, the base class and the backbones."""

from __future__ import annotations

import lightning_vtr.models
from lightning_vtr.models import lrgt, pix2vox, resnet, vit
from lightning_vtr.protocol import VIEW_SETS


def test_exports_both_models_and_their_specs():
    m = lightning_vtr.models
    assert m.LRGT is lrgt.LRGT and m.LRGTSpec is lrgt.LRGTSpec and m.LRGT_PRESETS is lrgt.LRGT_PRESETS
    assert m.Pix2VoxPlusPlus is pix2vox.Pix2VoxPlusPlus and m.Pix2VoxSpec is pix2vox.Pix2VoxSpec
    assert m.PIX2VOX_PRESETS is pix2vox.PIX2VOX_PRESETS
    assert m.ResNet50Stem is resnet.ResNet50Stem and m.DistilledVisionTransformer is vit.DistilledVisionTransformer
    assert issubclass(m.LRGT, m.VoxelReconstructionModule) and issubclass(
        m.Pix2VoxPlusPlus, m.VoxelReconstructionModule
    )
    assert m.VIEW_SETS is VIEW_SETS


def test_all_lists_exactly_the_public_names():
    m = lightning_vtr.models
    assert set(m.__all__) == {
        "LRGT",
        "LRGTSpec",
        "LRGT_PRESETS",
        "PIX2VOX_PRESETS",
        "Pix2VoxPlusPlus",
        "Pix2VoxSpec",
        "VIEW_SETS",
        "VoxelReconstructionModule",
        "ResNet50Stem",
        "DistilledVisionTransformer",
        "load_timm_deit",
        "load_torchvision_resnet50",
        "IMAGENET_WEIGHTS",
        "WeightsDownloadError",
        "load_weights",
        "MODELS",
        "check_checkpoint",
        "load_model",
    }
    assert set(m.__all__) <= set(dir(m))

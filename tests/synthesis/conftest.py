"""Fixtures for the Zero-1-to-3 tests: a tiny random model saved in both checkpoint layouts found in the wild."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

# no test may touch the network; must be set before huggingface_hub is imported
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import pytest  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402

#: sizes from DESIGN section 4: a 64x64 model (UNet sample size 8, VAE factor 8)
TINY_CLIP_DIM = 32
TINY_CROSS_DIM = 32


def build_tiny_components(seed: int = 0) -> dict:
    """A randomly initialised UNet / VAE / CLIP vision encoder / 36->32 projection / DDIM scheduler."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        sample_size=8,
        in_channels=8,
        out_channels=4,
        block_out_channels=(32, 64),
        layers_per_block=1,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=TINY_CROSS_DIM,
        attention_head_dim=8,
        norm_num_groups=8,
    )
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(8, 8, 16, 16),
        latent_channels=4,
        norm_num_groups=8,
        layers_per_block=1,
        sample_size=64,
    )
    image_encoder = CLIPVisionModelWithProjection(
        CLIPVisionConfig(
            hidden_size=32,
            intermediate_size=37,
            num_hidden_layers=2,
            num_attention_heads=4,
            image_size=224,
            patch_size=32,
            projection_dim=TINY_CLIP_DIM,
        )
    )
    projection = nn.Linear(TINY_CLIP_DIM + 4, TINY_CROSS_DIM)
    scheduler = DDIMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
    )
    return dict(unet=unet, vae=vae, image_encoder=image_encoder, projection=projection, scheduler=scheduler)


def save_layout(components: dict, root: Path, layout: str) -> Path:
    """Write ``components`` as a diffusers-format checkpoint: ``layout`` is ``"cc_projection"`` or ``"clip_camera_projection"``."""
    from safetensors.torch import save_file

    root.mkdir(parents=True, exist_ok=True)
    components["unet"].save_pretrained(root / "unet")
    components["vae"].save_pretrained(root / "vae")
    components["image_encoder"].save_pretrained(root / "image_encoder")
    components["scheduler"].save_pretrained(root / "scheduler")
    proj: nn.Linear = components["projection"]
    folder = root / layout
    folder.mkdir()
    if layout == "cc_projection":
        # layout (a): a config without sizes, linear "projection", a .bin state dict
        (folder / "config.json").write_text(
            json.dumps({"_class_name": "CCProjection", "_diffusers_version": "0.15.0.dev0"})
        )
        torch.save(
            {"projection.weight": proj.weight.detach().clone(), "projection.bias": proj.bias.detach().clone()},
            folder / "diffusion_pytorch_model.bin",
        )
        # a feature extractor with CLIP's normalisation and crop size
        fe = root / "feature_extractor"
        fe.mkdir()
        (fe / "preprocessor_config.json").write_text(
            json.dumps(
                {
                    "crop_size": {"height": 224, "width": 224},
                    "do_center_crop": True,
                    "do_normalize": True,
                    "do_resize": True,
                    "image_mean": [0.48145466, 0.4578275, 0.40821073],
                    "image_processor_type": "CLIPImageProcessor",
                    "image_std": [0.26862954, 0.26130258, 0.27577711],
                    "resample": 3,
                    "size": {"shortest_edge": 224},
                }
            )
        )
        index_name = "cc_projection"
    else:
        # layout (b): sizes in the config, linear "proj", safetensors
        (folder / "config.json").write_text(
            json.dumps(
                {
                    "_class_name": "CLIPCameraProjection",
                    "embedding_dim": proj.out_features,
                    "additional_embeddings": proj.in_features - proj.out_features,
                }
            )
        )
        save_file(
            {"proj.weight": proj.weight.detach().clone().contiguous(), "proj.bias": proj.bias.detach().clone()},
            str(folder / "diffusion_pytorch_model.safetensors"),
        )
        index_name = "clip_camera_projection"
    (root / "model_index.json").write_text(
        json.dumps(
            {
                "_class_name": "Zero1to3StableDiffusionPipeline",
                "unet": ["diffusers", "UNet2DConditionModel"],
                "vae": ["diffusers", "AutoencoderKL"],
                "image_encoder": ["transformers", "CLIPVisionModelWithProjection"],
                "scheduler": ["diffusers", "DDIMScheduler"],
                index_name: [None, None],
            }
        )
    )
    return root


@dataclass
class TinyZero123:
    components: dict
    layout_a: Path
    layout_b: Path


@pytest.fixture(scope="session")
def tiny_zero123(tmp_path_factory) -> TinyZero123:
    """One tiny random model, saved once per session in layout (a) and layout (b)."""
    components = build_tiny_components()
    root = tmp_path_factory.mktemp("zero123")
    return TinyZero123(
        components=components,
        layout_a=save_layout(components, root / "layout_a", "cc_projection"),
        layout_b=save_layout(components, root / "layout_b", "clip_camera_projection"),
    )

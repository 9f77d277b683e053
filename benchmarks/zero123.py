"""Seconds per generated image of :class:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer`.

Random weights only (nothing is downloaded): timings depend on the architecture, not on the weights.

* CPU, the tiny test model (64x64) at 2 and 50 DDIM steps, guidance 3.0.
* GPU (if ``torch.cuda.is_available()``), a full-size model: SD 1.x UNet (block_out_channels
  (320, 640, 1280, 1280), cross_attention_dim 768, 8 input channels, 256x256), the SD VAE and a CLIP
  ViT-L/14 vision encoder (projection 768), 50 steps in fp16 with guidance 3.0.

Run: ``python benchmarks/zero123.py [--images 4] [--batch-size 4] [--threads 1] [--skip-gpu]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "synthesis"))

from lightning_vtr.synthesis.zero123 import Zero123Synthesizer


def _inputs(n: int, size: int = 128) -> tuple[list[np.ndarray], torch.Tensor, torch.Tensor]:
    img = np.zeros((size, size, 4), dtype=np.uint8)
    img[size // 4 : 3 * size // 4, size // 3 : 2 * size // 3] = (180, 90, 40, 255)
    source = torch.tensor([[0.0, 30.0]]).repeat(n, 1)
    target = torch.stack([torch.linspace(-150.0, 150.0, n), torch.full((n,), 10.0)], dim=1)
    return [img] * n, source, target


def _time(synth: Zero123Synthesizer, n: int, steps: int, sync: bool) -> float:
    images, source, target = _inputs(n)
    synth(images[:1], source[:1], target[:1], num_inference_steps=1)  # warm-up (allocations, kernels)
    if sync:
        torch.cuda.synchronize()
    start = time.perf_counter()
    synth(images, source, target, num_inference_steps=steps)
    if sync:
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / n


def full_size_components() -> dict:
    """A randomly initialised model with Zero-1-to-3's real architecture (~860M UNet, SD VAE, CLIP ViT-L/14)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    unet = UNet2DConditionModel(
        sample_size=32,
        in_channels=8,
        out_channels=4,
        block_out_channels=(320, 640, 1280, 1280),
        layers_per_block=2,
        down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=768,
        attention_head_dim=8,
    )
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(128, 256, 512, 512),
        latent_channels=4,
        layers_per_block=2,
        sample_size=256,
    )
    image_encoder = CLIPVisionModelWithProjection(
        CLIPVisionConfig(
            hidden_size=1024,
            intermediate_size=4096,
            num_hidden_layers=24,
            num_attention_heads=16,
            image_size=224,
            patch_size=14,
            projection_dim=768,
            hidden_act="quick_gelu",
        )
    )
    # no scheduler: the synthesizer's default is the SD 1.x schedule Zero-1-to-3 was trained with
    return dict(unet=unet, vae=vae, image_encoder=image_encoder, projection=nn.Linear(772, 768))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=4, help="images per timed call")
    parser.add_argument("--batch-size", type=int, default=4, help="pairs per UNet call")
    parser.add_argument(
        "--threads", type=int, default=1, help="CPU threads (the tiny model's ops are too small to split)"
    )
    parser.add_argument("--skip-gpu", action="store_true")
    args = parser.parse_args()

    from conftest import build_tiny_components  # the tests' tiny-model builder

    torch.set_num_threads(args.threads)
    tiny = Zero123Synthesizer(**build_tiny_components(), device="cpu", batch_size=args.batch_size, weights_id="tiny")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, {args.images} images per call")
    for steps in (2, 50):
        s = _time(tiny, args.images, steps, sync=False)
        print(f"tiny model, CPU fp32, 64x64, {steps:>2} steps, guidance 3.0: {s:.3f} s/image")

    if args.skip_gpu or not torch.cuda.is_available():
        print("full-size model on GPU: skipped (no CUDA device)" if not args.skip_gpu else "full-size model: skipped")
        return
    torch.manual_seed(0)
    full = Zero123Synthesizer(
        **full_size_components(), device="cuda", dtype=torch.float16, batch_size=args.batch_size, weights_id="random"
    )
    n_params = sum(p.numel() for p in full.unet.parameters()) / 1e6
    s = _time(full, args.images, 50, sync=True)
    name = torch.cuda.get_device_name()
    print(
        f"full-size model ({n_params:.0f}M-parameter UNet), {name} fp16, 256x256, 50 steps, guidance 3.0: {s:.3f} s/image"
    )
    print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**30:.1f} GiB")


if __name__ == "__main__":
    main()

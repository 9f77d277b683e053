"""Training throughput (samples/s) of a tiny reconstruction preset on CPU.

Runs full optimisation steps (forward, loss, backward, Adam) on random images and voxels, after
warm-up steps, with a fixed number of torch threads. Add a model by adding a factory to ``MODELS``.

    python benchmarks/train_throughput.py --model pix2vox-tiny --batch-size 16 --views 3 --threads 2
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch

from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

#: name -> factory of a model to benchmark (a VoxelReconstructionModule with ``configure_optimizers``).
MODELS: dict[str, Callable[[], VoxelReconstructionModule]] = {
    "pix2vox-tiny": lambda: Pix2VoxPlusPlus(preset="tiny"),
    "lrgt-tiny": lambda: LRGT(preset="tiny"),
}


def measure(model: VoxelReconstructionModule, batch_size: int, views: int, steps: int, warmup: int) -> float:
    """Training samples per second over ``steps`` timed optimisation steps."""
    generator = torch.Generator().manual_seed(0)
    s, r = model.image_size, model.voxel_resolution
    images = torch.randn(batch_size, views, 3, s, s, generator=generator)
    voxels = (torch.rand(batch_size, r, r, r, generator=generator) > 0.7).float()
    optimizers = model.configure_optimizers()
    optimizer = optimizers["optimizer"] if isinstance(optimizers, dict) else optimizers
    model.train()
    start = 0.0
    for step in range(warmup + steps):
        if step == warmup:
            start = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        loss = model.loss(model(images), voxels)
        loss.backward()
        optimizer.step()
    return batch_size * steps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=sorted(MODELS), default="pix2vox-tiny")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = MODELS[args.model]()
    rate = measure(model, args.batch_size, args.views, args.steps, args.warmup)
    n_params = sum(p.numel() for p in model.parameters())
    print(
        f"{args.model}: {rate:.1f} training samples/s "
        f"(batch {args.batch_size}, {args.views} views, {model.image_size} px, {n_params / 1e6:.2f} M params, "
        f"{args.threads} threads, {args.steps} timed steps)"
    )


if __name__ == "__main__":
    main()

"""Training throughput (samples/s) of a tiny reconstruction preset on CPU.

Runs full optimisation steps (forward, loss, backward, Adam) on random images and voxels, after
warm-up steps, with a fixed number of torch threads. Add a model by adding a factory to ``MODELS``.

    python benchmarks/train_throughput.py --model pix2vox-tiny --batch-size 16 --views 3 --threads 2

``--jobs J`` also runs J processes at once, each with ``threads // J`` threads (what ``lightning-vtr report
--jobs J`` does with its fits), and prints their summed rate against the one-process rate of the same run:

    python benchmarks/train_throughput.py --batch-size 8 --threads 2 --jobs 2 --steps 20
"""

from __future__ import annotations

import argparse
import multiprocessing
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


def _rate_in_child(name: str, threads: int, batch_size: int, views: int, steps: int, warmup: int, start_at) -> float:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = MODELS[name]()
    start_at.wait()  # every process starts timing together, after its imports and model build
    return measure(model, batch_size, views, steps, warmup)


def _concurrent_rate(args: argparse.Namespace) -> float:
    """Summed samples/s of ``args.jobs`` processes training at once, ``threads // jobs`` threads each."""
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        start_at = manager.Barrier(args.jobs)
        threads = max(1, args.threads // args.jobs)
        work = (args.model, threads, args.batch_size, args.views, args.steps, args.warmup, start_at)
        with context.Pool(args.jobs) as pool:
            return sum(pool.starmap(_rate_in_child, [work] * args.jobs))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=sorted(MODELS), default="pix2vox-tiny")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=1, help="also measure this many processes at once")
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
    if args.jobs > 1:
        together = _concurrent_rate(args)
        print(
            f"{args.jobs} processes x {max(1, args.threads // args.jobs)} thread(s) at once: {together:.1f} training "
            f"samples/s in all, {together / rate:.2f}x one process with {args.threads} threads"
        )


if __name__ == "__main__":
    main()

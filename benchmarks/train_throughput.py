"""Training and inference throughput (samples/s) of the tiny reconstruction presets on CPU.

Times full optimisation steps (forward, loss, backward, Adam) and inference (``predict_voxels`` under
``torch.inference_mode``) on random images and voxels, after warm-up steps, with a fixed number of torch
threads. Add a model by adding a factory to ``MODELS``.

    python benchmarks/train_throughput.py --model pix2vox-tiny --batch-size 16 --views 3 --threads 2

``--baseline-rev REV`` also measures the code of git revision ``REV`` (extracted with ``git archive``) in the
same run: each repeat times the working tree and then the baseline, each in a fresh process, so both see
the same machine load; the table gives the median of the repeats and the speed-up:

    python benchmarks/train_throughput.py --model all --baseline-rev 0a4ca47 --repeats 3

``--memory`` sets how each process's allocator treats freed memory: ``default`` (glibc as it starts, the
default), ``retained`` (both processes keep freed memory for reuse, set through glibc's ``MALLOC_*`` variables:
the code alone, without page faults between steps) or ``as-package`` (each process as that version's own
training processes set themselves up: the working tree calls ``retain_freed_memory``, a version without it
does nothing; what a user of ``lightning-vtr`` or the examples sees):

    python benchmarks/train_throughput.py --model all --baseline-rev 0a4ca47 --memory as-package

``--jobs J`` also runs J processes at once, each with ``threads // J`` threads (what ``lightning-vtr report
--jobs J`` does with its fits), and prints their summed rate against the one-process rate of the same run:

    python benchmarks/train_throughput.py --batch-size 8 --threads 2 --jobs 2 --steps 20
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

#: name -> factory of a model to benchmark (a VoxelReconstructionModule with ``configure_optimizers``).
MODELS: dict[str, Callable[[], VoxelReconstructionModule]] = {
    "pix2vox-tiny": lambda: Pix2VoxPlusPlus(preset="tiny"),
    "lrgt-tiny": lambda: LRGT(preset="tiny"),
}


def _inputs(model: VoxelReconstructionModule, batch_size: int, views: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    s, r = model.image_size, model.voxel_resolution
    images = torch.randn(batch_size, views, 3, s, s, generator=generator)
    voxels = (torch.rand(batch_size, r, r, r, generator=generator) > 0.7).float()
    return images, voxels


def measure(model: VoxelReconstructionModule, batch_size: int, views: int, steps: int, warmup: int) -> float:
    """Training samples per second over ``steps`` timed optimisation steps."""
    images, voxels = _inputs(model, batch_size, views)
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


def measure_inference(model: VoxelReconstructionModule, batch_size: int, views: int, steps: int, warmup: int) -> float:
    """Inference samples per second (``predict_voxels`` in eval mode) over ``steps`` timed batches."""
    images, _ = _inputs(model, batch_size, views)
    model.eval()
    start = 0.0
    with torch.inference_mode():
        for step in range(warmup + steps):
            if step == warmup:
                start = time.perf_counter()
            model.predict_voxels(images)
    return batch_size * steps / (time.perf_counter() - start)


def _rate_in_child(
    name: str, threads: int, batch_size: int, views: int, steps: int, warmup: int, memory: str, start_at
) -> float:
    torch.set_num_threads(threads)
    if memory != "default":  # as the one-process measurement of main() does
        set_up_memory("as-package")
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
        work = (args.model, threads, args.batch_size, args.views, args.steps, args.warmup, args.memory, start_at)
        with context.Pool(args.jobs) as pool:
            return sum(pool.starmap(_rate_in_child, [work] * args.jobs))


# ------------------------------------------------------------------------------ A/B against a revision
_WORKER = """
import json, sys, torch
import lightning_vtr
from train_throughput import MODELS, measure, measure_inference, set_up_memory
name, threads, batch, views, steps, warmup = sys.argv[1], *map(int, sys.argv[2:7])
set_up_memory(sys.argv[7])
torch.set_num_threads(threads)
torch.manual_seed(0)
model = MODELS[name]()
train = measure(model, batch, views, steps, warmup)
infer = measure_inference(model, batch, views, steps, warmup)
print(json.dumps({{"train": train, "inference": infer, "package": lightning_vtr.__file__}}))
"""


#: glibc settings of ``--memory retained``: those of ``lightning_vtr.utils.memory.retain_freed_memory``.
_RETAINED_ENV = {"MALLOC_MMAP_THRESHOLD_": str(32 * 2**20), "MALLOC_TRIM_THRESHOLD_": str(256 * 2**20)}


def set_up_memory(mode: str) -> bool:
    """``--memory as-package``: call the imported version's ``retain_freed_memory`` if it has one (``True`` if it
    did). The other modes need nothing here (``retained`` is set by the environment the process starts with)."""
    if mode != "as-package":
        return False
    try:
        from lightning_vtr.utils.memory import retain_freed_memory
    except ImportError:  # a version from before the setting: its processes kept glibc's defaults
        return False
    return retain_freed_memory()


def _extract(revision: str, into: Path) -> Path:
    """The package and this benchmark at git ``revision``, extracted under ``into``."""
    root = Path(__file__).resolve().parents[1]
    archive = into / "rev.tar"
    with archive.open("wb") as out:
        subprocess.run(
            ["git", "-C", str(root), "archive", revision, "lightning_vtr", "benchmarks"], stdout=out, check=True
        )
    with tarfile.open(archive) as tar:
        tar.extractall(into / "tree", filter="data")
    return into / "tree"


def _run_worker(tree: Path, args: argparse.Namespace, name: str) -> dict[str, float]:
    code = _WORKER.format()
    # The package from ``tree``, the timing code from this file, so both sides are timed the same way.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), str(Path(__file__).resolve().parent)])}
    if args.memory == "retained":
        env.update(_RETAINED_ENV)
    argv = [name, args.threads, args.batch_size, args.views, args.steps, args.warmup, args.memory]
    done = subprocess.run(
        [sys.executable, "-c", code, *map(str, argv)], env=env, cwd=tree, capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"benchmark worker failed in {tree}:\n{done.stderr[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if not Path(result.pop("package")).is_relative_to(tree):
        raise RuntimeError(f"the worker imported lightning_vtr from outside {tree}")
    return result


def compare(args: argparse.Namespace, names: list[str]) -> None:
    """Median samples/s of the working tree and of ``args.baseline_rev``, interleaved, per model and mode."""
    here = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        baseline = _extract(args.baseline_rev, Path(tmp))
        print(
            f"| model | mode | {args.baseline_rev} (samples/s) | working tree (samples/s) | speed-up |\n"
            "|---|---|---|---|---|"
        )
        for name in names:
            runs: dict[str, list[dict[str, float]]] = {"base": [], "new": []}
            for _ in range(args.repeats):
                runs["new"].append(_run_worker(here, args, name))
                runs["base"].append(_run_worker(baseline, args, name))
            for mode in ("train", "inference"):
                old = statistics.median(r[mode] for r in runs["base"])
                new = statistics.median(r[mode] for r in runs["new"])
                print(f"| {name} | {mode} | {old:.1f} | {new:.1f} | {new / old:.2f}x |", flush=True)
    print(
        f"\nbatch {args.batch_size}, {args.views} views, {args.threads} threads, {args.steps} timed steps after "
        f"{args.warmup} warm-up, median of {args.repeats} interleaved repeats, each in a fresh process; "
        f"memory: {args.memory}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=[*sorted(MODELS), "all"], default="pix2vox-tiny")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=1, help="also measure this many processes at once")
    parser.add_argument("--baseline-rev", help="also measure this git revision, interleaved, and print speed-ups")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats of an A/B comparison")
    parser.add_argument(
        "--memory",
        choices=["default", "retained", "as-package"],
        default="default",
        help="how each process's allocator treats freed memory (see the module docstring)",
    )
    args = parser.parse_args(argv)
    names = sorted(MODELS) if args.model == "all" else [args.model]
    if args.baseline_rev:
        compare(args, names)
        return
    torch.set_num_threads(args.threads)
    if args.memory != "default":  # one version here: both modes are its own setting
        set_up_memory("as-package")
    for name in names:
        torch.manual_seed(0)
        model = MODELS[name]()
        rate = measure(model, args.batch_size, args.views, args.steps, args.warmup)
        inference = measure_inference(model, args.batch_size, args.views, args.steps, args.warmup)
        n_params = sum(p.numel() for p in model.parameters())
        print(
            f"{name}: {rate:.1f} training samples/s, {inference:.1f} inference samples/s "
            f"(batch {args.batch_size}, {args.views} views, {model.image_size} px, {n_params / 1e6:.2f} M params, "
            f"{args.threads} threads, {args.steps} timed steps)"
        )
        if args.jobs > 1:
            args.model = name
            together = _concurrent_rate(args)
            print(
                f"{args.jobs} processes x {max(1, args.threads // args.jobs)} thread(s) at once: {together:.1f} "
                f"training samples/s in all, {together / rate:.2f}x one process with {args.threads} threads"
            )


if __name__ == "__main__":
    main()

"""Builder throughput: objects/s on the procedural source at 1 and 2 workers, and the embedded build time.

Each object is 3 view sets x ``views_per_set`` renders, a voxelization, a binvox, a PLY and the PNGs.
The 1-worker run is the reference; the 2-worker run includes the worker start-up (spawned processes
import torch and open their own GL context), which is why it is reported separately. The embedded
dataset's build time is extrapolated from the measured per-object cost plus that start-up.

    python benchmarks/build_speed.py                     # defaults: 3 categories x 8 objects, 128 px
    python benchmarks/build_speed.py --objects 4 --image-size 64
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _run(workers: int, args: argparse.Namespace, tmp: str) -> tuple[float, int]:
    from lightning_vtr.data.builder import build_dataset

    root = os.path.join(tmp, f"w{workers}")
    start = time.perf_counter()
    report = build_dataset(
        root,
        categories=args.categories.split(","),
        objects_per_category=args.objects,
        image_size=args.image_size,
        views_per_set=args.views_per_set,
        workers=workers,
        progress=False,
    )
    seconds = time.perf_counter() - start
    if report.failed:
        raise RuntimeError(f"benchmark build failed: {report.failed}")
    return seconds, len(report.built)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--categories", default="chair,airplane,sofa")
    parser.add_argument("--objects", type=int, default=8, help="objects per category")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--views-per-set", type=int, default=24)
    args = parser.parse_args()

    import torch

    from lightning_vtr.data.builder import EMBEDDED_DEFAULTS
    from lightning_vtr.renderer import get_renderer

    torch.set_num_threads(1)  # as in a build worker; the comparison is then workers, not threads
    # Open the GL context before timing, so the 1-worker figure is the steady per-object cost.
    get_renderer(args.image_size).render(__import__("trimesh").creation.box(), [[0.0, 0.0]])
    with tempfile.TemporaryDirectory() as tmp:
        t1, n = _run(1, args, tmp)
        t2, _ = _run(2, args, tmp)
    per_object = t1 / n
    # The 2-worker run = start-up + n objects at twice the rate (if it scales); solve for the start-up.
    startup = max(0.0, t2 - n * per_object / 2)
    embedded = EMBEDDED_DEFAULTS["objects_per_category"] * len(EMBEDDED_DEFAULTS["categories"])
    size, views = EMBEDDED_DEFAULTS["image_size"], EMBEDDED_DEFAULTS["views_per_set"]
    print(
        f"procedural source, {n} objects, {args.image_size} px, 3 x {args.views_per_set} views, {os.cpu_count()} CPUs"
    )
    print(f"  1 worker : {n / t1:6.2f} objects/s  ({t1:6.1f} s, {1000 * per_object:.0f} ms per object)  [reference]")
    print(f"  2 workers: {n / t2:6.2f} objects/s  ({t2:6.1f} s incl. worker start-up; x{t1 / t2:.2f} vs 1 worker)")
    if (args.image_size, args.views_per_set) == (size, views):
        est1 = embedded * per_object
        est2 = startup + embedded * per_object / 2
        print(
            f"embedded default ({embedded} objects, {size} px): ~{est1 / 60:.1f} min at 1 worker, ~{est2 / 60:.1f} min at 2 workers (extrapolated)"
        )


if __name__ == "__main__":
    main()

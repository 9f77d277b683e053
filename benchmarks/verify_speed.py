"""``verify_dataset`` throughput: objects/s, and the projected time to verify ShapeNet-VTR's 39,000 objects.

A few procedural objects are built with the embedded builder into a temporary directory (3 view sets x
``--views-per-set`` PNGs and a binvox each, as ``lightning-vtr build-dataset`` writes them) and cloned up to
``--objects`` objects, since verifying reads every file of every object the same way whatever its shape and
rendering them all would take far longer than the check. The files were just written, so they are read from
the page cache: the figure is the decoding cost, the floor of a first read from disk or a network filesystem.

Besides wall-clock objects/s it prints the CPU time per object (this process and its workers), which does not
depend on what else the machine runs: ``39,000 x CPU per object / free cores`` projects a verify elsewhere.

    python benchmarks/verify_speed.py                      # 240 objects of 3 x 24 views at 128 px
    python benchmarks/verify_speed.py --image-size 224 --workers 1 2 default
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

#: Objects of ShapeNet-VTR (the 13 ShapeNetCore categories of 3D-R2N2), the scale the projection is for.
SHAPENET_VTR_OBJECTS = 39_000


def _build(root: Path, args: argparse.Namespace) -> None:
    """Build ``--build-objects`` procedural objects, then clone them until the dataset has ``--objects``."""
    from lightning_vtr.data.builder import build_dataset
    from lightning_vtr.data.format import object_dir

    report = build_dataset(
        root,
        categories=["chair", "table"],
        objects_per_category=max(1, args.build_objects // 2),
        image_size=args.image_size,
        views_per_set=args.views_per_set,
        workers=1,
        progress=False,
    )
    if report.failed:
        raise RuntimeError(f"benchmark build failed: {report.failed}")
    meta = json.loads((root / "metadata.json").read_text())
    built = list(meta["objects"].items())
    for index in range(args.objects - len(built)):
        key, info = built[index % len(built)]
        category, object_id = key.split("/")
        clone = f"{object_id}_clone{index:05d}"
        shutil.copytree(object_dir(root, category, object_id), object_dir(root, category, clone))
        meta["objects"][f"{category}/{clone}"] = info
    (root / "metadata.json").write_text(json.dumps(meta))


def _cpu_seconds() -> float:
    """User + system CPU time of this process and of its finished workers."""
    own, workers = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + workers.ru_utime + workers.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, default=240, help="objects verified (clones of the built ones)")
    parser.add_argument("--build-objects", type=int, default=6, help="objects actually rendered")
    parser.add_argument("--image-size", type=int, default=128, help="image side (the builder's default: 128)")
    parser.add_argument("--views-per-set", type=int, default=24)
    parser.add_argument(
        "--workers",
        type=lambda word: None if word == "default" else int(word),
        nargs="+",
        default=[1, None],
        help="worker processes to time; 'default' is verify_dataset's (one per usable CPU)",
    )
    args = parser.parse_args()

    from lightning_vtr.data.verify import verify_dataset

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "vtr"
        start = time.perf_counter()
        _build(root, args)
        print(
            f"dataset: {args.objects} objects x (1 binvox + 3 x {args.views_per_set} PNGs of {args.image_size} px), "
            f"built and cloned in {time.perf_counter() - start:.1f} s; {os.cpu_count()} CPUs"
        )
        verify_dataset(root, progress=False)  # warm-up: imports, and every file in the page cache
        for workers in args.workers:
            before = _cpu_seconds()
            report = verify_dataset(root, workers=workers, progress=False)
            cpu_per_object = (_cpu_seconds() - before) / report.objects
            if not report.ok:
                raise RuntimeError(report.error_message())
            rate = report.objects_per_second
            projected = SHAPENET_VTR_OBJECTS / rate
            label = workers if workers is not None else f"default ({len(os.sched_getaffinity(0))})"
            print(
                f"workers {label}: {report.objects} objects ({report.files} files) in {report.seconds:.2f} s = "
                f"{rate:.1f} objects/s, {report.files / report.seconds:.0f} files/s, "
                f"{cpu_per_object * 1000:.1f} ms CPU per object; {SHAPENET_VTR_OBJECTS:,} objects: "
                f"{projected / 60:.1f} min here, {SHAPENET_VTR_OBJECTS * cpu_per_object / 60:.1f} CPU-min"
            )


if __name__ == "__main__":
    main()

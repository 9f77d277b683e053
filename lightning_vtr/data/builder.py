"""The ShapeNet-VTR builder: render the Aligned / Hemispherical / Spherical view sets and voxelize each object.

Sources: the embedded procedural generator, a ShapeNetCore v1 (``<synset>/<model>/model.obj``) or v2
(``<synset>/<model>/models/model_normalized.obj``) folder (+Y up, converted), or a generic
``<category>/<object>.<ext>`` folder (+Z up unless told). Output: ``docs/dataset_format.md``.

View sets (``views_per_set`` each, default 24, seeded per object so a build is deterministic whatever the
worker count or sharding):

* Aligned: pitch = ``aligned_pitch`` (default 30 degrees), yaw every ``360 / views_per_set`` degrees. The
  paper's "phi of 60 degrees" is Zero-1-to-3's polar angle (measured from +Z), i.e. an elevation of 30,
  which is also the classic ShapeNetRendering's typical elevation.
* Hemispherical: uniform over the upper hemisphere's *area* (yaw uniform, sin(pitch) uniform in [0, 1]):
  "randomly rendered in the upper hemisphere" without crowding views at the pole.
* Spherical: uniform over the whole sphere's area.

Robustness: every file is written atomically and ``object.json`` last, so a killed build re-run redoes only
unfinished objects; a mesh that fails is recorded in ``errors.json`` (message naming the file) instead of
stopping the build; ``shard=(i, n)`` builds every n-th object for cluster array jobs, and the metadata is
written once every object is present (a plain re-run, or ``finalize=True``).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from lightning_vtr.data.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    VIEW_SETS,
    atomic_write_json,
    object_dir,
    read_object_json,
)
from lightning_vtr.geometry import sample_uniform_viewpoints, wrap_yaw

__all__ = ["BuildReport", "EMBEDDED_DEFAULTS", "build_dataset", "ensure_embedded_dataset", "view_set_viewpoints"]

MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")

#: The embedded dataset's build options: 8 categories x 24 objects at 96 px builds in a few minutes on 2 cores.
EMBEDDED_DEFAULTS: dict[str, Any] = dict(
    categories=["airplane", "bench", "car", "chair", "lamp", "sofa", "table", "vessel"],
    objects_per_category=24,
    image_size=96,
    resolution=32,
    views_per_set=24,
    aligned_pitch=30.0,
    seed=0,
)


@dataclass
class BuildReport:
    """What a build did: objects built now, skipped (already complete), failed (with messages), seconds."""

    built: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    finalized: bool = False

    def summary(self) -> str:
        return (
            f"built {len(self.built)}, skipped {len(self.skipped)} (already complete), failed {len(self.failed)} "
            f"in {self.seconds:.1f} s; metadata {'written' if self.finalized else 'not written (incomplete)'}"
        )


def _stable_int(*parts: Any) -> int:
    return zlib.crc32("/".join(str(p) for p in parts).encode())


def view_set_viewpoints(category: str, object_id: str, *, views_per_set: int = 24, aligned_pitch: float = 30.0, seed: int = 0) -> dict[str, np.ndarray]:
    """The three view sets of one object, ``{name: (views_per_set, 2)}`` degrees, a pure function of its arguments."""
    g = torch.Generator().manual_seed(_stable_int(seed, category, object_id))
    yaw = wrap_yaw(torch.arange(views_per_set, dtype=torch.float64) * (360.0 / views_per_set))
    aligned = torch.stack([yaw, torch.full_like(yaw, float(aligned_pitch))], dim=-1)
    hemi = sample_uniform_viewpoints(views_per_set, mode="area", pitch_range=(0.0, 90.0), generator=g)
    sphere = sample_uniform_viewpoints(views_per_set, mode="area", generator=g)
    return {
        "aligned": aligned.numpy().astype(np.float64),
        "hemispherical": hemi.double().numpy(),
        "spherical": sphere.double().numpy(),
    }


@dataclass
class _Task:
    category: str
    object_id: str
    kind: str  # "procedural" or "mesh"
    index: int = 0
    path: str | None = None
    up_axis: str = "z"


def _discover(source: str | Path, layout: str, objects_per_category: int | None, categories: Sequence[str] | None, seed: int) -> list[_Task]:
    if str(source) == "procedural":
        from lightning_vtr.data.procedural import CATEGORIES, object_id

        cats = list(categories) if categories else list(CATEGORIES)
        unknown = sorted(set(cats) - set(CATEGORIES))
        if unknown:
            raise ValueError(f"`categories` {unknown} are not procedural categories; choose from {list(CATEGORIES)}")
        n = objects_per_category or 30
        return [_Task(c, object_id(c, i), "procedural", index=i) for c in cats for i in range(n)]
    root = Path(source)
    if not root.is_dir():
        raise ValueError(f"`source` must be 'procedural' or an existing directory, got {source!r}")
    if layout == "auto":
        sample = next((p for p in root.glob("*/*") if p.is_dir()), None)
        if sample is not None and (sample / "models" / "model_normalized.obj").is_file():
            layout = "shapenet_v2"
        elif sample is not None and (sample / "model.obj").is_file():
            layout = "shapenet_v1"
        else:
            layout = "generic"
    tasks = []
    for cat_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        if categories and cat_dir.name not in categories:
            continue
        if layout == "generic":
            found = [(p.stem, p) for p in sorted(cat_dir.iterdir()) if p.suffix.lower() in MESH_SUFFIXES]
            up = "z"
        else:
            rel = Path("models/model_normalized.obj") if layout == "shapenet_v2" else Path("model.obj")
            found = [(p.name, p / rel) for p in sorted(cat_dir.iterdir()) if p.is_dir()]
            up = "y"
        if objects_per_category:
            found = found[:objects_per_category]
        tasks += [_Task(cat_dir.name, oid, "mesh", path=str(path), up_axis=up) for oid, path in found]
    if not tasks:
        raise ValueError(f"No meshes found under {root} (layout {layout!r})")
    return tasks


def _save_png(image: np.ndarray, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    Image.fromarray(image).save(tmp, format="PNG")
    os.replace(tmp, path)


def _build_object(args: tuple[_Task, dict[str, Any], str]) -> tuple[str, str | None]:
    task, opts, out = args
    key = f"{task.category}/{task.object_id}"
    try:
        from lightning_vtr.data.binvox import write_binvox
        from lightning_vtr.data.mesh import load_mesh, save_mesh
        from lightning_vtr.data.voxelize import voxelize
        from lightning_vtr.render import get_renderer

        if task.kind == "procedural":
            from lightning_vtr.data.procedural import make_object

            mesh = make_object(task.category, task.index, seed=opts["seed"])
        else:
            mesh = load_mesh(task.path, up_axis=task.up_axis)
        directory = object_dir(out, task.category, task.object_id)
        directory.mkdir(parents=True, exist_ok=True)
        voxels = voxelize(mesh, opts["resolution"])
        if not voxels.any():
            raise ValueError(f"voxelization of {task.path or key} at R={opts['resolution']} is empty")
        write_binvox(directory / "model.binvox", voxels)
        save_mesh(mesh, directory / "mesh.ply")
        views = view_set_viewpoints(
            task.category, task.object_id, views_per_set=opts["views_per_set"], aligned_pitch=opts["aligned_pitch"], seed=opts["seed"]
        )
        renderer = get_renderer(opts["image_size"])
        for name, viewpoints in views.items():
            (directory / name).mkdir(exist_ok=True)
            for i, image in enumerate(renderer.render(mesh, viewpoints)):
                _save_png(image, directory / name / f"{i:02d}.png")
        atomic_write_json(
            directory / "object.json",
            {
                "category": task.category,
                "object_id": task.object_id,
                "source": task.path or f"procedural:seed={opts['seed']}",
                "views": {k: v.round(6).tolist() for k, v in views.items()},
            },
        )
        return key, None
    except Exception as err:  # noqa: BLE001 - one bad mesh must not stop a 40k-object build
        return key, f"{type(err).__name__}: {err}"


def _record(report: BuildReport, key: str, error: str | None) -> None:
    if error:
        report.failed[key] = error
    else:
        report.built.append(key)


def _splits(keys: list[tuple[str, str]], ratios: Sequence[float], seed: int) -> dict[str, dict[str, list[str]]]:
    out: dict[str, dict[str, list[str]]] = {}
    for category in sorted({c for c, _ in keys}):
        ids = sorted(o for c, o in keys if c == category)
        order = np.random.default_rng([seed, _stable_int(category)]).permutation(len(ids))
        n_train = int(round(ratios[0] * len(ids)))
        n_val = int(round(ratios[1] * len(ids)))
        shuffled = [ids[i] for i in order]
        out[category] = {
            "train": sorted(shuffled[:n_train]),
            "val": sorted(shuffled[n_train : n_train + n_val]),
            "test": sorted(shuffled[n_train + n_val :]),
        }
    return out


def build_dataset(
    output_dir: str | Path,
    *,
    source: str | Path = "procedural",
    objects_per_category: int | None = 30,
    categories: Sequence[str] | None = None,
    image_size: int = 128,
    resolution: int = 32,
    views_per_set: int = 24,
    aligned_pitch: float = 30.0,
    split: Sequence[float] = (0.7, 0.1, 0.2),
    seed: int = 0,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
    finalize: bool = True,
    progress: bool = True,
    source_layout: str = "auto",
) -> BuildReport:
    """Build (or finish building) a ShapeNet-VTR dataset in ``output_dir``; see the module docstring.

    Raises:
        ValueError: for invalid arguments (names the argument and the value).
    """
    if image_size <= 0 or resolution <= 0 or views_per_set <= 0:
        raise ValueError(f"`image_size`, `resolution` and `views_per_set` must be positive, got {image_size}, {resolution}, {views_per_set}")
    if not -90.0 <= aligned_pitch <= 90.0:
        raise ValueError(f"`aligned_pitch` must be in [-90, 90] degrees, got {aligned_pitch}")
    if len(split) != 3 or abs(sum(split) - 1.0) > 1e-6 or min(split) < 0:
        raise ValueError(f"`split` must be three non-negative ratios summing to 1, got {tuple(split)}")
    index, count = shard
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"`shard` must be (i, n) with 0 <= i < n, got {index}/{count}")
    if source_layout not in ("auto", "shapenet_v1", "shapenet_v2", "generic"):
        raise ValueError(f"`source_layout` must be auto, shapenet_v1, shapenet_v2 or generic, got {source_layout!r}")
    start = time.perf_counter()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    opts = dict(image_size=image_size, resolution=resolution, views_per_set=views_per_set, aligned_pitch=float(aligned_pitch), seed=seed)
    tasks = sorted(_discover(source, source_layout, objects_per_category, categories, seed), key=lambda t: (t.category, t.object_id))
    mine = tasks[index::count]
    report = BuildReport()
    todo = []
    for task in mine:
        if (object_dir(out, task.category, task.object_id) / "object.json").is_file():
            report.skipped.append(f"{task.category}/{task.object_id}")
        else:
            todo.append(task)
    jobs = [(t, opts, str(out)) for t in todo]
    bar = tqdm(total=len(jobs), desc="building ShapeNet-VTR", unit="obj", disable=not progress, dynamic_ncols=True)
    if workers > 1 and len(jobs) > 1:
        # 'spawn': every worker opens its own GL context; forking after GL initialisation is unsafe.
        with mp.get_context("spawn").Pool(workers) as pool:
            results = pool.imap_unordered(_build_object, jobs)
            for key, error in results:
                _record(report, key, error)
                bar.update()
    else:
        for job in jobs:
            _record(report, *_build_object(job))
            bar.update()
    bar.close()
    errors_path = out / "errors.json"
    errors = json.loads(errors_path.read_text()) if errors_path.is_file() else {}
    errors = {k: v for k, v in errors.items() if k not in report.built} | report.failed
    atomic_write_json(errors_path, errors)
    if finalize:
        report.finalized = _finalize(out, tasks, errors, split, seed, opts, source)
    report.seconds = time.perf_counter() - start
    return report


def _finalize(out: Path, tasks: list[_Task], errors: dict[str, str], split: Sequence[float], seed: int, opts: dict, source: Any) -> bool:
    complete = []
    for t in tasks:
        key = f"{t.category}/{t.object_id}"
        if (object_dir(out, t.category, t.object_id) / "object.json").is_file():
            complete.append((t.category, t.object_id))
        elif key not in errors:
            return False  # another shard is still working
    splits = _splits(complete, split, seed)
    atomic_write_json(out / "splits.json", splits)
    objects = {}
    for category, parts in splits.items():
        for name, ids in parts.items():
            for oid in ids:
                info = read_object_json(object_dir(out, category, oid))
                objects[f"{category}/{oid}"] = {"split": name, "views": info["views"]}
    from lightning_vtr.render import DEFAULT_DISTANCE, DEFAULT_YFOV_DEG

    atomic_write_json(
        out / "metadata.json",
        {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "resolution": opts["resolution"],
            "image_size": opts["image_size"],
            "views_per_set": opts["views_per_set"],
            "view_sets": list(VIEW_SETS),
            "aligned_pitch": opts["aligned_pitch"],
            "camera": {"type": "perspective", "yfov_deg": DEFAULT_YFOV_DEG, "distance": DEFAULT_DISTANCE},
            "split_ratios": list(split),
            "seed": seed,
            "source": str(source),
            "categories": sorted(splits),
            "failed": sorted(errors),
            "objects": objects,
        },
    )
    return True


def ensure_embedded_dataset(root: str | Path | None = None, *, progress: bool = True, workers: int | None = None, **overrides: Any) -> Path:
    """Build the embedded procedural dataset once (cached) and return its directory.

    The default location is ``$LIGHTNING_VTR_DATA`` or ``~/.cache/lightning_vtr``, in a sub-directory named
    after a hash of the build options, so different options never mix.
    """
    opts = {**EMBEDDED_DEFAULTS, **overrides}
    if root is None:
        base = Path(os.environ.get("LIGHTNING_VTR_DATA", Path.home() / ".cache" / "lightning_vtr"))
        digest = hashlib.sha1(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:10]
        root = base / f"embedded-{digest}"
    root = Path(root)
    if not (root / "metadata.json").is_file():
        report = build_dataset(root, source="procedural", progress=progress, workers=workers or min(2, os.cpu_count() or 1), **opts)
        if not report.finalized:
            raise RuntimeError(f"Building the embedded dataset in {root} did not complete: {report.summary()}; see {root / 'errors.json'}")
    return root

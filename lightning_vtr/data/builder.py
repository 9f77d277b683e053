"""The ShapeNet-VTR builder: render the Aligned / Hemispherical / Spherical view sets and voxelize each object.

Sources: the embedded procedural generator (:mod:`lightning_vtr.data.procedural`), a ShapeNetCore v1
(``<synset>/<model>/model.obj``) or v2 (``<synset>/<model>/models/model_normalized.obj``) folder (+Y up,
converted; known synsets are named as in :data:`~lightning_vtr.data.format.SHAPENET_SYNSETS`), or a
generic ``<category>/<object>.<ext>`` folder (+Z up unless ``up_axis`` says otherwise). Output:
``docs/dataset_format.md``.

View sets (``views_per_set`` each, default 24, seeded per object from ``(seed, category, object_id)`` so
a build is identical whatever the worker count or sharding):

* Aligned: pitch = ``aligned_pitch`` (default 30 degrees), yaw ``0, 360/N, ...`` (view 0 faces the
  object's front, +X). The paper's "phi of 60 degrees" is Zero-1-to-3's polar angle (measured from +Z),
  i.e. an elevation of 30 degrees, which is also the elevation range of the classic ShapeNetRendering
  (25-30 degrees) the paper calls "Aligned".
* Hemispherical: uniform over the upper hemisphere's *area* (yaw uniform, ``sin(pitch)`` uniform in
  ``[0, 1]``). The paper says views are "randomly rendered in the upper hemisphere"; area-uniform is the
  reading that does not crowd views near the pole (angle-uniform puts as many views above 60 degrees as
  in ``[0, 30]``, although that cap is a quarter of the hemisphere's area).
* Spherical: uniform over the whole sphere's area (``sin(pitch)`` uniform in ``[-1, 1]``).

``protocol="pix3d"`` instead renders one view set, ``pix3d``, of ``views_per_object`` views per object
(default 60: the training set of the paper's Pix3D experiment, after Pix2Vox++: ShapeNet chairs, 60
renders per object, composited over random SUN backgrounds at training time, see
``VTRDataModule(background="folder:PATH")``). Its viewpoints imitate photographs of furniture: yaw uniform
in ``[-180, 180)`` (every side), pitch uniform in ``pitch_range`` (default ``[0, 40]`` degrees: from seat
height to a moderate look down, seldom from below or straight above; our choice, as neither the paper nor
Pix2Vox++ states its angles), seeded per object from ``(seed, category, object_id)`` like the random VTR
sets (:func:`pix3d_viewpoints`).

Robustness: every file is written atomically and ``object.json`` last, so a killed build re-run redoes
only unfinished objects. A failing object leaves ``<object dir>/error.json`` (message naming the file)
instead of stopping the build; every pass collects these into ``<root>/errors.json``. ``shard=(i, n)``
builds every n-th object (of the sorted object list) for cluster array jobs; ``metadata.json`` is
written by whichever pass finds every object finished (built or failed): the last shard to finish, a
plain re-run, or :func:`finalize_dataset` (``lightning-vtr build-dataset ROOT --finalize``).
``build_config.json`` records the options that shape the content; a re-run or another shard with
different ones is refused, so one dataset never mixes image sizes or view sets.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import multiprocessing as mp
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from lightning_vtr.data.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SHAPENET_SYNSETS,
    UP_AXES,
    atomic_write_json,
    image_path,
    object_dir,
    read_object_json,
)
from lightning_vtr.data.mesh import MESH_EXTENSIONS
from lightning_vtr.data.splits import empty_split_warning, split_objects, stable_int
from lightning_vtr.geometry import sample_uniform_viewpoints, wrap_yaw
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import atomic_write, remove_stale_temporaries
from lightning_vtr.utils.limits import read_json
from lightning_vtr.utils.paths import check_name, check_no_case_collisions, join_under
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "EMBEDDED_DEFAULTS",
    "PIX3D_PITCH_RANGE",
    "PIX3D_VIEWS_PER_OBJECT",
    "PIX3D_VIEW_SET",
    "PROTOCOLS",
    "SOURCE_LAYOUTS",
    "BuildReport",
    "build_dataset",
    "embedded_dataset_dir",
    "ensure_embedded_dataset",
    "finalize_dataset",
    "pix3d_viewpoints",
    "view_set_viewpoints",
]

#: Objects per category of the procedural source when ``objects_per_category`` is None.
DEFAULT_PROCEDURAL_OBJECTS = 30
#: The values of ``source_layout``: ``"auto"`` detects one of the other three.
SOURCE_LAYOUTS: tuple[str, ...] = ("auto", "shapenet_v1", "shapenet_v2", "generic")
#: The values of ``protocol``: ``"vtr"`` (the Aligned / Hemispherical / Spherical view sets) or ``"pix3d"``
#: (one set of ``views_per_object`` random views per object: the training set of the Pix3D experiment).
PROTOCOLS: tuple[str, ...] = ("vtr", "pix3d")
#: The one view set of a ``protocol="pix3d"`` build.
PIX3D_VIEW_SET = "pix3d"
#: Views per object of a ``protocol="pix3d"`` build by default (the paper's 60, as Pix2Vox++'s Pix3D training set).
PIX3D_VIEWS_PER_OBJECT = 60
#: The pitch range (degrees) of a ``protocol="pix3d"`` build by default: seat height to a moderate look down.
PIX3D_PITCH_RANGE: tuple[float, float] = (0.0, 40.0)
# Level 1 of zlib: PNGs of flat-shaded renders come out a little larger than at the default 6 but encode
# several times faster, and encoding is a large share of the build time.
_PNG_COMPRESS_LEVEL = 1

#: The embedded dataset's build options: 10 categories x 24 objects (17 / 2 / 5 per split) at 96 px, sized so
#: the examples build it and train twice on a laptop CPU.
EMBEDDED_DEFAULTS: dict[str, Any] = dict(
    categories=["airplane", "bed", "bench", "car", "chair", "lamp", "monitor", "sofa", "table", "vessel"],
    objects_per_category=24,
    image_size=96,
    resolution=32,
    views_per_set=24,
    aligned_pitch=30.0,
    seed=0,
)


@dataclass
class BuildReport:
    """What a build pass did.

    Attributes:
        output_dir: the dataset directory.
        built: ``"<category>/<object_id>"`` keys built in this pass.
        skipped: keys already complete (``object.json`` present), not redone.
        failed: key -> error message (naming the file) for objects that failed in this pass.
        seconds: wall time of the pass.
        finalized: whether ``metadata.json`` was written (every object of every shard finished).

    Example:
        >>> report = BuildReport(Path("out"), built=["chair/c0"], failed={"car/c1": "ValueError: bad mesh"})
        >>> print(report.summary())
        built 1, skipped 0 (already complete), failed 1 in 0.0 s; metadata not written (objects of other ...)
          FAILED car/c1: ValueError: bad mesh
    """

    output_dir: Path
    built: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    finalized: bool = False

    def summary(self) -> str:
        meta = "written" if self.finalized else "not written (objects of other shards still missing)"
        lines = [
            f"built {len(self.built)}, skipped {len(self.skipped)} (already complete), failed {len(self.failed)} "
            f"in {self.seconds:.1f} s; metadata {meta}"
        ]
        lines += [f"  FAILED {key}: {msg}" for key, msg in sorted(self.failed.items())]
        return "\n".join(lines)


def view_set_viewpoints(
    category: str, object_id: str, *, views_per_set: int = 24, aligned_pitch: float = 30.0, seed: int = 0
) -> dict[str, np.ndarray]:
    """The three view sets of one object (see the module docstring), a pure function of its arguments.

    Returns:
        ``{"aligned" | "hemispherical" | "spherical": (views_per_set, 2)}`` float64 (yaw, pitch) in degrees.
    """
    g = torch.Generator().manual_seed(stable_int(seed, category, object_id))
    yaw = wrap_yaw(torch.arange(views_per_set, dtype=torch.float64) * (360.0 / views_per_set))
    aligned = torch.stack([yaw, torch.full_like(yaw, float(aligned_pitch))], dim=-1)
    hemi = sample_uniform_viewpoints(views_per_set, mode="area", pitch_range=(0.0, 90.0), generator=g)
    sphere = sample_uniform_viewpoints(views_per_set, mode="area", generator=g)
    return {
        "aligned": aligned.numpy().astype(np.float64),
        "hemispherical": hemi.double().numpy(),
        "spherical": sphere.double().numpy(),
    }


def pix3d_viewpoints(
    category: str,
    object_id: str,
    *,
    views_per_object: int = PIX3D_VIEWS_PER_OBJECT,
    pitch_range: tuple[float, float] = PIX3D_PITCH_RANGE,
    seed: int = 0,
) -> np.ndarray:
    """The ``pix3d`` view set of one object: yaw uniform in ``[-180, 180)``, pitch uniform in ``pitch_range``.

    A pure function of its arguments (seeded from ``(seed, category, object_id)``, in a stream apart from
    :func:`view_set_viewpoints`'s), so shards and workers agree.

    Returns:
        ``(views_per_object, 2)`` float64 (yaw, pitch) in degrees.
    """
    g = torch.Generator().manual_seed(stable_int(seed, category, object_id, PIX3D_VIEW_SET))
    vp = sample_uniform_viewpoints(
        views_per_object, mode="angle", pitch_range=cast("tuple[float, float]", tuple(pitch_range)), generator=g
    )
    return vp.double().numpy()


def _object_viewpoints(category: str, object_id: str, opts: dict[str, Any]) -> dict[str, np.ndarray]:
    """Every view set of one object under the build options ``opts``."""
    if opts.get("protocol", "vtr") == "pix3d":
        views = pix3d_viewpoints(
            category,
            object_id,
            views_per_object=opts["views_per_set"],
            pitch_range=tuple(opts["pitch_range"]),
            seed=opts["seed"],
        )
        return {PIX3D_VIEW_SET: views}
    return view_set_viewpoints(
        category,
        object_id,
        views_per_set=opts["views_per_set"],
        aligned_pitch=opts["aligned_pitch"],
        seed=opts["seed"],
    )


@dataclass
class _Task:
    category: str
    object_id: str
    kind: str  # "procedural" or "mesh"
    index: int = 0
    path: str | None = None
    up_axis: str = "z"

    @property
    def key(self) -> str:
        return f"{self.category}/{self.object_id}"


def _detect_layout(root: Path) -> str:
    for cat_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for sample in sorted(p for p in cat_dir.iterdir() if p.is_dir()):
            if (sample / "models" / "model_normalized.obj").is_file():
                return "shapenet_v2"
            if (sample / "model.obj").is_file():
                return "shapenet_v1"
        if any(p.suffix.lower() in MESH_EXTENSIONS for p in cat_dir.iterdir()):
            return "generic"
    return "generic"


def _discover(
    source: str | Path,
    layout: str,
    objects_per_category: int | None,
    categories: Sequence[str] | None,
    up_axis: str | None,
) -> list[_Task]:
    """Every object of the source, sorted by (category, object_id); independent of shards and workers."""
    if str(source) == "procedural":
        from lightning_vtr.data.procedural import CATEGORIES, object_id

        cats = list(categories) if categories else list(CATEGORIES)
        unknown = sorted(set(cats) - set(CATEGORIES))
        if unknown:
            raise ValueError(
                f"`categories` must be procedural categories (of {list(CATEGORIES)}), got unknown {unknown}"
            )
        n = DEFAULT_PROCEDURAL_OBJECTS if objects_per_category is None else objects_per_category
        return [_Task(c, object_id(c, i), "procedural", index=i) for c in sorted(cats) for i in range(n)]
    root = Path(source)
    if not root.is_dir():
        raise ValueError(f"`source` must be 'procedural' or an existing directory, got {str(source)!r}")
    if layout == "auto":
        layout = _detect_layout(root)
    wanted = set(categories) if categories else None
    tasks = []
    for cat_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        category = SHAPENET_SYNSETS.get(cat_dir.name, cat_dir.name) if layout != "generic" else cat_dir.name
        if wanted is not None and not {cat_dir.name, category} & wanted:
            continue
        if layout == "generic":
            found = [
                (p.stem, p) for p in sorted(cat_dir.iterdir()) if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS
            ]
            up = up_axis or "z"
        else:
            rel = Path("models/model_normalized.obj") if layout == "shapenet_v2" else Path("model.obj")
            found = [(p.name, p / rel) for p in sorted(cat_dir.iterdir()) if p.is_dir()]
            up = up_axis or "y"
        if objects_per_category is not None:
            found = found[:objects_per_category]
        # Both names become folders of the output: one plain component each, unique per folder in any case.
        check_name(category, source=root, entry="category folder")
        for oid, _ in found:
            check_name(oid, source=cat_dir, entry="mesh file" if layout == "generic" else "model folder")
        check_no_case_collisions([f"{category}/{oid}" for oid, _ in found], source=cat_dir, entry="object")
        stems = [oid for oid, _ in found]
        twice = sorted({oid for oid in stems if stems.count(oid) > 1})
        if twice:
            raise ValueError(
                f"{cat_dir}: every object must have one mesh file, got several for {twice} (one stem, several "
                "suffixes); keep one of them"
            )
        tasks += [_Task(category, oid, "mesh", path=str(path), up_axis=up) for oid, path in found]
    check_no_case_collisions([t.key for t in tasks], source=root, entry="category folder")
    if wanted is not None:
        missing = wanted - {t.category for t in tasks} - {p.name for p in root.iterdir()}
        if missing:
            raise ValueError(f"`categories` must name folders under {root}, got {sorted(missing)} without one")
    if not tasks:
        raise ValueError(f"No meshes found under {root} (layout {layout!r}); expected {_layout_hint(layout)}")
    return sorted(tasks, key=lambda t: (t.category, t.object_id))


def _layout_hint(layout: str) -> str:
    return {
        "shapenet_v1": "<synset>/<model>/model.obj",
        "shapenet_v2": "<synset>/<model>/models/model_normalized.obj",
    }.get(layout, f"<category>/<object>.<ext> with ext in {MESH_EXTENSIONS}")


def _png_bytes(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image, mode="RGBA").save(buf, format="PNG", compress_level=_PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _worker_init() -> None:
    # One torch thread per worker: the workers themselves are the parallelism on a small machine.
    torch.set_num_threads(1)


def _build_object(args: tuple[_Task, dict[str, Any], str]) -> tuple[str, str | None]:
    """Build one object; returns ``(key, None)`` or ``(key, error message)`` and never raises."""
    task, opts, out = args
    directory = join_under(out, "objects", task.category, task.object_id)
    try:
        from lightning_vtr.data.binvox import write_binvox
        from lightning_vtr.data.mesh import load_mesh, save_mesh
        from lightning_vtr.data.voxelize import voxelize
        from lightning_vtr.renderer import get_renderer

        if task.kind == "procedural":
            from lightning_vtr.data.procedural import make_object

            mesh = make_object(task.category, task.index, seed=opts["seed"])
        else:
            # a "mesh" task has a path; load_mesh checks the up axis
            mesh = load_mesh(cast(str, task.path), up_axis=cast(Literal["y", "z"], task.up_axis))
        directory.mkdir(parents=True, exist_ok=True)
        voxels = voxelize(mesh, opts["resolution"])
        if not voxels.any():
            raise ValueError(f"the voxelization of {task.path or task.key} at R={opts['resolution']} is empty")
        write_binvox(directory / "model.binvox", voxels)
        save_mesh(mesh, directory / "mesh.ply")
        views = _object_viewpoints(task.category, task.object_id, opts)
        renderer = get_renderer(opts["image_size"])
        names = list(views)
        # One render call for all view sets: the mesh is uploaded to the GL context once.
        images = renderer.render(mesh, np.concatenate([views[n] for n in names]))
        for s, name in enumerate(names):
            for i in range(opts["views_per_set"]):
                atomic_write(image_path(directory, name, i), _png_bytes(images[s * opts["views_per_set"] + i]))
        (directory / "error.json").unlink(missing_ok=True)
        atomic_write_json(
            directory / "object.json",
            {
                "category": task.category,
                "object_id": task.object_id,
                "source": task.path or f"procedural:seed={opts['seed']}",
                "views": {k: v.round(6).tolist() for k, v in views.items()},
            },
        )
        return task.key, None
    except Exception as err:
        message = f"{type(err).__name__}: {err}"
        with contextlib.suppress(OSError):  # the report still carries the message
            atomic_write_json(directory / "error.json", {"key": task.key, "source": task.path, "error": message})
        return task.key, message


def _check_args(
    image_size: int,
    resolution: int,
    views_per_set: int,
    aligned_pitch: float,
    split: Sequence[float],
    shard: tuple[int, int],
    layout: str,
    workers: int,
    up_axis: str | None,
) -> None:
    check_int("image_size", image_size, minimum=1)
    check_int("resolution", resolution, minimum=1)
    check_int("views_per_set", views_per_set, minimum=1, maximum=100)  # images are named 00..99.png
    check_int("workers", workers, minimum=1)
    check_float("aligned_pitch", aligned_pitch, minimum=-90.0, maximum=90.0)
    try:
        ratios = [float(r) for r in split]
    except (TypeError, ValueError):
        raise TypeError(f"`split` must be three (train, val, test) ratios, got {split!r}") from None
    if len(ratios) != 3 or abs(sum(ratios) - 1.0) > 1e-6 or min(ratios) < 0:
        raise ValueError(
            f"`split` must be three non-negative (train, val, test) ratios summing to 1, got {tuple(split)}"
        )
    try:
        index, count = shard
    except (TypeError, ValueError):
        raise TypeError(f"`shard` must be a pair (i, n), got {shard!r}") from None
    check_int("shard[0]", index)
    check_int("shard[1]", count, minimum=1)
    if not 0 <= index < count:
        raise ValueError(f"`shard` must be (i, n) with 0 <= i < n, got {tuple(shard)}")
    check_choice("source_layout", layout, SOURCE_LAYOUTS)
    check_choice("up_axis", up_axis, (None, *UP_AXES))


def _protocol_opts(
    protocol: str, views_per_set: int, views_per_object: int | None, pitch_range: Sequence[float] | None
) -> tuple[int, dict[str, Any]]:
    """``(views per view set, the options only a Pix3D build has)``; checks the protocol's arguments."""
    check_choice("protocol", protocol, PROTOCOLS)
    if protocol == "vtr":
        for name, value in (("views_per_object", views_per_object), ("pitch_range", pitch_range)):
            if value is not None:
                raise ValueError(
                    f"`{name}` applies to protocol='pix3d' only (protocol 'vtr' renders `views_per_set` views per "
                    f"view set), got {name}={value!r}"
                )
        return views_per_set, {}
    if views_per_set != 24:
        raise ValueError(
            "`views_per_set` applies to protocol='vtr' only; protocol='pix3d' renders `views_per_object` views "
            f"per object (default {PIX3D_VIEWS_PER_OBJECT}), got views_per_set={views_per_set!r}"
        )
    count = PIX3D_VIEWS_PER_OBJECT if views_per_object is None else views_per_object
    check_int("views_per_object", count, minimum=1, maximum=100)  # images are named 00..99.png
    low, high = PIX3D_PITCH_RANGE if pitch_range is None else _pair("pitch_range", pitch_range)
    check_float("pitch_range[0]", low, minimum=-90.0, maximum=90.0)
    check_float("pitch_range[1]", high, minimum=-90.0, maximum=90.0)
    if low > high:
        raise ValueError(f"`pitch_range` must be (low, high) with low <= high, got {(low, high)}")
    return int(count), {"protocol": "pix3d", "pitch_range": [float(low), float(high)]}


def _pair(name: str, value: Any) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise TypeError(f"`{name}` must be a pair of numbers (low, high) in degrees, got {value!r}") from None
    return low, high


def _content_config(source, categories, objects_per_category, opts, split, layout, up_axis) -> dict[str, Any]:
    source = "procedural" if str(source) == "procedural" else str(Path(source).resolve())
    return {
        "source": source,
        "source_layout": layout,
        "up_axis": up_axis,
        "categories": sorted(categories) if categories else None,
        "objects_per_category": objects_per_category,
        "split": [float(r) for r in split],
        **opts,
    }


def _check_output_dir(out: Path) -> None:
    """Refuse an output that is a file, or a folder of other files (no ``build_config.json``: not a build)."""
    if out.exists() and not out.is_dir():
        raise ValueError(
            f"the output folder must be a folder (new, empty or an earlier build), got {str(out)!r} (a file)"
        )
    if out.is_dir() and not (out / "build_config.json").is_file():
        others = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
        if others:
            shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
            raise ValueError(
                f"the output folder must be new, empty or an earlier build (with build_config.json), got "
                f"{str(out)!r} holding {len(others)} other {'entry' if len(others) == 1 else 'entries'} ({shown}); choose another folder"
            )


def _write_or_check_config(out: Path, config: dict[str, Any]) -> None:
    path = out / "build_config.json"
    if path.is_file():
        old = read_json(path)
        # Both sides' keys: a Pix3D build's config has keys a VTR build's lacks.
        diff = {k: (old.get(k), config.get(k)) for k in {*old, *config} if old.get(k) != config.get(k)}
        if diff:
            details = ", ".join(f"{k}: {a!r} on disk vs {b!r} now" for k, (a, b) in sorted(diff.items()))
            raise ValueError(
                f"{out} was built with other options ({details}); use a new output directory or the same options"
            )
    else:
        atomic_write_json(path, config)


def build_dataset(
    output_dir: str | Path,
    *,
    source: str | Path = "procedural",
    objects_per_category: int | None = None,
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
    up_axis: str | None = None,
    protocol: str = "vtr",
    views_per_object: int | None = None,
    pitch_range: tuple[float, float] | None = None,
) -> BuildReport:
    """Build (or finish building) a ShapeNet-VTR dataset in ``output_dir``; see the module docstring.

    Args:
        output_dir: the dataset directory (created).
        source: ``"procedural"`` or a folder of meshes (ShapeNetCore v1/v2 or ``<category>/<object>.<ext>``).
        objects_per_category: the first N objects (sorted by id) of each category; ``None``: 30 for the
            procedural source, all for a folder.
        categories: the categories to build (names, or synset ids for ShapeNet); ``None``: all.
        image_size: rendered image side in pixels.
        resolution: voxel grid side R.
        views_per_set: views per view set (the paper: 24).
        aligned_pitch: the Aligned set's elevation in degrees (default 30; see the module docstring).
        split: (train, val, test) ratios per category, rounded to object counts; a category of at least 3
            objects whose validation or test ratio is positive but rounds to no object gets one, taken from its
            largest other split (so 4 objects split 2 / 1 / 1). A category too small for that warns.
        seed: seeds the procedural shapes, the random view sets and the split.
        workers: processes rendering in parallel ('spawn' context: each opens its own GL context).
        shard: ``(i, n)``: build only objects ``i, i + n, ...`` of the sorted object list.
        finalize: write ``splits.json`` / ``metadata.json`` when every object (of every shard) is finished.
        progress: show a tqdm progress bar.
        source_layout: ``"auto"`` (detect), ``"shapenet_v1"``, ``"shapenet_v2"`` or ``"generic"``.
        up_axis: the meshes' up axis; ``None``: ``"y"`` for ShapeNet layouts, ``"z"`` for generic folders.
        protocol: ``"vtr"`` (the three view sets) or ``"pix3d"`` (one ``pix3d`` view set of
            ``views_per_object`` random views; see the module docstring). Pass ``categories=["chair"]`` for the
            paper's Pix3D training set.
        views_per_object: ``protocol="pix3d"`` only: views per object (default 60, at most 100).
        pitch_range: ``protocol="pix3d"`` only: ``(low, high)`` pitch in degrees (default ``(0, 40)``).

    Returns:
        A :class:`BuildReport` of this pass.

    Warns:
        UserWarning: when writing ``metadata.json``, naming every category left without a validation or test
            object that its ratio asks for (fewer than 3 objects).

    Raises:
        TypeError: an argument of the wrong type (names the argument and the value), e.g. a ``split`` or
            ``shard`` that is not a sequence of numbers.
        ValueError: for invalid arguments (names the argument and the value), a source that is neither
            ``"procedural"`` nor a folder, an ``output_dir`` that is a file or a folder of other files, or an
            ``output_dir`` that was built with other options.

    Example::

        from lightning_vtr.data import build_dataset

        report = build_dataset("data/vtr-chairs", categories=["chair"], objects_per_category=10, workers=4)
        print(report.summary())  # built 10, skipped 0 (already complete), failed 0 in ... s; metadata written
    """
    _check_args(image_size, resolution, views_per_set, aligned_pitch, split, shard, source_layout, workers, up_axis)
    views_per_set, pix3d = _protocol_opts(protocol, views_per_set, views_per_object, pitch_range)
    start = time.perf_counter()
    out = Path(output_dir)
    opts = dict(
        image_size=int(image_size),
        resolution=int(resolution),
        views_per_set=int(views_per_set),
        aligned_pitch=float(aligned_pitch),
        seed=int(seed),
        **pix3d,  # only in a Pix3D build: a VTR build's config stays what it was before protocols existed
    )
    _check_output_dir(out)
    tasks = _discover(source, source_layout, objects_per_category, categories, up_axis)
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out)
    config = _content_config(source, categories, objects_per_category, opts, split, source_layout, up_axis)
    _write_or_check_config(out, config)
    index, count = shard
    report = BuildReport(output_dir=out)
    todo = []
    for task in tasks[index::count]:
        if (object_dir(out, task.category, task.object_id) / "object.json").is_file():
            report.skipped.append(task.key)
        else:
            todo.append(task)
    jobs = [(t, opts, str(out)) for t in todo]
    bar = tqdm(total=len(jobs), desc=f"building {out.name}", unit="obj", disable=not progress, dynamic_ncols=True)
    if workers > 1 and len(jobs) > 1:
        # 'spawn': every worker opens its own GL context; forking a process that holds one is unsafe.
        with mp.get_context("spawn").Pool(min(workers, len(jobs)), initializer=_worker_init) as pool:
            _track(pool.imap_unordered(_build_object, jobs), report, bar)
    else:
        _track(map(_build_object, jobs), report, bar)
    bar.close()
    errors = _collect_errors(out, tasks)
    atomic_write_json(out / "errors.json", errors)
    if finalize:
        report.finalized = _finalize(out, tasks, errors, split, seed, opts, config)
    report.seconds = time.perf_counter() - start
    return report


def _track(results, report: BuildReport, bar) -> None:
    for key, error in results:
        if error:
            report.failed[key] = error
        else:
            report.built.append(key)
        bar.update()
        bar.set_postfix(failed=len(report.failed), refresh=False)


def _collect_errors(out: Path, tasks: list[_Task]) -> dict[str, str]:
    """``{key: message}`` of every object with an ``error.json`` and no ``object.json`` (any shard's)."""
    errors = {}
    for t in tasks:
        directory = object_dir(out, t.category, t.object_id)
        path = directory / "error.json"
        if path.is_file() and not (directory / "object.json").is_file():
            try:
                errors[t.key] = read_json(path)["error"]
            except (OSError, ValueError, KeyError):
                errors[t.key] = f"unreadable error report {path}"
    return errors


def _finalize(
    out: Path, tasks: list[_Task], errors: dict[str, str], split: Sequence[float], seed: int, opts: dict, config: dict
) -> bool:
    complete = []
    for t in tasks:
        if (object_dir(out, t.category, t.object_id) / "object.json").is_file():
            complete.append((t.category, t.object_id))
        elif t.key not in errors:
            return False  # another shard is still working on it
    splits = split_objects(complete, split, seed)
    message = empty_split_warning(splits, split)
    if message:
        warnings.warn(message, UserWarning, stacklevel=3)
    atomic_write_json(out / "splits.json", splits)
    objects = {}
    for category, parts in splits.items():
        for name, ids in parts.items():
            for oid in ids:
                info = read_object_json(object_dir(out, category, oid))
                objects[f"{category}/{oid}"] = {"split": name, "views": info["views"]}
    from lightning_vtr.renderer import DEFAULT_DISTANCE, DEFAULT_YFOV_DEG

    protocol = opts.get("protocol", "vtr")
    if protocol == "pix3d":
        low, high = opts["pitch_range"]
        view_sets = [PIX3D_VIEW_SET]
        sampling = {PIX3D_VIEW_SET: f"yaw uniform in [-180, 180), pitch uniform in [{low:g}, {high:g}]"}
        extra = {"views_per_object": opts["views_per_set"], "pitch_range": [low, high]}
    else:
        view_sets = list(VIEW_SETS)
        sampling = {
            "aligned": "yaw every 360/views_per_set deg at aligned_pitch",
            "hemispherical": "area-uniform, pitch in [0, 90]",
            "spherical": "area-uniform, pitch in [-90, 90]",
        }
        extra = {}
    atomic_write_json(
        out / "metadata.json",
        {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "protocol": protocol,
            "resolution": opts["resolution"],
            "image_size": opts["image_size"],
            "views_per_set": opts["views_per_set"],
            "view_sets": view_sets,
            "aligned_pitch": opts["aligned_pitch"],
            **extra,
            "sampling": sampling,
            "camera": {"type": "perspective", "yfov_deg": DEFAULT_YFOV_DEG, "distance": DEFAULT_DISTANCE},
            "split_ratios": [float(r) for r in split],
            "seed": seed,
            "source": config["source"],
            "categories": sorted(splits),
            "failed": sorted(errors),
            "objects": objects,
        },
    )
    return True


def finalize_dataset(output_dir: str | Path) -> BuildReport:
    """Write ``metadata.json`` of a sharded build once every shard has finished; builds nothing.

    Reads the options from ``build_config.json``.

    Raises:
        FileNotFoundError: ``output_dir`` has no ``build_config.json`` (no build was started there).
        RuntimeError: some objects are neither built nor failed; the message lists the first ones.
    """
    start = time.perf_counter()
    out = Path(output_dir)
    path = out / "build_config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: start a build with `lightning-vtr build-dataset {out}` first")
    config = read_json(path)
    tasks = _discover(
        config["source"],
        config["source_layout"],
        config["objects_per_category"],
        config["categories"],
        config["up_axis"],
    )
    errors = _collect_errors(out, tasks)
    atomic_write_json(out / "errors.json", errors)
    opts = {k: config[k] for k in ("image_size", "resolution", "views_per_set", "aligned_pitch", "seed")}
    opts.update({k: config[k] for k in ("protocol", "pitch_range") if k in config})  # a Pix3D build's
    report = BuildReport(output_dir=out, failed=errors)
    report.finalized = _finalize(out, tasks, errors, config["split"], config["seed"], opts, config)
    if not report.finalized:
        missing = [
            t.key
            for t in tasks
            if t.key not in errors and not (object_dir(out, t.category, t.object_id) / "object.json").is_file()
        ]
        raise RuntimeError(
            f"Cannot finalize {out}: {len(missing)} object(s) are not built yet (e.g. {missing[:5]}); "
            "wait for every shard, or re-run a shard to finish them"
        )
    report.skipped = [t.key for t in tasks if t.key not in errors]
    report.seconds = time.perf_counter() - start
    return report


def embedded_dataset_dir(**overrides: Any) -> Path:
    """Where :func:`ensure_embedded_dataset` keeps the dataset for these options (it may not exist yet)."""
    opts = {**EMBEDDED_DEFAULTS, **overrides}
    base = Path(os.environ.get("LIGHTNING_VTR_DATA") or Path.home() / ".cache" / "lightning_vtr")
    digest = hashlib.sha1(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:10]
    return base / f"embedded-{digest}"


def ensure_embedded_dataset(
    root: str | Path | None = None, *, progress: bool = True, workers: int | None = None, **overrides: Any
) -> Path:
    """Build the embedded procedural dataset once (cached) and return its directory.

    Args:
        root: where to build it; ``None``: ``$LIGHTNING_VTR_DATA`` or ``~/.cache/lightning_vtr``, in a
            sub-directory ``embedded-<hash of the options>`` so different options never mix.
        progress: show a progress bar while building.
        workers: build processes; ``None``: up to 2.
        overrides: build options replacing :data:`EMBEDDED_DEFAULTS` (see :func:`build_dataset`).

    Returns:
        The dataset directory, holding a finished build (with ``metadata.json``).

    Raises:
        RuntimeError: an object failed to build (the procedural source should never fail).
        ValueError: an invalid build option (see :func:`build_dataset`).

    Example::

        from lightning_vtr.data import VTRDataModule, ensure_embedded_dataset

        root = ensure_embedded_dataset()  # built on the first call, then reused
        datamodule = VTRDataModule(root)
    """
    opts = {**EMBEDDED_DEFAULTS, **overrides}
    root = embedded_dataset_dir(**overrides) if root is None else Path(root)
    if not (root / "metadata.json").is_file():
        report = build_dataset(
            root, source="procedural", progress=progress, workers=workers or min(2, os.cpu_count() or 1), **opts
        )
        if not report.finalized or report.failed:
            raise RuntimeError(
                f"Building the embedded dataset in {root} did not complete: {report.summary()}; see {root / 'errors.json'}"
            )
    return root

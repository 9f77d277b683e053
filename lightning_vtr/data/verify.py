"""Check a ShapeNet-VTR directory before a long run: read every image and voxel file once, in parallel, and
list every file that is missing, unreadable or disagrees with ``metadata.json``.

A truncated PNG otherwise surfaces as ``OSError: Cannot read image ...`` at the first epoch that draws it,
possibly hours into a run. :func:`verify_dataset` decodes every image in full with Pillow, as the loaders'
:func:`~lightning_vtr.data.dataset.load_rgba` does, and every voxel file with
:func:`~lightning_vtr.data.binvox.read_binvox`, so a dataset it passes is one the loaders can read.
``lightning-vtr dataset-info ROOT --verify`` and ``VTRDataModule(verify=True)`` call it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import stat
import time
import warnings
from collections.abc import Iterator, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from tqdm.auto import tqdm

from lightning_vtr.data.binvox import read_binvox
from lightning_vtr.data.format import SPLITS, image_path, load_metadata, object_dir, unsafe_names
from lightning_vtr.utils.limits import file_kind
from lightning_vtr.utils.paths import UnsafeNameError, check_name, check_no_case_collisions
from lightning_vtr.utils.validation import check_int

__all__ = ["PROBLEM_KINDS", "DatasetProblem", "VerifyReport", "verify_dataset"]

#: What a :class:`DatasetProblem` can be about, in the order a file is checked.
PROBLEM_KINDS: tuple[str, ...] = (
    "metadata",
    "missing",
    "unreadable",
    "image_size",
    "view_count",
    "voxel_resolution",
    "inconsistent",
    "unsafe_name",
    "outside",
    "prerendered",
)

#: Problems an error message lists before it says how many more there are.
_LISTED_PROBLEMS = 20


@dataclass(frozen=True)
class DatasetProblem:
    """One file that a training run would fail on or silently misread.

    Attributes:
        path: the file (or directory) at fault.
        kind: one of :data:`PROBLEM_KINDS`; ``"unsafe_name"``: a category, object id or view-set name that is
            not a plain path component (the message names the entry and the rule it breaks, see
            :mod:`lightning_vtr.utils.paths`); ``"outside"``: an image, voxel file or folder of an object that is
            a symlink leading out of the dataset (it is not read); ``"unreadable"`` also: a file that is not a regular
            file (a FIFO, a socket, a device, a folder; it is not opened); ``"prerendered"``: the object's
            ``prerendered/`` views (``build-dataset --prerender-views``) lack their index, a listed image, or an
            image that decodes at the dataset's size, or a training object has none in a prerendered dataset.
        message: what is wrong with it.
        expected: the value ``metadata.json`` implies (``None`` when there is no single value).
        actual: the value found.
    """

    path: Path
    kind: str
    message: str
    expected: Any = None
    actual: Any = None

    def __str__(self) -> str:
        values = f" (expected {self.expected}, got {self.actual})" if self.expected is not None else ""
        return f"{self.path}: {self.message}{values}"


@dataclass
class VerifyReport:
    """What :func:`verify_dataset` found.

    Attributes:
        root: the dataset directory.
        objects: objects checked (every entry of ``metadata.json["objects"]``).
        files: image and voxel files read.
        problems: every problem found, in the order of ``metadata.json``.
        seconds: wall time of the check.

    Example:
        >>> missing = DatasetProblem(Path("data/objects/chair/c0/model.binvox"), "missing", "does not exist")
        >>> report = VerifyReport(Path("data"), objects=10, files=250, problems=[missing])
        >>> report.ok, str(report.problems[0])
        (False, 'data/objects/chair/c0/model.binvox: does not exist')
    """

    root: Path
    objects: int = 0
    files: int = 0
    problems: list[DatasetProblem] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        """Whether no problem was found."""
        return not self.problems

    @property
    def objects_per_second(self) -> float:
        """Objects checked per second of wall time."""
        return self.objects / self.seconds if self.seconds > 0 else float("inf")

    def summary(self) -> str:
        """One line: objects and files checked, problems found, speed."""
        return (
            f"verified {self.objects} objects ({self.files} files) in {self.seconds:.1f} s "
            f"({self.objects_per_second:.1f} objects/s): {len(self.problems)} problem(s)"
        )

    def error_message(self, limit: int = _LISTED_PROBLEMS) -> str:
        """A message listing the first ``limit`` problems and how many more there are (for an exception)."""
        lines = [f"Verifying the dataset at {self.root} found {len(self.problems)} problem(s):"]
        lines += [f"  {problem}" for problem in self.problems[:limit]]
        if len(self.problems) > limit:
            lines.append(
                f"  ... and {len(self.problems) - limit} more; `lightning-vtr dataset-info {self.root} --verify` "
                "lists them all"
            )
        return "\n".join(lines)


@dataclass(frozen=True)
class _Expected:
    """What every object of the dataset must match, from ``metadata.json``."""

    root: Path
    resolved_root: Path
    metadata: Path
    image_size: int
    resolution: int
    view_sets: tuple[str, ...]
    views_per_set: int | None
    prerendered: bool = False  # the dataset records prerendered views: every training object must have them


def verify_dataset(root: str | Path, *, workers: int | None = None, progress: bool = True) -> VerifyReport:
    """Read every image and voxel file of a ShapeNet-VTR dataset once and list what is wrong.

    Checked once: ``splits.json`` exists, is JSON of ``{category: {split: [object ids]}}`` and puts every object
    in the split ``metadata.json`` gives it (kind ``"inconsistent"`` otherwise). Checked per object of
    ``metadata.json``: its ``object.json`` exists, is valid and names the object; its ``mesh.ply``, where there
    is one (the renderer's), loads with faces; its directory and ``model.binvox`` exist; the voxel file decodes
    to ``R x R x R`` with ``R = metadata["resolution"]``; every view set of ``metadata["view_sets"]`` lists
    ``metadata["views_per_set"]`` viewpoints and its directory holds exactly those images, ``00.png`` ..;
    every image decodes and is ``image_size x image_size``. Each problem names the file and, where there is
    one, the expected and the actual value.

    Args:
        root: the dataset directory.
        workers: processes reading files in parallel (``1``: this process alone); ``None``: one per CPU this
            process may run on. Decoding is mostly Python-bound, so processes, not threads, scale it. Workers
            are forked (they import nothing); where ``fork`` does not exist they are threads.
        progress: show a tqdm progress bar (one step per object).

    Returns:
        A :class:`VerifyReport`; ``report.ok`` when nothing is wrong.

    Raises:
        DatasetFormatError: ``metadata.json`` is missing or invalid (nothing else can be checked then).
        ValueError: ``workers`` is not a positive int.

    Example:
        >>> report = verify_dataset("/data/shapenet_vtr", progress=False)  # doctest: +SKIP
        >>> report.ok, report.objects, report.files  # doctest: +SKIP
        (True, 39000, 2847000)
    """
    # 1. check inputs and read what every object must match
    if workers is not None:
        check_int("workers", workers, minimum=1)
    start = time.perf_counter()
    root = Path(root)
    meta = load_metadata(root, check_names=False, check_entries=False)
    views_per_set = meta.get("views_per_set")
    # An unsafe name is reported, never joined to a path: its objects and view sets are not read.
    unsafe = unsafe_names(meta, root / "metadata.json")
    bad_names = {err.name for err in unsafe}
    expected = _Expected(
        root=root,
        resolved_root=root.resolve(),
        metadata=root / "metadata.json",
        image_size=int(meta["image_size"]),
        resolution=int(meta["resolution"]),
        view_sets=tuple(name for name in meta["view_sets"] if name not in bad_names),
        views_per_set=int(views_per_set) if views_per_set is not None else None,
        prerendered=(root / "prerendered.json").is_file(),
    )
    objects = [(key, info) for key, info in meta["objects"].items() if key not in bad_names]

    # 2. check the objects in parallel, in metadata order
    report = VerifyReport(root=root, objects=len(meta["objects"]))
    report.problems.extend(_unsafe_problem(err) for err in unsafe)
    report.problems.extend(_check_splits(root, meta))
    if expected.prerendered:  # imported once here, not in every forked worker
        import lightning_vtr.synthesis.prerendered  # noqa: F401
    bar = tqdm(total=len(objects), desc=f"verifying {root.name}", unit="obj", disable=not progress, dynamic_ncols=True)
    for problems, files in _map_objects(expected, objects, workers or _usable_cpus()):
        report.problems.extend(problems)
        report.files += files
        bar.update()
    bar.close()
    report.seconds = time.perf_counter() - start
    return report


def _unsafe_problem(err: UnsafeNameError) -> DatasetProblem:
    """An ``"unsafe_name"`` problem from the error of a name check."""
    return DatasetProblem(Path(err.source), "unsafe_name", f"{err.entry} {err.name!r}: {err.reason}")


def _usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one, e.g. under a job scheduler)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def _map_objects(
    expected: _Expected, objects: list[tuple[str, Any]], workers: int
) -> Iterator[tuple[list[DatasetProblem], int]]:
    """:func:`_check_object` of every object, in order, on ``workers`` processes (threads without ``fork``)."""
    check = partial(_check_object, expected)
    keys, infos = [key for key, _ in objects], [info for _, info in objects]
    workers = min(workers, len(objects))
    if workers <= 1:
        yield from map(check, keys, infos)
        return
    # "fork": a spawned worker would import torch (seconds) and re-run an unguarded __main__ script.
    pool: Executor
    if "fork" in mp.get_all_start_methods():
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"))
    else:  # pragma: no cover - Windows
        pool = ThreadPoolExecutor(max_workers=workers)
    with pool:
        # Chunks of a few objects: per-object messages would cost more than the check on small images.
        chunksize = max(1, min(16, len(objects) // (workers * 8)))
        yield from pool.map(check, keys, infos, chunksize=chunksize)


def _check_object(expected: _Expected, key: str, info: Any) -> tuple[list[DatasetProblem], int]:
    """The problems of one object of ``metadata.json`` and the number of files read."""
    problems: list[DatasetProblem] = []
    category, _, object_id = key.partition("/")  # a safe key (verify_dataset left the others out)
    if not isinstance(info, Mapping):
        problems.append(DatasetProblem(expected.metadata, "metadata", f"object entry {key!r} is not a dict of fields"))
        return problems, 0
    if info.get("split") not in SPLITS:
        problems.append(
            DatasetProblem(
                expected.metadata, "metadata", f"object {key!r} has an unknown split", list(SPLITS), info.get("split")
            )
        )
    directory = object_dir(expected.root, category, object_id)
    if not directory.is_dir():
        problems.append(
            DatasetProblem(directory, "missing", f"metadata.json lists object {key!r} but its directory does not exist")
        )
        return problems, 0
    outside = _outside(directory, expected)
    if outside is not None:
        return [*problems, outside], 0
    problems += _check_object_json(directory, category, object_id)
    problems += _check_mesh(directory / "mesh.ply")
    voxel_path = directory / "model.binvox"
    files = int(voxel_path.is_file())
    voxel_problem = _outside(voxel_path, expected) or _check_voxels(voxel_path, expected.resolution)
    if voxel_problem is not None:
        problems.append(voxel_problem)
    views = info.get("views")
    for view_set in expected.view_sets:
        if not isinstance(views, Mapping) or view_set not in views:
            problems.append(
                DatasetProblem(expected.metadata, "metadata", f"object {key!r} lists no view set {view_set!r}")
            )
            continue
        set_problems, set_files = _check_view_set(directory, view_set, views[view_set], key, expected)
        problems += set_problems
        files += set_files
    prerendered_problems, prerendered_files = _check_prerendered(directory, key, info.get("split"), expected)
    return problems + prerendered_problems, files + prerendered_files


def _check_prerendered(directory: Path, key: str, split: Any, expected: _Expected) -> tuple[list[DatasetProblem], int]:
    """The object's ``prerendered/`` folder, where it has one (a training object of a prerendered dataset must):
    its index reads, and every viewpoint it lists has an image that decodes at the dataset's size."""
    folder = directory / "prerendered"  # lightning_vtr.synthesis.prerendered.PRERENDERED_DIR
    if not folder.is_dir():
        if expected.prerendered and split == "train":
            hint = f"run `lightning-vtr build-dataset {expected.root} --prerender-views`"
            return [
                DatasetProblem(folder, "prerendered", f"training object {key!r} has no prerendered views; {hint}")
            ], 0
        return [], 0
    outside = _outside(folder, expected)
    if outside is not None:
        return [outside], 0
    # imported only for a dataset that has prerendered views (it imports torch)
    from lightning_vtr.synthesis.prerendered import INDEX_FILE, read_prerendered_index

    try:
        _, paths, size = read_prerendered_index(folder)
    except FileNotFoundError:
        return [DatasetProblem(folder / INDEX_FILE, "prerendered", "the prerendered views' index does not exist")], 0
    except ValueError as err:
        return [DatasetProblem(folder / INDEX_FILE, "prerendered", str(err))], 0
    problems = []
    if size != expected.image_size:
        problems.append(
            DatasetProblem(folder / INDEX_FILE, "prerendered", "index of another image size", expected.image_size, size)
        )
    files = 0
    for path in paths:
        if not path.exists():
            problems.append(DatasetProblem(path, "prerendered", "a prerendered view listed in index.json is missing"))
            continue
        files += 1
        problem = _outside(path, expected) or _check_image(path, expected.image_size)
        if problem is not None:
            problems.append(
                DatasetProblem(problem.path, "prerendered", problem.message, problem.expected, problem.actual)
            )
    return problems, files


def _check_splits(root: Path, meta: Mapping[str, Any]) -> list[DatasetProblem]:
    """``splits.json``: present, ``{category: {split: [ids]}}``, and agreeing with ``metadata.json``'s splits."""
    from lightning_vtr.utils.limits import read_json

    path = root / "splits.json"
    if not path.exists():
        return [DatasetProblem(path, "missing", "the dataset's splits.json does not exist")]
    special = _not_regular(path)
    if special is not None:
        return [special]
    try:
        splits = read_json(path)
    except (OSError, ValueError) as err:
        return [DatasetProblem(path, "unreadable", f"cannot read splits.json: {err}")]
    listed: dict[str, str] = {}
    unsafe: list[DatasetProblem] = []
    shape = "splits.json must map categories to {split: [object ids]}"
    if isinstance(splits, Mapping):
        for category, parts in splits.items():
            try:
                check_name(category, source=path, entry="category")
            except UnsafeNameError as err:
                unsafe.append(_unsafe_problem(err))
            if not isinstance(parts, Mapping):
                found = f"a {type(parts).__name__}"
                unsafe.append(DatasetProblem(path, "unreadable", f"{shape}; category {category!r} holds {found}"))
                continue
            for split, ids in parts.items():
                if split not in SPLITS or not isinstance(ids, list):
                    found = f"split {split!r} holding a {type(ids).__name__}"
                    unsafe.append(
                        DatasetProblem(path, "unreadable", f"{shape} of {list(SPLITS)}; {category!r} has {found}")
                    )
                    continue
                for oid in ids:
                    try:
                        check_name(oid, source=path, entry=f"object id of {category!r}")
                    except UnsafeNameError as err:
                        unsafe.append(_unsafe_problem(err))
                    listed[f"{category}/{oid}"] = split
        try:
            check_no_case_collisions(listed, source=path, entry="object")
        except UnsafeNameError as err:
            unsafe.append(_unsafe_problem(err))
    if not isinstance(splits, Mapping) or (not listed and meta["objects"] and not unsafe):
        return [DatasetProblem(path, "unreadable", shape, None, None)]
    problems = unsafe
    for key, info in meta["objects"].items():
        split = info.get("split") if isinstance(info, Mapping) else None
        if split in SPLITS and key in listed and listed[key] != split:  # other faults are metadata.json's
            problems.append(
                DatasetProblem(
                    path, "inconsistent", f"splits.json disagrees with metadata.json on {key!r}", split, listed.get(key)
                )
            )
    return problems


def _check_object_json(directory: Path, category: str, object_id: str) -> list[DatasetProblem]:
    """``object.json``: present, valid, and naming the object."""
    from lightning_vtr.data.format import DatasetFormatError, read_object_json
    from lightning_vtr.errors import DataError

    path = directory / "object.json"
    if not path.exists():
        return [DatasetProblem(path, "missing", "the object's object.json does not exist")]
    special = _not_regular(path)
    if special is not None:
        return [special]
    try:
        own = read_object_json(directory)
    except UnsafeNameError as err:
        return [_unsafe_problem(err)]
    except (DatasetFormatError, DataError) as err:
        return [DatasetProblem(path, "unreadable", f"invalid object.json: {err}")]
    problems = []
    if (own["category"], own["object_id"]) != (category, object_id):
        found = f"{own['category']}/{own['object_id']}"
        problems.append(
            DatasetProblem(path, "inconsistent", "object.json names another object", f"{category}/{object_id}", found)
        )
    return problems


def _check_mesh(path: Path) -> list[DatasetProblem]:
    """``mesh.ply`` (optional): where there is one, it is a regular file, loads and has faces."""
    if not path.exists():
        return []
    special = _not_regular(path)
    if special is not None:
        return [special]
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds for a damaged file
        return [DatasetProblem(path, "unreadable", f"cannot read the mesh: {err}")]
    if len(getattr(mesh, "faces", ())) == 0:
        return [DatasetProblem(path, "unreadable", "the mesh has no faces")]
    return []


def _check_voxels(path: Path, resolution: int) -> DatasetProblem | None:
    """The problem of one voxel file, if any."""
    if not path.exists():
        return DatasetProblem(path, "missing", "the object's voxel file does not exist")
    special = _not_regular(path)
    if special is not None:
        return special
    try:
        voxels = read_binvox(path)
    except (OSError, ValueError) as err:
        return DatasetProblem(path, "unreadable", f"cannot read the voxel file: {err}")
    if voxels.shape != (resolution,) * 3:
        return DatasetProblem(
            path,
            "voxel_resolution",
            "voxel grid of the wrong resolution",
            "x".join([str(resolution)] * 3),
            "x".join(map(str, voxels.shape)),
        )
    return None


def _check_view_set(
    directory: Path, view_set: str, viewpoints: Any, key: str, expected: _Expected
) -> tuple[list[DatasetProblem], int]:
    """The problems of one view set of one object and the number of images read."""
    problems: list[DatasetProblem] = []
    try:
        listed = np.asarray(viewpoints, dtype=np.float64)
    except (TypeError, ValueError):
        listed = np.zeros((0, 0))
    if listed.ndim != 2 or listed.shape[1] != 2 or not np.isfinite(listed).all():
        problems.append(
            DatasetProblem(
                expected.metadata,
                "metadata",
                f"view set {view_set!r} of object {key!r} is not a list of finite [yaw, pitch] pairs (shape {listed.shape})",
            )
        )
        return problems, 0
    count = listed.shape[0]
    set_dir = directory / view_set
    if expected.views_per_set is not None and count != expected.views_per_set:
        problems.append(
            DatasetProblem(
                set_dir,
                "view_count",
                f"metadata.json lists {count} viewpoints for this view set",
                expected.views_per_set,
                count,
            )
        )
    if not set_dir.is_dir():
        problems.append(DatasetProblem(set_dir, "missing", f"view set {view_set!r} of object {key!r} does not exist"))
        return problems, 0
    outside = _outside(set_dir, expected)
    if outside is not None:
        return [*problems, outside], 0
    listed_paths = [image_path(directory, view_set, i) for i in range(count)]
    on_disk = {p.name for p in set_dir.glob("*.png")}
    for path in listed_paths:
        if path.name not in on_disk:
            problems.append(
                DatasetProblem(
                    path,
                    "view_count",
                    f"view {path.stem} of {count} listed in metadata.json is missing; the view set has "
                    f"{len(on_disk)} images",
                    count,
                    len(on_disk),
                )
            )
    for name in sorted(on_disk - {p.name for p in listed_paths}):
        problems.append(
            DatasetProblem(
                set_dir / name,
                "view_count",
                f"image not listed in metadata.json (which lists {count} views); the view set has {len(on_disk)} images",
                count,
                len(on_disk),
            )
        )
    files = 0
    for path in listed_paths:
        if path.name in on_disk:
            files += 1
            problem = _outside(path, expected) or _check_image(path, expected.image_size)
            if problem is not None:
                problems.append(problem)
    return problems, files


def _outside(path: Path, expected: _Expected) -> DatasetProblem | None:
    """An ``"outside"`` problem when ``path`` is a symlink that resolves to a place outside the dataset."""
    if not path.is_symlink():
        return None
    target = path.resolve()
    if target == expected.resolved_root or expected.resolved_root in target.parents:
        return None
    return DatasetProblem(path, "outside", f"a symlink leading out of the dataset, to {target}; not read")


def _not_regular(path: Path) -> DatasetProblem | None:
    """An ``"unreadable"`` problem when ``path`` (links followed) is not a regular file: a FIFO would block its
    reader forever, a device may never end; ``None`` when it is one or cannot be looked at (its reader says why)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode):
        return None
    return DatasetProblem(path, "unreadable", f"a regular file was expected, found {file_kind(mode)}; not read")


def _check_image(path: Path, size: int) -> DatasetProblem | None:
    """The problem of one image, if any: its size read from the header, then decoded in full, as the training
    loader decodes it (a picture of another size is not decoded); a FIFO or another file that is not a regular
    file is not opened."""
    special = _not_regular(path)
    if special is not None:
        return special
    try:
        with warnings.catch_warnings():  # PIL warns of a large header: its size is what is checked here
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(path)
        with image:
            width, height = image.size
            if (height, width) == (size, size):
                image.load()
    except Exception as err:  # whatever a decoder raises (Pillow has many kinds), the file is what is wrong
        return DatasetProblem(path, "unreadable", f"cannot read the image: {err}")
    if (height, width) != (size, size):
        return DatasetProblem(
            path, "image_size", "image of the wrong size (W x H)", f"{size}x{size}", f"{width}x{height}"
        )
    return None

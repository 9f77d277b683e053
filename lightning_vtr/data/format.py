"""The ShapeNet-VTR on-disk format (``docs/dataset_format.md``): paths, atomic writes, metadata and scanning.

The builder writes through these helpers and the DataModule reads through them, so the two cannot
disagree on a path or a field. Every reader validates what it reads and raises
:class:`DatasetFormatError` with a message naming the file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import atomic_write_json as _atomic_write_json
from lightning_vtr.utils.limits import read_json
from lightning_vtr.utils.paths import (
    UnsafeNameError,
    check_name,
    check_no_case_collisions,
    check_object_key,
    printable,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "IMAGE_SUFFIXES",
    "SHAPENET_SYNSETS",
    "SPLITS",
    "UP_AXES",
    "VIEW_SETS",
    "DatasetFormatError",
    "DatasetNotFoundError",
    "ObjectRecord",
    "atomic_write_json",
    "dataset_summary",
    "image_path",
    "load_metadata",
    "object_dir",
    "read_object",
    "read_object_json",
    "scan_dataset",
    "unsafe_names",
]

FORMAT_NAME = "lightning_vtr.shapenet_vtr"
FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
#: The up axes a source frame may have (``up_axis`` arguments): ``"y"`` (ShapeNet, glTF, ShapeNetVox32) is
#: converted into the package's ``"z"`` (:mod:`lightning_vtr.geometry`).
UP_AXES: tuple[str, ...] = ("y", "z")
#: The picture files the readers take (suffix, compared case-insensitively): image folders of
#: ``lightning-vtr predict``, folder test sets and background folders. PIL reads each of them.
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".webp", ".bmp")

#: The 13 ShapeNetCore synsets of 3D-R2N2 / Pix2Vox / ShapeNet-VTR and the category names used for them.
SHAPENET_SYNSETS: dict[str, str] = {
    "02691156": "airplane",
    "02828884": "bench",
    "02933112": "cabinet",
    "02958343": "car",
    "03001627": "chair",
    "03211117": "display",
    "03636649": "lamp",
    "03691459": "speaker",
    "04090263": "rifle",
    "04256520": "sofa",
    "04379243": "table",
    "04401088": "telephone",
    "04530566": "watercraft",
}


class DatasetFormatError(ValueError):
    """A dataset directory is missing, incomplete or of an unsupported version (the message names the file)."""

    #: ``lightning-vtr``'s exit status for it: a data error (see :mod:`lightning_vtr.errors`).
    exit_status = 1


class DatasetNotFoundError(DatasetFormatError):
    """The folder holds no ``metadata.json``: not a (finished) dataset, most likely the wrong path."""

    exit_status = 2  # a usage error


@dataclass
class ObjectRecord:
    """One object of a dataset, whatever its layout (ShapeNet-VTR or ShapeNetRendering).

    Attributes:
        category: category name.
        object_id: id within the category.
        split: ``"train"``, ``"val"`` or ``"test"``.
        voxel_path: its binvox file.
        mesh_path: its normalised mesh, when the layout has one.
        views: view-set name -> (image paths, ``(N, 2)`` (yaw, pitch) in degrees).
        voxel_up_axis: the up axis of the frame ``voxel_path`` was made in: ``"z"`` for files this package
            writes, ``"y"`` for ShapeNetVox32; pass it to :func:`lightning_vtr.data.binvox.read_binvox`.
        image_size: the side in pixels of the dataset's images, where the layout states it (``metadata.json``):
            the loaders refuse a larger picture before decoding it (:mod:`lightning_vtr.utils.limits`).
        resolution: the ``R`` of the dataset's voxel grids, where the layout states it: the loaders refuse a
            voxel file of another size before allocating it.
        root: the dataset's folder, resolved (``os.path.realpath``), where the layout has one: the loaders refuse
            an image or voxel file whose resolved path is not inside it (a symlink leading out of the dataset).

    Example:
        >>> directory = object_dir("data", "chair", "chair_0001")
        >>> record = ObjectRecord("chair", "chair_0001", "test", directory / "model.binvox", None)
        >>> record.key, record.voxel_path.as_posix()
        ('chair/chair_0001', 'data/objects/chair/chair_0001/model.binvox')
    """

    category: str
    object_id: str
    split: str
    voxel_path: Path
    mesh_path: Path | None
    views: dict[str, tuple[list[Path], np.ndarray]] = field(default_factory=dict)
    voxel_up_axis: str = "z"
    image_size: int | None = None
    resolution: int | None = None
    root: Path | None = None

    @property
    def key(self) -> str:
        """``"<category>/<object_id>"``, the key of ``metadata.json["objects"]``."""
        return f"{self.category}/{self.object_id}"


# ------------------------------------------------------------------------------------------ writing


def atomic_write_json(path: str | Path, payload: Any) -> None:
    """Write ``payload`` as JSON atomically (see :func:`lightning_vtr.utils.io.atomic_write_json`)."""
    _atomic_write_json(path, payload)


# ------------------------------------------------------------------------------------------ paths


def object_dir(root: str | Path, category: str, object_id: str) -> Path:
    """``<root>/objects/<category>/<object_id>``; the readers check both names before they call it."""
    return Path(root) / "objects" / category / object_id


def image_path(directory: str | Path, view_set: str, index: int) -> Path:
    """``<object dir>/<view_set>/<index:02d>.png``."""
    return Path(directory) / view_set / f"{index:02d}.png"


# ------------------------------------------------------------------------------------------ reading


def _read_json(path: Path) -> Any:
    try:
        return read_json(path)
    except OSError as err:
        raise DatasetFormatError(f"Cannot read {path}: {err}") from err
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"{path} is not valid JSON: {err}") from err


def _check_views(views: Any, source: Path, view_sets: tuple[str, ...] | list[str]) -> dict[str, np.ndarray]:
    if not isinstance(views, Mapping):
        raise DatasetFormatError(
            f"{source}: 'views' must map view-set names to viewpoint lists, got {type(views).__name__}"
        )
    out = {}
    for name in view_sets:
        if name not in views:
            raise DatasetFormatError(f"{source}: view set {name!r} is missing; it has {sorted(views)}")
        vp = np.asarray(views[name], dtype=np.float64)
        if vp.ndim != 2 or vp.shape[1] != 2 or not np.isfinite(vp).all():
            raise DatasetFormatError(
                f"{source}: view set {name!r} must be a list of finite [yaw, pitch] pairs, got shape {vp.shape}"
            )
        out[name] = vp
    return out


def read_object_json(directory: str | Path) -> dict:
    """Read and check ``<object dir>/object.json`` (category, object_id and the three view sets).

    Raises:
        DatasetFormatError: the file is missing, not JSON, lacks a field or holds bad viewpoints.
        UnsafeNameError: its category, object id or a view-set name is not a plain path component.
    """
    path = Path(directory) / "object.json"
    info = _read_json(path)
    if not isinstance(info, dict):
        raise DatasetFormatError(f"{path} must hold a JSON object, got {type(info).__name__}")
    missing = [k for k in ("category", "object_id", "views") if k not in info]
    if missing:
        raise DatasetFormatError(f"{path} lacks the fields {missing}")
    check_name(info["category"], source=path, entry="category")
    check_name(info["object_id"], source=path, entry="object_id")
    if isinstance(info["views"], Mapping):
        for name in info["views"]:
            check_name(name, source=path, entry="view set")
    _check_views(info["views"], path, list(info["views"]))
    return info


def unsafe_names(meta: Mapping[str, Any], source: str | Path) -> list[UnsafeNameError]:
    """Every name of a ``metadata.json`` that is not a plain path component, one error each.

    Checks the view-set names, the object keys (``'<category>/<object_id>'``, both plain) and that no two
    categories, or two object ids of one category, differ only in case (see :mod:`lightning_vtr.utils.paths`).

    Args:
        meta: the parsed ``metadata.json`` (with ``objects`` and ``view_sets``).
        source: the file it was read from (named in each message).

    Returns:
        One :class:`~lightning_vtr.utils.paths.UnsafeNameError` per bad name, in file order; empty when all
        names are safe.

    Example:
        >>> meta = {"view_sets": ["aligned"], "objects": {"chair/c0": {}, "chair/../../x": {}}}
        >>> [err.rule for err in unsafe_names(meta, "metadata.json")]
        ['dot']
    """
    found: list[UnsafeNameError] = []
    for name in meta.get("view_sets") or ():
        try:
            check_name(name, source=source, entry="view set")
        except UnsafeNameError as err:
            found.append(err)
    plain = []
    for key in meta.get("objects") or {}:
        try:
            check_object_key(key, source=source, entry="object key")
            plain.append(key)
        except UnsafeNameError as err:
            found.append(err)
    try:
        check_no_case_collisions(plain, source=source, entry="object key")
    except UnsafeNameError as err:
        found.append(err)
    return found


def load_metadata(root: str | Path, *, check_names: bool = True, check_entries: bool = True) -> dict:
    """Read and validate ``<root>/metadata.json``.

    Args:
        root: the dataset directory.
        check_names: refuse a view-set name or object key that is not a plain path component (see
            :func:`unsafe_names`); ``False`` leaves that to the caller (``verify_dataset`` lists them all).
        check_entries: refuse an object entry that is not a JSON object or has no valid ``split``; ``False``
            leaves that to the caller (``verify_dataset`` lists them all).

    Returns:
        The parsed file.

    Raises:
        DatasetFormatError: the file is missing (the message says how to build or finish the dataset),
            is not JSON, is of another format or of a newer version than this package reads.
        UnsafeNameError: (``check_names``) a name is not a plain path component; the message names the file,
            the entry and the rule.
    """
    path = Path(root) / "metadata.json"
    if not path.exists():  # one that is not a regular file (a FIFO, a folder) is refused by read_json
        hint = (
            "the build has not finished: re-run `lightning-vtr build-dataset` with the same options "
            "(or `lightning-vtr build-dataset ROOT --finalize` once every shard is done)"
            if (Path(root) / "objects").is_dir()
            else "build one with `lightning-vtr build-dataset ROOT`"
        )
        raise DatasetNotFoundError(f"{path} does not exist: {root} is not a complete ShapeNet-VTR dataset; {hint}.")
    meta = _read_json(path)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise DatasetFormatError(f"{path}: format is {found!r}, expected {FORMAT_NAME!r}")
    version = meta.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        expected = f"{FORMAT_VERSION}" if FORMAT_VERSION == 1 else f"1..{FORMAT_VERSION}"
        if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
            advice = "a newer lightning_vtr wrote it: upgrade lightning_vtr to read it"
        else:
            advice = "rebuild it with `lightning-vtr build-dataset`"
        raise DatasetFormatError(
            f"{path}: unsupported format version: expected {expected}, found {version!r}; {advice}"
        )
    missing = [k for k in ("objects", "view_sets", "resolution", "image_size") if k not in meta]
    if missing:
        raise DatasetFormatError(f"{path} lacks the fields {missing}")
    for name in ("resolution", "image_size"):
        value = meta[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise DatasetFormatError(f"{path}: {name!r} must be a positive integer, found {value!r}")
    if not isinstance(meta["objects"], Mapping) or not isinstance(meta["view_sets"], list):
        raise DatasetFormatError(
            f"{path}: 'objects' must be a JSON object and 'view_sets' a list, got "
            f"{type(meta['objects']).__name__} and {type(meta['view_sets']).__name__}"
        )
    if check_names:
        bad = unsafe_names(meta, path)
        if bad:
            raise bad[0]
    if check_entries:
        for key, info in meta["objects"].items():
            problem = _entry_problem(key, info)
            if problem is not None:
                raise DatasetFormatError(f"{path}: {problem}")
    return meta


def _entry_problem(key: str, info: Any) -> str | None:
    """What is wrong with the entry of object ``key`` in ``metadata.json["objects"]``, or ``None``."""
    if not isinstance(info, Mapping):
        return f"object {key!r} must map to a JSON object of fields, found {type(info).__name__}"
    split = info.get("split")
    if not isinstance(split, str) or split not in SPLITS:
        return f"object {key!r} has split {split!r}, expected one of {SPLITS}"
    return None


def _record(
    root: Path, key: str, info: Mapping, meta: Mapping[str, Any], source: Path, resolved_root: Path
) -> ObjectRecord:
    category, object_id = check_object_key(key, source=source, entry="object key")
    problem = _entry_problem(key, info)
    if problem is not None:
        raise DatasetFormatError(f"{source}: {problem}")
    split = info["split"]
    view_sets = list(meta["view_sets"])
    directory = object_dir(root, category, object_id)
    viewpoints = _check_views(info.get("views", {}), source, view_sets)
    views = {name: ([image_path(directory, name, i) for i in range(len(vp))], vp) for name, vp in viewpoints.items()}
    mesh = directory / "mesh.ply"
    return ObjectRecord(
        category=category,
        object_id=object_id,
        split=split,
        voxel_path=directory / "model.binvox",
        mesh_path=mesh if mesh.is_file() else None,
        views=views,
        image_size=int(meta["image_size"]),
        resolution=int(meta["resolution"]),
        root=resolved_root,
    )


def scan_dataset(root: str | Path, *, check_files: bool = False) -> list[ObjectRecord]:
    """All objects of a complete dataset as :class:`ObjectRecord` s, in the order of ``metadata.json``.

    Args:
        root: the dataset directory.
        check_files: also check that every voxel file and image exists (one ``stat`` per file).

    Returns:
        One record per object, each with the image paths and ``(N, 2)`` float64 viewpoints (yaw, pitch in
        degrees) of every view set of ``metadata.json``.

    Raises:
        DatasetFormatError: see :func:`load_metadata`; an object entry is malformed (bad split or view
            set); or a listed file is missing (``check_files``).
        UnsafeNameError: an object key or view-set name is not a plain path component (see
            :func:`unsafe_names`), checked before any object is read.

    Example::

        from lightning_vtr.data import scan_dataset

        records = scan_dataset("data/shapenet-vtr", check_files=True)
        test = [r for r in records if r.split == "test"]
        paths, viewpoints = test[0].views["spherical"]  # 24 image paths, (24, 2) (yaw, pitch) in degrees
    """
    root = Path(root)
    meta = load_metadata(root)
    source = root / "metadata.json"
    resolved = Path(os.path.realpath(root))  # once: the loaders check every file's resolved path against it
    records = [_record(root, key, info, meta, source, resolved) for key, info in meta["objects"].items()]
    if check_files:
        for r in records:
            for path in [r.voxel_path, *(p for paths, _ in r.views.values() for p in paths)]:
                if not path.is_file():
                    raise DatasetFormatError(f"{path} is listed in {source} but does not exist")
    return records


def read_object(root: str | Path, category: str, object_id: str) -> ObjectRecord:
    """One object of a complete dataset as an :class:`ObjectRecord` (split from ``metadata.json``).

    Raises:
        DatasetFormatError: the dataset is incomplete or does not list ``<category>/<object_id>``.
        UnsafeNameError: a name of ``metadata.json`` is not a plain path component.
    """
    root = Path(root)
    meta = load_metadata(root)
    key = f"{category}/{object_id}"
    if key not in meta["objects"]:
        raise DatasetFormatError(f"{root / 'metadata.json'} lists no object {key!r}")
    return _record(root, key, meta["objects"][key], meta, root / "metadata.json", Path(os.path.realpath(root)))


def dataset_summary(root: str | Path, *, check_entries: bool = True) -> str:
    """A table of object counts per category and split, plus the build options and failures.

    It joins no name to a path, so it reads a ``metadata.json`` with unsafe names too (``--verify`` lists them);
    names are shown through :func:`~lightning_vtr.utils.paths.printable`.

    Args:
        root: the dataset directory.
        check_entries: refuse a malformed object entry (see :func:`load_metadata`); ``False`` counts such
            entries in a line of their own (``--verify`` lists them).
    """
    root = Path(root)
    meta = load_metadata(root, check_names=False, check_entries=check_entries)
    counts: dict[str, dict[str, int]] = {}
    malformed = 0
    for key, info in meta["objects"].items():
        if _entry_problem(key, info) is not None:
            malformed += 1
            continue
        row = counts.setdefault(printable(str(key).split("/", 1)[0]), dict.fromkeys(SPLITS, 0))
        row[info["split"]] += 1
    width = max([len("category"), *map(len, counts)])
    lines = [
        f"ShapeNet-VTR dataset {root} (format version {meta['version']})",
        f"  source {printable(repr(meta.get('source')))}, {meta['image_size']} px, R={meta['resolution']}, "
        f"{meta.get('views_per_set')} views per set {list(meta['view_sets'])}, aligned pitch {meta.get('aligned_pitch')} deg",
        f"  {'category':<{width}}  {'train':>6} {'val':>6} {'test':>6} {'total':>6}",
    ]
    for category in sorted(counts):
        row = counts[category]
        lines.append(
            f"  {category:<{width}}  {row['train']:>6} {row['val']:>6} {row['test']:>6} {sum(row.values()):>6}"
        )
    totals = {s: sum(r[s] for r in counts.values()) for s in SPLITS}
    lines.append(
        f"  {'all':<{width}}  {totals['train']:>6} {totals['val']:>6} {totals['test']:>6} {sum(totals.values()):>6}"
    )
    if malformed:
        lines.append(f"  {malformed} object entry(ies) not a JSON object or without a valid split (not counted)")
    failed = meta.get("failed", [])
    if failed:
        lines.append(f"  {len(failed)} object(s) failed to build; see {root / 'errors.json'}")
    return "\n".join(lines)

"""The ShapeNet-VTR on-disk format (``docs/dataset_format.md``): paths, atomic writes, metadata and scanning."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "VIEW_SETS",
    "DatasetFormatError",
    "ObjectRecord",
    "atomic_write_json",
    "load_metadata",
    "object_dir",
    "read_object_json",
    "scan_dataset",
]

FORMAT_NAME = "lightning_vtr.shapenet_vtr"
FORMAT_VERSION = 1
VIEW_SETS = ("aligned", "hemispherical", "spherical")


class DatasetFormatError(ValueError):
    """A dataset directory is missing, incomplete or of an unsupported version (the message names the file)."""


@dataclass
class ObjectRecord:
    """One object of a dataset, whatever its layout.

    Attributes:
        category: category name.
        object_id: id within the category.
        split: ``"train"``, ``"val"`` or ``"test"``.
        voxel_path: its binvox file (in the package frame, +Z up).
        mesh_path: its normalised mesh, when the layout has one.
        views: view-set name -> (image paths, ``(N, 2)`` (yaw, pitch) degrees).
    """

    category: str
    object_id: str
    split: str
    voxel_path: Path
    mesh_path: Path | None
    views: dict[str, tuple[list[Path], np.ndarray]] = field(default_factory=dict)


def atomic_write_json(path: str | Path, payload: Any) -> None:
    """Write JSON so that readers see the old file or the whole new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(payload, indent=1))
    os.replace(tmp, path)


def object_dir(root: str | Path, category: str, object_id: str) -> Path:
    return Path(root) / "objects" / category / object_id


def read_object_json(directory: str | Path) -> dict:
    path = Path(directory) / "object.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DatasetFormatError(f"Cannot read {path}: {err}") from err


def load_metadata(root: str | Path) -> dict:
    """Read and validate ``<root>/metadata.json``."""
    path = Path(root) / "metadata.json"
    if not path.is_file():
        hint = (
            "the build has not finished: re-run `lightning-vtr build-dataset` (or `--finalize` after sharded builds)"
            if (Path(root) / "objects").is_dir()
            else "build one with `lightning-vtr build-dataset OUT`"
        )
        raise DatasetFormatError(f"{path} does not exist: {root} is not a complete ShapeNet-VTR dataset; {hint}.")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"{path} is not valid JSON: {err}") from err
    if meta.get("format") != FORMAT_NAME:
        raise DatasetFormatError(f"{path}: format is {meta.get('format')!r}, expected {FORMAT_NAME!r}")
    if int(meta.get("version", -1)) > FORMAT_VERSION or int(meta.get("version", -1)) < 1:
        raise DatasetFormatError(
            f"{path}: format version {meta.get('version')!r}; this lightning_vtr reads versions 1..{FORMAT_VERSION}"
        )
    return meta


def scan_dataset(root: str | Path) -> list[ObjectRecord]:
    """All objects of a complete dataset as :class:`ObjectRecord` s (order of ``metadata.json``)."""
    root = Path(root)
    meta = load_metadata(root)
    view_sets = meta.get("view_sets", list(VIEW_SETS))
    records = []
    for key, info in meta["objects"].items():
        category, object_id = key.split("/", 1)
        directory = object_dir(root, category, object_id)
        views = {}
        for name in view_sets:
            viewpoints = np.asarray(info["views"][name], dtype=np.float64).reshape(-1, 2)
            views[name] = ([directory / name / f"{i:02d}.png" for i in range(len(viewpoints))], viewpoints)
        mesh = directory / "mesh.ply"
        records.append(
            ObjectRecord(
                category=category,
                object_id=object_id,
                split=info["split"],
                voxel_path=directory / "model.binvox",
                mesh_path=mesh if mesh.is_file() else None,
                views=views,
            )
        )
    return records

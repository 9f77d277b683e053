"""Reader for the layout users already have: 3D-R2N2's ShapeNetRendering + ShapeNetVox32 + a Pix2Vox split file.

Layout::

    <rendering_root>/<taxonomy>/<model>/rendering/00.png .. 23.png
    <rendering_root>/<taxonomy>/<model>/rendering/rendering_metadata.txt   # one line per image
    <voxel_root>/<taxonomy>/<model>/model.binvox                           # 32^3, made in ShapeNet's +Y-up frame
    <split_file>: [{"taxonomy_id": "02691156", "taxonomy_name": "aeroplane",
                    "train": [...], "val": [...], "test": [...]}, ...]

Each ``rendering_metadata.txt`` line is ``azimuth elevation in_plane_rotation distance_ratio fov``
(degrees, except the distance ratio, which scales 3D-R2N2's maximum camera distance of 1.75).

Viewpoint conversion (``yaw = -azimuth`` wrapped to ``[-180, 180)``, ``pitch = elevation``), reasoned from
how 3D-R2N2 rendered (its released Blender renderer):

1. The ShapeNet OBJ is imported with Blender's default axes (forward ``-Z``, up ``Y``), which maps an
   OBJ point ``(x, y, z)`` to Blender's ``(x, -z, y)``. That is exactly
   :func:`lightning_vtr.data.mesh.convert_up_axis` (``up_axis="y"``), so Blender's world frame *is* the
   package's +Z-up frame, and ShapeNetVox32 read with ``up_axis="y"`` lands in it too.
2. The camera sits at ``(d, 0, 0)`` on an empty parent at the origin whose XYZ Euler rotation is
   ``(-in_plane, -elevation, -azimuth)``; Blender applies it as ``Rz(-azimuth) Ry(-elevation) Rx(-in_plane)``.
   ``Ry(-elevation)`` lifts ``(d, 0, 0)`` to ``d (cos e, 0, sin e)`` and ``Rz(-azimuth)`` turns it to
   ``d (cos e cos a, -cos e sin a, sin e)``.
3. The package's camera centre is ``r (cos p cos y, cos p sin y, sin p)``
   (:mod:`lightning_vtr.geometry`), hence ``p = e`` and ``y = -a``: 3D-R2N2's azimuth turns clockwise
   seen from above, the package's yaw counter-clockwise. (Mesh R-CNN's and PyTorch3D's R2N2 camera
   matrices negate the azimuth the same way.)

The in-plane rotation (camera roll) is 0 in the released data; the package's viewpoints have no roll,
so a non-zero value is reported with a warning and otherwise ignored.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from lightning_vtr.data.format import SHAPENET_SYNSETS, SPLITS, DatasetFormatError, ObjectRecord
from lightning_vtr.geometry import wrap_yaw
from lightning_vtr.utils.limits import read_json
from lightning_vtr.utils.paths import check_name, check_no_case_collisions
from lightning_vtr.utils.validation import check_choice

__all__ = [
    "R2N2_MAX_CAMERA_DISTANCE",
    "ShapeNetRenderingSource",
    "r2n2_to_viewpoints",
    "read_rendering_metadata",
    "read_split_file",
]

#: 3D-R2N2's ``cfg.RENDERING.MAX_CAMERA_DIST``: the camera distance is ``distance_ratio`` times this.
R2N2_MAX_CAMERA_DISTANCE = 1.75

#: The view-set name this layout's renders are served under (they are the paper's "Aligned" kind).
VIEW_SET = "aligned"


def r2n2_to_viewpoints(azimuth: np.ndarray | Sequence[float], elevation: np.ndarray | Sequence[float]) -> np.ndarray:
    """Convert 3D-R2N2 (azimuth, elevation) in degrees to package viewpoints ``(N, 2)`` (yaw, pitch) in degrees.

    ``yaw = -azimuth`` wrapped into ``[-180, 180)``, ``pitch = elevation`` (see the module docstring).
    """
    azimuth = np.asarray(azimuth, dtype=np.float64).reshape(-1)
    elevation = np.asarray(elevation, dtype=np.float64).reshape(-1)
    if azimuth.shape != elevation.shape:
        raise ValueError(
            f"`azimuth` and `elevation` must have the same length, got {azimuth.shape} and {elevation.shape}"
        )
    if np.any(np.abs(elevation) > 90.0):
        raise ValueError(f"`elevation` must be within [-90, 90] degrees, got values up to {np.abs(elevation).max()}")
    yaw = wrap_yaw(-azimuth).numpy()
    return np.stack([yaw, elevation], axis=-1)


def read_rendering_metadata(path: str | Path) -> np.ndarray:
    """Read a ``rendering_metadata.txt``: ``(N, 5)`` float64 rows (azimuth, elevation, in-plane, distance ratio, fov).

    Raises:
        DatasetFormatError: the file is missing, empty, or a line does not hold 5 numbers (names file and line).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise DatasetFormatError(f"Cannot read {path}: {err}") from err
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            values = []
        if len(values) != 5:
            raise DatasetFormatError(
                f"{path}, line {number}: expected 5 numbers (azimuth elevation in-plane distance fov), got {line.strip()!r}"
            )
        rows.append(values)
    if not rows:
        raise DatasetFormatError(f"{path} lists no views")
    return np.asarray(rows, dtype=np.float64)


def read_split_file(path: Path) -> list[dict]:
    """The entries of a ShapeNet split file (3D-R2N2's JSON layout), checked.

    Args:
        path: a JSON list of ``{"taxonomy_id", "taxonomy_name"?, "train"?, "val"?, "test"?}`` entries.

    Returns:
        The entries as read; every taxonomy id and name and every model id is a safe file name.

    Raises:
        DatasetFormatError: naming the file, when it cannot be read, is not JSON, is not a list, or an entry
            lacks ``taxonomy_id`` or holds a name that is not a safe path component.
    """
    try:
        entries = read_json(path)
    except OSError as err:
        raise DatasetFormatError(f"Cannot read the split file {path}: {err}") from err
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"The split file {path} is not valid JSON: {err}") from err
    if not isinstance(entries, list):
        raise DatasetFormatError(f"The split file {path} must hold a list of taxonomies, got {type(entries).__name__}")
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or "taxonomy_id" not in entry:
            raise DatasetFormatError(f"The split file {path}: entry {i} has no 'taxonomy_id'")
        # Every name becomes a path component (of the inputs read and of the outputs written for them).
        check_name(str(entry["taxonomy_id"]), source=path, entry=f"entry {i} taxonomy_id")
        if entry.get("taxonomy_name"):
            check_name(str(entry["taxonomy_name"]), source=path, entry=f"entry {i} taxonomy_name")
        for split in SPLITS:
            models = [str(m) for m in entry.get(split) or ()]
            for model in models:
                check_name(model, source=path, entry=f"{entry['taxonomy_id']} {split} model")
            check_no_case_collisions(models, source=path, entry=f"{entry['taxonomy_id']} {split} model")
    return entries


class ShapeNetRenderingSource:
    """The objects of a ShapeNetRendering / ShapeNetVox32 download as :class:`ObjectRecord` s.

    Each record has one view set, ``"aligned"`` (the 24 renders with their converted viewpoints), and
    ``voxel_up_axis="y"``: read its voxels with ``read_binvox(record.voxel_path, up_axis=record.voxel_up_axis)``.

    Args:
        rendering_root: the ``ShapeNetRendering`` directory.
        voxel_root: the ``ShapeNetVox32`` directory.
        split_file: a Pix2Vox-style JSON split file.
        categories: keep only these categories (names or taxonomy ids); ``None``: all in the split file.
        missing: what to do with a listed model whose files are absent: ``"warn"`` (skip it and warn
            once with the count), ``"skip"`` (silently) or ``"error"``.

    Category names are the split file's ``taxonomy_name`` (Pix2Vox: "aeroplane", "watercraft", ...), or
    :data:`~lightning_vtr.data.format.SHAPENET_SYNSETS`'s name, or the taxonomy id.

    Raises:
        FileNotFoundError: a root is not a directory, or ``split_file`` does not exist.
        ValueError: ``missing`` is not ``"warn"``, ``"skip"`` or ``"error"``.

    Example::

        records = list(ShapeNetRenderingSource("ShapeNetRendering", "ShapeNetVox32", "ShapeNet.json"))
        paths, viewpoints = records[0].views["aligned"]   # 24 PNG paths, (24, 2) (yaw, pitch) degrees
    """

    def __init__(
        self,
        rendering_root: str | Path,
        voxel_root: str | Path,
        split_file: str | Path,
        *,
        categories: Sequence[str] | None = None,
        missing: str = "warn",
    ) -> None:
        self.rendering_root = Path(rendering_root)
        self.voxel_root = Path(voxel_root)
        self.split_file = Path(split_file)
        check_choice("missing", missing, ("warn", "skip", "error"))
        for name, path in (("rendering_root", self.rendering_root), ("voxel_root", self.voxel_root)):
            if not path.is_dir():
                raise FileNotFoundError(f"`{name}` {str(path)!r} is not a directory")
        if not self.split_file.is_file():
            raise FileNotFoundError(f"`split_file` {str(self.split_file)!r} does not exist")
        self.categories = tuple(categories) if categories is not None else None
        self.missing = missing
        self._records: list[ObjectRecord] | None = None

    def _category(self, entry: dict) -> str:
        tid = str(entry["taxonomy_id"])
        return str(entry.get("taxonomy_name") or SHAPENET_SYNSETS.get(tid, tid))

    def _object(self, taxonomy: str, category: str, model: str, split: str) -> ObjectRecord | str:
        """The record, or a reason why the model cannot be used."""
        render_dir = self.rendering_root / taxonomy / model / "rendering"
        meta_path = render_dir / "rendering_metadata.txt"
        voxel_path = self.voxel_root / taxonomy / model / "model.binvox"
        if not meta_path.is_file():
            return f"{meta_path} does not exist"
        if not voxel_path.is_file():
            return f"{voxel_path} does not exist"
        meta = read_rendering_metadata(meta_path)
        if np.any(meta[:, 2] != 0):
            warnings.warn(
                f"{meta_path}: non-zero in-plane rotations are ignored (viewpoints have no roll)", stacklevel=3
            )
        images = [render_dir / f"{i:02d}.png" for i in range(len(meta))]
        absent = [p for p in images if not p.is_file()]
        if absent:
            return f"{absent[0]} does not exist ({len(absent)} of {len(images)} renders missing)"
        return ObjectRecord(
            category=category,
            object_id=model,
            split=split,
            voxel_path=voxel_path,
            mesh_path=None,
            views={VIEW_SET: (images, r2n2_to_viewpoints(meta[:, 0], meta[:, 1]))},
            voxel_up_axis="y",
        )

    def records(self) -> list[ObjectRecord]:
        """Every usable object, sorted by (category, object_id).

        Raises:
            DatasetFormatError: a malformed split or metadata file, or (``missing="error"``) an absent file.
            ValueError: ``categories`` names a category the split file does not have.
        """
        if self._records is not None:
            return self._records
        entries = read_split_file(self.split_file)
        if self.categories is not None:
            known = {self._category(e) for e in entries} | {str(e["taxonomy_id"]) for e in entries}
            unknown = sorted(set(self.categories) - known)
            if unknown:
                raise ValueError(
                    f"`categories` must be in the split file {self.split_file} (it has {sorted(known)}), "
                    f"got unknown {unknown}"
                )
        records, skipped = [], []
        for entry in entries:
            taxonomy, category = str(entry["taxonomy_id"]), self._category(entry)
            if self.categories is not None and not {taxonomy, category} & set(self.categories):
                continue
            for split in SPLITS:
                for model in entry.get(split, []):
                    result = self._object(taxonomy, category, str(model), split)
                    if isinstance(result, str):
                        if self.missing == "error":
                            raise DatasetFormatError(f"{self.split_file} lists {taxonomy}/{model}, but {result}")
                        skipped.append(result)
                    else:
                        records.append(result)
        if skipped and self.missing == "warn":
            warnings.warn(
                f"Skipped {len(skipped)} model(s) listed in {self.split_file} whose files are missing, e.g. {skipped[0]}",
                stacklevel=2,
            )
        self._records = sorted(records, key=lambda r: (r.category, r.object_id))
        return self._records

    def __iter__(self) -> Iterator[ObjectRecord]:
        return iter(self.records())

    def __len__(self) -> int:
        return len(self.records())

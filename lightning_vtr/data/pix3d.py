"""Pix3D (Sun et al., CVPR 2018): real photographs with masks, poses and voxels, read as a test set.

Layout (paths in ``pix3d.json`` are relative to the Pix3D root)::

    <root>/pix3d.json                    # a list of records, one per photograph
    <root>/img/<category>/0001.jpg       # the photograph (JPEG or PNG; RGB, grey or RGBA)
    <root>/mask/<category>/0001.png      # the object's mask, same size
    <root>/model/<category>/<model>/voxel.mat   # MATLAB file, variable "voxel": 128^3 uint8 occupancy

A record holds ``img``, ``mask``, ``voxel``, ``model``, ``category``, ``bbox`` ``[x0, y0, x1, y1]``,
``img_size`` ``[w, h]``, ``rot_mat`` (3 x 3), ``trans_mat`` (3), ``focal_length``, ``cam_position``,
``inplane_rotation``, ``truncated``, ``occluded``, ``slightly_occluded``. :func:`read_pix3d` checks every key
it uses and names the file, the record and the key when one is wrong.

**Frames.** Three frames are involved; the facts come from Pix3D's README and its rendering script
(``demo.py``), and the voxel axis order from Mesh R-CNN's Pix3D voxel reader, which rotates ``voxel.mat`` into
the model frame before applying ``rot_mat`` to it:

1. *Model frame* (``model.obj``): ``+x`` leftward, ``+y`` up, ``+z`` inward in Pix3D's canonical view, i.e.
   the object's front faces ``-z``. ``rot_mat`` and ``trans_mat`` act on this frame: ``demo.py`` sets the
   object's world matrix to ``T @ R`` (overwriting the OBJ importer's axis conversion) and renders with a
   camera at the origin whose Euler rotation is ``(0, pi, 0)``: it looks along world ``+Z``, its up is
   world ``+Y`` and its right is world ``-X``. So with ``w = R p + t``, image right is ``-w_x``, image up is
   ``+w_y`` and depth is ``+w_z``; in OpenGL camera coordinates (x right, y up, looking along -z)
   ``c = diag(-1, 1, -1) (R p + t)`` (:data:`BLENDER_TO_CAMERA`).
2. *Voxel frame* (``voxel.mat``): ``+x`` leftward, ``+y`` outward, ``+z`` up, and ``voxel[i, j, k]`` indexes
   ``(x, y, z)`` with increasing coordinates. Hence ``(x_v, y_v, z_v) = (x_m, -z_m, y_m)`` (the same
   +Y-up -> +Z-up rotation :func:`lightning_vtr.data.mesh.convert_up_axis` applies to ShapeNet) and
   :data:`VOXEL_TO_MODEL` is its inverse, ``(x_m, y_m, z_m) = (x_v, z_v, -y_v)``. Mesh R-CNN's
   ``np.rot90(voxel, k=3, axes=(1, 2))`` before using the indices as model coordinates is exactly that map.
3. *Package frame* (:mod:`lightning_vtr.geometry`): ``+Z`` up, the object's front facing ``+X`` (the
   procedural dataset's and the ShapeNet conversion's canonical pose, so a camera at yaw 0 sees the front).
   Pix3D's front is ``+y_v`` (outward, toward the canonical camera) and its ``+x_v`` is the viewer's left,
   so ``(X, Y, Z) = (y_v, -x_v, z_v)``: a quarter turn about ``+Z`` (:data:`VOXEL_TO_PACKAGE`).
   ``yaw_offset`` adds a further turn about ``+Z`` (multiples of 90 degrees) for models whose training
   objects faced elsewhere.

**What the frame check checks.** :func:`lightning_vtr.evaluation.pix3d.frame_check` projects the record's
voxels with its ``rot_mat``, ``trans_mat`` and ``focal_length`` and compares the silhouette with the mask. It
tests items 1 and 2, i.e. that ``voxel.mat`` and ``rot_mat`` are combined the right way round: a swapped or
mirrored voxel axis, a transposed rotation or a mirrored image lowers the IoU. Item 3 is a convention no
photograph can check (a turn applied to both the voxels and the camera cancels); :attr:`Pix3DDataset.yaw_offset`
exists for it.

**Images.** :func:`crop_to_bbox` cuts a square around the annotated box: side ``(1 + 2 margin)`` times the
box's longer side, centred on the box (``margin = 0.1`` by default, so the object spans about 83 % of the
crop, as it spans most of a ShapeNetRendering view). Pixels outside the photograph are transparent and,
with ``use_mask=True``, so is everything the mask excludes, so the model's transform composites the object
on the background it was trained with (240 grey for the Pix2Vox++/LRGT recipes, white for ``plain``);
``background`` composites here instead. (Pix2Vox's Pix3D loader crops the same kind of square without a
margin, pads by repeating edge pixels and keeps the photograph's own background.)

**Voxels.** :func:`downsample_voxels` takes ``voxel.mat`` to the model's resolution. With ``fit=True`` (the
default) it first fits the object's bounding box, padded to a centred cube, to the grid, as Pix3D's own
evaluation does and as this package normalises meshes (longest side = the grid); ``pooling="max"`` (default)
marks a cell occupied when any source voxel in it is (Pix3D's evaluation max-pools for the same reason: chair
legs a few 128^3 voxels thick survive), ``"mean"`` when at least half of them are (thinner, loses thin parts).

**Evaluation.** :class:`Pix3DDataset` returns ``VTRDataset``'s batch dictionaries (one view per item), so
:func:`~lightning_vtr.evaluation.dataset.evaluate_dataset` and a model's ``test_step`` take it;
:func:`lightning_vtr.evaluation.pix3d.evaluate_pix3d` is the loop, ``lightning-vtr pix3d`` the command (Table 5
layout). By default the
photographs Pix3D's own evaluation list keeps are used: not truncated, not occluded, not slightly occluded.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from lightning_vtr.data.dataset import apply_image_transform
from lightning_vtr.data.format import DatasetFormatError
from lightning_vtr.data.shapenet_rendering import read_split_file
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.utils.limits import open_image, read_json
from lightning_vtr.utils.paths import check_name, check_no_case_collisions, check_relative_path
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "BLENDER_TO_CAMERA",
    "PIX3D_ANNOTATIONS",
    "POOLINGS",
    "VOXEL_TO_MODEL",
    "VOXEL_TO_PACKAGE",
    "Pix3DDataset",
    "Pix3DRecord",
    "camera_rotation",
    "crop_to_bbox",
    "downsample_voxels",
    "load_voxel_mat",
    "pix3d_viewpoint",
    "read_pix3d",
    "read_pix3d_image",
    "read_pix3d_mask",
    "rotate_grid",
    "yaw_rotation",
]

#: The annotation file at the Pix3D root.
PIX3D_ANNOTATIONS = "pix3d.json"
#: ``voxel.mat``'s ``(x_v, y_v, z_v)`` -> model frame ``(x_m, y_m, z_m) = (x_v, z_v, -y_v)``.
VOXEL_TO_MODEL = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
#: ``voxel.mat``'s ``(x_v, y_v, z_v)`` -> package frame ``(X, Y, Z) = (y_v, -x_v, z_v)`` (front to +X).
VOXEL_TO_PACKAGE = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
#: Pix3D's render world frame (``demo.py``'s camera at the origin, Euler ``(0, pi, 0)``) -> OpenGL camera
#: coordinates (x right, y up, looking along -z).
BLENDER_TO_CAMERA = np.diag([-1, 1, -1])
#: The down-sampling rules of :func:`downsample_voxels`.
POOLINGS = ("max", "mean")
_REQUIRED = ("img", "mask", "voxel", "category", "bbox", "img_size", "rot_mat", "trans_mat")
_HIDDEN = ("truncated", "occluded", "slightly_occluded")


def yaw_rotation(degrees: int) -> np.ndarray:
    """The integer rotation by ``degrees`` (a multiple of 90) about ``+Z``, counter-clockwise seen from above."""
    degrees = check_int("yaw_offset", degrees)
    if degrees % 90:
        raise ValueError(f"`yaw_offset` must be a multiple of 90 degrees, got {degrees}")
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][(degrees // 90) % 4]
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rotate_grid(grid: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Re-index a cubic grid under a signed permutation ``rotation`` of its centred cell coordinates.

    Cell ``(i, j, k)`` of an ``N^3`` grid has its centre at ``((i + 0.5) / N - 0.5, ...)``; the result holds at
    the cell whose centre is ``rotation @ centre`` what ``grid`` holds at ``centre`` (so a ``-1`` entry flips
    an axis and an off-diagonal ``1`` moves one). ``rotation`` may be a mirror (determinant -1).

    Example:
        >>> g = np.zeros((2, 2, 2), bool); g[1, 0, 0] = True        # centre (0.25, -0.25, -0.25)
        >>> np.argwhere(rotate_grid(g, yaw_rotation(90))).tolist()  # +90 deg about Z: (0.25, 0.25, -0.25)
        [[1, 1, 0]]
    """
    rotation = np.asarray(rotation)
    if (
        rotation.shape != (3, 3)
        or not np.array_equal(np.abs(rotation).sum(0), [1, 1, 1])
        or not (np.array_equal(np.abs(rotation).sum(1), [1, 1, 1]) and set(np.unique(rotation)) <= {-1, 0, 1})
    ):
        raise ValueError(f"`rotation` must be a 3x3 signed permutation matrix, got {rotation.tolist()}")
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise ValueError(f"`grid` must be a cubic 3-D array, got shape {grid.shape}")
    sources = [int(np.flatnonzero(row)[0]) for row in rotation]
    out = grid.transpose(sources)
    flips = [axis for axis, row in enumerate(rotation) if row[sources[axis]] < 0]
    return np.ascontiguousarray(np.flip(out, axis=tuple(flips)) if flips else out)


# ---------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Pix3DRecord:
    """One Pix3D photograph and what :func:`read_pix3d` checked about it.

    Attributes:
        index: its position in ``pix3d.json``.
        category: the category (``"chair"``).
        object_id: the photograph's file stem (``"0001"``).
        model_id: the 3D model's folder name (``"IKEA_POANG_1"``).
        image_path: the photograph, an absolute path.
        mask_path: the object's mask, an absolute path.
        voxel_path: the model's ``voxel.mat``, an absolute path.
        bbox: ``(x0, y0, x1, y1)``, pixel indices of the box's first and last columns and rows.
        image_size: ``(width, height)`` in pixels.
        rotation: ``rot_mat``, ``(3, 3)`` float64.
        translation: ``trans_mat``, ``(3,)`` float64.
        camera_position: ``cam_position`` ``(3,)`` (model frame) when the record has one.
        focal_length: ``focal_length`` in mm (on a 32 mm wide sensor) when the record has one.
        truncated: Pix3D's flag: the object is cut by the photograph's border.
        occluded: Pix3D's flag: the object is occluded.
        slightly_occluded: Pix3D's flag: the object is slightly occluded.

    Example:
        >>> root = Path("/data/pix3d")
        >>> record = Pix3DRecord(
        ...     0, "chair", "0001", "IKEA_POANG_1", root / "img/chair/0001.jpg", root / "mask/chair/0001.png",
        ...     root / "model/chair/IKEA_POANG_1/voxel.mat", (10.0, 20.0, 200.0, 300.0), (640, 480),
        ...     np.eye(3), np.array([0.0, 0.0, 2.0]),
        ... )
        >>> record.key, record.hidden
        ('chair/0001', False)
    """

    index: int
    category: str
    object_id: str
    model_id: str
    image_path: Path
    mask_path: Path
    voxel_path: Path
    bbox: tuple[float, float, float, float]
    image_size: tuple[int, int]
    rotation: np.ndarray
    translation: np.ndarray
    camera_position: np.ndarray | None = None
    focal_length: float | None = None
    truncated: bool = False
    occluded: bool = False
    slightly_occluded: bool = False

    @property
    def key(self) -> str:
        """``"<category>/<object_id>"``, the sample name of Pix2Vox's Pix3D split file."""
        return f"{self.category}/{self.object_id}"

    @property
    def hidden(self) -> bool:
        """Truncated, occluded or slightly occluded (what Pix3D's evaluation list leaves out)."""
        return self.truncated or self.occluded or self.slightly_occluded


def _numbers(value: Any, shape: tuple[int, ...], where: str, key: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != shape or not np.isfinite(array).all():
        got = array.shape if array is not None else type(value).__name__
        raise DatasetFormatError(f"{where}: key {key!r} must be {_what(shape)}, got {value!r} (shape {got})")
    return array


def _what(shape: tuple[int, ...]) -> str:
    return "a finite number" if not shape else f"{'x'.join(map(str, shape))} finite numbers"


def _flag(value: Any, where: str, key: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    raise DatasetFormatError(f"{where}: key {key!r} must be true or false, got {value!r}")


def _record(root: Path, index: int, entry: Any, annotations: Path) -> Pix3DRecord:
    where = f"{annotations}, record {index}"
    if not isinstance(entry, dict):
        raise DatasetFormatError(f"{where}: expected an object with keys {list(_REQUIRED)}, got {type(entry).__name__}")
    absent = [k for k in _REQUIRED if k not in entry]
    if absent:
        raise DatasetFormatError(
            f"{where} ({entry.get('img', '?')}): missing key(s) {absent}; expected {list(_REQUIRED)}"
        )
    where = f"{annotations}, record {index} ({entry['img']})"
    bbox = _numbers(entry["bbox"], (4,), where, "bbox")
    if not (bbox[2] >= bbox[0] and bbox[3] >= bbox[1]):
        raise DatasetFormatError(
            f"{where}: key 'bbox' must be [x0, y0, x1, y1] with x1 >= x0 and y1 >= y0, got {entry['bbox']}"
        )
    size = _numbers(entry["img_size"], (2,), where, "img_size")
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise DatasetFormatError(
            f"{where}: key 'img_size' must be [width, height], two positive ints, got {entry['img_size']}"
        )
    rotation = _numbers(entry["rot_mat"], (3, 3), where, "rot_mat")
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > 1e-3 or np.linalg.det(rotation) < 0:
        raise DatasetFormatError(
            f"{where}: key 'rot_mat' must be a rotation (orthonormal, determinant +1), got {entry['rot_mat']} "
            f"(|R^T R - I| = {error:.2g}, det = {np.linalg.det(rotation):.3g})"
        )
    translation = _numbers(entry["trans_mat"], (3,), where, "trans_mat")
    camera = entry.get("cam_position")
    camera = None if camera is None else _numbers(camera, (3,), where, "cam_position")
    focal = entry.get("focal_length")
    if focal is not None:
        focal = float(_numbers(focal, (), where, "focal_length"))
        if focal <= 0:
            raise DatasetFormatError(f"{where}: key 'focal_length' must be a positive number (mm), got {focal!r}")
    flags = {k: _flag(entry.get(k, False), where, k) for k in _HIDDEN}
    # Every name becomes a path: the files read stay under `root`, the outputs written for them under theirs.
    for key in ("img", "mask", "voxel"):
        check_relative_path(str(entry[key]), source=where, entry=f"key {key!r}")
    image = Path(str(entry["img"]))
    voxel = Path(str(entry["voxel"]))
    category = check_name(str(entry["category"]), source=where, entry="key 'category'")
    check_name(image.stem, source=where, entry="image name (key 'img')")
    return Pix3DRecord(
        index=index,
        category=category,
        object_id=image.stem,
        model_id=voxel.parent.name,
        image_path=root / image,
        mask_path=root / str(entry["mask"]),
        voxel_path=root / voxel,
        bbox=tuple(float(v) for v in bbox),  # type: ignore[arg-type]  # _numbers checked it has 4 numbers
        image_size=(int(size[0]), int(size[1])),
        rotation=rotation,
        translation=translation,
        camera_position=camera,
        focal_length=focal,
        **flags,
    )


def read_pix3d(
    root: str | Path,
    *,
    categories: Sequence[str] | None = None,
    include_hidden: bool = False,
    split_file: str | Path | None = None,
    split: str = "test",
    annotations: str | Path = PIX3D_ANNOTATIONS,
    missing: str = "warn",
) -> list[Pix3DRecord]:
    """The photographs of a Pix3D copy, checked, in ``pix3d.json`` order.

    Args:
        root: the Pix3D root (holds ``pix3d.json``, ``img/``, ``mask/``, ``model/``).
        categories: keep only these categories (``None``: all).
        include_hidden: also keep truncated, occluded and slightly occluded photographs (Pix3D's own
            evaluation list, 2,894 chair images, leaves them out).
        split_file: a Pix2Vox-style split JSON (``[{"taxonomy_name": "chair", "test": ["0011", ...]}]``): keep
            only the photographs ``<category>/<stem>`` it lists under ``split``.
        split: the split of ``split_file``.
        annotations: the annotation file, relative to ``root`` unless absolute.
        missing: a record whose image, mask or voxel file is absent: ``"warn"`` (skip, warn once with the
            count), ``"skip"`` or ``"error"``.

    Returns:
        The kept records, in ``pix3d.json`` order.

    Raises:
        FileNotFoundError: ``root``, the annotation file or ``split_file`` is absent; (``missing="error"``) a
            listed file is.
        DatasetFormatError: the annotation file is not a JSON list, or a record lacks a key or holds a bad
            value (the message names the file, the record, the key, what was expected and what it held).
        ValueError: ``categories`` names a category the file does not have, or ``missing`` is not one of
            ``"warn"``, ``"skip"``, ``"error"``.

    Example::

        from lightning_vtr.data import read_pix3d

        records = read_pix3d("data/pix3d", categories=["chair"])  # the unoccluded, untruncated chair photographs
        print(len(records), records[0].key, records[0].image_path)
    """
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"`root` must be the Pix3D directory, got {str(root)!r} (not a directory)")
    check_choice("missing", missing, ("warn", "skip", "error"))
    path = root / annotations
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r} does not exist: `root` must hold Pix3D's {PIX3D_ANNOTATIONS}")
    try:
        entries = read_json(path)
    except json.JSONDecodeError as err:
        raise DatasetFormatError(f"{path} is not valid JSON: {err}") from err
    if not isinstance(entries, list):
        raise DatasetFormatError(f"{path} must hold a list of records, got {type(entries).__name__}")
    records = [_record(root, i, entry, path) for i, entry in enumerate(entries)]
    check_no_case_collisions(list(dict.fromkeys(r.key for r in records)), source=path, entry="photograph")
    if categories is not None:
        known = sorted({r.category for r in records})
        unknown = sorted(set(categories) - set(known))
        if unknown:
            raise ValueError(f"`categories` must be categories of {path} ({known}), got unknown {unknown}")
        records = [r for r in records if r.category in set(categories)]
    if split_file is not None:
        split_path = Path(split_file).expanduser()
        if not split_path.is_file():
            raise FileNotFoundError(f"`split_file` {str(split_path)!r} does not exist")
        listed = {
            f"{e.get('taxonomy_name') or e['taxonomy_id']}/{s}"
            for e in read_split_file(split_path)
            for s in e.get(split, [])
        }
        records = [r for r in records if r.key in listed]
    if not include_hidden:
        records = [r for r in records if not r.hidden]
    kept, absent = [], []
    for record in records:
        lost = next((p for p in (record.image_path, record.mask_path, record.voxel_path) if not p.is_file()), None)
        if lost is None:
            kept.append(record)
        elif missing == "error":
            raise FileNotFoundError(
                f"{path}, record {record.index} ({record.key}) names {str(lost)!r}, which does not exist"
            )
        else:
            absent.append(str(lost))
    if absent and missing == "warn":
        warnings.warn(f"Skipped {len(absent)} Pix3D record(s) whose files are missing, e.g. {absent[0]}", stacklevel=2)
    return kept


# ---------------------------------------------------------------------------------------------- voxels
def load_voxel_mat(path: str | Path, variable: str = "voxel") -> np.ndarray:
    """``voxel.mat``'s grid as stored (voxel frame, see the module docstring), as bool.

    Raises:
        DatasetFormatError: unreadable file, no ``variable`` in it, or not a cubic 3-D grid (names the file).
    """
    from scipy.io import loadmat

    path = Path(path)
    try:
        content = loadmat(str(path), variable_names=[variable])
    except (OSError, ValueError, NotImplementedError) as err:
        raise DatasetFormatError(
            f"Cannot read {path}: {err} (expected a MATLAB file with variable {variable!r})"
        ) from err
    if variable not in content:
        found = sorted(k for k in loadmat(str(path)) if not k.startswith("__"))
        raise DatasetFormatError(f"{path} has no variable {variable!r}; it holds {found}")
    grid = np.asarray(content[variable])
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise DatasetFormatError(
            f"{path}: variable {variable!r} must be a cubic N x N x N grid, got shape {grid.shape}"
        )
    return grid > 0


def downsample_voxels(
    grid: np.ndarray, resolution: int = 32, *, fit: bool = True, pooling: str = "max", threshold: float = 0.5
) -> np.ndarray:
    """Resample an occupancy grid to ``resolution^3`` (see the module docstring), keeping its axes.

    The source region is the whole grid (``fit=False``) or the occupied voxels' bounding box padded to a
    centred cube (``fit=True``), a cube of side ``L`` source voxels. A source voxel belongs to the output cell
    that contains its centre. When ``L >= resolution``: ``"max"`` marks a cell occupied when any source voxel in
    it is, ``"mean"`` when the occupied fraction of its source voxels is at least ``threshold``. When
    ``L < resolution`` (up-sampling) each cell takes the source voxel under its centre.

    Returns:
        ``(resolution,) * 3`` bool; all empty for an empty grid.
    """
    resolution = check_int("resolution", resolution, minimum=1)
    check_choice("pooling", pooling, POOLINGS)
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0, min_open=True)
    occupied = np.asarray(grid) > 0
    if occupied.ndim != 3:
        raise ValueError(f"`grid` must be a 3-D array, got shape {occupied.shape}")
    out_shape = (resolution,) * 3
    if not occupied.any():
        return np.zeros(out_shape, bool)
    if fit:
        idx = np.argwhere(occupied)
        low, high = idx.min(0), idx.max(0) + 1
        side = int((high - low).max())
        origin = low - ((side - (high - low)) / 2.0)  # float: the cube is centred on the box
    else:
        if len(set(occupied.shape)) != 1:
            raise ValueError(f"`grid` must be cubic when fit=False, got shape {occupied.shape}")
        side, origin = occupied.shape[0], np.zeros(3)
    if side < resolution:  # up-sampling: nearest source voxel under each output centre
        picks = [np.floor(origin[a] + (np.arange(resolution) + 0.5) * side / resolution).astype(int) for a in range(3)]
        valid = [(p >= 0) & (p < occupied.shape[a]) for a, p in enumerate(picks)]
        out = np.zeros(out_shape, bool)
        sub = occupied[np.ix_(*[np.clip(p, 0, occupied.shape[a] - 1) for a, p in enumerate(picks)])]
        mask = valid[0][:, None, None] & valid[1][None, :, None] & valid[2][None, None, :]
        out[mask] = sub[mask]
        return out
    # One-hot membership matrix per axis (resolution x N): source voxel s goes to cell floor((s + .5 - o) R / L).
    members = []
    for a in range(3):
        cell = np.floor((np.arange(occupied.shape[a]) + 0.5 - origin[a]) * resolution / side).astype(int)
        members.append((cell[None, :] == np.arange(resolution)[:, None]).astype(np.float32))
    counts = np.einsum("ia,abc->ibc", members[0], occupied.astype(np.float32))
    counts = np.einsum("jb,ibc->ijc", members[1], counts)
    counts = np.einsum("kc,ijc->ijk", members[2], counts)
    if pooling == "max":
        return counts > 0
    totals = np.einsum("i,j,k->ijk", *(m.sum(1) for m in members))
    return counts >= threshold * np.maximum(totals, 1) - 1e-6


# ---------------------------------------------------------------------------------------------- cameras
def _model_to_package(yaw_offset: int) -> np.ndarray:
    # package <- voxel <- model: VOXEL_TO_MODEL is orthogonal, so its transpose is model -> voxel.
    return yaw_rotation(yaw_offset) @ VOXEL_TO_PACKAGE @ VOXEL_TO_MODEL.T


def camera_rotation(record: Pix3DRecord, yaw_offset: int = 0) -> np.ndarray:
    """World-to-camera rotation ``(3, 3)`` of the photograph in the package frame, OpenGL convention.

    Rows are the camera's right, up and backward axes in package coordinates, as
    :func:`lightning_vtr.geometry.camera_basis` gives them for the package's own viewpoints:
    ``diag(-1, 1, -1) @ rot_mat @ M^T`` with ``M`` the model -> package rotation (module docstring).
    """
    return BLENDER_TO_CAMERA @ record.rotation @ _model_to_package(yaw_offset).T


def pix3d_viewpoint(record: Pix3DRecord, yaw_offset: int = 0) -> np.ndarray:
    """The photograph's viewpoint ``(yaw, pitch)`` in degrees in the package frame (its in-plane roll is dropped).

    The camera's position relative to the object is ``cam_position`` when the record has one (Pix3D's
    estimate, model frame), else ``-rot_mat^T trans_mat`` (the origin of ``demo.py``'s render seen from the
    object).
    """
    position = record.camera_position
    if position is None:
        position = -record.rotation.T @ record.translation
    x, y, z = _model_to_package(yaw_offset) @ position
    norm = math.sqrt(x * x + y * y + z * z)
    if norm == 0:
        raise ValueError(f"record {record.index} ({record.key}): the camera position is the object's centre")
    yaw = (math.degrees(math.atan2(y, x)) + 180.0) % 360.0 - 180.0
    return np.array([yaw, math.degrees(math.asin(max(-1.0, min(1.0, z / norm))))])


# ---------------------------------------------------------------------------------------------- images
def crop_to_bbox(
    image: np.ndarray,
    mask: np.ndarray | None,
    bbox: Sequence[float],
    *,
    margin: float = 0.1,
    background: Sequence[int] | None = None,
) -> np.ndarray:
    """A square RGBA crop around ``bbox`` (see the module docstring).

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        mask: ``(H, W)`` uint8, the object's alpha (255 inside); ``None`` keeps every pixel of the photograph.
        bbox: ``(x0, y0, x1, y1)``: the box covers columns ``x0 .. x1`` and rows ``y0 .. y1`` (inclusive).
        margin: added on each side, as a fraction of the box's longer side.
        background: RGB (0-255) to composite on here (the result is then opaque); ``None`` leaves the alpha.

    Returns:
        ``(S, S, 4)`` uint8 with ``S = round((1 + 2 margin) max(x1 - x0 + 1, y1 - y0 + 1))``, centred on the
        box's centre; pixels outside the photograph are transparent (or ``background``).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3 or image.dtype != np.uint8:
        raise ValueError(f"`image` must be (H, W, 3) uint8 RGB, got shape {image.shape} {image.dtype}")
    height, width = image.shape[:2]
    if mask is not None and np.asarray(mask).shape != (height, width):
        raise ValueError(f"`mask` must be ({height}, {width}) like the image, got {np.asarray(mask).shape}")
    margin = check_float("margin", margin, minimum=0.0)
    x0, y0, x1, y1 = (float(v) for v in bbox)
    side = max(1, round((1.0 + 2.0 * margin) * max(x1 - x0 + 1.0, y1 - y0 + 1.0)))
    left = math.floor((x0 + x1 + 1.0) / 2.0 - side / 2.0 + 0.5)
    top = math.floor((y0 + y1 + 1.0) / 2.0 - side / 2.0 + 0.5)
    alpha = np.full((height, width), 255, np.uint8) if mask is None else np.asarray(mask, np.uint8)
    rgba = np.concatenate([image, alpha[..., None]], axis=-1)
    out = np.zeros((side, side, 4), np.uint8)
    src_top, src_left = max(top, 0), max(left, 0)
    src_bottom, src_right = min(top + side, height), min(left + side, width)
    if src_bottom > src_top and src_right > src_left:
        out[src_top - top : src_bottom - top, src_left - left : src_right - left] = rgba[
            src_top:src_bottom, src_left:src_right
        ]
    if background is not None:
        bg = np.asarray(background, np.float64).reshape(1, 1, 3)
        a = out[..., 3:].astype(np.float64) / 255.0
        rgb = np.rint(out[..., :3] * a + bg * (1.0 - a))
        out = np.concatenate([rgb.astype(np.uint8), np.full((side, side, 1), 255, np.uint8)], axis=-1)
    return out


def read_pix3d_image(path: Path) -> np.ndarray:
    """A Pix3D photograph as ``(H, W, 3)`` uint8 RGB.

    Raises:
        OSError: naming ``path``, when it cannot be read as an image.
    """
    try:
        with open_image(path) as img:  # its size checked before decoding
            return np.asarray(img.convert("RGB"))
    except (OSError, ValueError) as err:
        raise OSError(f"Cannot read image {path}: {err}") from err


def read_pix3d_mask(path: Path, shape: tuple[int, int], image_path: Path) -> np.ndarray:
    """A Pix3D mask as ``(H, W)`` uint8 (0 background), of the size ``shape`` of its photograph ``image_path``.

    Raises:
        OSError: naming ``path``, when it cannot be read as an image.
        DatasetFormatError: naming both files, when the mask's size is not ``shape``.
    """
    try:
        with open_image(path) as img:
            mask = np.asarray(img.convert("L"))
    except (OSError, ValueError) as err:
        raise OSError(f"Cannot read mask {path}: {err}") from err
    if mask.shape != shape:
        raise DatasetFormatError(
            f"the mask {path} must have the size of {image_path} ({shape[1]}x{shape[0]}), "
            f"got {mask.shape[1]}x{mask.shape[0]}"
        )
    return mask


# ---------------------------------------------------------------------------------------------- the dataset
class Pix3DDataset(Dataset):
    """Pix3D photographs as test items: ``VTRDataset``'s batch dictionaries with one view.

    Items: ``images`` ``(1, 3, S, S)`` (the cropped photograph through ``transform``), ``voxels``
    ``(R, R, R)`` float32 in the package frame, ``viewpoints`` ``(1, 2)`` (:func:`pix3d_viewpoint`),
    ``category``, ``object_id`` (the photograph's stem) and ``view_set``.

    Args:
        records: from :func:`read_pix3d` (or a Pix3D root, read with its defaults).
        transform: RGBA uint8 -> model input (default the plain :class:`ImageTransform` at ``image_size``); use
            the one the model was validated with.
        image_size: the default transform's output size.
        resolution: ``R``, the model's voxel resolution.
        margin: the crop's margin, as in :func:`crop_to_bbox`.
        use_mask: whether to composite with the mask, as in :func:`crop_to_bbox` (``False`` keeps the
            photograph's own background).
        background: the colour under the mask, as in :func:`crop_to_bbox`.
        fit: as in :func:`downsample_voxels`.
        pooling: as in :func:`downsample_voxels`.
        yaw_offset: an extra turn about +Z (multiple of 90 degrees) of voxels and viewpoints.
        view_set: the ``view_set`` name items carry. The package's models accept only
            :data:`~lightning_vtr.protocol.VIEW_SETS` there (their ``test_step`` logs per set), so Pix3D is
            served as ``"aligned"`` by default; the name only routes the metrics.

    Raises:
        FileNotFoundError: ``records`` is a root without Pix3D's annotation file (see :func:`read_pix3d`).
        DatasetFormatError: ``records`` is a root whose annotation file is malformed (see :func:`read_pix3d`).
        TypeError: ``resolution`` is not an int, or ``margin`` not a number.
        ValueError: ``resolution`` below 1, a negative ``margin``, an unknown ``pooling``, or a ``yaw_offset``
            that is not a multiple of 90.

    Example::

        from lightning_vtr.data import Pix3DDataset, read_pix3d

        dataset = Pix3DDataset(read_pix3d("data/pix3d", categories=["chair"]), image_size=224, resolution=32)
        item = dataset[0]  # item["images"]: (1, 3, 224, 224), item["voxels"]: (32, 32, 32) float32
    """

    def __init__(
        self,
        records: Sequence[Pix3DRecord] | str | Path,
        *,
        transform: Any = None,
        image_size: int = 224,
        resolution: int = 32,
        margin: float = 0.1,
        use_mask: bool = True,
        background: Sequence[int] | None = None,
        fit: bool = True,
        pooling: str = "max",
        yaw_offset: int = 0,
        view_set: str = "aligned",
    ) -> None:
        self.records = read_pix3d(records) if isinstance(records, (str, Path)) else list(records)
        self.transform = transform if transform is not None else ImageTransform(image_size)
        self.resolution = check_int("resolution", resolution, minimum=1)
        self.margin = check_float("margin", margin, minimum=0.0)
        self.use_mask = bool(use_mask)
        self.background = None if background is None else tuple(int(c) for c in background)
        self.fit = bool(fit)
        self.pooling = check_choice("pooling", pooling, POOLINGS)
        self.yaw_offset = int(yaw_offset)
        self._to_package = yaw_rotation(self.yaw_offset) @ VOXEL_TO_PACKAGE
        self.view_set = view_set
        self._voxels: dict[Path, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.records)

    def voxels(self, record: Pix3DRecord) -> np.ndarray:
        """The record's ``(R, R, R)`` bool grid in the package frame (cached per voxel file)."""
        grid = self._voxels.get(record.voxel_path)
        if grid is None:
            raw = load_voxel_mat(record.voxel_path)
            small = downsample_voxels(raw, self.resolution, fit=self.fit, pooling=self.pooling)
            grid = self._voxels[record.voxel_path] = rotate_grid(small, self._to_package)
        return grid

    def crop(self, record: Pix3DRecord) -> np.ndarray:
        """The record's square RGBA crop, before the transform."""
        image = read_pix3d_image(record.image_path)
        mask = read_pix3d_mask(record.mask_path, image.shape[:2], record.image_path) if self.use_mask else None
        return crop_to_bbox(image, mask, record.bbox, margin=self.margin, background=self.background)

    def __getitem__(self, index: int) -> dict:
        record = self.records[index]
        crop = self.crop(record)[None]
        return {
            "images": apply_image_transform(self.transform, crop, (0, 0, index)),
            "voxels": torch.from_numpy(self.voxels(record).astype(np.float32)),
            "viewpoints": torch.as_tensor(pix3d_viewpoint(record, self.yaw_offset)[None], dtype=torch.float32),
            "category": record.category,
            "object_id": record.object_id,
            "view_set": self.view_set,
        }

"""Load, re-orient, normalise and save triangle meshes in the package's world frame.

Every mesh that reaches the renderer or the voxelizer goes through :func:`load_mesh`, so it is
+Z up (``lightning_vtr.geometry``) and sits in the cube ``[-0.5, 0.5]^3``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, cast

import numpy as np
import trimesh

from lightning_vtr.data.format import UP_AXES
from lightning_vtr.utils.io import atomic_open
from lightning_vtr.utils.validation import check_choice, check_float

__all__ = ["MESH_EXTENSIONS", "MeshError", "convert_up_axis", "load_mesh", "normalize_mesh", "save_mesh"]

#: File extensions :func:`load_mesh` accepts (lower case, with the dot).
MESH_EXTENSIONS = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")

# Relative size below which an axis of the bounding box counts as flat: finer than float32
# resolution of a unit object, so such a mesh cannot be scaled into a solid of non-zero volume.
_FLAT_TOLERANCE = 1e-7

# Rotation by +90 degrees about +X: takes +Y to +Z and +Z to -Y, a proper rotation, so
# handedness (and face winding) is preserved.
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


class MeshError(ValueError):
    """A mesh file cannot be used: unreadable, empty or degenerate.

    ``MeshError(path, reason)`` builds the message ``"Cannot use mesh '<path>': <reason>"``;
    ``MeshError(message)`` keeps a ready-made message. ``path`` and ``reason`` are kept as attributes.
    """

    def __init__(self, path_or_message: str | os.PathLike, reason: str | None = None) -> None:
        if reason is None:
            self.path, self.reason = None, str(path_or_message)
            message = self.reason
        else:
            self.path, self.reason = str(path_or_message), reason
            message = f"Cannot use mesh '{self.path}': {reason}"
        super().__init__(message)


def convert_up_axis(mesh: trimesh.Trimesh, up_axis: Literal["y", "z"]) -> trimesh.Trimesh:
    """Return a copy of ``mesh`` re-expressed in the +Z-up world frame.

    ``up_axis="y"`` (ShapeNet, glTF) rotates by +90 degrees about +X, i.e. ``(x, y, z) -> (x, -z, y)``:
    the source's +Y becomes +Z and its +Z becomes -Y. It is a rotation,
    not a mirror, so the frame stays right-handed and outward normals stay outward.
    ``up_axis="z"`` returns an unchanged copy.
    """
    check_choice("up_axis", up_axis, UP_AXES)
    out = mesh.copy()
    if up_axis == "y":
        out.apply_transform(_Y_UP_TO_Z_UP)
    return out


def _check_geometry(mesh: trimesh.Trimesh) -> str | None:
    """Why ``mesh`` cannot be normalised, or None if it can."""
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        return "it has no triangles"
    vertices = np.asarray(mesh.vertices)
    if not np.isfinite(vertices).all():
        return "it has NaN or infinite vertex coordinates"
    used = vertices[np.unique(np.asarray(mesh.faces))]
    extent = used.max(axis=0) - used.min(axis=0)
    longest = float(extent.max())
    if longest <= 0.0:
        return "all its vertices coincide (zero extent)"
    flat = [axis for axis, e in zip("xyz", extent) if e <= _FLAT_TOLERANCE * longest]
    if flat:
        return f"it is flat (zero extent along {', '.join(flat)}; bounding box {extent.tolist()}), so it has no volume"
    return None


def normalize_mesh(mesh: trimesh.Trimesh, longest_side: float = 1.0) -> trimesh.Trimesh:
    """Return a copy of ``mesh`` with its bounding box centred at the origin and longest side ``longest_side``.

    With the default ``longest_side=1`` the result lies in ``[-0.5, 0.5]^3``.

    Raises:
        TypeError: ``longest_side`` is not a number.
        ValueError: ``longest_side`` is not positive, or the mesh is empty, has NaN vertices or is flat.
    """
    longest_side = check_float("longest_side", longest_side, minimum=0.0, min_open=True)
    problem = _check_geometry(mesh)
    if problem is not None:
        raise ValueError(f"Cannot normalise the mesh: {problem}")
    out = mesh.copy()
    # Bounds of the referenced vertices only: stray unreferenced vertices must not shift the object.
    used = np.asarray(out.vertices)[np.unique(np.asarray(out.faces))]
    lo, hi = used.min(axis=0), used.max(axis=0)
    scale = longest_side / float((hi - lo).max())
    transform = np.eye(4)
    transform[:3, :3] *= scale
    transform[:3, 3] = -scale * (lo + hi) / 2.0
    out.apply_transform(transform)
    return out


def _merge_scene(loaded: trimesh.Scene | trimesh.Trimesh | object) -> trimesh.Trimesh | None:
    """One Trimesh from whatever trimesh.load returned, scene-graph transforms applied."""
    if isinstance(loaded, trimesh.Trimesh):
        return loaded
    if isinstance(loaded, trimesh.Scene):
        # Only triangle geometry is kept: points and paths (e.g. OBJ line elements) have no surface.
        meshes = []
        for node in loaded.graph.nodes_geometry:
            transform, name = loaded.graph[node]
            geometry = loaded.geometry.get(name)
            if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces) > 0:
                meshes.append(geometry.copy().apply_transform(transform))
        if not meshes:
            return None
        return meshes[0] if len(meshes) == 1 else cast(trimesh.Trimesh, trimesh.util.concatenate(meshes))
    return None


def load_mesh(
    path: str | os.PathLike,
    *,
    up_axis: Literal["y", "z"] = "z",
    normalize: bool = True,
    longest_side: float = 1.0,
) -> trimesh.Trimesh:
    """Load a mesh file as one +Z-up :class:`trimesh.Trimesh`, normalised into the unit cube.

    Args:
        path: an OBJ, OFF, PLY, STL, GLB or glTF file. Multi-object files (scenes) are merged into one
            mesh with their scene-graph transforms applied; materials and vertex colours are kept.
        up_axis: the source's up axis. ShapeNetCore is +Y up: pass ``"y"`` (see :func:`convert_up_axis`).
        normalize: centre the bounding box at the origin and scale its longest side to ``longest_side``.
        longest_side: the longest bounding-box side after normalisation (world units).

    Raises:
        MeshError: the file is missing, of an unsupported type, unreadable, holds no triangles, has
            NaN vertices or is flat (zero extent along an axis). The message names the file.
    """
    check_choice("up_axis", up_axis, UP_AXES)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_EXTENSIONS:
        raise MeshError(path, f"unsupported file type {suffix!r}; expected one of {', '.join(MESH_EXTENSIONS)}")
    if not path.is_file():
        raise MeshError(path, "no such file")
    try:
        loaded = trimesh.load(str(path), file_type=suffix[1:], force="scene", process=False)
    except Exception as err:  # trimesh raises many types (ValueError, KeyError, struct.error, ...)
        raise MeshError(path, f"the file could not be parsed ({type(err).__name__}: {err})") from err
    mesh = _merge_scene(loaded)
    if mesh is None:
        raise MeshError(path, "it contains no triangles")
    problem = _check_geometry(mesh)
    if problem is not None:
        raise MeshError(path, problem)
    # Merge duplicate vertices and drop degenerate faces only now: processing NaN input is undefined.
    mesh.process(validate=False)
    mesh = convert_up_axis(mesh, up_axis)
    if normalize:
        try:
            mesh = normalize_mesh(mesh, longest_side)
        except ValueError as err:
            raise MeshError(path, str(err)) from err
    return mesh


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> None:
    """Write ``mesh`` to ``path`` atomically; the format follows the extension (e.g. ``.ply``, ``.obj``).

    The file is written with :func:`lightning_vtr.utils.io.atomic_open`, so a reader (or a killed build)
    never sees a half-written file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_EXTENSIONS:
        raise ValueError(
            f"`path` must have a mesh extension ({', '.join(MESH_EXTENSIONS)}), got '{path}' (extension {suffix!r})"
        )
    with atomic_open(path, "wb") as f:
        mesh.export(f, file_type=suffix[1:])

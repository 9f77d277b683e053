"""Read and write binvox voxel files with the axis order made explicit.

The binvox format (https://www.patrickmin.com/binvox/binvox.html) is an ASCII header::

    #binvox 1
    dim D H W          # sizes along x, y, z
    translate tx ty tz
    scale s
    data

followed by run-length-encoded bytes: pairs ``(value, count)`` with ``value`` in {0, 1} and
``count`` in 1..255. The voxels are listed with **y varying fastest, then z, then x**: the flat
position of voxel ``(x, y, z)`` is ``x * (W * H) + z * H + y`` (binvox calls it "xzy" order; the
size along y is taken as the row length, as trimesh and the binvox tools do for the cubic grids
used in practice). A voxel ``(x, y, z)`` has its centre at ``translate + (index + 0.5) / dim * scale``
in the frame of the file.

In memory this package always uses ``V[i, j, k]`` with ``(i, j, k)`` the ``(x, y, z)`` indices of
:func:`lightning_vtr.geometry.voxel_centers`; ``translate = (-0.5, -0.5, -0.5)`` and ``scale = 1`` make
the file's voxel centres exactly the package's. Files made in a +Y-up frame (ShapeNetVox32,
3D-R2N2, Pix2Vox) are converted on reading with ``up_axis="y"``, with the same rotation as
:func:`lightning_vtr.data.mesh.convert_up_axis` applies to meshes.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, overload

import numpy as np

from lightning_vtr.data.format import UP_AXES
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.validation import check_choice, check_float

__all__ = ["read_binvox", "voxels_to_y_up", "voxels_to_z_up", "write_binvox"]

_MAX_HEADER_LINES = 16


def voxels_to_z_up(voxels: np.ndarray) -> np.ndarray:
    """Re-express a grid made in a +Y-up frame in the +Z-up frame.

    The rotation is ``(x, y, z) -> (x, -z, y)`` (+90 degrees about +X), as for meshes. On the grid's
    cell centres it maps source cell ``(i, j, k)`` to cell ``(i, R - 1 - k, j)``, so
    ``out[i, j, k] = voxels[i, k, R - 1 - j]``.
    """
    return np.ascontiguousarray(np.flip(voxels, axis=2).transpose(0, 2, 1))


def voxels_to_y_up(voxels: np.ndarray) -> np.ndarray:
    """Inverse of :func:`voxels_to_z_up`: ``out[i, j, k] = voxels[i, R - 1 - k, j]``."""
    return np.ascontiguousarray(np.flip(voxels.transpose(0, 2, 1), axis=2))


def _read_header(f, path: Path) -> tuple[tuple[int, int, int], tuple[float, float, float], float]:
    first = f.readline()
    if not first.startswith(b"#binvox"):
        raise ValueError(f"'{path}' is not a binvox file: first line is {first[:40]!r}, expected b'#binvox 1'")
    dims = translate = scale = None
    for _ in range(_MAX_HEADER_LINES):
        line = f.readline()
        if not line:
            break
        words = line.strip().split()
        if not words or words[0].startswith(b"#"):
            continue
        key = words[0]
        try:
            if key == b"dim":
                dims = tuple(int(w) for w in words[1:])
            elif key == b"translate":
                translate = tuple(float(w) for w in words[1:])
            elif key == b"scale":
                scale = float(words[1])
            elif key == b"data":
                break
            else:
                raise ValueError(f"unknown header line {line.strip()[:40]!r}")
        except (ValueError, IndexError) as err:
            raise ValueError(f"Bad binvox header in '{path}': {err} (line {line.strip()[:40]!r})") from err
    else:
        raise ValueError(f"Bad binvox header in '{path}': no 'data' line within {_MAX_HEADER_LINES} lines")
    if dims is None or len(dims) != 3 or min(dims) < 1:
        raise ValueError(f"Bad binvox header in '{path}': expected 'dim D H W' with three positive sizes, got {dims}")
    if translate is not None and len(translate) != 3:
        raise ValueError(f"Bad binvox header in '{path}': 'translate' needs three numbers, got {translate}")
    # Both lines are optional in practice; binvox's own defaults are no translation and unit scale.
    return dims, translate or (0.0, 0.0, 0.0), 1.0 if scale is None else scale


def _check_dims(dims: tuple[int, int, int], resolution: int | None, path: Path) -> None:
    """Refuse a header whose grid is not ``resolution`` cubed or exceeds :data:`MAX_VOXEL_SIDE` (before allocating)."""
    from lightning_vtr.errors import DataError
    from lightning_vtr.utils.limits import MAX_VOXEL_SIDE

    found = "x".join(map(str, dims))
    if resolution is not None and tuple(dims) != (int(resolution),) * 3:
        raise DataError(f"{path}: a {resolution}x{resolution}x{resolution} voxel grid was expected, found {found}")
    if max(dims) > MAX_VOXEL_SIDE:
        limit = MAX_VOXEL_SIDE
        raise DataError(f"{path}: a voxel grid of at most {limit}x{limit}x{limit} was expected, found {found}")


@overload
def read_binvox(
    path: str | os.PathLike,
    *,
    up_axis: Literal["y", "z"] = ...,
    return_transform: Literal[False] = ...,
    resolution: int | None = ...,
    root: str | os.PathLike | None = ...,
) -> np.ndarray: ...
@overload
def read_binvox(
    path: str | os.PathLike,
    *,
    up_axis: Literal["y", "z"] = ...,
    return_transform: Literal[True],
    resolution: int | None = ...,
    root: str | os.PathLike | None = ...,
) -> tuple[np.ndarray, tuple[float, float, float], float]: ...
@overload
def read_binvox(
    path: str | os.PathLike,
    *,
    up_axis: Literal["y", "z"] = ...,
    return_transform: bool = ...,
    resolution: int | None = ...,
    root: str | os.PathLike | None = ...,
) -> np.ndarray | tuple[np.ndarray, tuple[float, float, float], float]: ...
def read_binvox(
    path: str | os.PathLike,
    *,
    up_axis: Literal["y", "z"] = "z",
    return_transform: bool = False,
    resolution: int | None = None,
    root: str | os.PathLike | None = None,
) -> np.ndarray | tuple[np.ndarray, tuple[float, float, float], float]:
    """Read a binvox file into a bool array ``V[i, j, k]`` indexed ``(x, y, z)``.

    The header is checked before the grid is allocated: its sizes must be ``resolution`` (when given) and at
    most :data:`~lightning_vtr.utils.limits.MAX_VOXEL_SIDE` each, so a small file cannot ask for gigabytes.

    Args:
        path: the ``.binvox`` file.
        up_axis: the up axis of the frame the file was made in. ``"z"`` (files this package writes)
            returns the grid as stored; ``"y"`` (ShapeNetVox32 / 3D-R2N2, made from +Y-up ShapeNet
            meshes) rotates it into the +Z-up frame with :func:`voxels_to_z_up`.
        return_transform: also return the header's ``translate`` and ``scale`` (as stored, file frame).
        resolution: the ``R`` of the ``R x R x R`` grid expected (a dataset's ``resolution``); ``None`` takes
            any size up to the limit.
        root: the dataset's folder the file belongs to, if any: a file whose resolved path is not inside it (a
            symlink leading out of the dataset) is refused, see :func:`~lightning_vtr.utils.limits.check_regular_file`.

    Returns:
        ``(D, H, W)`` bool (``(R, R, R)`` for the usual cubic files), or ``(voxels, translate, scale)``.

    Raises:
        ValueError: bad header or data that do not decode to ``D * H * W`` voxels; names the file.
        DataError: (a ``ValueError``) the header's sizes are not ``resolution`` or exceed the limit; the file is not
            a regular file (a FIFO, a device, a folder) or leads out of ``root``.
    """
    from lightning_vtr.utils.limits import check_regular_file

    check_choice("up_axis", up_axis, UP_AXES)
    path = Path(path)
    check_regular_file(path, root=root)
    with open(path, "rb") as f:
        dims, translate, scale = _read_header(f, path)
        _check_dims(dims, resolution, path)
        raw = np.frombuffer(f.read(), dtype=np.uint8)
    if raw.size % 2:
        raise ValueError(f"Bad binvox data in '{path}': odd number of run-length bytes ({raw.size})")
    values, counts = raw[0::2], raw[1::2].astype(np.int64)
    total = int(counts.sum())
    expected = dims[0] * dims[1] * dims[2]
    if total != expected:
        raise ValueError(
            f"Bad binvox data in '{path}': runs cover {total} voxels, header 'dim {dims}' needs {expected}"
        )
    flat = np.repeat(values > 0, counts)
    # Stored order x (slowest), z, y (fastest): reshape to (x, z, y) then swap to (x, y, z).
    voxels = flat.reshape(dims[0], dims[2], dims[1]).transpose(0, 2, 1)
    voxels = voxels_to_z_up(voxels) if up_axis == "y" else np.ascontiguousarray(voxels)
    if return_transform:
        return voxels, translate, scale
    return voxels


def _run_length_encode(flat: np.ndarray) -> bytes:
    """``(value, count)`` byte pairs with counts of at most 255, as binvox requires."""
    flat = flat.astype(np.uint8)
    change = np.flatnonzero(np.diff(flat)) + 1
    starts = np.concatenate([[0], change])
    lengths = np.diff(np.concatenate([starts, [flat.size]]))
    values = flat[starts]
    # Split runs longer than 255 into full runs of 255 plus a remainder.
    pieces = np.where(lengths % 255 == 0, lengths // 255, lengths // 255 + 1)
    run_values = np.repeat(values, pieces)
    run_counts = np.full(int(pieces.sum()), 255, dtype=np.int64)
    last = np.cumsum(pieces) - 1
    run_counts[last] = lengths - 255 * (pieces - 1)
    return np.stack([run_values, run_counts.astype(np.uint8)], axis=1).tobytes()


def write_binvox(
    path: str | os.PathLike,
    voxels: np.ndarray,
    *,
    translate: tuple[float, float, float] = (-0.5, -0.5, -0.5),
    scale: float = 1.0,
    up_axis: Literal["y", "z"] = "z",
) -> None:
    """Write a ``(D, H, W)`` voxel array ``V[i, j, k]`` (``(x, y, z)`` indices) as a binvox file, atomically.

    Args:
        path: destination, written atomically (:func:`lightning_vtr.utils.io.atomic_write`).
        voxels: occupancy per voxel; any non-zero value counts as occupied.
        translate, scale: the header's normalisation (see the module docstring); the defaults make the
            file's voxel centres those of :func:`lightning_vtr.geometry.voxel_centers`.
        up_axis: ``"y"`` writes the grid re-expressed in a +Y-up frame (inverse of reading with
            ``up_axis="y"``), for tools that expect ShapeNetVox32's orientation.
    """
    check_choice("up_axis", up_axis, UP_AXES)
    voxels = np.asarray(voxels)
    if voxels.ndim != 3 or min(voxels.shape) < 1:
        raise ValueError(f"`voxels` must be a non-empty 3-D array (D, H, W), got shape {voxels.shape}")
    try:
        offsets = tuple(float(t) for t in translate)
    except (TypeError, ValueError):
        raise TypeError(f"`translate` must be three numbers, got {translate!r}") from None
    if len(offsets) != 3 or not np.isfinite(offsets).all():
        raise ValueError(f"`translate` must be three finite numbers, got {translate!r}")
    translate = offsets
    scale = check_float("scale", scale, minimum=0.0, min_open=True)
    grid = voxels != 0
    if up_axis == "y":
        grid = voxels_to_y_up(grid)
    dims = grid.shape
    header = (
        f"#binvox 1\ndim {dims[0]} {dims[1]} {dims[2]}\n"
        f"translate {translate[0]!r} {translate[1]!r} {translate[2]!r}\nscale {scale!r}\ndata\n"
    ).encode("ascii")
    body = _run_length_encode(grid.transpose(0, 2, 1).reshape(-1))  # x, z, y(fastest)
    atomic_write(path, header + body)

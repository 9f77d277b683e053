"""The package's single definition of viewpoints, camera frames, angle bins and voxel grids.

Every module that touches an angle, a camera or a voxel index imports from here, so the
renderer, the error projection and the Zero-1-to-3 pose cannot drift apart.

Conventions (all angles in **degrees** unless a name says ``rad``):

* World frame: right-handed, +Z up. Objects live in the cube ``[-0.5, 0.5]^3``.
* A viewpoint is ``(yaw, pitch)``; roll is 0. Yaw is measured about +Z from +X toward +Y and
  lives in ``[-180, 180)``; pitch is the elevation above the XY plane, in ``[-90, 90]``.
* The camera centre is ``r (cos p cos y, cos p sin y, sin p)`` and looks at the origin.
  Its up vector is ``(-sin p cos y, -sin p sin y, cos p)``, defined at the poles too.
  Its right vector is ``forward x up``.
* Images are indexed ``[row, col]`` with row 0 at the top (largest camera-up coordinate) and
  col 0 at the left (smallest camera-right coordinate). An orthographic view of half-extent
  ``s`` maps pixel centre ``(row, col)`` of an ``H x W`` image to camera coordinates
  ``x = -s + (col + 0.5) 2s / W``, ``y = s - (row + 0.5) 2s / H``.
* Voxel ``V[i, j, k]`` of an ``R^3`` grid has its centre at
  ``((i + 0.5) / R - 0.5, (j + 0.5) / R - 0.5, (k + 0.5) / R - 0.5)`` in ``(x, y, z)``.
* Angle bins of interval ``K`` (``K`` divides 180): yaw centres ``-180 + (i - 1/2) K`` for
  ``i = 1..360/K`` and pitch centres ``-90 + (i - 1/2) K`` for ``i = 1..180/K``.
  :func:`candidate_viewpoints` flattens them pitch-major: index ``= i_pitch * n_yaw + i_yaw``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from lightning_vtr.utils.validation import check_choice, check_int, check_range

__all__ = [
    "DEFAULT_HALF_EXTENT",
    "DEFAULT_RESOLUTION",
    "angle_bins",
    "angular_distance",
    "camera_basis",
    "camera_center",
    "camera_pose",
    "camera_up",
    "candidate_viewpoints",
    "check_bin_interval",
    "check_viewpoints",
    "clamp_pitch",
    "normalize_viewpoints",
    "orthographic_pixel_coords",
    "rotate_directions",
    "sample_gaussian_viewpoints",
    "sample_uniform_viewpoints",
    "view_direction",
    "voxel_centers",
    "world_to_voxel_index",
    "wrap_yaw",
]

DEFAULT_RESOLUTION = 32
"""Side ``R`` of the voxel grids (``R x R x R``), as in ShapeNet-VTR and 3D-R2N2."""
DEFAULT_HALF_EXTENT = math.sqrt(3.0) / 2.0
"""Radius of the sphere around the object cube ``[-0.5, 0.5]^3``, ``sqrt(3) / 2`` world units. An
orthographic view whose square image reaches this far from the centre keeps the whole cube in frame
from every viewpoint, so it is the default half-extent of the error projection, the differentiable
projection and the orthographic renderer (which also sizes its depth range with it)."""


def _as_tensor(x: Tensor | np.ndarray | float | list, dtype: torch.dtype | None = None) -> Tensor:
    if isinstance(x, Tensor):
        return x if dtype is None or x.dtype == dtype else x.to(dtype)
    t = torch.as_tensor(np.asarray(x))
    if dtype is not None:
        return t.to(dtype)
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def check_viewpoints(viewpoints: Tensor, name: str = "viewpoints") -> Tensor:
    """Check that ``viewpoints`` has shape ``(..., 2)`` and finite values; return it as a float tensor.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees: a tensor, array or nested list.
        name: the argument's name in error messages.

    Returns:
        The viewpoints as a tensor of the same shape: a floating-point input keeps its dtype, any other
        becomes the default float dtype. Angles are not wrapped (see :func:`normalize_viewpoints`).

    Raises:
        ValueError: for another shape or a NaN / infinite angle; the message names ``name`` and the first
            row holding one (its index over the leading dimensions: ``3`` for ``(V, 2)``, ``(0, 3)`` for
            ``(B, V, 2)``) with the row's values.

    Example:
        >>> check_viewpoints([[30, 10]])
        tensor([[30., 10.]])
        >>> check_viewpoints(torch.tensor([1.0, 2.0, 3.0]))
        Traceback (most recent call last):
        ...
        ValueError: `viewpoints` must have shape (..., 2) holding (yaw, pitch) in degrees, got (3,)
    """
    vp = _as_tensor(viewpoints)
    if not vp.is_floating_point():
        vp = vp.to(torch.get_default_dtype())
    if vp.ndim == 0 or vp.shape[-1] != 2:
        raise ValueError(f"`{name}` must have shape (..., 2) holding (yaw, pitch) in degrees, got {tuple(vp.shape)}")
    bad_rows = ~torch.isfinite(vp).all(dim=-1)
    if bad_rows.any():
        first = tuple(int(i) for i in bad_rows.nonzero()[0]) if vp.ndim > 1 else ()
        values = [float(v) for v in vp[first].tolist()]
        if not first:  # a single (yaw, pitch)
            raise ValueError(f"`{name}` must hold finite (yaw, pitch) angles in degrees, got {values}")
        row = first[0] if len(first) == 1 else first
        raise ValueError(
            f"`{name}` must hold finite (yaw, pitch) angles in degrees, got {values} at row {row} "
            f"({int(bad_rows.sum())} of {bad_rows.numel()} rows hold NaN or infinite values)"
        )
    return vp


def wrap_yaw(yaw: Tensor | np.ndarray) -> Tensor:
    """Wrap yaw angles (degrees) into ``[-180, 180)``.

    Args:
        yaw: yaw angles of any shape, in degrees (a tensor, array or number).

    Returns:
        The wrapped angles in degrees, same shape; a floating-point input keeps its dtype, any other becomes
        the default float dtype.

    Example:
        >>> wrap_yaw(torch.tensor([180.0, -190.0, 370.0]))
        tensor([-180.,  170.,   10.])
    """
    yaw = _as_tensor(yaw)
    return torch.remainder(yaw + 180.0, 360.0) - 180.0


def clamp_pitch(pitch: Tensor) -> Tensor:
    """Clamp pitch angles (degrees) into ``[-90, 90]``.

    Args:
        pitch: pitch angles of any shape, in degrees.

    Returns:
        The clamped angles in degrees, same shape and (for a floating-point input) dtype.

    Example:
        >>> clamp_pitch(torch.tensor([-100.0, 45.0, 95.0]))
        tensor([-90.,  45.,  90.])
    """
    return _as_tensor(pitch).clamp(-90.0, 90.0)


def normalize_viewpoints(viewpoints: Tensor) -> Tensor:
    """Wrap yaw and clamp pitch of ``(..., 2)`` viewpoints in degrees.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.

    Returns:
        ``(..., 2)`` float viewpoints in degrees, yaw in ``[-180, 180)`` and pitch in ``[-90, 90]``.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> normalize_viewpoints(torch.tensor([[190.0, 100.0]]))
        tensor([[-170.,   90.]])
    """
    vp = check_viewpoints(viewpoints)
    return torch.stack([wrap_yaw(vp[..., 0]), clamp_pitch(vp[..., 1])], dim=-1)


def _trig(viewpoints: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    vp = check_viewpoints(viewpoints)
    yaw, pitch = torch.deg2rad(vp[..., 0]), torch.deg2rad(vp[..., 1])
    return torch.cos(yaw), torch.sin(yaw), torch.cos(pitch), torch.sin(pitch)


def camera_center(viewpoints: Tensor, radius: float = 1.0) -> Tensor:
    """Camera centres ``(..., 3)`` for viewpoints ``(..., 2)`` (degrees) at distance ``radius``.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.
        radius: distance of the camera from the origin, in world units.

    Returns:
        ``(..., 3)`` world coordinates ``radius (cos p cos y, cos p sin y, sin p)``, float.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> camera_center(torch.tensor([0.0, 0.0]), radius=2.0)
        tensor([2., 0., 0.])
        >>> camera_center(torch.zeros(4, 3, 2)).shape
        torch.Size([4, 3, 3])
    """
    cy, sy, cp, sp = _trig(viewpoints)
    return torch.stack([cp * cy, cp * sy, sp], dim=-1) * radius


def view_direction(viewpoints: Tensor) -> Tensor:
    """Unit viewing directions ``(..., 3)``: from the camera toward the origin.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.

    Returns:
        ``(..., 3)`` unit vectors in world coordinates, the negated :func:`camera_center` at radius 1.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> looking_down = view_direction(torch.tensor([0.0, 90.0]))  # a camera above the object
        >>> torch.allclose(looking_down, torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)
        True
    """
    return -camera_center(viewpoints)


def camera_up(viewpoints: Tensor) -> Tensor:
    """Camera up vectors ``(..., 3)``; well defined at pitch = +-90 degrees.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.

    Returns:
        ``(..., 3)`` unit vectors ``(-sin p cos y, -sin p sin y, cos p)`` in world coordinates, orthogonal to
        the viewing direction.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> up = camera_up(torch.tensor([[0.0, 0.0], [0.0, 90.0]]))  # a level camera on +X; one above
        >>> torch.allclose(up, torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]), atol=1e-6)
        True
    """
    cy, sy, cp, sp = _trig(viewpoints)
    return torch.stack([-sp * cy, -sp * sy, cp], dim=-1)


def camera_basis(viewpoints: Tensor) -> Tensor:
    """World-to-camera rotations ``(..., 3, 3)`` in the OpenGL camera convention.

    Rows are the camera's right, up and backward (``-forward``) axes in world coordinates,
    so ``R @ p`` gives camera coordinates with x right, y up and the camera looking along -z.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.

    Returns:
        ``(..., 3, 3)`` float rotation matrices ``R``.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> R = camera_basis(torch.tensor([0.0, 0.0]))  # on +X, looking toward the origin: right is +Y, up +Z
        >>> torch.allclose(R, torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), atol=1e-6)
        True
    """
    forward = view_direction(viewpoints)
    up = camera_up(viewpoints)
    right = torch.linalg.cross(forward, up, dim=-1)
    return torch.stack([right, up, -forward], dim=-2)


def camera_pose(viewpoints: Tensor, radius: float = 1.0) -> Tensor:
    """Camera-to-world 4x4 matrices ``(..., 4, 4)`` (OpenGL / pyrender convention).

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.
        radius: distance of the camera from the origin, in world units.

    Returns:
        ``(..., 4, 4)`` float poses: the transposed :func:`camera_basis` as rotation and the
        :func:`camera_center` as translation.

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> pose = camera_pose(torch.tensor([[0.0, 0.0], [90.0, 30.0]]), radius=2.0)
        >>> pose.shape
        torch.Size([2, 4, 4])
        >>> pose[0, :3, 3]  # the camera's position
        tensor([2., 0., 0.])
    """
    rot = camera_basis(viewpoints)
    center = camera_center(viewpoints, radius)
    pose = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    pose[..., :3, :3] = rot.transpose(-1, -2)
    pose[..., :3, 3] = center
    pose[..., 3, 3] = 1.0
    return pose


def rotate_directions(directions: Tensor, rotation: Tensor) -> Tensor:
    """Apply rotations ``(..., 3, 3)`` to vectors ``(..., 3)`` (broadcasting over leading dims).

    Args:
        directions: ``(..., 3)`` vectors.
        rotation: ``(..., 3, 3)`` rotation matrices, converted to the dtype of ``directions``.

    Returns:
        ``(..., 3)`` rotated vectors ``rotation @ directions``, leading dimensions broadcast.

    Example:
        >>> R = camera_basis(torch.tensor([0.0, 0.0]))
        >>> rotate_directions(torch.tensor([1.0, 0.0, 0.0]), R)  # world +X is the camera's backward axis
        tensor([0., 0., 1.])
    """
    directions = _as_tensor(directions)
    rotation = _as_tensor(rotation, directions.dtype)
    return (rotation @ directions[..., None])[..., 0]


def orthographic_pixel_coords(points: Tensor, viewpoints: Tensor, image_size: int, half_extent: float) -> Tensor:
    """Project world points onto orthographic image planes.

    Args:
        points: ``(N, 3)`` world coordinates.
        viewpoints: ``(V, 2)`` (yaw, pitch) in degrees.
        image_size: ``H = W`` in pixels.
        half_extent: half the side of the square the image covers, in world units.

    Returns:
        ``(V, N, 3)``: continuous ``(row, col)`` pixel coordinates (pixel centres at ``.5``) and the
        depth along the viewing direction (smaller is nearer the camera; relative to the origin).

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> points = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.25, 0.25]])
        >>> orthographic_pixel_coords(points, torch.tensor([[0.0, 0.0]]), 4, 0.5)[..., :2]  # (row, col)
        tensor([[[2., 2.],
                 [1., 3.]]])
    """
    rot = camera_basis(viewpoints).to(_as_tensor(points).dtype)  # (V, 3, 3)
    cam = torch.einsum("vij,nj->vni", rot, _as_tensor(points))
    scale = image_size / (2.0 * half_extent)
    col = (cam[..., 0] + half_extent) * scale
    row = (half_extent - cam[..., 1]) * scale
    depth = -cam[..., 2]  # distance in front of a camera placed at the origin looking along -z
    return torch.stack([row, col, depth], dim=-1)


def check_bin_interval(k: float, name: str = "k") -> int:
    """Validate an angle-bin interval ``K`` (degrees): a positive integer dividing 180; returns it as an int.

    A float with an integral value (``30.0``) is accepted, as angles often arrive as floats.

    Args:
        k: the bin interval ``K`` in degrees.
        name: the argument's name in error messages.

    Returns:
        ``K`` as an int.

    Raises:
        TypeError: ``k`` is not a real number.
        ValueError: ``k`` is not a positive integer that divides 180.

    Example:
        >>> check_bin_interval(30.0)
        30
        >>> check_bin_interval(7)
        Traceback (most recent call last):
        ...
        ValueError: `k` must be a bin interval K in degrees that divides 180, got 7
    """
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, float, np.integer, np.floating)):
        raise TypeError(f"`{name}` must be a bin interval K in degrees (a number), got {type(k).__name__} {k!r}")
    if not float(k).is_integer() or k <= 0 or 180 % int(k) != 0:
        raise ValueError(f"`{name}` must be a bin interval K in degrees that divides 180, got {k!r}")
    return int(k)


def angle_bins(k: float = 30) -> tuple[Tensor, Tensor]:
    """Bin centres of interval ``K``: ``(yaw_centres (360/K,), pitch_centres (180/K,))`` in degrees.

    Args:
        k: bin interval ``K`` in degrees (a positive integer dividing 180).

    Returns:
        ``(yaw, pitch)``: yaw centres ``(360/K,)`` from ``-180 + K/2`` and pitch centres ``(180/K,)`` from
        ``-90 + K/2``, in degrees, ascending, in the default float dtype.

    Raises:
        TypeError: ``k`` is not a real number.
        ValueError: ``k`` is not a positive integer that divides 180.

    Example:
        >>> angle_bins(90)
        (tensor([-135.,  -45.,   45.,  135.]), tensor([-45.,  45.]))
    """
    k = check_bin_interval(k)
    yaw = -180.0 + (torch.arange(360 // k, dtype=torch.float64) + 0.5) * k
    pitch = -90.0 + (torch.arange(180 // k, dtype=torch.float64) + 0.5) * k
    return yaw.to(torch.get_default_dtype()), pitch.to(torch.get_default_dtype())


def candidate_viewpoints(k: float = 30) -> Tensor:
    """All bin-centre viewpoints ``(180/K * 360/K, 2)``, pitch-major (``i_pitch * n_yaw + i_yaw``).

    Args:
        k: bin interval ``K`` in degrees (a positive integer dividing 180).

    Returns:
        ``(180/K * 360/K, 2)`` (yaw, pitch) of the bin centres of :func:`angle_bins`, in degrees, in the default
        float dtype; row ``i_pitch * (360/K) + i_yaw`` is bin ``(i_yaw, i_pitch)``.

    Raises:
        TypeError: ``k`` is not a real number.
        ValueError: ``k`` is not a positive integer that divides 180.

    Example:
        >>> candidate_viewpoints(30).shape
        torch.Size([72, 2])
        >>> candidate_viewpoints(90)[[0, 1, 4]]  # yaw varies fastest
        tensor([[-135.,  -45.],
                [ -45.,  -45.],
                [-135.,   45.]])
    """
    yaw, pitch = angle_bins(k)
    p, y = torch.meshgrid(pitch, yaw, indexing="ij")
    return torch.stack([y.reshape(-1), p.reshape(-1)], dim=-1)


def sample_uniform_viewpoints(
    n: int,
    *,
    mode: Literal["angle", "area"] = "area",
    yaw_range: tuple[float, float] = (-180.0, 180.0),
    pitch_range: tuple[float, float] = (-90.0, 90.0),
    generator: torch.Generator | None = None,
) -> Tensor:
    """Sample ``n`` viewpoints ``(n, 2)`` in degrees.

    ``mode="angle"`` draws yaw and pitch uniformly in their ranges; ``mode="area"`` draws
    uniformly over the covered patch of the sphere (``sin(pitch)`` uniform). Yaw is wrapped into
    ``[-180, 180)`` afterwards, so ``yaw_range`` itself is not bounded.

    Args:
        n: number of viewpoints (0 gives an empty ``(0, 2)`` tensor).
        mode: ``"area"`` (uniform over the sphere's area) or ``"angle"`` (uniform in yaw and pitch).
        yaw_range: ``(low, high)`` yaw in degrees.
        pitch_range: ``(low, high)`` pitch in degrees, within ``[-90, 90]``.
        generator: the random source (``None``: torch's global one).

    Returns:
        ``(n, 2)`` (yaw, pitch) in degrees, in the default float dtype.

    Raises:
        TypeError: ``n`` is not an int, or a range is not a pair of numbers.
        ValueError: ``n < 0``, an unknown ``mode``, ``pitch_range`` outside ``[-90, 90]`` or a range with
            ``low > high``.

    Example:
        >>> vp = sample_uniform_viewpoints(100, pitch_range=(0.0, 90.0), generator=torch.Generator().manual_seed(0))
        >>> vp.shape, bool((vp[:, 1] >= 0).all())
        (torch.Size([100, 2]), True)
    """
    n = check_int("n", n, minimum=0)
    check_choice("mode", mode, ("angle", "area"))
    y0, y1 = check_range("yaw_range", yaw_range, -math.inf, math.inf, "degrees")
    p0, p1 = check_range("pitch_range", pitch_range, -90.0, 90.0, "degrees")
    u = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    yaw = y0 + (y1 - y0) * u[:, 0]
    if mode == "angle":
        pitch = p0 + (p1 - p0) * u[:, 1]
    else:
        s0, s1 = math.sin(math.radians(p0)), math.sin(math.radians(p1))
        pitch = torch.rad2deg(torch.asin((s0 + (s1 - s0) * u[:, 1]).clamp(-1.0, 1.0)))
    vp = torch.stack([wrap_yaw(yaw), pitch], dim=-1)
    return vp.to(torch.get_default_dtype())


def sample_gaussian_viewpoints(centres: Tensor, sigma: float, generator: torch.Generator | None = None) -> Tensor:
    """Sample one viewpoint per centre from ``N(centre, sigma)`` per angle; wrap yaw, clamp pitch.

    Args:
        centres: ``(..., 2)`` (yaw, pitch) in degrees.
        sigma: standard deviation of the noise added to each angle, in degrees.
        generator: the random source (``None``: torch's global one).

    Returns:
        ``(..., 2)`` (yaw, pitch) in degrees, shape and dtype of ``centres``; yaw in ``[-180, 180)``, pitch in
        ``[-90, 90]``.

    Raises:
        ValueError: ``centres`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> sample_gaussian_viewpoints(torch.zeros(5, 3, 2), 10.0, torch.Generator().manual_seed(0)).shape
        torch.Size([5, 3, 2])
        >>> sample_gaussian_viewpoints(torch.tensor([[190.0, 95.0]]), 0.0)  # no noise: only wrapped and clamped
        tensor([[-170.,   90.]])
    """
    centres = check_viewpoints(centres, "centres")
    noise = torch.randn(centres.shape, generator=generator, dtype=torch.float64).to(centres)
    return normalize_viewpoints(centres + sigma * noise)


def angular_distance(a: Tensor, b: Tensor) -> Tensor:
    """Great-circle angle (degrees) between the viewing directions of viewpoints ``a`` and ``b`` (broadcast).

    Args:
        a: ``(..., 2)`` (yaw, pitch) in degrees.
        b: ``(..., 2)`` (yaw, pitch) in degrees, broadcastable with ``a``.

    Returns:
        The angles in degrees, in ``[0, 180]``, over the broadcast leading dimensions.

    Raises:
        ValueError: ``a`` or ``b`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> angular_distance(torch.tensor([0.0, 0.0]), torch.tensor([[90.0, 0.0], [0.0, 90.0], [180.0, 0.0]]))
        tensor([ 90.,  90., 180.])
    """
    da, db = camera_center(a), camera_center(b)
    cos = (da * db).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def voxel_centers(resolution: int = DEFAULT_RESOLUTION, dtype: torch.dtype = torch.float32) -> Tensor:
    """World coordinates ``(R, R, R, 3)`` of voxel centres; ``out[i, j, k] = (x, y, z)``.

    Args:
        resolution: side ``R`` of the grid, in voxels.
        dtype: dtype of the result.

    Returns:
        ``(R, R, R, 3)`` centres ``(i + 0.5) / R - 0.5`` (and so on per axis) in world units, inside
        ``[-0.5, 0.5]^3``.

    Example:
        >>> centres = voxel_centers(2)
        >>> centres.shape, centres[0, 0, 0], centres[1, 0, 1]
        (torch.Size([2, 2, 2, 3]), tensor([-0.2500, -0.2500, -0.2500]), tensor([ 0.2500, -0.2500,  0.2500]))
    """
    c = (torch.arange(resolution, dtype=torch.float64) + 0.5) / resolution - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return torch.stack([x, y, z], dim=-1).to(dtype)


def world_to_voxel_index(points: Tensor, resolution: int = DEFAULT_RESOLUTION) -> Tensor:
    """Integer voxel indices ``(..., 3)`` containing world points (may fall outside ``[0, R)``).

    Args:
        points: ``(..., 3)`` world coordinates, in world units.
        resolution: side ``R`` of the grid, which covers ``[-0.5, 0.5]^3``.

    Returns:
        ``(..., 3)`` int64 indices ``floor((p + 0.5) R)``; points outside the cube get indices outside
        ``[0, R)``, so check them before indexing.

    Example:
        >>> world_to_voxel_index(torch.tensor([[0.0, 0.0, 0.0], [-0.5, 0.49, 0.6]]), 32)
        tensor([[16, 16, 16],
                [ 0, 31, 35]])
    """
    return torch.floor((_as_tensor(points) + 0.5) * resolution).long()

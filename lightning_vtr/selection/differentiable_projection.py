"""A differentiable orthographic first-hit projection of voxel volumes (what MVTN trains through).

The error-guided selector's :func:`~lightning_vtr.selection.projection.error_projection` takes the
error value at the *first hit* along each orthographic ray; that is a hard, piecewise-constant
function of the viewpoint. MVTN needs gradients with respect to the viewing angles, so this module
replaces the hard first hit by the opacity a ray accumulates through the volume (one minus its
transmittance, the volume acting as absorption density): the volume is resampled trilinearly
(``F.grid_sample``) on rays laid out with :func:`lightning_vtr.geometry.camera_basis` and the image-plane
convention of :func:`lightning_vtr.geometry.orthographic_pixel_coords`, so the maps line up pixel for pixel
with the rest of the package. As ``density`` grows, the soft map tends to the hard first-hit map, which
``hard=True`` computes directly (nearest-voxel sampling, not differentiable).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from lightning_vtr.geometry import DEFAULT_HALF_EXTENT, camera_basis, check_viewpoints
from lightning_vtr.utils.validation import check_float, check_int

# DEFAULT_HALF_EXTENT is re-exported: half the side of the square each projection covers (world units), the
# radius of the unit cube's circumsphere, so no rotation of the grid leaves the image.
__all__ = ["DEFAULT_HALF_EXTENT", "soft_error_projection"]


def _check_inputs(volumes: Tensor, viewpoints: Tensor) -> tuple[Tensor, Tensor]:
    if not isinstance(volumes, Tensor):
        raise TypeError(f"`volumes` must be a torch.Tensor of shape (B, R, R, R), got {type(volumes).__name__}")
    if volumes.ndim != 4 or not (volumes.shape[1] == volumes.shape[2] == volumes.shape[3]):
        raise ValueError(f"`volumes` must be a tensor of shape (B, R, R, R), got {tuple(volumes.shape)}")
    vp = check_viewpoints(viewpoints)
    if vp.ndim == 2:
        vp = vp.unsqueeze(0).expand(volumes.shape[0], -1, -1)
    elif vp.ndim != 3 or vp.shape[0] != volumes.shape[0]:
        raise ValueError(
            f"`viewpoints` must have shape (V, 2) or (B, V, 2) with B={volumes.shape[0]}, got {tuple(vp.shape)}"
        )
    if not volumes.is_floating_point():
        volumes = volumes.to(vp.dtype if vp.is_floating_point() else torch.get_default_dtype())
    return volumes, vp.to(volumes.dtype)


def _ray_grid(viewpoints: Tensor, image_size: int, half_extent: float, num_samples: int) -> Tensor:
    """``grid_sample`` coordinates ``(B, V, D, S, S, 3)`` of the ray samples, nearest the camera first.

    A sample at image-plane coordinates ``(x, y)`` and depth ``d`` (along the viewing direction,
    relative to the origin) lies at ``x * right + y * up + d * forward`` in world space, the inverse
    of :func:`~lightning_vtr.geometry.orthographic_pixel_coords`.
    """
    dtype, device = viewpoints.dtype, viewpoints.device
    batch, num_views = viewpoints.shape[:2]
    pixel = 2.0 * half_extent / image_size
    coords = (torch.arange(image_size, dtype=dtype, device=device) + 0.5) * pixel
    cols = -half_extent + coords  # x grows with the column index
    rows = half_extent - coords  # y shrinks with the row index (row 0 at the top)
    # The depth range is the circumsphere's diameter so that every voxel of the cube is crossed.
    reach = DEFAULT_HALF_EXTENT
    depths = -reach + (torch.arange(num_samples, dtype=dtype, device=device) + 0.5) * (2.0 * reach / num_samples)
    d, y, x = torch.meshgrid(depths, rows, cols, indexing="ij")
    camera = torch.stack([x, y, -d], dim=-1).reshape(-1, 3)  # camera frame: x right, y up, z backward
    # World point p = basis^T c, i.e. the row vector c @ basis. grid_sample reads the last grid axis
    # as (W, H, D) = (k, j, i) = (z, y, x), so the basis columns are reversed; with
    # align_corners=False the normalised coordinate of voxel centre i is 2 * x_i, x_i in (-0.5, 0.5).
    basis = camera_basis(viewpoints).flip(-1) * 2.0  # (B, V, 3, 3)
    grid = camera @ basis.reshape(batch * num_views, 3, 3)  # (B * V, D * S * S, 3)
    return grid.reshape(batch, num_views, num_samples, image_size, image_size, 3)


def soft_error_projection(
    volumes: Tensor,
    viewpoints: Tensor,
    image_size: int | None = None,
    half_extent: float = DEFAULT_HALF_EXTENT,
    num_samples: int | None = None,
    density: float = 5.0,
    hard: bool = False,
    eps: float = 0.0,
) -> Tensor:
    r"""Orthographic first-hit maps of (error) volumes, differentiable in the volumes and the angles.

    Along each ray the volume value ``e_t`` (trilinear) at samples ``t = 1..D`` ordered from the
    camera acts as opacity; the map is the opacity accumulated front to back:

    .. math::

        \alpha_t = 1 - \exp(-\rho\, e_t\, \Delta), \quad
        T_t = \prod_{s < t} (1 - \alpha_s), \quad
        P(u, v) = \sum_t T_t\, \alpha_t = 1 - T_{D + 1}

    with ``Δ`` the sample spacing in voxels and ``ρ = density``. For a binary volume and large
    ``ρ``, ``P`` is the silhouette of the volume, i.e. the binary error at the first hit. (Using
    ``e_t`` as the colour too would make a sharp ``P`` read the small trilinear values at the
    entry of each ray into the volume; for soft errors ``P`` is instead a saturating amount of
    error met along the ray.)

    Args:
        volumes: ``(B, R, R, R)`` values in ``[0, 1]`` indexed per :mod:`lightning_vtr.geometry`.
        viewpoints: ``(V, 2)`` shared or ``(B, V, 2)`` per-object (yaw, pitch) in **degrees**;
            gradients flow to them.
        image_size: ``S`` of the ``S x S`` maps (default ``R``).
        half_extent: half the side of the square each map covers, in world units.
        num_samples: ray samples ``D`` across the circumsphere (default ``2 R``).
        density: opacity per voxel of unit value crossed; larger is sharper.
        hard: return the exact first-hit map instead (nearest-voxel sampling; no gradient).
        eps: with ``hard=True``, a sample counts as a hit when its value exceeds ``eps``.

    Returns:
        ``(B, V, S, S)`` projected maps; ``[..., row, col]`` follows the package image convention.

    Raises:
        ValueError: if ``volumes`` is not ``(B, R, R, R)``, ``viewpoints`` has the wrong shape,
            or a size, ``half_extent`` or ``density`` is not positive.
        TypeError: if a size is not an int or ``half_extent`` / ``density`` is not a number.

    Example:
        A 2x2 patch of error on the top layer of a ``4^3`` grid, seen from above:

        >>> volume = torch.zeros(1, 4, 4, 4)
        >>> volume[0, 1:3, 1:3, 3] = 1.0
        >>> viewpoints = torch.tensor([[0.0, 90.0]], requires_grad=True)
        >>> soft_error_projection(volume, viewpoints, hard=True)[0, 0]
        tensor([[0., 0., 0., 0.],
                [0., 1., 1., 0.],
                [0., 1., 1., 0.],
                [0., 0., 0., 0.]])
        >>> round(float(soft_error_projection(volume, viewpoints, density=1000.0).detach().sum()), 3)
        4.0
        >>> soft_error_projection(volume, viewpoints).sum().backward()  # gradients reach the angles
        >>> viewpoints.grad.shape
        torch.Size([1, 2])
    """
    volumes, vp = _check_inputs(volumes, viewpoints)
    resolution = volumes.shape[-1]
    image_size = resolution if image_size is None else check_int("image_size", image_size, minimum=1)
    num_samples = 2 * resolution if num_samples is None else check_int("num_samples", num_samples, minimum=1)
    check_float("half_extent", half_extent, minimum=0.0, min_open=True)
    check_float("density", density, minimum=0.0, min_open=True)
    batch, num_views = vp.shape[:2]

    grid = _ray_grid(vp, image_size, half_extent, num_samples)
    grid = grid.reshape(batch, num_views * num_samples, image_size, image_size, 3)
    mode = "nearest" if hard else "bilinear"  # "bilinear" is trilinear for 5-D inputs
    samples = F.grid_sample(volumes[:, None], grid, mode=mode, padding_mode="zeros", align_corners=False)
    samples = samples.reshape(batch, num_views, num_samples, image_size, image_size)

    if hard:
        hit = samples > eps
        first = hit.to(torch.uint8).argmax(dim=2, keepdim=True)  # index of the first hit (0 if none)
        value = samples.gather(2, first)[:, :, 0]
        return torch.where(hit.any(dim=2), value, torch.zeros_like(value)).detach()

    step = 2.0 * DEFAULT_HALF_EXTENT / num_samples * resolution  # spacing in voxels
    optical = density * step * samples
    # P = sum_t T_t alpha_t telescopes to 1 - T_final; the closed form is cheaper and exact.
    return 1.0 - torch.exp(-optical.sum(dim=2))

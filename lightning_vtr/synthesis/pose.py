"""The relative camera pose that conditions Zero-1-to-3, derived from the package's viewpoint conventions.

This is the only place where our ``(yaw, pitch)`` viewpoints (degrees, :mod:`lightning_vtr.geometry`)
are turned into Zero-1-to-3's spherical coordinates, so the sign conventions live in one file.

Zero-1-to-3 describes a camera by the spherical coordinates of its centre in a right-handed, +Z-up
world (Blender's frame, the same as ours):

* polar angle ``theta`` measured from +Z, so ``theta = 90 deg - pitch``;
* azimuth ``atan2(y, x)``, which is exactly our yaw (both turn about +Z from +X toward +Y);
* radius, the camera distance.

For a source (input) view ``s`` and a target view ``t`` the conditioning vector ``T`` (radians) is

* ``"zero123"`` (original Zero-1-to-3 / Zero123-XL, in either checkpoint layout):
  ``T = [theta_t - theta_s, sin(psi_t - psi_s), cos(psi_t - psi_s), r_t - r_s]``.
  A positive first entry moves the camera *down* (toward the equator and below), a positive
  azimuth difference turns the camera counter-clockwise seen from +Z.
* ``"stable"`` (Stable Zero123; the checkpoint layout does not tell it apart): the same first three entries;
  the fourth is the *source* view's polar angle ``theta_s`` in radians instead of a radius difference.
  Ports that assume the input photo is taken at the horizon write the constant ``deg2rad(90)``, which
  is what this gives for a source pitch of 0; we know the source pitch, so we use it.

The azimuth difference is wrapped into ``[-180, 180)`` degrees (the original wraps into ``[0, 360)``;
sine and cosine do not see the difference).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import angular_distance, check_viewpoints, wrap_yaw
from lightning_vtr.utils.validation import check_choice

__all__ = [
    "POSE_EMBEDDINGS",
    "PoseEmbedding",
    "nearest_source_view",
    "relative_pose",
    "relative_spherical",
    "spherical_coordinates",
]

PoseEmbedding = Literal["zero123", "stable"]
POSE_EMBEDDINGS: tuple[str, ...] = ("zero123", "stable")


def spherical_coordinates(viewpoints: Tensor) -> tuple[Tensor, Tensor]:
    """Zero-1-to-3's ``(polar, azimuth)`` in **degrees** of viewpoints ``(..., 2)`` given as (yaw, pitch) degrees.

    ``polar = 90 - pitch`` (from +Z, in ``[0, 180]``) and ``azimuth = yaw``. These are the spherical
    coordinates of :func:`lightning_vtr.geometry.camera_center`; we read them from the angles rather than
    from ``atan2`` of the centre so the azimuth stays defined at the poles (where the camera's up
    vector, and hence the image orientation, still depends on yaw).

    Returns:
        ``(polar (...,), azimuth (...,))`` in degrees.
    """
    vp = check_viewpoints(viewpoints)
    return 90.0 - vp[..., 1], wrap_yaw(vp[..., 0])


def relative_spherical(source: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Polar and azimuth differences ``target - source`` in **degrees**, azimuth wrapped into ``[-180, 180)``.

    Args:
        source: ``(..., 2)`` source viewpoints (yaw, pitch) in degrees.
        target: ``(..., 2)`` target viewpoints in degrees (broadcast against ``source``).

    Returns:
        ``(d_polar (...,), d_azimuth (...,))`` in degrees.
    """
    polar_s, azim_s = spherical_coordinates(check_viewpoints(source, "source"))
    polar_t, azim_t = spherical_coordinates(check_viewpoints(target, "target"))
    return polar_t - polar_s, wrap_yaw(azim_t - azim_s)


def relative_pose(
    source: Tensor,
    target: Tensor,
    embedding: PoseEmbedding = "zero123",
    *,
    source_radius: float | Tensor = 1.0,
    target_radius: float | Tensor = 1.0,
) -> Tensor:
    """The 4-vector ``T`` that conditions Zero-1-to-3 on a move from ``source`` to ``target``.

    Args:
        source: ``(..., 2)`` (yaw, pitch) in degrees of the input view.
        target: ``(..., 2)`` (yaw, pitch) in degrees of the view to synthesize (broadcast against ``source``).
        embedding: ``"zero123"`` ``[d_polar, sin d_azimuth, cos d_azimuth, d_radius]`` or ``"stable"``
            ``[d_polar, sin d_azimuth, cos d_azimuth, polar_source]`` (see the module docstring).
        source_radius: camera distance of the source view (only ``"zero123"`` uses it).
        target_radius: camera distance of the target view (only ``"zero123"`` uses it).

    Returns:
        ``(..., 4)`` float tensor; angles in **radians**.

    Raises:
        ValueError: an unknown ``embedding`` or malformed viewpoints.

    Example:
        From the horizon to 30 degrees up, same yaw: the polar angle drops by 30 degrees (``pi / 6``):

        >>> relative_pose(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 30.0]))
        tensor([-0.5236,  0.0000,  1.0000,  0.0000])
        >>> relative_pose(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 30.0]), "stable")  # 4th: source polar
        tensor([-0.5236,  0.0000,  1.0000,  1.5708])
        >>> relative_pose(torch.tensor([0.0, 0.0]), torch.tensor([[0.0, 30.0], [90.0, 0.0], [180.0, 0.0]])).shape
        torch.Size([3, 4])
    """
    check_choice("embedding", embedding, POSE_EMBEDDINGS)
    source = check_viewpoints(source, "source")
    target = check_viewpoints(target, "target")
    source, target = torch.broadcast_tensors(source, target.to(source.dtype))
    d_polar, d_azim = relative_spherical(source, target)
    d_polar, d_azim = torch.deg2rad(d_polar), torch.deg2rad(d_azim)
    if embedding == "zero123":
        r_s = torch.as_tensor(source_radius, dtype=source.dtype)
        r_t = torch.as_tensor(target_radius, dtype=source.dtype)
        fourth = torch.broadcast_to(r_t - r_s, d_polar.shape)
    else:
        polar_s, _ = spherical_coordinates(source)
        fourth = torch.deg2rad(polar_s)
    return torch.stack([d_polar, torch.sin(d_azim), torch.cos(d_azim), fourth], dim=-1)


def nearest_source_view(source_viewpoints: Tensor, target_viewpoints: Tensor) -> Tensor:
    """For each target, the index of the source view nearest in great-circle angle.

    Args:
        source_viewpoints: ``(S, 2)`` (yaw, pitch) in degrees, ``S >= 1``.
        target_viewpoints: ``(T, 2)`` (yaw, pitch) in degrees.

    Returns:
        ``(T,)`` long tensor of indices into ``source_viewpoints`` (ties go to the lowest index).

    Raises:
        ValueError: ``source_viewpoints`` is not ``(S, 2)`` with ``S >= 1``, ``target_viewpoints`` is not
            ``(T, 2)``, or either holds non-finite angles.

    Example:
        >>> sources = torch.tensor([[0.0, 0.0], [180.0, 0.0]])
        >>> nearest_source_view(sources, torch.tensor([[30.0, 10.0], [-150.0, 0.0], [170.0, 60.0]]))
        tensor([0, 1, 1])
    """
    src = check_viewpoints(source_viewpoints, "source_viewpoints")
    tgt = check_viewpoints(target_viewpoints, "target_viewpoints")
    if src.ndim != 2 or src.shape[0] == 0:
        raise ValueError(f"`source_viewpoints` must have shape (S, 2) with S >= 1, got {tuple(src.shape)}")
    if tgt.ndim != 2:
        raise ValueError(f"`target_viewpoints` must have shape (T, 2), got {tuple(tgt.shape)}")
    # float64 keeps acos well conditioned near 0 so nearly equal distances still rank correctly
    dist = angular_distance(src.double()[None, :, :], tgt.double()[:, None, :])  # (T, S)
    return dist.argmin(dim=1) if dist.shape[0] else torch.zeros(0, dtype=torch.long)

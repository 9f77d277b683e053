"""The error-guided view scores: first-hit projections of an error volume and the scores of every view.

``error_volume`` -> ``error_projection`` -> ``view_scores`` -> ``select_views``: the reconstruction error
``E = |V - V_gt|`` (:mod:`lightning_vtr.selection.volumes`) is projected orthographically onto every candidate
viewpoint (first hit from the camera side, :mod:`lightning_vtr.selection.first_hit`), each view is scored by
the error it sees, and the final viewpoints are sampled around the best-scoring angle bins
(:mod:`lightning_vtr.selection.bins`). All angles are in **degrees**; the camera, pixel layout, depth and bins
come from :mod:`lightning_vtr.geometry`. No Python loops run over voxels, pixels or views, and every function
works on CPU and CUDA tensors alike.

The names of those modules are importable from here as well.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import DEFAULT_HALF_EXTENT, check_viewpoints
from lightning_vtr.selection.bins import nearest_bins, sample_around_bins, select_views, top_bins
from lightning_vtr.selection.first_hit import (
    clear_projection_cache,
    first_hits,
    hit_sums,
    hit_values,
    is_binary,
    object_chunks,
    projection_table,
    value_rows,
)
from lightning_vtr.selection.volumes import (
    check_grid_shape,
    check_tensor_ndim,
    check_volume_pair,
    check_volumes,
    error_volume,
)
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "check_volume_pair",
    "check_volumes",
    "clear_projection_cache",
    "error_projection",
    "error_volume",
    "nearest_bins",
    "projection_scores",
    "sample_around_bins",
    "select_views",
    "soft_error_scores",
    "top_bins",
    "view_scores",
    "visible_error_scores",
]


def projection_scores(
    volumes: Tensor,
    viewpoints: Tensor,
    *,
    reduction: Literal["sum", "mean"] = "sum",
    eps: float = 0.0,
    binary: bool | None = None,
) -> Tensor:
    """``view_scores(error_projection(volumes, viewpoints, eps=eps), reduction=...)`` without building the maps.

    The error-guided selector scores every candidate view of a batch this way: it skips the ``(B, V, R, R)``
    float maps (and, for a binary error, the gather of hit values), which dominate the cost of the two-step form.
    Images have the default size ``R`` and half-extent :data:`~lightning_vtr.geometry.DEFAULT_HALF_EXTENT`.

    Args:
        volumes: ``(B, R, R, R)`` errors, floating-point or bool (a bool grid is used as is, not converted).
        viewpoints: ``(V, 2)`` (yaw, pitch) in degrees.
        reduction: ``"sum"`` or ``"mean"`` over hit pixels, as in :func:`view_scores`.
        eps: voxels with value ``<= eps`` are transparent.
        binary: ``True`` asserts that ``volumes`` holds only 0 and 1 (skips checking it; scores are then
            hit-pixel counts); ``None`` checks.

    Returns:
        ``(B, V)`` scores, dtype of ``volumes`` (the default float dtype for a bool grid).

    Raises:
        TypeError: ``volumes`` is not a floating-point or bool tensor.
        ValueError: ``volumes`` is not ``(B, R, R, R)`` or ``reduction`` is unknown.

    Example:
        >>> volume = torch.zeros(1, 4, 4, 4)
        >>> volume[0, 1:3, 1:3, 3] = 1.0  # a 2x2 patch of error on the top layer
        >>> viewpoints = torch.tensor([[0.0, 90.0], [0.0, 0.0]])  # from above, from the side
        >>> projection_scores(volume, viewpoints)
        tensor([[4., 2.]])
        >>> torch.equal(projection_scores(volume, viewpoints), view_scores(error_projection(volume, viewpoints)))
        True
    """
    # Shape only: converting a bool grid to float would cost what this function exists to save.
    check_grid_shape(volumes, "volumes")
    if not (volumes.is_floating_point() or volumes.dtype == torch.bool):
        raise TypeError(f"`volumes` must be a floating-point (or bool) tensor, got dtype {volumes.dtype}")
    check_choice("reduction", reduction, ("sum", "mean"))
    batch = volumes.shape[0]
    dtype = volumes.dtype if volumes.is_floating_point() else torch.get_default_dtype()
    if batch == 0:
        return torch.zeros(0, viewpoints.shape[0], dtype=dtype, device=volumes.device)
    flat = volumes.reshape(batch, -1)
    occupied = flat.bool() if binary else flat > eps  # binary: values are exactly 0 or 1
    if binary or (binary is None and is_binary(flat, eps)):
        return _value_scores(occupied, volumes.shape[1], None, viewpoints, reduction, dtype)
    return _value_scores(
        occupied,
        volumes.shape[1],
        lambda chunk: value_rows(flat[chunk], counts=reduction == "mean"),
        viewpoints,
        reduction,
        dtype,
    )


def _value_scores(
    occupied: Tensor,
    resolution: int,
    rows_of: Callable[[slice], Tensor] | None,
    viewpoints: Tensor,
    reduction: str,
    dtype: torch.dtype,
) -> Tensor:
    """:func:`projection_scores` of ``occupied (B, N)`` voxels worth their :func:`value_rows` ``rows_of(chunk)``
    (with hit counts for ``"mean"``), or 1 each for ``rows_of=None``."""
    batch = occupied.shape[0]
    table = projection_table(resolution, viewpoints, resolution, DEFAULT_HALF_EXTENT, occupied.device)
    columns = table.column_of_view
    total = torch.zeros(batch, viewpoints.shape[0], dtype=dtype, device=occupied.device)
    hits = torch.zeros(batch, viewpoints.shape[0], dtype=torch.int32, device=occupied.device)
    for chunk in object_chunks(occupied, viewpoints.shape[0], table.pixel_of.numel()):
        if rows_of is None:  # every hit is worth 1: count the hit slots
            count = first_hits(occupied[chunk], resolution, table, hits_only=True).sum(-1, dtype=torch.int32)
            hits[chunk] = count.index_select(1, columns)
            total[chunk] = hits[chunk].to(dtype)
        else:  # values: gathered and summed, with the hit count in a second column for a mean
            best = first_hits(occupied[chunk], resolution, table)
            sums = hit_sums(best, rows_of(chunk)).index_select(1, columns)
            total[chunk] = sums[..., 0].to(dtype)
            if reduction == "mean":
                hits[chunk] = sums[..., 1].to(torch.int32)  # exact: a count <= S^2 is exact in float32
    if reduction == "sum":
        return total
    return torch.where(hits > 0, total / hits.clamp_min(1).to(dtype), torch.zeros_like(total))


def soft_error_scores(
    predicted: Tensor,
    target: Tensor,
    viewpoints: Tensor,
    *,
    mask: Literal[None, "gt"] = None,
    reduction: Literal["sum", "mean"] = "sum",
    eps: float = 0.0,
) -> Tensor:
    """``projection_scores(error_volume(predicted, target, mode="soft", mask=mask), viewpoints, reduction=reduction,
    eps=eps, binary=False)``, exactly, without the error volume.

    The error is written once, straight into the rows the hit values are summed from (the released code's score:
    the soft error inside the truth, mean over the hit pixels). Grids other than two float32 or two float64
    ones take the two-step form.
    """
    predicted, target = check_volume_pair(predicted, target)
    check_choice("mask", mask, (None, "gt"))
    check_choice("reduction", reduction, ("sum", "mean"))
    batch = predicted.shape[0]
    if batch == 0 or predicted.dtype not in (torch.float32, torch.float64) or target.dtype != predicted.dtype:
        errors = error_volume(predicted, target, mode="soft", mask=mask)
        return projection_scores(errors, viewpoints, reduction=reduction, eps=eps, binary=False)
    flat_target = target.reshape(batch, -1)
    # as value_rows(error_volume(...)): |predicted - target| (0 outside the truth), then a 0 for a miss; for a
    # mean a second column of ones (0 for a miss) counts the hits
    shape = (batch, flat_target.shape[1] + 1, 2 if reduction == "mean" else 1)
    rows = predicted.new_ones(shape) if reduction == "mean" else predicted.new_empty(shape)
    rows[:, -1] = 0
    errors = rows[:, :-1, 0]
    torch.sub(predicted.reshape(batch, -1), flat_target, out=errors).abs_()
    if mask == "gt":
        errors.masked_fill_(flat_target.ge(0.5).logical_not_(), 0.0)  # as error_volume: not >= 0.5 (NaN too)
    rows_of = lambda chunk: rows[chunk].view(-1, shape[2])  # noqa: E731
    return _value_scores(errors > eps, predicted.shape[1], rows_of, viewpoints, reduction, predicted.dtype)


def visible_error_scores(
    predicted: Tensor,
    target: Tensor,
    viewpoints: Tensor,
    *,
    threshold: float = 0.4,
    mode: Literal["binary", "soft"] = "binary",
) -> Tensor:
    """What a camera at each viewpoint would see wrong: the side-aware view score.

    Along each pixel's ray the first voxel occupied in the prediction (``>= threshold``) *or* in the ground
    truth is the surface that camera sees; the pixel takes the error at that voxel (``mode`` as in
    :func:`error_volume`) and the view's score is the sum over pixels. Unlike the sum of the error's own
    first-hit map, which is the area of the error's silhouette and the same for a view and its antipode, a
    wrong top slab scores high from above and 0 from below, where correct voxels hide it.

    Args:
        predicted: ``(B, R, R, R)`` occupancy probabilities in ``[0, 1]``.
        target: ``(B, R, R, R)`` ground-truth occupancy in ``{0, 1}``.
        viewpoints: ``(V, 2)`` (yaw, pitch) in degrees.
        threshold: occupancy threshold of the prediction.
        mode: ``"binary"`` (the error is 1 where prediction and truth disagree) or ``"soft"``
            (``|predicted - target|`` at the visible voxel).

    Returns:
        ``(B, V)`` scores, dtype of ``predicted``.

    Example:
        >>> target = torch.zeros(1, 8, 8, 8)
        >>> target[0, 2:6, 2:6, 2:6] = 1.0  # a cube of side 4 voxels
        >>> predicted = target.clone()
        >>> predicted[0, 2:6, 2:6, 5] = 0.0  # its top slab missed
        >>> scores = visible_error_scores(predicted, target, torch.tensor([[0.0, 90.0], [0.0, -90.0]]))
        >>> bool(scores[0, 0] > 0), scores[0, 1].item()  # from above the missed top is seen; from below nothing
        (True, 0.0)
    """
    predicted, target = check_volume_pair(predicted, target)
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    check_choice("mode", mode, ("binary", "soft"))
    batch, resolution = predicted.shape[0], predicted.shape[1]
    if batch == 0:
        return predicted.new_zeros(0, viewpoints.shape[0])
    occupied_pred, occupied_gt = predicted >= threshold, target >= 0.5
    errors = occupied_pred != occupied_gt if mode == "binary" else (predicted - target).abs()
    surface, errors = (occupied_pred | occupied_gt).reshape(batch, -1), errors.reshape(batch, -1)
    table = projection_table(resolution, viewpoints, resolution, DEFAULT_HALF_EXTENT, predicted.device)
    scores = predicted.new_zeros(batch, viewpoints.shape[0])
    for chunk in object_chunks(surface, viewpoints.shape[0], table.pixel_of.numel()):
        if mode == "binary":  # the keys carry the error bit of the first hit
            best = first_hits(surface[chunk], resolution, table, errors[chunk])
            seen = best.bitwise_and_(1).sum(-1, dtype=torch.int32)
        else:
            best = first_hits(surface[chunk], resolution, table)
            seen = hit_sums(best, value_rows(errors[chunk], predicted.dtype))[..., 0]
        scores[chunk] = seen.index_select(1, table.column_of_view).to(scores.dtype)
    return scores


def error_projection(
    volumes: Tensor,
    viewpoints: Tensor,
    *,
    image_size: int | None = None,
    half_extent: float = DEFAULT_HALF_EXTENT,
    eps: float = 0.0,
) -> Tensor:
    """Orthographic first-hit projection of voxel grids onto a set of viewpoints.

    Each pixel takes the value of the first voxel with value ``> eps`` along its ray from the camera
    side, and 0 where nothing is hit (see the module docstring for the exact definition of the hit and
    its tie break). Pixel layout and depth are those of
    :func:`~lightning_vtr.geometry.orthographic_pixel_coords`; voxel centres those of
    :func:`~lightning_vtr.geometry.voxel_centers`.

    Args:
        volumes: ``(B, R, R, R)`` or ``(R, R, R)`` values (e.g. an error volume), any float dtype.
        viewpoints: ``(V, 2)`` (yaw, pitch) in degrees.
        image_size: ``S``, the side of the square projection in pixels; defaults to ``R``.
        half_extent: half the side of the square the image covers, in world units. The default
            :data:`~lightning_vtr.geometry.DEFAULT_HALF_EXTENT` (``sqrt(3) / 2``) keeps the whole unit cube
            in view from any direction.
        eps: voxels with value ``<= eps`` are transparent.

    Returns:
        ``(B, V, S, S)`` (``(V, S, S)`` for an unbatched input), dtype and device of ``volumes``.
        ``B = 0`` gives an empty result.

    Raises:
        ValueError: for a non-cubic or empty grid, no viewpoints, or a bad ``image_size`` / ``half_extent``.
        TypeError: for a non-tensor ``volumes``, a non-int ``image_size`` or a non-number ``half_extent``.

    Example:
        A 2x2 patch of error on the top layer of a ``4^3`` grid, seen from above and from the side:

        >>> volume = torch.zeros(4, 4, 4)
        >>> volume[1:3, 1:3, 3] = 1.0
        >>> maps = error_projection(volume, torch.tensor([[0.0, 90.0], [0.0, 0.0]]))
        >>> maps.shape
        torch.Size([2, 4, 4])
        >>> maps[0]
        tensor([[0., 0., 0., 0.],
                [0., 1., 1., 0.],
                [0., 1., 1., 0.],
                [0., 0., 0., 0.]])
        >>> maps[1]
        tensor([[0., 0., 0., 0.],
                [0., 1., 1., 0.],
                [0., 0., 0., 0.],
                [0., 0., 0., 0.]])
    """
    unbatched = isinstance(volumes, Tensor) and volumes.ndim == 3
    vol = check_volumes(volumes[None] if unbatched else volumes, "volumes")
    vp = check_viewpoints(viewpoints)
    if vp.ndim != 2 or vp.shape[0] == 0:
        raise ValueError(f"`viewpoints` must have shape (V, 2) with V >= 1, got {tuple(vp.shape)}")
    batch, resolution = vol.shape[0], vol.shape[1]
    size = resolution if image_size is None else check_int("image_size", image_size, minimum=1)
    check_float("half_extent", half_extent, minimum=0.0, min_open=True)
    out_shape = (batch, vp.shape[0], size, size)
    if batch == 0:
        result = vol.new_zeros(out_shape)
        return result[0] if unbatched else result

    flat = vol.reshape(batch, -1)
    table = projection_table(resolution, vp, size, half_extent, vol.device)
    if is_binary(flat, eps):  # the paper's binary error: every hit has value 1
        maps = first_hits(flat > eps, resolution, table, hits_only=True).to(vol.dtype)
    else:
        maps = hit_values(first_hits(flat > eps, resolution, table), flat)
    # from the slots of each view's column back to its image (unused slots and the sink go to pixel S^2, dropped)
    columns = table.column_of_view
    result = vol.new_zeros(batch, vp.shape[0], size * size + 1)
    result.scatter_(2, table.pixel_of.expand(batch, -1, -1), maps.index_select(1, columns))
    result = result[..., : size * size].reshape(out_shape)
    return result[0] if unbatched else result


def view_scores(projections: Tensor, *, reduction: Literal["sum", "mean"] = "sum") -> Tensor:
    """Score every view by the error it sees.

    Args:
        projections: ``(B, V, S, S)`` maps from :func:`error_projection`.
        reduction: ``"sum"`` of the map (the paper) or ``"mean"`` over hit (non-zero) pixels, which is 0
            for a map with no hit (the released code divides by zero there).

    Returns:
        ``(B, V)`` scores, dtype of ``projections``.

    Raises:
        TypeError: ``projections`` is not a tensor.
        ValueError: another shape, or an unknown ``reduction``.

    Example:
        >>> volume = torch.zeros(1, 4, 4, 4)
        >>> volume[0, 1:3, 1:3, 3] = 1.0  # a 2x2 patch of error on the top layer
        >>> maps = error_projection(volume, torch.tensor([[0.0, 90.0], [0.0, 0.0]]))  # from above, from the side
        >>> view_scores(maps)
        tensor([[4., 2.]])
        >>> view_scores(maps, reduction="mean")
        tensor([[1., 1.]])
    """
    check_tensor_ndim(projections, "projections", 4, "(B, V, S, S)")
    check_choice("reduction", reduction, ("sum", "mean"))
    total = projections.sum(dim=(-2, -1))
    if reduction == "sum":
        return total
    hits = (projections != 0).sum(dim=(-2, -1))
    return torch.where(hits > 0, total / hits.clamp_min(1).to(total.dtype), torch.zeros_like(total))

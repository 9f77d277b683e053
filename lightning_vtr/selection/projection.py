"""The paper's error-guided view selection as batched tensor functions.

``error_volume`` -> ``error_projection`` -> ``view_scores`` -> ``select_views``: the reconstruction error
``E = |V - V_gt|`` is projected orthographically onto every candidate viewpoint (first hit from the camera
side), each view is scored by the error it sees, and the final viewpoints are sampled around the
best-scoring angle bins. All angles are in **degrees**; the camera, pixel layout, depth and bins come from
:mod:`lightning_vtr.geometry`. No Python loops run over voxels, pixels or views, and every function works
on CPU and CUDA tensors alike.

How the first hit is defined: each voxel is represented by its **centre**. A centre projects to the
pixel that contains it (``floor`` of the continuous ``(row, col)`` of
:func:`~lightning_vtr.geometry.orthographic_pixel_coords`); among the voxels above ``eps`` that land in a
pixel, the one with the smallest depth (nearest the camera) wins and the pixel takes its value. Depths
within ``1e-9`` world units of each other count as equal and such ties go to the lowest flat voxel index
``i * R^2 + j * R + k``, so the result does not depend on float rounding or scatter order. With the
default ``image_size = R`` and ``half_extent = sqrt(3) / 2`` a pixel is ``sqrt(3) ~ 1.7`` voxels wide, so
no voxel leaves the image from any viewpoint and a solid's projection has no holes.

The implementation is sparse: for a given grid size and set of viewpoints it precomputes (once, cached)
the pixel of every voxel centre and its depth rank in every view. Per call it takes only the voxels above
``eps``, looks up their pixels and ranks, keeps the smallest rank per ``(object, view, pixel)`` with a
``scatter_reduce(..., "amin")`` (the rank encodes depth and the tie break in one sortable integer), and
sums (``embedding_bag``) or gathers the values of the winning voxels.

Occluded voxels are left out before the scatter. The views are grouped by the octant their cameras look
from; a voxel whose 2x2x2 block towards that octant is full is skipped for the group's views when the
table found, for every one of them, a voxel of that block in the same pixel with a smaller rank (true of
every voxel off the grid's front faces for the candidate views). That changes no first hit, and keeps
about a quarter of a solid's (voxel, view) pairs.
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from collections.abc import Callable
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from lightning_vtr.geometry import (
    DEFAULT_HALF_EXTENT,
    candidate_viewpoints,
    check_bin_interval,
    check_viewpoints,
    orthographic_pixel_coords,
    sample_gaussian_viewpoints,
    voxel_centers,
    wrap_yaw,
)
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "check_volume_pair",
    "clear_projection_cache",
    "check_volumes",
    "error_projection",
    "error_volume",
    "nearest_bins",
    "projection_scores",
    "sample_around_bins",
    "select_views",
    "top_bins",
    "view_scores",
    "visible_error_scores",
]

#: Depths closer than this (world units; a voxel is 1/R >= 1e-3 wide) are treated as equal.
_DEPTH_TIE_TOLERANCE = 1e-9
#: How many projection tables (one per grid size, viewpoint set, image size, device) are kept.
_TABLE_CACHE_SIZE = 6
#: Views processed together while building a table, to bound the float64 temporaries.
_TABLE_VIEW_CHUNK = 16
#: Occupied (voxel, view) pairs per chunk of objects in the score functions, before culling: bounds the
#: index buffers (tens of MB). The scatter writes one view group's (B, V / 8, S^2 + 1) buffer at a time, which
#: stays in cache, so chunks can be big: on 2 cores, 64 objects at R = 32, K = 30 (about 2^24 pairs) scored
#: fastest in chunks of 2^24 to 2^25 pairs, ~20 % faster than in chunks of 2^22.
_SCORE_CHUNK_PAIRS = 1 << 25
#: The per-group culling runs when the full 2x2x2 blocks number more than this share of the occupied voxels
#: (each block culls at most one voxel per group). On the benchmark's objects it paid for the "visible"
#: surfaces (0.75 blocks per voxel, 1.2x faster) and cost the "paper" score's error blobs (0.36, 0.9x).
_CULL_MIN_SHARE = 0.5

_table_cache: OrderedDict[tuple, _Table] = OrderedDict()


# --------------------------------------------------------------------------------------------- checks
def _check_grid_shape(volumes: Tensor, name: str) -> None:
    if not isinstance(volumes, Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor, got {type(volumes).__name__}")
    if volumes.ndim != 4 or not (volumes.shape[1] == volumes.shape[2] == volumes.shape[3]):
        raise ValueError(f"`{name}` must have shape (B, R, R, R), got {tuple(volumes.shape)}")
    if volumes.shape[1] == 0:
        raise ValueError(f"`{name}` must be a non-empty grid (R >= 1), got shape {tuple(volumes.shape)}")


def _check_tensor_ndim(value: Tensor, name: str, ndim: int, shape: str) -> None:
    if not isinstance(value, Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape {shape}, got {type(value).__name__}")
    if value.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape}, got {tuple(value.shape)}")


def check_volumes(volumes: Tensor, name: str = "volumes") -> Tensor:
    """Check a batch of cubic voxel grids ``(B, R, R, R)``, ``R >= 1``; returns it as a float tensor.

    A bool tensor is converted to the default float dtype; a float tensor is returned as is.

    Args:
        volumes: the grids to check.
        name: the argument's name in error messages.

    Raises:
        TypeError: ``volumes`` is not a tensor, or is neither floating-point nor bool.
        ValueError: another shape, or an empty grid (``R = 0``).
    """
    _check_grid_shape(volumes, name)
    if volumes.dtype == torch.bool:
        return volumes.to(torch.get_default_dtype())
    if not volumes.is_floating_point():
        raise TypeError(f"`{name}` must be a floating-point (or bool) tensor, got dtype {volumes.dtype}")
    return volumes


def check_volume_pair(predicted: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Check what every :class:`~lightning_vtr.selection.base.ViewSelector` receives: two batches of grids.

    ``predicted`` and ``target`` must be ``(B, R, R, R)`` tensors of the same shape (see
    :func:`check_volumes`); a custom selector can call this first to fail with the package's messages.

    Returns:
        ``(predicted, target)`` as float tensors (bool grids converted).

    Raises:
        TypeError: either is not a floating-point or bool tensor.
        ValueError: the shapes differ (the message names both) or are not ``(B, R, R, R)`` with ``R >= 1``.
    """
    if not isinstance(predicted, Tensor) or not isinstance(target, Tensor):
        raise TypeError(
            f"`predicted` and `target` must be torch.Tensors, got {type(predicted).__name__} and {type(target).__name__}"
        )
    if predicted.shape != target.shape:
        raise ValueError(
            f"`predicted` and `target` must have the same shape (B, R, R, R), got predicted "
            f"{tuple(predicted.shape)} and target {tuple(target.shape)}"
        )
    return check_volumes(predicted, "predicted"), check_volumes(target, "target")


# --------------------------------------------------------------------------------------- error volume
def error_volume(
    predicted: Tensor,
    target: Tensor,
    *,
    threshold: float = 0.4,
    mode: Literal["binary", "soft"] = "binary",
    mask: Literal[None, "gt"] = None,
) -> Tensor:
    """Reconstruction error ``E = |V - V_gt|`` of a batch of voxel grids.

    Args:
        predicted: ``(B, R, R, R)`` occupancy probabilities in ``[0, 1]``.
        target: ``(B, R, R, R)`` ground-truth occupancy in ``{0, 1}`` (binarised at 0.5).
        threshold: ``mode="binary"`` binarises the prediction as ``predicted >= threshold`` (the IoU
            convention), so ``E`` is in ``{0, 1}`` (the paper's definition, threshold 0.4).
        mode: ``"binary"`` (paper) or ``"soft"`` (``|predicted - target|`` of the continuous output).
        mask: ``"gt"`` keeps only errors inside ground-truth voxels (missed parts, as the released code
            does); ``None`` keeps every error.

    Returns:
        ``(B, R, R, R)`` error in ``[0, 1]``, dtype of ``predicted``.

    Raises:
        ValueError: on mismatched shapes (naming both) or a bad ``threshold`` / ``mode`` / ``mask``.
        TypeError: a non-tensor input or a non-number ``threshold``.
    """
    predicted, target = check_volume_pair(predicted, target)
    check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    check_choice("mode", mode, ("binary", "soft"))
    check_choice("mask", mask, (None, "gt"))
    gt = target >= 0.5
    if mode == "binary":
        err = ((predicted >= threshold) != gt).to(predicted.dtype)
    else:
        err = (predicted - target.to(predicted.dtype)).abs()
    if mask == "gt":
        err.masked_fill_(~gt, 0.0)  # err is a fresh tensor in both modes
    return err


# ---------------------------------------------------------------------------------- projection table
class _ViewGroup(NamedTuple):
    """The views whose cameras lie in one octant, with their columns of the projection table.

    ``occludable[n]`` says that voxel ``n`` is never a first hit in these views while the 2x2x2 block
    made of it and its 7 neighbours one step towards the cameras is occupied: in every view of the group
    one of those neighbours falls in the same pixel with a smaller key. The scatter leaves such voxels out.
    That changes no first hit: from a left-out voxel, "a smaller key in the same pixel" leads through
    strictly smaller keys to a voxel that was kept.
    """

    views: Tensor  # (Vg,) int64: the group's views in the viewpoint order
    slot: Tensor  # (N, Vg) scatter slots: v * (S^2 + 1) + pixel, v numbering the group's views
    key: Tensor  # (N, Vg) first-hit keys
    flag_key: Tensor  # (N, Vg) the keys' ranks, doubled: room for a flag bit (see _first_hits)
    occludable: Tensor  # (N,) bool
    block_offset: int  # where the voxel's block towards the cameras sits in the padded block grid


class _Table(NamedTuple):
    groups: list[_ViewGroup]
    block_index: Tensor  # (N,) int64: voxel (i, j, k) at (i, j, k) of an (R + 1)^3 grid
    occludable: Tensor  # (N,) bool: occludable in every group


def _key_bits(n_vox: int) -> int:
    """Low bits of a first-hit key that hold the voxel index (room for ``0..N``: ``N`` marks a miss)."""
    return n_vox.bit_length()


def _missed_key(n_vox: int) -> int:
    """The key of a pixel nothing hits: above every voxel's key, and its low bits name voxel ``N``.

    Gathering values at the low bits of the keys, from volumes padded with one zero voxel ``N``, then
    values a missed pixel 0 without a separate mask.
    """
    return ((n_vox - 1) << _key_bits(n_vox)) | n_vox


def _view_groups(slot: Tensor, key: Tensor, resolution: int, viewpoints: Tensor, pixels: int) -> list[_ViewGroup]:
    """Split the ``(N, V)`` pixel and key table by the octant the cameras look from; find the occludable voxels."""
    centres = voxel_centers(max(resolution, 2), torch.float64)
    points = torch.stack([centres[0, 0, 0], centres[1, 0, 0], centres[0, 1, 0], centres[0, 0, 1]])
    depth = orthographic_pixel_coords(points, viewpoints, 1, 1.0)[..., 2]  # (V, 4)
    # per grid axis: +1 if a step up the axis moves towards the camera (smaller depth), else -1
    towards = torch.where(depth[:, 1:] < depth[:, :1], 1, -1)
    by_steps: dict[tuple[int, ...], list[int]] = {}
    for view, steps in enumerate(towards.tolist()):
        by_steps.setdefault(tuple(steps), []).append(view)

    axis = torch.arange(resolution)
    ijk = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    strides = torch.tensor([resolution * resolution, resolution, 1])
    padded_strides = torch.tensor([(resolution + 1) ** 2, resolution + 1, 1])
    groups = []
    for steps, views in by_steps.items():
        columns = torch.tensor(views)
        group_slot = slot[:, columns] + torch.arange(len(views)) * (pixels + 1)
        group_key = key[:, columns].contiguous()
        hidden = torch.zeros(group_slot.shape, dtype=torch.bool)
        for offset in itertools.product(*[(0, step) for step in steps]):
            if not any(offset):
                continue
            moved = ijk + torch.tensor(offset)
            inside = ((moved >= 0) & (moved < resolution)).all(-1, keepdim=True)
            index = (moved.clamp(0, resolution - 1) * strides).sum(-1)
            hidden |= (group_slot[index] == group_slot) & (group_key[index] < group_key) & inside
        block_offset = int((padded_strides * (torch.tensor(steps) > 0)).sum())
        flag_key = (group_key >> _key_bits(resolution**3)) << 1
        groups.append(_ViewGroup(columns, group_slot, group_key, flag_key, hidden.all(1), block_offset))
    return groups


def _projection_table(
    resolution: int, viewpoints: Tensor, image_size: int, half_extent: float, device: torch.device
) -> _Table:
    """Per voxel and view: the scatter slot and the sortable first-hit key (cached per argument set).

    ``slot``: ``v * (S^2 + 1) + row * S + col``, or ``v * (S^2 + 1) + S^2`` (a discarded slot) for a
    centre outside the image, ``v`` numbering the views of a group. ``key``: ``(rank << b) | n`` with ``b =`` :func:`_key_bits` ``(N)``, where
    ``rank`` is the position of voxel ``n`` in the view's (depth, flat index) order, so the smallest key in
    a pixel is its first hit and the low ``b`` bits name the voxel. Both int32 where they fit. The table is
    voxel-major, so a call gathers whole contiguous rows for its occupied voxels, and split into
    :class:`_ViewGroup` s by camera octant.
    """
    vp64 = viewpoints.detach().to("cpu", torch.float64)
    cache_key = (resolution, image_size, float(half_extent), str(device), tuple(vp64.flatten().tolist()))
    if cache_key in _table_cache:
        _table_cache.move_to_end(cache_key)
        return _table_cache[cache_key]

    n_vox = resolution**3
    pixels = image_size * image_size
    bits = _key_bits(n_vox)
    int32_max = torch.iinfo(torch.int32).max
    key_dtype = torch.int32 if _missed_key(n_vox) <= int32_max else torch.int64
    slot_dtype = torch.int32 if vp64.shape[0] * (pixels + 1) <= int32_max else torch.int64
    centres = voxel_centers(resolution, torch.float64).reshape(-1, 3)
    flat = torch.arange(n_vox, dtype=torch.int64)
    slots, keys = [], []
    for start in range(0, vp64.shape[0], _TABLE_VIEW_CHUNK):
        chunk = vp64[start : start + _TABLE_VIEW_CHUNK]
        coords = orthographic_pixel_coords(centres, chunk, image_size, half_extent)  # (v, N, 3)
        row, col, depth = coords.unbind(-1)
        row_i, col_i = torch.floor(row).long(), torch.floor(col).long()
        inside = (row_i >= 0) & (row_i < image_size) & (col_i >= 0) & (col_i < image_size)
        slots.append(torch.where(inside, row_i * image_size + col_i, torch.full_like(row_i, pixels)))
        # Group depths that differ only by rounding, then order by (group, flat index): one integer
        # rank that makes "nearest, then lowest index" a single amin.
        sorted_depth, by_depth = torch.sort(depth, dim=-1, stable=True)
        step = torch.diff(sorted_depth, dim=-1) > _DEPTH_TIE_TOLERANCE
        group_sorted = torch.cat([torch.zeros_like(step[:, :1], dtype=torch.int64), step.long().cumsum(-1)], -1)
        group = torch.empty_like(group_sorted).scatter_(-1, by_depth, group_sorted)
        order = torch.argsort(group * n_vox + flat, dim=-1)
        rank = torch.empty_like(order).scatter_(-1, order, flat.expand_as(order).contiguous())
        keys.append((rank << bits) | flat)
    slot, key = torch.cat(slots).t().contiguous(), torch.cat(keys).t().contiguous()
    groups = [
        _ViewGroup(
            group.views.to(device),
            group.slot.to(device=device, dtype=slot_dtype),
            group.key.to(device=device, dtype=key_dtype),
            group.flag_key.to(device=device, dtype=torch.int32 if 2 * n_vox < int32_max else torch.int64),
            group.occludable.to(device),
            group.block_offset,
        )
        for group in _view_groups(slot, key, resolution, vp64, pixels)
    ]
    axis = torch.arange(resolution, device=device)
    block_index = (axis[:, None, None] * (resolution + 1) + axis[:, None]) * (resolution + 1) + axis
    occludable = torch.stack([group.occludable for group in groups]).all(0)
    table = _Table(groups, block_index.reshape(-1), occludable)
    _table_cache[cache_key] = table
    while len(_table_cache) > _TABLE_CACHE_SIZE:
        _table_cache.popitem(last=False)
    return table


def clear_projection_cache() -> None:
    """Drop the cached projection tables (the next call rebuilds them; benchmarks time that build)."""
    _table_cache.clear()


def _all_of_2x2x2(grid: Tensor) -> Tensor:
    """``(B, D - 1, D - 1, D - 1)`` bool of a ``(B, D, D, D)`` bool grid: entry ``(i, j, k)`` says the 2x2x2 block
    from ``(i, j, k)`` to ``(i + 1, j + 1, k + 1)`` is all set."""
    grid = grid[:, 1:] & grid[:, :-1]
    grid = grid[:, :, 1:] & grid[:, :, :-1]
    return grid[:, :, :, 1:] & grid[:, :, :, :-1]


def _full_blocks(grid: Tensor) -> Tensor:
    """``(B, (R + 1)^3)`` bool: entry ``(i, j, k)`` says voxels ``(i - 1 .. i, j - 1 .. j, k - 1 .. k)`` are all occupied.

    Zero on the border, so the block towards the cameras of voxel ``n`` is entry ``n + (steps > 0)``.
    """
    batch, resolution = grid.shape[0], grid.shape[1]
    padded = grid.new_zeros(batch, resolution + 1, resolution + 1, resolution + 1)
    padded[:, 1:resolution, 1:resolution, 1:resolution] = _all_of_2x2x2(grid)
    return padded.view(batch, -1)


def _first_hits(
    occupied: Tensor,
    resolution: int,
    viewpoints: Tensor,
    image_size: int,
    half_extent: float,
    consume: Callable[[Tensor, Tensor], None],
    flags: Tensor | None = None,
) -> None:
    """Smallest first-hit key per ``(object, view, pixel)`` for ``occupied (B, N)`` bool voxels, group by group.

    Calls ``consume(views, keys)`` once per :class:`_ViewGroup`, with the group's view numbers ``(Vg,)`` and
    its ``(B, Vg, S^2 + 1)`` keys: :func:`_missed_key` where nothing is hit (the last pixel of each view
    collects centres outside the image and is reset to a miss); ``consume`` may overwrite the keys. A
    group's buffer is an eighth of all the views' and stays in cache while the scatter writes it.

    With ``flags`` (``(B, N)`` bool) the keys are ``(rank << 1) | flag``: bit 0 of a pixel's key is the flag
    of its first hit (no gather needed to read it), a miss is ``2 N`` (bit 0 clear), and the voxel index is
    not kept.
    """
    batch = occupied.shape[0]
    pixels = image_size * image_size
    table = _projection_table(resolution, viewpoints, image_size, half_extent, occupied.device)
    n_vox = resolution**3
    missed = _missed_key(n_vox) if flags is None else 2 * n_vox
    blocks = _full_blocks(occupied.view(batch, resolution, resolution, resolution))
    # A voxel whose 3x3x3 neighbourhood is full (its 8 blocks are) is culled in every group: leave it out now.
    deep = _all_of_2x2x2(blocks.view(batch, resolution + 1, resolution + 1, resolution + 1))
    deep = deep.reshape(batch, -1).logical_and_(table.occludable)
    # one flat nonzero is cheaper than a 2-d one; split it into (object, voxel) arithmetically
    flat_ids = torch.nonzero(occupied.reshape(batch, -1).logical_and(deep.logical_not_()).view(-1)).squeeze(1)
    obj, vox = flat_ids // n_vox, flat_ids % n_vox
    flag_bits = None if flags is None else flags.reshape(-1).index_select(0, flat_ids)
    blocks = blocks.view(-1)
    # A full block culls one voxel per group: with few of them (sparse errors) the culling costs more than it saves.
    cull = int(torch.count_nonzero(blocks)) > _CULL_MIN_SHARE * flat_ids.numel()
    block_at = table.block_index.index_select(0, vox).add_(obj * (resolution + 1) ** 3) if cull else None

    for group in table.groups:
        if cull:
            hidden = blocks.index_select(0, block_at + group.block_offset)
            hidden.logical_and_(group.occludable.index_select(0, vox))
            kept = torch.nonzero(hidden.logical_not_()).squeeze(1)
            voxels, objects = vox.index_select(0, kept), obj.index_select(0, kept)
        else:
            kept, voxels, objects = None, vox, obj
        stride = group.slot.shape[1] * (pixels + 1)
        # int32 indices on CPU, where scatter_reduce takes them and they fit (they halve the index traffic)
        index = group.slot.index_select(0, voxels)
        if index.device.type != "cpu" or batch * stride > torch.iinfo(index.dtype).max:
            index = index.long()
        index.add_((objects * stride).to(index.dtype)[:, None])
        if flag_bits is None:
            keys = group.key.index_select(0, voxels)
        else:
            keys = group.flag_key.index_select(0, voxels)
            keys.bitwise_or_((flag_bits if kept is None else flag_bits.index_select(0, kept)).to(keys.dtype)[:, None])
        best = torch.full((batch, group.slot.shape[1], pixels + 1), missed, dtype=keys.dtype, device=obj.device)
        best.view(-1).scatter_reduce_(0, index.view(-1), keys.view(-1), reduce="amin")
        best[..., pixels] = missed
        consume(group.views, best)


def _object_chunks(occupied: Tensor, num_views: int) -> list[slice]:
    """Consecutive slices of the ``(B, N)`` batch, each scattering about :data:`_SCORE_CHUNK_PAIRS` pairs."""
    chunks, start, pairs = [], 0, 0
    for index, count in enumerate((occupied.sum(1, dtype=torch.int32).long() * num_views).tolist()):
        if pairs and pairs + count > _SCORE_CHUNK_PAIRS:
            chunks.append(slice(start, index))
            start, pairs = index, 0
        pairs += count
    chunks.append(slice(start, occupied.shape[0]))
    return chunks


def _hit_values(best: Tensor, flat: Tensor) -> Tensor:
    """Values of the winning voxels of ``best (B, V, P)`` keys in ``flat (B, N)``; 0 where nothing is hit."""
    winner = best.long().bitwise_and_((1 << _key_bits(flat.shape[1])) - 1).view(best.shape[0], -1)
    padded = torch.cat([flat, flat.new_zeros(flat.shape[0], 1)], 1)  # voxel N: the value of a miss
    return torch.gather(padded, 1, winner).view_as(best)


def _value_rows(flat: Tensor, dtype: torch.dtype | None = None) -> Tensor:
    """``(B * (N + 1), 1)`` rows for :func:`_hit_sums`: each object's ``N`` values, then a 0 (voxel ``N``, a miss).

    In ``dtype`` (default: that of ``flat``) if it is float32 or float64, else in float32.
    """
    dtype = flat.dtype if dtype is None else dtype
    dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    return torch.cat([flat.to(dtype), flat.new_zeros(flat.shape[0], 1, dtype=dtype)], 1).view(-1, 1)


def _hit_sums(best: Tensor, rows: Tensor) -> Tensor:
    """``(B, V)`` sums over pixels of the values (:func:`_value_rows`) of the voxels that ``best (B, V, P)`` hit.

    The keys are turned into row numbers in place (``best`` is overwritten); one ``embedding_bag`` gathers and
    sums, without a ``(B, V, P)`` tensor of values.
    """
    batch = best.shape[0]
    per_object = rows.shape[0] // batch
    if rows.shape[0] > torch.iinfo(best.dtype).max:
        best = best.long()
    best.bitwise_and_((1 << _key_bits(per_object - 1)) - 1)
    best.add_(torch.arange(0, rows.shape[0], per_object, dtype=best.dtype, device=best.device).view(-1, 1, 1))
    sums = torch.nn.functional.embedding_bag(best.view(-1, best.shape[-1]), rows, mode="sum")
    return sums.view(batch, best.shape[1])


def _is_binary(flat: Tensor, eps: float) -> bool:
    """Whether every voxel above ``eps`` is exactly 1 (then every hit has value 1, no gather needed)."""
    return bool((flat == 1).logical_or_(flat <= eps).all())


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
    """
    # Shape only: converting a bool grid to float would cost what this function exists to save.
    _check_grid_shape(volumes, "volumes")
    if not (volumes.is_floating_point() or volumes.dtype == torch.bool):
        raise TypeError(f"`volumes` must be a floating-point (or bool) tensor, got dtype {volumes.dtype}")
    check_choice("reduction", reduction, ("sum", "mean"))
    batch, resolution = volumes.shape[0], volumes.shape[1]
    dtype = volumes.dtype if volumes.is_floating_point() else torch.get_default_dtype()
    if batch == 0:
        return torch.zeros(0, viewpoints.shape[0], dtype=dtype, device=volumes.device)
    flat = volumes.reshape(batch, -1)
    occupied = flat.bool() if binary else flat > eps  # binary: values are exactly 0 or 1
    counts_only = binary or (binary is None and _is_binary(flat, eps))
    missed = _missed_key(flat.shape[1])
    total = torch.zeros(batch, viewpoints.shape[0], dtype=dtype, device=volumes.device)
    hits = torch.zeros(batch, viewpoints.shape[0], dtype=torch.int32, device=volumes.device)
    for chunk in _object_chunks(occupied, viewpoints.shape[0]):
        # binary: only the hits are counted; values: gathered and summed (after counting the hits, for a mean)
        rows = None if counts_only else _value_rows(flat[chunk])
        chunk_hits, chunk_total = hits[chunk], total[chunk]

        def score(views: Tensor, best: Tensor) -> None:
            if rows is None or reduction == "mean":
                count = (best != missed).sum(-1, dtype=torch.int32)
                chunk_hits.index_copy_(1, views, count)
            if rows is None:
                chunk_total.index_copy_(1, views, count.to(dtype))
            else:  # _hit_sums overwrites best: after the count
                chunk_total.index_copy_(1, views, _hit_sums(best, rows).to(dtype))

        _first_hits(occupied[chunk], resolution, viewpoints, resolution, DEFAULT_HALF_EXTENT, score)
    if reduction == "sum":
        return total
    return torch.where(hits > 0, total / hits.clamp_min(1).to(dtype), torch.zeros_like(total))


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
    scores = predicted.new_zeros(batch, viewpoints.shape[0])
    for chunk in _object_chunks(surface, viewpoints.shape[0]):
        chunk_scores = scores[chunk]
        if mode == "binary":  # the keys carry the error bit of the first hit

            def score(views: Tensor, best: Tensor) -> None:
                chunk_scores.index_copy_(1, views, best.bitwise_and_(1).sum(-1, dtype=torch.int32).to(scores.dtype))

            flags = errors[chunk]
        else:
            rows, flags = _value_rows(errors[chunk], predicted.dtype), None

            def score(views: Tensor, best: Tensor) -> None:
                chunk_scores.index_copy_(1, views, _hit_sums(best, rows).to(scores.dtype))

        _first_hits(surface[chunk], resolution, viewpoints, resolution, DEFAULT_HALF_EXTENT, score, flags)
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
    binary = _is_binary(flat, eps)  # the paper's binary error: every hit has value 1
    result = vol.new_zeros(batch, vp.shape[0], size * size)

    def project(views: Tensor, best: Tensor) -> None:
        best = best[..., : size * size]
        maps = (best != _missed_key(flat.shape[1])).to(vol.dtype) if binary else _hit_values(best, flat)
        result.index_copy_(1, views, maps)

    _first_hits(flat > eps, resolution, vp, size, half_extent, project)
    result = result.view(out_shape)
    return result[0] if unbatched else result


# -------------------------------------------------------------------------------------------- scores
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
    """
    _check_tensor_ndim(projections, "projections", 4, "(B, V, S, S)")
    check_choice("reduction", reduction, ("sum", "mean"))
    total = projections.sum(dim=(-2, -1))
    if reduction == "sum":
        return total
    hits = (projections != 0).sum(dim=(-2, -1))
    return torch.where(hits > 0, total / hits.clamp_min(1).to(total.dtype), torch.zeros_like(total))


# ------------------------------------------------------------------------------------------ sampling
def nearest_bins(viewpoints: Tensor, k: int = 30) -> Tensor:
    """Index in :func:`~lightning_vtr.geometry.candidate_viewpoints` order of the bin holding each viewpoint.

    Bins are the paper's intervals ``[-180 + (i - 1) K, -180 + i K)`` in yaw (after wrapping) and
    ``[-90 + (i - 1) K, -90 + i K)`` in pitch, half-open so a boundary angle belongs to the bin above it;
    pitch 90 belongs to the top bin.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.
        k: bin interval in degrees (must divide 180).

    Returns:
        ``(...)`` int64 flat bin indices ``i_pitch * (360 / K) + i_yaw`` (0-based).
    """
    k = check_bin_interval(k)
    vp = check_viewpoints(viewpoints).to(torch.float64)
    n_yaw, n_pitch = 360 // k, 180 // k
    i_yaw = torch.floor((wrap_yaw(vp[..., 0]) + 180.0) / k).long().clamp(0, n_yaw - 1)
    i_pitch = torch.floor((vp[..., 1].clamp(-90.0, 90.0) + 90.0) / k).long().clamp(0, n_pitch - 1)
    return i_pitch * n_yaw + i_yaw


def top_bins(scores: Tensor, n: int = 3, *, generator: torch.Generator | None = None) -> Tensor:
    """Indices ``(B, n)`` of the ``n`` highest scores per row, best first.

    Exactly equal scores are ordered at random (one uniform per score from ``generator``). Ties are
    common: with a binary error a view and its antipode see mirror-image silhouettes and score the same,
    and a fixed order would always favour the lower-index (southern, western) bin.

    Raises:
        TypeError: ``scores`` is not a tensor or ``n`` is not an int.
        ValueError: ``scores`` is not ``(B, V)`` or ``n`` is not in ``[1, V]``.
    """
    _check_tensor_ndim(scores, "scores", 2, "(B, V)")
    check_int("n", n, minimum=1, maximum=scores.shape[1])
    priority = torch.rand(scores.shape, generator=generator, dtype=torch.float64).to(scores.device)
    shuffled = torch.argsort(priority, dim=1)
    by_score = torch.argsort(-scores.detach().to(torch.float64).gather(1, shuffled), dim=1, stable=True)
    return shuffled.gather(1, by_score[:, :n])


def select_views(
    scores: Tensor,
    k: int = 30,
    n: int = 3,
    *,
    generator: torch.Generator | None = None,
    sigma: float | None = None,
) -> Tensor:
    """Sample ``n`` viewpoints per object around its ``n`` best-scoring candidate bins.

    The ``n`` highest scores are kept (:func:`top_bins`: exact ties in random order); each final viewpoint
    is drawn from ``N(bin centre, sigma)`` independently in yaw and pitch, then yaw is wrapped into
    ``[-180, 180)`` and pitch clamped into ``[-90, 90]``. Objects whose scores are all zero are not
    special-cased here (see :class:`ErrorGuidedSelector` for the uniform fallback). Random draws from
    ``generator``: ``(B, V)`` uniforms for the tie order, then ``(B, n, 2)`` normals.

    Args:
        scores: ``(B, V)`` with ``V = (180 / K) * (360 / K)`` in
            :func:`~lightning_vtr.geometry.candidate_viewpoints` order.
        k: bin interval ``K`` in degrees (must divide 180).
        n: views per object, ``1 <= n <= V``.
        generator: CPU generator.
        sigma: standard deviation in degrees; ``None`` means the paper's ``K / 6``.

    Returns:
        ``(B, n, 2)`` (yaw, pitch) in degrees, best bin first, on the device of ``scores``.

    Raises:
        TypeError: ``scores`` is not a tensor, or ``n`` / ``sigma`` has the wrong type.
        ValueError: a bad ``k``, ``scores`` not ``(B, V)`` for that ``k``, ``n`` out of range or ``sigma < 0``.
    """
    k = check_bin_interval(k)
    candidates = candidate_viewpoints(k)
    expected = f"(B, {candidates.shape[0]}) for K={k}"
    _check_tensor_ndim(scores, "scores", 2, expected)
    if scores.shape[1] != candidates.shape[0]:
        raise ValueError(f"`scores` must have shape {expected}, got {tuple(scores.shape)}")
    sigma = k / 6.0 if sigma is None else check_float("sigma", sigma, minimum=0.0)
    best = top_bins(scores, n, generator=generator)  # (B, n)
    return sample_around_bins(best, k, sigma=sigma, generator=generator).to(
        scores.dtype if scores.is_floating_point() else torch.get_default_dtype()
    )


def sample_around_bins(
    bins: Tensor, k: int = 30, *, sigma: float | None = None, generator: torch.Generator | None = None
) -> Tensor:
    """Viewpoints ``(..., 2)`` in degrees drawn from ``N(centre of bin, sigma)`` for flat bin indices ``(...)``.

    ``sigma`` defaults to ``K / 6``; yaw is wrapped and pitch clamped.

    Raises:
        ValueError: a bad ``k`` or a negative ``sigma``.
    """
    k = check_bin_interval(k)
    sigma = k / 6.0 if sigma is None else check_float("sigma", sigma, minimum=0.0)
    centres = candidate_viewpoints(k).to(bins.device, torch.float64)[bins]
    return sample_gaussian_viewpoints(centres, sigma, generator=generator)

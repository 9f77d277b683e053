"""The first-hit engine behind the projection scores: which voxel each pixel of each view sees first.

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
``eps``, looks up their pixels and ranks, keeps the smallest rank per ``(object, view, pixel)`` with one
``scatter_reduce(..., "amin")`` for all views (the rank encodes depth and the tie break in one sortable
integer), and sums (``embedding_bag``) or gathers the values of the winning voxels. A view's pixels are
numbered in the buffer only if some voxel centre falls in them, in pixel order, so
per-view sums add the same values in the same order as over the whole image: the scores are bit-exact.

Occluded voxels are left out before the scatter. The views are grouped by the octant their cameras look
from, and a voxel is skipped for a group's views when occupied voxels of its 2x2x2 block towards that
octant hide it in every one of them (the table keeps, per voxel and group, a smallest set of block voxels
that does: one falls in the same pixel with a smaller rank in each view). That changes no first hit.
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from typing import NamedTuple, cast

import torch
from torch import Tensor

from lightning_vtr.geometry import orthographic_pixel_coords, voxel_centers

__all__ = [
    "clear_projection_cache",
    "first_hits",
    "hit_sums",
    "hit_values",
    "is_binary",
    "object_chunks",
    "projection_table",
    "value_rows",
]

#: Depths closer than this (world units; a voxel is 1/R >= 1e-3 wide) are treated as equal.
_DEPTH_TIE_TOLERANCE = 1e-9
#: How many projection tables (one per grid size, viewpoint set, image size, device) are kept.
_TABLE_CACHE_SIZE = 6
#: Views processed together while building a table, to bound the float64 temporaries.
_TABLE_VIEW_CHUNK = 16
#: Occupied (voxel, view) pairs per chunk of objects in the score functions, before culling: bounds the
#: index buffers (12 bytes per pair kept).
_SCORE_CHUNK_PAIRS = 1 << 25
#: Buffer slots (objects x views x slots per view) per chunk of objects: at most 64 MB of int32 keys.
_SCORE_CHUNK_SLOTS = 1 << 24

_table_cache: OrderedDict[tuple, _Table] = OrderedDict()


class _ViewGroup(NamedTuple):
    """The views whose cameras lie in one octant, with their columns of the projection table.

    ``occludable[n]`` says that voxel ``n`` is never a first hit in these views while the 2x2x2 block
    made of it and its 7 neighbours one step towards the cameras is occupied: in every view of the group
    one of those neighbours falls in the same pixel with a smaller key. Leaving such voxels out of the
    scatter changes no first hit: from a left-out voxel, "a smaller key in the same pixel" leads through
    strictly smaller keys to a voxel that was kept. (:func:`first_hits` uses a finer test of the same kind,
    the table's hiding sets, and ``occludable`` for the voxels deep inside a solid.)
    """

    views: Tensor  # (Vg,) int64: the group's views in the viewpoint order
    slot: Tensor  # (N, Vg) buffer slots: c * S + the slot of the voxel's pixel, c the view's buffer column
    key: Tensor  # (N, Vg) first-hit keys
    flag_key: Tensor  # (N, Vg) the keys' ranks, doubled: room for a flag bit (see first_hits)
    occludable: Tensor  # (N,) bool
    block_offset: int  # where the voxel's block towards the cameras sits in the padded block grid


class _Table(NamedTuple):
    """The projection of every voxel centre onto every view, split into :class:`_ViewGroup` s by camera octant.

    The first hits of a chunk of ``b`` objects go to one ``(b, V, S)`` buffer: a column per view, the
    groups' views one group after the other (``column_of_view`` says where a view is), and ``S`` slots per
    column. The slots are the view's *used* pixels only (those some voxel centre falls in), in pixel order:
    about half the image's, so every pass over the buffer is half as long as over ``S^2`` pixels, and a
    per-view sum over the slots adds the same values in the same order as one over the pixels. A table with
    centres outside the image (small images only) has one more slot per column, a sink reset to a miss.
    """

    groups: list[_ViewGroup]
    slot: Tensor  # (G, N, W): the groups' slots (_ViewGroup.slot), padded to W by repeating the first view
    key: Tensor  # (G, N, W) the groups' keys, padded alike
    flag_key: Tensor  # (G, N, W) the groups' flag keys, padded alike
    block_index: Tensor  # (N,) int64: voxel (i, j, k) at (i, j, k) of an (R + 1)^3 grid
    occludable: Tensor  # (N,) bool: occludable in every group
    hiding: Tensor  # (N,) int64: per voxel, 8 bytes of block-code bits, one per group (see first_hits)
    not_own: Tensor  # (G, 1) uint8: the block code bits of the other voxels than the voxel itself
    block_offsets: Tensor  # (G, 1) int64: each group's block offset
    column_of_view: Tensor  # (V,) int64: the buffer column of each view
    pixel_of: Tensor  # (V, S) int64: the image pixel of each slot of a column, S^2 for unused slots and the sink
    stride: int  # S
    sink: bool  # whether slot S - 1 of each column collects the centres outside the image


def _key_bits(n_vox: int) -> int:
    """Low bits of a first-hit key that hold the voxel index (room for ``0..N``: ``N`` marks a miss)."""
    return n_vox.bit_length()


def _missed_key(n_vox: int) -> int:
    """The key of a pixel nothing hits: above every voxel's key, and its low bits name voxel ``N``.

    Gathering values at the low bits of the keys, from volumes padded with one zero voxel ``N``, then
    values a missed pixel 0 without a separate mask.
    """
    return ((n_vox - 1) << _key_bits(n_vox)) | n_vox


def _view_groups(
    slot: Tensor, key: Tensor, resolution: int, viewpoints: Tensor
) -> list[tuple[Tensor, Tensor, Tensor, int, int]]:
    """Split the ``(V, N)`` pixel and key tables by the octant the cameras look from.

    Per group: its views, its occludable voxels (see :class:`_ViewGroup`), each voxel's hiding set and own bit
    of the block code (see :func:`first_hits`), and its block offset.
    """
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
    codes = torch.arange(256)
    bit_count = cast(Tensor, sum((codes >> bit) & 1 for bit in range(8)))  # a sum of tensors: a tensor
    groups = []
    for steps, views in by_steps.items():
        columns = torch.tensor(views)
        # (N, Vg) of the (V, N) tables: a row gather, then one transposing copy
        group_slot, group_key = slot[columns].t().contiguous(), key[columns].t().contiguous()
        up = [int(step > 0) for step in steps]
        # hides[n, w]: which voxels of n's block towards the cameras hide it in view w (same pixel, smaller
        # key), as bits of the block code (bit 4 e_x + 2 e_y + e_z for the block voxel at offset e - 1 + up)
        hides = torch.zeros(group_slot.shape, dtype=torch.uint8)
        for offset in itertools.product(*[(0, step) for step in steps]):
            if not any(offset):
                continue
            moved = ijk + torch.tensor(offset)
            inside = ((moved >= 0) & (moved < resolution)).all(-1, keepdim=True)
            index = (moved.clamp(0, resolution - 1) * strides).sum(-1)
            hidden = (group_slot[index] == group_slot) & (group_key[index] < group_key) & inside
            e = [o - u + 1 for o, u in zip(offset, up)]
            hides.add_(hidden, alpha=1 << (4 * e[0] + 2 * e[1] + e[2]))  # distinct bits: add = or
        # A voxel is hidden in every view of the group if its block's occupied voxels (code c) include one that
        # hides it in each view: c & hides[:, w] != 0 for every w. The table keeps one smallest such set
        # (`hiding`): an occupied `hiding` proves the voxel hidden. Among the smallest, face neighbours first
        # (more often occupied on a surface than edge or corner ones). Without any, it keeps the voxel's own bit,
        # which the lookup clears from the code: never all set.
        own = 4 * (1 - up[0]) + 2 * (1 - up[1]) + (1 - up[2])
        hiding = _smallest_hitting_sets(hides, own, codes, bit_count)
        block_offset = int((padded_strides * (torch.tensor(steps) > 0)).sum())
        groups.append((columns, (hides != 0).all(1), hiding, own, block_offset))
    return groups


def _smallest_hitting_sets(hides: Tensor, own: int, codes: Tensor, bit_count: Tensor) -> Tensor:
    """Per row of ``hides (N, W)`` (block-code masks), the first block code, in order of (bits set, distance of
    its voxels from the voxel ``own`` names), without bit ``own``, that has a bit in common with every mask;
    ``1 << own`` where none has.

    Bit-parallel: the 128 candidate codes in that order are bits of 3 int64 words (43 per word, clear of the
    sign bit); ANDing each row's ``covers`` words over its masks leaves the candidates that hit them all, and
    the lowest set bit is the first.
    """
    # a sum of tensors: a tensor
    distance = cast(Tensor, sum(((codes >> bit) & 1) * bin(bit ^ own).count("1") for bit in range(8)))
    candidates = codes[(codes >> own) & 1 == 0]
    candidates = candidates[torch.argsort(bit_count[candidates] * 64 + distance[candidates], stable=True)]
    position = torch.arange(len(candidates))
    # covers[d]: the candidates with a bit in common with mask d, as bits (position % 43) of word (position // 43)
    hits = (candidates[None, :] & codes[:, None]) != 0  # (256 masks, 128 candidates)
    covers = torch.zeros(256, 3, dtype=torch.int64)
    covers.index_add_(1, position // 43, hits.long() << (position % 43))
    hides = hides.long()
    words = covers[hides[:, 0]]
    for w in range(1, hides.shape[1]):
        words &= covers[hides[:, w]]
    # the lowest set bit of the first nonzero word: its position is log2 of the bit, exact in float64
    first = torch.full((hides.shape[0],), len(candidates), dtype=torch.int64)
    for k in reversed(range(3)):
        word = words[:, k]
        bit = torch.log2((word & -word).double()).round().long() + 43 * k
        first = torch.where(word != 0, bit, first)
    found = first < len(candidates)
    return torch.where(found, candidates[first.clamp(max=len(candidates) - 1)], 1 << own)


def projection_table(
    resolution: int, viewpoints: Tensor, image_size: int, half_extent: float, device: torch.device
) -> _Table:
    """Per voxel and view: the buffer slot and the sortable first-hit key (cached per argument set).

    ``key``: ``(rank << b) | n`` with ``b =`` :func:`_key_bits` ``(N)``, where ``rank`` is the position of
    voxel ``n`` in the view's (depth, flat index) order, so the smallest key in a pixel is its first hit
    and the low ``b`` bits name the voxel; int32 where it fits. The tables are ``(group, voxel, view)``, so a
    call gathers contiguous rows, group after group; see :class:`_Table` for the buffer layout.
    """
    vp64 = viewpoints.detach().to("cpu", torch.float64)
    cache_key = (resolution, image_size, float(half_extent), str(device), tuple(vp64.flatten().tolist()))
    if cache_key in _table_cache:
        _table_cache.move_to_end(cache_key)
        return _table_cache[cache_key]

    n_vox = resolution**3
    n_views = vp64.shape[0]
    pixels = image_size * image_size
    bits = _key_bits(n_vox)
    int32_max = torch.iinfo(torch.int32).max
    centres = voxel_centers(resolution, torch.float64).reshape(-1, 3)
    flat = torch.arange(n_vox, dtype=torch.int64)
    slots, keys = [], []
    for start in range(0, n_views, _TABLE_VIEW_CHUNK):
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
    pixel, key = torch.cat(slots), torch.cat(keys)  # (V, N) each
    groups = _view_groups(pixel, key, resolution, vp64)

    # Each view's used pixels, numbered in pixel order; the centres outside the image (pixel S^2) go to the sink.
    used = torch.zeros(n_views, pixels + 1, dtype=torch.bool).scatter_(1, pixel, True)
    sink = bool(used[:, pixels].any())
    used = used[:, :pixels]
    stride = int(used.sum(1).max()) + sink
    numbering = torch.cat([used.long().cumsum(1) - 1, torch.full((n_views, 1), stride - 1)], 1)
    compact = numbering.gather(1, pixel)  # (V, N)
    # The buffer's columns: the groups' views, group after group.
    column_views = torch.cat([group[0] for group in groups])
    column_of_view = torch.empty(n_views, dtype=torch.int64)
    column_of_view[column_views] = torch.arange(n_views)
    # unused slots (and the sink) map to pixel S^2, which error_projection drops
    pixel_of = torch.full((n_views, stride), pixels, dtype=torch.int64)
    where = used.nonzero()
    pixel_of[where[:, 0], numbering[:, :pixels][used]] = where[:, 1]
    key_dtype = torch.int32 if _missed_key(n_vox) <= int32_max else torch.int64
    flag_dtype = torch.int32 if 2 * n_vox < int32_max else torch.int64
    # Group-major tables (G, N, W), each group padded to the widest by repeating its first view's column: a
    # repeated (slot, key) pair changes no minimum, and a group's rows are one contiguous block to gather from.
    width = max(len(group[0]) for group in groups)
    padded = torch.stack([torch.cat([group[0], group[0][:1].expand(width - len(group[0]))]) for group in groups])
    # row gathers of the (V, N) tables into (G, W, N), then (G, N, W)
    slot = (compact[padded] + (column_of_view[padded] * stride)[..., None]).transpose(1, 2).contiguous()
    group_key = key[padded].transpose(1, 2).contiguous()
    # int32 slots where they fit: half the table's memory (the gather, the add and scatter_reduce's conversion to
    # int64 cost about what int64 slots do)
    slot = slot.to(device=device, dtype=torch.int32 if n_views * stride <= int32_max else torch.int64)
    group_key = group_key.to(device=device, dtype=key_dtype)
    flag_key = ((group_key >> bits) << 1).to(flag_dtype)
    view_groups = [
        _ViewGroup(
            views.to(device),
            slot[g, :, : len(views)],
            group_key[g, :, : len(views)],
            flag_key[g, :, : len(views)],
            occludable.to(device),
            block_offset,
        )
        for g, (views, occludable, _, _, block_offset) in enumerate(groups)
    ]
    axis = torch.arange(resolution, device=device)
    block_index = (axis[:, None, None] * (resolution + 1) + axis[:, None]) * (resolution + 1) + axis
    table = _Table(
        groups=view_groups,
        slot=slot,
        key=group_key,
        flag_key=flag_key,
        block_index=block_index.reshape(-1),
        occludable=torch.stack([group.occludable for group in view_groups]).all(0),
        # (N, 8) uint8, one column per group (8 octants at most), viewed as one int64 per voxel: one 1-d gather
        hiding=torch.cat(
            [torch.stack([group[2] for group in groups], 1), torch.zeros(n_vox, 8 - len(groups), dtype=torch.int64)], 1
        )
        .to(torch.uint8)
        .view(torch.int64)
        .view(-1)
        .to(device),
        not_own=torch.tensor([[255 - (1 << group[3])] for group in groups], dtype=torch.uint8, device=device),
        block_offsets=torch.tensor([[group.block_offset] for group in view_groups], device=device),
        column_of_view=column_of_view.to(device),
        pixel_of=pixel_of.to(device),
        stride=stride,
        sink=sink,
    )
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


def _block_codes(grid: Tensor) -> Tensor:
    """``(B, (R + 1)^3)`` uint8 codes of the 2x2x2 blocks of a ``(B, R, R, R)`` bool grid, zero-padded.

    Entry ``(i, j, k)`` covers voxels ``(i - 1 .. i, j - 1 .. j, k - 1 .. k)``: bit ``4 e_x + 2 e_y + e_z`` is
    voxel ``(i - 1 + e_x, j - 1 + e_y, k - 1 + e_z)``, so 255 is a full block. The block towards the cameras of
    voxel ``n`` is entry ``n + (steps > 0)``.
    """
    batch, resolution = grid.shape[0], grid.shape[1]
    padded = grid.new_zeros(batch, resolution + 2, resolution + 2, resolution + 2, dtype=torch.uint8)
    padded[:, 1:-1, 1:-1, 1:-1] = grid
    # one axis at a time, the upper neighbour's bits shifted above the lower one's (disjoint bits: add = or)
    codes = torch.add(padded[..., :-1], padded[..., 1:], alpha=2)
    codes = torch.add(codes[:, :, :-1], codes[:, :, 1:], alpha=4)
    return torch.add(codes[:, :-1], codes[:, 1:], alpha=16).view(batch, -1)


def _flat_nonzero(mask: Tensor) -> Tensor:
    """``torch.nonzero(mask).squeeze(1)`` of a 1-d bool tensor, faster where it is sparse (a surface in a grid).

    CPU ``nonzero`` costs per element scanned: scan it as int64 words of 8 flags first, then only the flags of
    the nonzero words.
    """
    if mask.device.type != "cpu" or mask.numel() % 8 or mask.storage_offset() % 8:
        return torch.nonzero(mask).squeeze(1)
    words = torch.nonzero(mask.view(torch.int64)).squeeze(1)
    flags = torch.nonzero(mask.view(-1, 8).index_select(0, words).view(-1)).squeeze(1)
    return words.mul_(8).index_select(0, flags >> 3).add_(flags & 7)


def first_hits(
    occupied: Tensor, resolution: int, table: _Table, flags: Tensor | None = None, *, hits_only: bool = False
) -> Tensor:
    """Smallest first-hit key per ``(object, column, slot)`` for ``occupied (B, N)`` bool voxels: ``(B, V, S)``.

    :func:`_missed_key` where nothing is hit; see :class:`_Table` for the layout. One gather, one add and one
    scatter serve all views: few, large tensor operations, in a (group, object, voxel) order that reads
    each group's rows of the table and writes its columns of the buffer together.

    With ``flags`` (``(B, N)`` bool) the keys are ``(rank << 1) | flag``: bit 0 of a slot's key is the flag
    of its first hit (no gather needed to read it), a miss is ``2 N`` (bit 0 clear), and the voxel index is
    not kept. With ``hits_only`` the buffer is uint8, 1 where anything is hit: which voxel is first does not
    matter then, so no key is gathered.
    """
    batch = occupied.shape[0]
    n_vox = resolution**3
    per_object = table.column_of_view.numel() * table.stride
    codes = _block_codes(occupied.view(batch, resolution, resolution, resolution))
    # A voxel whose 3x3x3 neighbourhood is full (its 8 blocks are) is culled in every group: leave it out now.
    deep = _all_of_2x2x2((codes == 255).view(batch, resolution + 1, resolution + 1, resolution + 1))
    deep = deep.reshape(batch, -1).logical_and_(table.occludable)
    # one flat nonzero is cheaper than a 2-d one; split it into (object, voxel) arithmetically
    flat_ids = _flat_nonzero(occupied.reshape(batch, -1).logical_and(deep.logical_not_()).view(-1))
    obj, vox = flat_ids // n_vox, flat_ids % n_vox
    flag_bits = None if flags is None else flags.reshape(-1).index_select(0, flat_ids)
    # CPU: buffer indices in the slots' dtype where the whole buffer fits it (it does in the score functions'
    # chunks); other devices get int64, as their scatter wants
    fits = obj.device.type == "cpu" and batch * per_object <= torch.iinfo(table.slot.dtype).max
    index_dtype = table.slot.dtype if fits else torch.int64
    base = (obj * per_object).to(index_dtype)
    if hits_only:
        # uint8 on CPU (a quarter of the bytes to fill and sum); int32 elsewhere, where atomics want 32 bits
        best = torch.zeros(
            batch * per_object, dtype=torch.uint8 if obj.device.type == "cpu" else torch.int32, device=obj.device
        )
        missed = 0
    else:
        key_dtype = table.key.dtype if flags is None else table.flag_key.dtype
        missed = _missed_key(n_vox) if flags is None else 2 * n_vox
        best = torch.full((batch * per_object,), missed, dtype=key_dtype, device=obj.device)
    # (group, voxel) pairs, found for all groups at once. A voxel is hidden in all views of a group when the
    # occupied voxels of its block towards the cameras (the block code, less its own bit) include its hiding
    # set from the table: then in each view one of them falls in the same pixel with a smaller key.
    n_groups = len(table.groups)
    block_at = table.block_index.index_select(0, vox).add_(obj * (resolution + 1) ** 3)
    code = codes.view(-1).index_select(0, (table.block_offsets + block_at).view(-1)).view(n_groups, -1)
    code.bitwise_and_(table.not_own)
    # the table's 8 bytes per voxel (one per group) come in one int64 gather
    hiding = table.hiding.index_select(0, vox).view(torch.uint8).view(-1, 8)[:, :n_groups].t()
    kept = code.bitwise_and_(hiding) != hiding
    counts = kept.sum(1).tolist()
    # Group-major positions in the (G, M) grid: group g's slice, minus g * M, are positions in `vox`, and its
    # table rows are g * N + voxel. Gathering group after group keeps each group's rows together in cache.
    kept = torch.nonzero(kept.view(-1)).squeeze(1)
    for g, part in enumerate(kept.split(counts)):
        part.sub_(g * vox.numel())
    rows = vox.index_select(0, kept)
    for g, part in enumerate(rows.split(counts)):
        part.add_(g * n_vox)
    width = table.slot.shape[-1]
    index = table.slot.view(-1, width).index_select(0, rows).to(index_dtype)
    index = index.add_(base.index_select(0, kept)[:, None]).view(-1)
    if hits_only:
        best.scatter_reduce_(0, index, best.new_ones(index.numel()), reduce="amax")
    else:
        if flag_bits is None:
            keys = table.key.view(-1, width).index_select(0, rows)
        else:
            keys = table.flag_key.view(-1, width).index_select(0, rows)
            keys.bitwise_or_(flag_bits.index_select(0, kept).to(keys.dtype)[:, None])
        best.scatter_reduce_(0, index, keys.view(-1), reduce="amin")
    best = best.view(batch, -1, table.stride)
    if table.sink:
        best[..., -1] = missed
    return best


def object_chunks(occupied: Tensor, num_views: int, slots_per_object: int) -> list[slice]:
    """Consecutive slices of the ``(B, N)`` batch of about equal numbers of (voxel, view) pairs, as few as keep each
    under :data:`_SCORE_CHUNK_PAIRS` pairs and :data:`_SCORE_CHUNK_SLOTS` buffer slots (an object alone may
    exceed them)."""
    pairs = (occupied.sum(1, dtype=torch.int32).long() * num_views).cumsum(0).tolist()
    batch = len(pairs)
    count = max(-(-pairs[-1] // _SCORE_CHUNK_PAIRS), -(-batch * slots_per_object // _SCORE_CHUNK_SLOTS), 1)
    max_objects = max(1, _SCORE_CHUNK_SLOTS // slots_per_object)
    chunks: list[slice] = []
    start = 0
    while start < batch:
        # chunk c < count ends where the running pair count first reaches c / count of the total; the last takes
        # the rest; all within the object bound
        c = len(chunks) + 1
        end = (
            next((i + 1 for i in range(start, batch) if pairs[i] * count >= pairs[-1] * c), batch)
            if c < count
            else batch
        )
        end = min(max(end, start + 1), start + max_objects)
        chunks.append(slice(start, end))
        start = end
    return chunks


def hit_values(best: Tensor, flat: Tensor) -> Tensor:
    """Values of the winning voxels of ``best (B, C, S)`` keys in ``flat (B, N)``; 0 where nothing is hit."""
    winner = best.long().bitwise_and_((1 << _key_bits(flat.shape[1])) - 1).view(best.shape[0], -1)
    padded = torch.cat([flat, flat.new_zeros(flat.shape[0], 1)], 1)  # voxel N: the value of a miss
    return torch.gather(padded, 1, winner).view_as(best)


def value_rows(flat: Tensor, dtype: torch.dtype | None = None, *, counts: bool = False) -> Tensor:
    """``(B * (N + 1), k)`` rows for :func:`hit_sums`: each object's ``N`` values, then a 0 (voxel ``N``, a miss).

    In ``dtype`` (default: that of ``flat``) if it is float32 or float64, else in float32. With ``counts`` the
    rows have a second column, 1 for a voxel and 0 for the miss: the same sum then also counts the hits.
    """
    dtype = flat.dtype if dtype is None else dtype
    dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    shape = (flat.shape[0], flat.shape[1] + 1, 2 if counts else 1)
    # the counts' ones in one contiguous fill, then the values over every other one: cheaper than a strided fill
    rows = flat.new_ones(shape, dtype=dtype) if counts else flat.new_empty(shape, dtype=dtype)
    rows[:, :-1, 0] = flat
    rows[:, -1] = 0
    return rows.view(-1, rows.shape[-1])


def hit_sums(best: Tensor, rows: Tensor) -> Tensor:
    """``(B, C, k)`` sums over slots of the ``k``-column rows (:func:`value_rows`) of the voxels ``best (B, C, S)``
    hit.

    The keys are turned into row numbers in place (``best`` is overwritten); one ``embedding_bag`` gathers and
    sums, without a ``(B, C, S)`` tensor of values. It adds a bag's values one after the other in slot order,
    so the sums do not depend on the thread count.
    """
    batch = best.shape[0]
    per_object = rows.shape[0] // batch
    if rows.shape[0] > torch.iinfo(best.dtype).max:
        best = best.long()
    best.bitwise_and_((1 << _key_bits(per_object - 1)) - 1)
    best.add_(torch.arange(0, rows.shape[0], per_object, dtype=best.dtype, device=best.device).view(-1, 1, 1))
    sums = torch.nn.functional.embedding_bag(best.view(-1, best.shape[-1]), rows, mode="sum")
    return sums.view(batch, best.shape[1], rows.shape[1])


def is_binary(flat: Tensor, eps: float) -> bool:
    """Whether every voxel above ``eps`` is exactly 1 (then every hit has value 1, no gather needed)."""
    return bool((flat == 1).logical_or_(flat <= eps).all())

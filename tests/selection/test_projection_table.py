"""The projection table's smallest hiding sets: the bit-parallel search against a direct search."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.selection.first_hit import _smallest_hitting_sets


def _direct(hides: torch.Tensor, own: int) -> torch.Tensor:
    """Per row, the block code without bit ``own`` with fewest bits (then smallest distance of its voxels from
    voxel ``own``, then smallest code) that has a bit in common with every mask; ``1 << own`` if none."""
    codes = torch.arange(256)
    bit_count = sum((codes >> bit) & 1 for bit in range(8))
    distance = sum(((codes >> bit) & 1) * bin(bit ^ own).count("1") for bit in range(8))
    out = []
    for row in hides.long().tolist():
        best = None
        for code in range(256):
            if code >> own & 1 or any(code & mask == 0 for mask in row):
                continue
            cost = (int(bit_count[code]), int(distance[code]), code)
            best = cost if best is None or cost < best else best
        out.append(1 << own if best is None else best[2])
    return torch.tensor(out)


@pytest.mark.parametrize("own", [0, 3, 7])
@pytest.mark.parametrize("views", [1, 4])
def test_smallest_hitting_sets_match_a_direct_search(own: int, views: int) -> None:
    generator = torch.Generator().manual_seed(own * 10 + views)
    # sparse masks (as occlusion gives: a few bits each), with some empty ones that no code can hit
    bits = torch.rand(300, views, 8, generator=generator) < 0.25
    hides = (bits.long() << torch.arange(8)).sum(-1).to(torch.uint8)
    codes = torch.arange(256)
    bit_count = sum((codes >> bit) & 1 for bit in range(8))
    fast = _smallest_hitting_sets(hides, own, codes, bit_count)
    expected = _direct(hides, own)
    assert torch.equal(fast, expected)
    # rows with an empty mask have no hitting set: the voxel's own bit, which the lookup clears
    empty = (hides == 0).any(1)
    assert empty.any() and bool((fast[empty] == 1 << own).all())

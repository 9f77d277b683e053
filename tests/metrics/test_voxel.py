"""The torchmetrics classes VoxelIoU / VoxelFScore: means of the functional forms, per category, synced."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.metrics import VoxelFScore, VoxelIoU, voxel_fscore, voxel_iou


def _batches():
    gen = torch.Generator().manual_seed(1)
    out = []
    for n in (2, 3):
        g = (torch.rand(n, 8, 8, 8, generator=gen) > 0.5).float()
        p = torch.rand(n, 8, 8, 8, generator=gen)
        out.append((p, g))
    return out


def test_iou_class_is_mean_of_functional_and_per_category():
    metric = VoxelIoU(categories=["chair", "lamp"])
    cats = [["chair", "lamp"], ["lamp", "lamp", "table"]]
    per_object = []
    for (p, g), c in zip(_batches(), cats):
        metric.update(p, g, c)
        per_object.append(voxel_iou(p, g))
    all_iou = torch.cat(per_object)
    torch.testing.assert_close(metric.compute(), all_iou.mean(0))
    per_cat = metric.compute_per_category()
    assert list(per_cat) == ["chair", "lamp", "table"]
    torch.testing.assert_close(per_cat["chair"], all_iou[0])
    torch.testing.assert_close(per_cat["lamp"], all_iou[[1, 2, 3]].mean(0))
    torch.testing.assert_close(per_cat["table"], all_iou[4])
    metric.reset()
    assert metric.category_count.shape == (3,) and metric.category_count.sum() == 0


def test_fscore_class_is_mean_of_functional():
    metric = VoxelFScore(num_points=256, seed=5)
    scores = []
    for p, g in _batches():
        metric.update(p, g)
        scores.append(voxel_fscore(p, g, num_points=256, seed=5))
    assert metric.compute().item() == pytest.approx(torch.cat(scores).mean().item(), abs=1e-6)


def test_metric_sync_equals_single_process_on_union():
    """Two "processes" holding half the data each: the synced result equals one process on all of it."""
    batches = _batches()
    cats = [["a", "b"], ["b", "b", "c"]]
    vocabulary = ["a", "b", "c"]
    ranks = [VoxelIoU(categories=vocabulary) for _ in range(2)]
    for metric, (p, g), c in zip(ranks, batches, cats):
        metric.update(p, g, c)

    def gather_from_both(tensor: torch.Tensor, group=None) -> list[torch.Tensor]:
        # Stands in for torch.distributed all_gather: every rank's copy of the same state.
        name = next(n for n in ranks[0]._defaults if getattr(rank_in_sync, n) is tensor)
        return [getattr(r, n).clone() for r in ranks for n in [name]]

    single = VoxelIoU(categories=vocabulary)
    for (p, g), c in zip(batches, cats):
        single.update(p, g, c)
    rank_in_sync = ranks[0]
    ranks[0].dist_sync_fn = gather_from_both
    ranks[0].distributed_available_fn = lambda: True
    torch.testing.assert_close(ranks[0].compute(), single.compute())
    synced = ranks[0].compute_per_category()
    expected = single.compute_per_category()
    assert synced.keys() == expected.keys()
    for k in expected:
        torch.testing.assert_close(synced[k], expected[k])
    # The local state is restored after syncing.
    assert ranks[0].count.item() == 2


def test_constructor_argument_errors():
    with pytest.raises(ValueError, match=r"^`thresholds\[0\]` must be a number in \[0, 1\], got 2.0$"):
        VoxelIoU(thresholds=(2.0,))
    with pytest.raises(ValueError, match=r"^`threshold` must be a number in \[0, 1\], got -0.1$"):
        VoxelFScore(threshold=-0.1)
    with pytest.raises(TypeError, match="^`num_points` must be an int, got str '8'$"):
        VoxelFScore(num_points="8")
    with pytest.raises(TypeError, match="^`categories` must be a sequence of names, got str 'chair'$"):
        VoxelIoU(categories="chair")

"""The torchmetrics classes VoxelIoU / VoxelFScore: means of the functional forms, per category, synced."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.metrics import VoxelFScore, VoxelIoU, VoxelIoUBest, voxel_fscore, voxel_iou, voxel_iou_best


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


def _one_at_a_time(p, g, **kw):
    return torch.cat([voxel_fscore(p[i : i + 1], g[i : i + 1], **kw) for i in range(p.shape[0])])


def test_fscore_class_is_mean_of_functional_on_one_object_at_a_time():
    metric = VoxelFScore(num_points=256, seed=5)
    scores = []
    for p, g in _batches():
        metric.update(p, g)
        scores.append(_one_at_a_time(p, g, num_points=256, seed=5))
    assert metric.compute().item() == pytest.approx(torch.cat(scores).mean().item(), abs=1e-6)


def test_fscore_class_does_not_depend_on_how_objects_are_batched():
    # The same five objects as one batch of 5, as batches of 2 + 3, and one by one (what DDP shards change).
    p, g = (torch.cat(t) for t in zip(*_batches()))
    together, split, alone = (VoxelFScore(num_points=256, seed=5) for _ in range(3))
    together.update(p, g)
    split.update(p[:2], g[:2])
    split.update(p[2:], g[2:])
    for i in range(5):
        alone.update(p[i : i + 1], g[i : i + 1])
    assert together.compute().item() == split.compute().item() == alone.compute().item()
    # One generator for the whole batch (the functional's form) draws other points for objects 2-5.
    assert voxel_fscore(p, g, num_points=256, seed=5).mean().item() != together.compute().item()


@pytest.mark.parametrize("convention", ["community", "centred"])
def test_fscore_class_passes_convention(convention):
    metric = VoxelFScore(num_points=256, seed=5, convention=convention)
    scores = []
    for p, g in _batches():
        metric.update(p, g)
        scores.append(_one_at_a_time(p, g, num_points=256, seed=5, convention=convention))
    assert metric.convention == convention
    assert metric.compute().item() == pytest.approx(torch.cat(scores).mean().item(), abs=1e-6)


def test_fscore_class_default_is_community():
    assert VoxelFScore().convention == "community"
    g = torch.zeros(1, 16, 16, 16)
    g[0, 4:12, 4:12, 4:12] = 1
    p = torch.roll(g, 1, dims=1)
    default, centred = VoxelFScore(), VoxelFScore(convention="centred")
    default.update(p, g)
    centred.update(p, g)
    assert default.compute().item() == voxel_fscore(p, g, convention="community").item()
    assert centred.compute().item() == voxel_fscore(p, g, convention="centred").item()
    assert default.compute().item() != centred.compute().item()


def _best_batches() -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Two batches; IoU at (0.4, 0.5): batch 0 holds (1, 0) and (1, 0), batch 1 holds (0.5, 1)."""
    g = torch.zeros(3, 2, 2, 2)
    g[:, 0] = 1
    p = torch.zeros(3, 2, 2, 2)
    p[:2, 0] = 0.45
    p[2] = 0.42
    p[2, 0] = 0.9
    return [(p[:2], g[:2]), (p[2:], g[2:])]


def test_iou_best_class_takes_the_max_of_overall_means():
    metric = VoxelIoUBest(thresholds=(0.4, 0.5), categories=["chair", "lamp"])
    batches = _best_batches()
    for (p, g), c in zip(batches, [["chair", "lamp"], ["lamp"]]):
        metric.update(p, g, c)
    # Overall means (2.5 / 3, 1 / 3): best 0.8333 at 0.4. The batch bests are 1 and 1, and the mean of
    # per-object maxima is 1: neither is VTR's number.
    assert metric.compute().item() == pytest.approx(2.5 / 3)
    assert metric.compute_threshold() == 0.4
    p_all = torch.cat([p for p, _ in batches])
    g_all = torch.cat([g for _, g in batches])
    assert metric.compute().item() == pytest.approx(voxel_iou_best(p_all, g_all, thresholds=(0.4, 0.5)).item())
    # Per category at the overall best threshold 0.4 (lamp alone would be best at 0.5 with 0.5).
    per_cat = metric.compute_per_category()
    assert list(per_cat) == ["chair", "lamp"]
    assert per_cat["chair"].item() == 1.0
    assert per_cat["lamp"].item() == pytest.approx(0.75)


def test_iou_best_class_switches_threshold_and_breaks_ties_low():
    metric = VoxelIoUBest(thresholds=(0.4, 0.5))
    p, g = _best_batches()[1]
    metric.update(p, g)
    assert metric.compute().item() == 1.0 and metric.compute_threshold() == 0.5
    tie = VoxelIoUBest(thresholds=(0.3, 0.4, 0.5))
    tie.update(g.clone(), g)  # IoU 1 at every threshold
    assert tie.compute().item() == 1.0 and tie.compute_threshold() == 0.3
    # Default thresholds are VTR's (0.2, 0.3, 0.4, 0.5).
    assert VoxelIoUBest().thresholds == (0.2, 0.3, 0.4, 0.5)


def test_iou_best_class_syncs_like_iou():
    batches = _best_batches()
    ranks = [VoxelIoUBest(thresholds=(0.4, 0.5)) for _ in range(2)]
    for metric, (p, g) in zip(ranks, batches):
        metric.update(p, g)

    def gather_from_both(tensor: torch.Tensor, group=None) -> list[torch.Tensor]:
        name = next(n for n in ranks[0]._defaults if getattr(ranks[0], n) is tensor)
        return [getattr(r, name).clone() for r in ranks]

    ranks[0].dist_sync_fn = gather_from_both
    ranks[0].distributed_available_fn = lambda: True
    # Alone, rank 0 (two objects best at 0.4) and rank 1 (best at 0.5) disagree; synced: 0.4.
    assert ranks[0].compute().item() == pytest.approx(2.5 / 3)
    assert ranks[0].compute_threshold() == 0.4
    assert ranks[0].count.item() == 2


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
    with pytest.raises(ValueError, match="^`convention` must be one of 'community', 'centred', got 'legoformer'$"):
        VoxelFScore(convention="legoformer")
    with pytest.raises(ValueError, match=r"^`thresholds\[0\]` must be a number in \[0, 1\], got -1.0$"):
        VoxelIoUBest(thresholds=(-1.0,))

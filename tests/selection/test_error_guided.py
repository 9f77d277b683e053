"""Tests of ErrorGuidedSelector: selection on hand-made errors, fallback, determinism, validation."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.geometry import angular_distance, candidate_viewpoints
from lightning_vtr.selection import ErrorGuidedSelector, PaperScore, ViewSelector, nearest_bins
from lightning_vtr.selection.error_guided import relative_to_category


def side_error_pair(res: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    """Object 0: the prediction misses a graded skin on the +Y face; object 1: perfect prediction."""
    gt = torch.zeros(2, res, res, res)
    gt[:, 2:-2, 2:-2, 2:-2] = 1.0
    pred = gt.clone()
    pred[0, 2:-2, res - 3, 2:-2] = 0.1  # outer layer: error 0.9
    pred[0, 2:-2, res - 4, 2:-2] = 0.7  # inner layer: error 0.3
    return pred, gt


def test_selects_around_the_side_with_the_error():
    pred, gt = side_error_pair()
    selector = ErrorGuidedSelector.paper(k=60, num_views=1, score=PaperScore(mode="soft", mask="gt"))
    views = selector.select(pred, gt, ["chair", "chair"], generator=torch.Generator().manual_seed(0))
    assert views.shape == (2, 1, 2)
    assert candidate_viewpoints(60)[selector.last_bins[0, 0]].tolist() == [90.0, 0.0]
    # sigma = K / 6 = 10 degrees: the sample stays near the +Y direction
    assert float(angular_distance(views[0, 0], torch.tensor([90.0, 0.0]))) < 40.0
    assert selector.last_fallback.tolist() == [False, True]
    assert selector.last_scores.shape == (2, 18) and float(selector.last_scores[1].abs().sum()) == 0.0


def test_binary_default_picks_bins_facing_the_error_axis():
    pred, gt = side_error_pair()
    selector = ErrorGuidedSelector.paper()  # K = 30, n = 3, binary at 0.4 (the paper)
    assert (selector.k, selector.num_views, selector.sigma, selector.uses_pool) == (30, 3, 5.0, True)
    selector.select(pred[:1], gt[:1], ["chair"], generator=torch.Generator().manual_seed(0))
    best = candidate_viewpoints(30)[selector.last_bins[0]]
    # binary errors look the same from +Y and -Y: the chosen bins are those nearest the Y axis
    assert bool((best[:, 0].abs() - 90.0).abs().eq(15.0).all()) and bool(best[:, 1].abs().eq(15.0).all())


def test_score_views_matches_select_scores_and_mean_reduction_has_no_nan():
    pred, gt = side_error_pair()
    selector = ErrorGuidedSelector.paper(k=90, score=PaperScore(reduction="mean"))
    scores = selector.score_views(pred, gt)
    assert scores.shape == (2, 8) and not torch.isnan(scores).any()
    assert torch.equal(scores[1], torch.zeros(8))  # no error: 0, not 0 / 0
    assert torch.allclose(scores[0][scores[0] > 0], torch.ones(int((scores[0] > 0).sum())))  # binary: mean of 1s


def test_no_error_falls_back_to_uniform_sampling():
    gt = torch.zeros(50, 6, 6, 6)
    gt[:, 1:5, 1:5, 1:5] = 1.0
    selector = ErrorGuidedSelector.paper(num_views=2, fallback="area")
    views = selector.select(gt.clone(), gt, ["a"] * 50, generator=torch.Generator().manual_seed(0))
    assert views.shape == (50, 2, 2) and torch.isfinite(views).all()
    assert bool(selector.last_fallback.all())
    # uniform on the sphere: sin(pitch) ~ U(-1, 1) has mean 0 and variance 1/3; 100 samples
    s = torch.sin(torch.deg2rad(views[..., 1])).flatten()
    assert abs(float(s.mean())) < 0.2 and abs(float(s.var()) - 1 / 3) < 0.1
    # bins are spread, not the first n candidates a zero-score argsort would give
    assert len(set(nearest_bins(views, 30).flatten().tolist())) > 20


def test_deterministic_with_seeded_generator():
    pred, gt = side_error_pair()
    selector = ErrorGuidedSelector.paper(k=30)
    a = selector.select(pred, gt, ["x", "x"], generator=torch.Generator().manual_seed(3))
    b = selector.select(pred, gt, ["x", "x"], generator=torch.Generator().manual_seed(3))
    c = selector.select(pred, gt, ["x", "x"], generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_empty_batch_returns_empty_selection():
    selector = ErrorGuidedSelector.paper()
    out = selector.select(torch.zeros(0, 8, 8, 8), torch.zeros(0, 8, 8, 8), [])
    assert out.shape == (0, 3, 2)


def test_validation_messages_name_argument_and_value():
    with pytest.raises(ValueError, match=r"`k` must be a bin interval K in degrees that divides 180, got 25"):
        ErrorGuidedSelector.paper(k=25)
    with pytest.raises(ValueError, match=r"`num_views`.*\[1, 8\].*9"):
        ErrorGuidedSelector.paper(k=90, num_views=9)
    with pytest.raises(ValueError, match="`threshold`.*1.5"):
        ErrorGuidedSelector.paper(threshold=1.5)
    with pytest.raises(ValueError, match="`mode`.*'hard'"):
        PaperScore(mode="hard")
    with pytest.raises(ValueError, match="`mask`.*'pred'"):
        PaperScore(mask="pred")
    with pytest.raises(ValueError, match="`reduction`.*'max'"):
        PaperScore(reduction="max")
    with pytest.raises(ValueError, match="`spread`.*-2"):
        ErrorGuidedSelector.paper(spread=-2)
    with pytest.raises(ValueError, match="`fallback`.*'none'"):
        ErrorGuidedSelector.paper(fallback="none")
    selector = ErrorGuidedSelector.paper()
    with pytest.raises(ValueError, match=r"predicted \(1, 8, 8, 8\) and target \(1, 6, 6, 6\)"):
        selector.select(torch.zeros(1, 8, 8, 8), torch.zeros(1, 6, 6, 6), ["a"])
    with pytest.raises(ValueError, match="`categories`.*2 for a batch of 1"):
        selector.select(torch.zeros(1, 8, 8, 8), torch.zeros(1, 8, 8, 8), ["a", "b"])
    assert isinstance(selector, ViewSelector)


@pytest.mark.parametrize("mode", ["binary", "soft"])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_score_views_equals_scores_of_the_projection_maps(mode, reduction):
    from lightning_vtr.selection import error_projection, error_volume, view_scores

    gen = torch.Generator().manual_seed(1)
    pred = torch.rand(3, 8, 8, 8, generator=gen)
    gt = (torch.rand(3, 8, 8, 8, generator=gen) < 0.4).float()
    selector = ErrorGuidedSelector.paper(k=60, score=PaperScore(mode=mode, reduction=reduction, eps=0.05))
    err = error_volume(pred, gt, mode=mode)
    expected = view_scores(error_projection(err, candidate_viewpoints(60), eps=0.05), reduction=reduction)
    assert torch.allclose(selector.score_views(pred, gt), expected, atol=1e-5)


def test_relative_to_category_divides_by_the_category_mean_of_erring_objects():
    scores = torch.tensor([[2.0, 0.0, 4.0], [6.0, 0.0, 4.0], [0.0, 0.0, 0.0], [5.0, 1.0, 0.0]])
    got = relative_to_category(scores, ["a", "a", "a", "b"])
    # category a: the mean over rows 0 and 1 (row 2 has no error) is (4, 0, 4); a view nobody errs in scores 0
    expected = torch.tensor([[0.5, 0.0, 1.0], [1.5, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    assert torch.equal(got, expected)
    with pytest.raises(ValueError, match="categories"):
        relative_to_category(scores, ["a"])


def slab_and_wall(res: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Both objects wrongly predict a horizontal slab (seen from above and below); object 1 also a wall
    across the x axis, half the slab's area (seen from the x sides)."""
    gt = torch.zeros(2, res, res, res)
    pred = gt.clone()
    pred[:, :, :, res // 2 - 1] = 1.0
    pred[1, res // 2 - 1, :, res // 2 :] = 1.0
    return pred, gt


def test_relative_scores_pick_where_an_object_is_worse_than_its_category():
    pred, gt = slab_and_wall()
    views = candidate_viewpoints(30)
    absolute = ErrorGuidedSelector.paper(num_views=1)
    absolute.select(pred, gt, ["c", "c"], generator=torch.Generator().manual_seed(0))
    # the slab's silhouette is the largest error for both: absolute scores look from the poles' bins
    assert views[absolute.last_bins[:, 0]][:, 1].abs().tolist() == [75.0, 75.0]
    relative = ErrorGuidedSelector.paper(num_views=1, relative=True)
    assert relative.batched and not absolute.batched
    relative.select(pred, gt, ["c", "c"], generator=torch.Generator().manual_seed(0))
    yaw, pitch = views[relative.last_bins[1, 0]].tolist()
    # what only object 1 gets wrong is the wall: the bins facing it, along the x axis, near the equator
    assert abs(pitch) == 15.0 and abs(yaw) in (15.0, 165.0)
    assert torch.equal(relative.last_scores, relative_to_category(absolute.last_scores, ["c", "c"]))
    # each object alone in its category: relative scores are 1 wherever it sees error
    relative.select(pred, gt, ["c", "d"], generator=torch.Generator().manual_seed(0))
    assert torch.equal(relative.last_scores, (absolute.last_scores > 0).to(relative.last_scores.dtype))


def test_relative_keeps_the_fallback_of_objects_without_error():
    pred, gt = side_error_pair()
    selector = ErrorGuidedSelector.paper(relative=True)
    selector.select(pred, gt, ["chair", "chair"], generator=torch.Generator().manual_seed(0))
    assert selector.last_fallback.tolist() == [False, True]
    assert float(selector.last_scores[1].abs().sum()) == 0.0
    with pytest.raises(TypeError, match="relative"):
        ErrorGuidedSelector.paper(relative=1)

"""Tests of the functional error-guided selection: error volume, first-hit projection, scores, sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lightning_vtr.geometry import candidate_viewpoints, orthographic_pixel_coords, voxel_centers
from lightning_vtr.selection.base import check_categories
from lightning_vtr.selection.projection import (
    check_volume_pair,
    check_volumes,
    error_projection,
    error_volume,
    nearest_bins,
    projection_scores,
    select_views,
    top_bins,
    view_scores,
)

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


# ------------------------------------------------------------------------------------ reference
def reference_projection(volume: np.ndarray, viewpoints: torch.Tensor, size: int, half_extent: float, eps: float):
    """Plain loops over views and voxels: each voxel above eps claims the pixel holding its centre if it
    is nearer than the current claimant (depths within 1e-9 tie and the earlier, lower flat index stays)."""
    res = volume.shape[0]
    centres = voxel_centers(res, torch.float64).reshape(-1, 3)
    values = volume.reshape(-1).tolist()
    out = np.zeros((viewpoints.shape[0], size, size), dtype=np.float64)
    for v in range(viewpoints.shape[0]):
        coords = orthographic_pixel_coords(centres, viewpoints[v : v + 1].double(), size, half_extent)[0].tolist()
        nearest: dict[tuple[int, int], tuple[float, int]] = {}
        for n, (row, col, depth) in enumerate(coords):
            r, c = math.floor(row), math.floor(col)
            if values[n] <= eps or not (0 <= r < size and 0 <= c < size):
                continue
            if (r, c) not in nearest or depth < nearest[(r, c)][0] - 1e-9:
                nearest[(r, c)] = (depth, n)
        for (r, c), (_, n) in nearest.items():
            out[v, r, c] = values[n]
    return out


@pytest.mark.parametrize("k", [90, 60, 30])
def test_projection_matches_loop_reference_on_random_grids(k):
    gen = torch.Generator().manual_seed(k)
    res, size = 8, 9
    vols = torch.rand(3, res, res, res, generator=gen)
    vols[0] = (vols[0] < 0.15).double()  # sparse binary (the {0,1} fast path)
    vols[1] = torch.where(vols[1] < 0.3, vols[1] + 0.2, torch.zeros(()))  # soft values (the gather path)
    vols[2] = (vols[2] < 0.6).double()  # dense binary
    vp = candidate_viewpoints(k)
    got = error_projection(vols, vp, image_size=size)
    assert got.shape == (3, vp.shape[0], size, size)
    for b in range(3):
        ref = reference_projection(vols[b].numpy(), vp, size, math.sqrt(3) / 2, 0.0)
        np.testing.assert_allclose(got[b].numpy(), ref, rtol=0, atol=1e-7)


def test_projection_matches_reference_at_random_viewpoints_with_eps_and_default_size():
    gen = torch.Generator().manual_seed(3)
    vol = torch.rand(6, 6, 6, generator=gen)
    vp = torch.rand(5, 2, generator=gen) * torch.tensor([360.0, 180.0]) - torch.tensor([180.0, 90.0])
    got = error_projection(vol, vp, eps=0.5, half_extent=0.7)  # unbatched input, S = R = 6
    assert got.shape == (5, 6, 6)
    ref = reference_projection(vol.numpy(), vp, 6, 0.7, 0.5)
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=1e-6)


def test_pixel_layout_by_hand_from_plus_x():
    # Camera at +X looking -X: up is +Z (row 0 = top = high z), right is +Y (col grows with j).
    # With S = R and half extent 0.5 each voxel centre sits at a pixel centre: (i, j, k) -> (R-1-k, j).
    vol = torch.zeros(4, 4, 4)
    vol[3, 1, 3] = 0.7  # nearest the camera: wins its pixel
    vol[2, 1, 3] = 0.2  # hidden behind it
    vol[0, 0, 0] = 1.0  # alone on its ray, far side of the grid
    got = error_projection(vol, torch.tensor([[0.0, 0.0]]), half_extent=0.5)[0]
    expected = torch.zeros(4, 4)
    expected[0, 1] = 0.7
    expected[3, 0] = 1.0
    assert torch.equal(got, expected)


def test_pixel_layout_by_hand_from_north_pole():
    # Camera above (yaw 0, pitch 90): up = (-1, 0, 0), so row = i (larger x lower in the image);
    # right = forward x up = (0, 0, -1) x (-1, 0, 0) = (0, 1, 0), so col = j; higher z is nearer.
    vol = torch.zeros(4, 4, 4)
    vol[0, 2, 1] = 0.5  # low, hidden by the one above
    vol[0, 2, 3] = 0.9
    got = error_projection(vol, torch.tensor([[0.0, 90.0]]), half_extent=0.5)[0]
    expected = torch.zeros(4, 4)
    expected[0, 2] = 0.9
    assert torch.equal(got, expected)


def test_ties_at_equal_depth_go_to_lowest_flat_index():
    # From +X with a coarse image, voxels of one x-slab share a depth; several land in one pixel.
    vol = torch.zeros(4, 4, 4)
    vol[3, 0, 3], vol[3, 1, 3], vol[3, 1, 2] = 0.3, 0.6, 0.9
    got = error_projection(vol, torch.tensor([[0.0, 0.0]]), image_size=1, half_extent=0.5)
    assert got.item() == pytest.approx(0.3)  # flat index of (3, 0, 3) is the lowest


def test_solid_projection_has_no_holes_from_any_view():
    vol = torch.ones(1, 16, 16, 16)
    gen = torch.Generator().manual_seed(0)
    vp = torch.rand(20, 2, generator=gen) * torch.tensor([360.0, 180.0]) - torch.tensor([180.0, 90.0])
    proj = error_projection(vol, vp)[0]  # (20, 16, 16)
    # The silhouette of a full cube is convex: every pixel between two hit pixels of a row is hit.
    for view in proj:
        for row in view:
            hits = torch.nonzero(row).flatten()
            if hits.numel():
                assert bool(row[hits.min() : hits.max() + 1].all())
    # and an axis-aligned view of the cube covers 16 / sqrt(3) ~ 9.2 pixels across: 9 or 10 per side
    side = error_projection(vol, torch.tensor([[0.0, 0.0]]))[0, 0].sum(1).max()
    assert side in (9.0, 10.0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_projection_dtypes_and_devices(device, dtype):
    vol = torch.zeros(2, 4, 4, 4, dtype=dtype, device=device)
    vol[1, 3, 1, 3] = 0.5
    got = error_projection(vol, torch.tensor([[0.0, 0.0]]), half_extent=0.5)
    assert got.dtype == dtype and got.device.type == device
    assert got[0].abs().sum() == 0 and got[1, 0, 0, 1] == 0.5 and got.sum() == 0.5


def test_empty_batch_and_bad_inputs():
    assert error_projection(torch.zeros(0, 4, 4, 4), candidate_viewpoints(90)).shape == (0, 8, 4, 4)
    with pytest.raises(ValueError, match=r"\(B, R, R, R\).*\(2, 4, 4, 5\)"):
        error_projection(torch.zeros(2, 4, 4, 5), candidate_viewpoints(90))
    with pytest.raises(ValueError, match=r"`volumes` must be a non-empty grid \(R >= 1\), got shape \(1, 0, 0, 0\)"):
        error_projection(torch.zeros(1, 0, 0, 0), candidate_viewpoints(90))
    with pytest.raises(ValueError, match="V >= 1"):
        error_projection(torch.zeros(1, 4, 4, 4), torch.zeros(0, 2))
    with pytest.raises(ValueError, match="image_size"):
        error_projection(torch.zeros(1, 4, 4, 4), candidate_viewpoints(90), image_size=0)
    with pytest.raises(ValueError, match="half_extent"):
        error_projection(torch.zeros(1, 4, 4, 4), candidate_viewpoints(90), half_extent=-1.0)


# ------------------------------------------------------------------------------------ error volume
def test_error_volume_binary_soft_and_gt_mask_by_hand():
    pred = torch.tensor([0.1, 0.39, 0.4, 0.9]).view(1, 4, 1, 1).expand(1, 4, 4, 4).clone()
    gt = torch.tensor([0.0, 1.0, 1.0, 0.0]).view(1, 4, 1, 1).expand(1, 4, 4, 4).clone()
    binary = error_volume(pred, gt)[0, :, 0, 0]
    assert binary.tolist() == [0.0, 1.0, 0.0, 1.0]  # threshold 0.4 inclusive, as the IoU metric
    soft = error_volume(pred, gt, mode="soft")[0, :, 0, 0]
    assert torch.allclose(soft, torch.tensor([0.1, 0.61, 0.6, 0.9]))
    masked = error_volume(pred, gt, mode="soft", mask="gt")[0, :, 0, 0]
    assert torch.allclose(masked, torch.tensor([0.0, 0.61, 0.6, 0.0]))
    assert error_volume(pred, gt, mask="gt")[0, :, 0, 0].tolist() == [0.0, 1.0, 0.0, 0.0]
    assert error_volume(pred, gt, threshold=0.95)[0, :, 0, 0].tolist() == [0.0, 1.0, 1.0, 0.0]


def test_error_volume_shape_mismatch_names_both_shapes():
    with pytest.raises(ValueError, match=r"predicted \(1, 4, 4, 4\) and target \(2, 4, 4, 4\)"):
        error_volume(torch.zeros(1, 4, 4, 4), torch.zeros(2, 4, 4, 4))
    with pytest.raises(ValueError, match="mode"):
        error_volume(torch.zeros(1, 4, 4, 4), torch.zeros(1, 4, 4, 4), mode="hard")


# ------------------------------------------------------------------------------------ scores
def test_view_scores_sum_and_mean_with_empty_map():
    proj = torch.zeros(2, 3, 2, 2)
    proj[0, 0] = torch.tensor([[0.5, 0.0], [0.25, 0.0]])
    proj[0, 2] = 1.0
    assert view_scores(proj).tolist() == [[0.75, 0.0, 4.0], [0.0, 0.0, 0.0]]
    mean = view_scores(proj, reduction="mean")
    assert mean.tolist() == [[0.375, 0.0, 1.0], [0.0, 0.0, 0.0]]
    assert not torch.isnan(mean).any()


# ------------------------------------------------------------------------------------ hand cases
def graded_side_error(res: int, axis: int, positive: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """A solid cube whose prediction misses a 2-voxel skin on one face, worst on the outside.

    Errors inside the skin: 0.9 on the outer layer, 0.3 on the inner one, so the error seen first from
    the face's own side (0.9) beats the one seen through the object from the opposite side (0.3).
    """
    gt = torch.zeros(1, res, res, res)
    lo, hi = 2, res - 2
    gt[0, lo:hi, lo:hi, lo:hi] = 1.0
    pred = gt.clone()
    outer, inner = (hi - 1, hi - 2) if positive else (lo, lo + 1)
    sl = [slice(lo, hi)] * 3
    sl[axis] = outer
    pred[(0, *sl)] = 0.1
    sl[axis] = inner
    pred[(0, *sl)] = 0.7
    return pred, gt


def _best_and_scores(pred, gt, k):
    err = error_volume(pred, gt, mode="soft", mask="gt")
    scores = view_scores(error_projection(err, candidate_viewpoints(k)))[0]
    return scores


def test_plus_x_error_is_best_seen_from_yaw_zero():
    scores = _best_and_scores(*graded_side_error(12, axis=0, positive=True), k=60)
    cand = candidate_viewpoints(60)
    best = set(torch.nonzero(scores > scores.max() - 1e-4).flatten().tolist())
    # bins centred nearest +X (yaw +-30, pitch 0), mirror images so tied up to float rounding
    assert {tuple(cand[i].tolist()) for i in best} == {(-30.0, 0.0), (30.0, 0.0)}
    facing_minus_x = [i for i, (y, p) in enumerate(cand.tolist()) if abs(y) > 120 and p == 0.0]
    assert all(scores[i] < scores.max() for i in facing_minus_x)


def test_plus_y_error_is_best_seen_from_yaw_90():
    scores = _best_and_scores(*graded_side_error(12, axis=1, positive=True), k=60)
    assert candidate_viewpoints(60)[int(scores.argmax())].tolist() == [90.0, 0.0]
    assert (scores > scores.max() - 1e-4).sum() == 1


@pytest.mark.parametrize(("positive", "pole_row"), [(True, 5), (False, 0)])
def test_top_and_bottom_errors_are_best_seen_from_their_pole(positive, pole_row):
    scores = _best_and_scores(*graded_side_error(12, axis=2, positive=positive), k=30).view(6, 12)
    assert int(scores.max(dim=1).values.argmax()) == pole_row
    opposite = 5 - pole_row
    assert bool(scores[pole_row].min() > scores[opposite].max())


def test_binary_error_scores_are_antipodally_symmetric():
    # A binary error is seen as the same (mirrored) silhouette from a view and its antipode, so the
    # paper's sum score cannot tell them apart. (Exactly so where no voxel centre lands on a pixel
    # boundary; at yaw +-45 / +-135 the diagonal's centres project onto the middle column boundary.)
    pred, gt = graded_side_error(12, axis=0, positive=True)
    err = error_volume(pred, gt)  # binary
    cand = candidate_viewpoints(30)
    scores = view_scores(error_projection(err, cand))[0]
    antipode = nearest_bins(torch.stack([cand[:, 0] + 180.0, -cand[:, 1]], -1), 30)
    off_diagonal = cand[:, 0].abs().remainder(90.0) != 45.0
    assert off_diagonal.sum() == 48
    assert torch.equal(scores[off_diagonal], scores[antipode][off_diagonal])
    order = torch.argsort(-scores, stable=True)[:8]
    assert {tuple(cand[i].tolist()) for i in order} == {
        (y, p) for y in (-165.0, -15.0, 15.0, 165.0) for p in (-15.0, 15.0)
    }


# ------------------------------------------------------------------------------------ bins & sampling
def test_nearest_bins_by_hand():
    vp = torch.tensor([[179.0, 90.0], [-180.0, -90.0], [0.0, 0.0], [14.9, 0.1], [180.0, 0.0], [-1.0, -0.1]])
    assert nearest_bins(vp, 30).tolist() == [71, 0, 42, 42, 36, 29]


def test_top_bins_orders_by_score_and_shuffles_exact_ties():
    scores = torch.tensor([[0.0, 5.0, 1.0, 5.0, 3.0]])
    first = {tuple(top_bins(scores, 2, generator=torch.Generator().manual_seed(s))[0].tolist()) for s in range(20)}
    assert first == {(1, 3), (3, 1)}
    assert top_bins(scores, 4, generator=torch.Generator().manual_seed(0))[0, 2:].tolist() == [4, 2]
    with pytest.raises(ValueError, match="`n`"):
        top_bins(scores, 6)


def test_select_views_statistics_sigma_is_k_over_6():
    k = 30
    scores = torch.zeros(4000, 72)
    scores[:, 42] = 1.0  # bin centre (yaw 15, pitch 15)
    views = select_views(scores, k, n=1, generator=torch.Generator().manual_seed(0))[:, 0]
    assert views.shape == (4000, 2)
    centre = candidate_viewpoints(k)[42]
    assert centre.tolist() == [15.0, 15.0]
    assert torch.allclose(views.mean(0), centre, atol=0.3)
    assert torch.allclose(views.std(0), torch.full((2,), k / 6.0), rtol=0.04)


def test_select_views_wraps_yaw_and_clamps_pitch():
    scores = torch.zeros(3000, 72)
    scores[:, 71] = 1.0  # bin centre (165, 75): near the seam and the north pole
    views = select_views(scores, 30, n=1, generator=torch.Generator().manual_seed(1), sigma=20.0)[:, 0]
    assert bool((views[:, 0] >= -180.0).all() and (views[:, 0] < 180.0).all())
    wrapped = (views[:, 0] < 0).float().mean()
    # P(165 + N(0, 20) >= 180) = P(Z >= 0.75) = 0.2266
    assert abs(float(wrapped) - 0.2266) < 0.03
    assert float(views[:, 1].max()) == 90.0
    # P(75 + N(0, 20) >= 90) = 0.2266 of samples clamped to the pole
    assert abs(float((views[:, 1] == 90.0).float().mean()) - 0.2266) < 0.03


def test_select_views_deterministic_and_validated():
    scores = torch.rand(5, 72, generator=torch.Generator().manual_seed(0))
    a = select_views(scores, 30, 3, generator=torch.Generator().manual_seed(7))
    b = select_views(scores, 30, 3, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b) and a.shape == (5, 3, 2)
    with pytest.raises(ValueError, match=r"`k` must be a bin interval K in degrees that divides 180, got 25"):
        select_views(scores, 25, 3)
    with pytest.raises(ValueError, match=r"\(B, 72\) for K=30, got \(5, 70\)"):
        select_views(scores[:, :70], 30, 3)
    with pytest.raises(ValueError, match="sigma"):
        select_views(scores, 30, 3, sigma=-1.0)
    assert select_views(torch.zeros(0, 72), 30, 3).shape == (0, 3, 2)


def test_select_views_centres_are_the_top_bins_with_zero_sigma():
    scores = torch.zeros(2, 8)
    scores[0, [6, 1, 3]] = torch.tensor([3.0, 2.0, 1.0])
    scores[1, [0, 7, 5]] = torch.tensor([9.0, 8.0, 7.0])
    views = select_views(scores, 90, 3, sigma=0.0, generator=torch.Generator().manual_seed(0))
    cand = candidate_viewpoints(90)
    assert torch.equal(views[0], cand[[6, 1, 3]]) and torch.equal(views[1], cand[[0, 7, 5]])


# ------------------------------------------------------------------------------------ public checks
def test_check_volumes_and_pair_messages():
    assert check_volumes(torch.ones(1, 2, 2, 2, dtype=torch.bool)).dtype == torch.get_default_dtype()
    grid = torch.zeros(1, 2, 2, 2, dtype=torch.float64)
    assert check_volumes(grid) is grid
    with pytest.raises(TypeError, match="^`volumes` must be a torch.Tensor, got list$"):
        check_volumes([[[[0.0]]]])
    message = r"^`target` must be a floating-point \(or bool\) tensor, got dtype torch.int64$"
    with pytest.raises(TypeError, match=message):
        check_volume_pair(torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2, dtype=torch.long))
    with pytest.raises(TypeError, match="^`predicted` and `target` must be torch.Tensors, got ndarray and Tensor$"):
        check_volume_pair(np.zeros((1, 2, 2, 2)), torch.zeros(1, 2, 2, 2))


def test_check_categories():
    assert check_categories(["a", "b"], 2) == ["a", "b"]
    with pytest.raises(ValueError, match="^`categories` must have one entry per object, got 1 for a batch of 2$"):
        check_categories(["a"], 2)
    with pytest.raises(TypeError, match="^`categories` must be a sequence of names, one per object, got str 'ab'$"):
        check_categories("ab", 2)


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_projection_scores_equal_the_scores_of_the_maps(reduction):
    gen = torch.Generator().manual_seed(3)
    soft = torch.rand(2, 6, 6, 6, generator=gen) * (torch.rand(2, 6, 6, 6, generator=gen) < 0.3)
    binary = soft > 0
    views = candidate_viewpoints(60)
    for volumes, flag in ((soft, None), (binary, True), (binary.float(), None)):
        expected = view_scores(error_projection(volumes.float(), views, eps=0.0), reduction=reduction)
        got = projection_scores(volumes, views, reduction=reduction, binary=flag)
        torch.testing.assert_close(got, expected)
    assert projection_scores(torch.zeros(0, 6, 6, 6), views).shape == (0, 18)  # 3 pitch x 6 yaw bins
    with pytest.raises(ValueError, match="^`reduction` must be one of 'sum', 'mean', got 'max'$"):
        projection_scores(soft, views, reduction="max")
    with pytest.raises(TypeError, match="^`volumes` must be a floating-point"):
        projection_scores(soft.long(), views)


def test_argument_types_raise_type_errors():
    with pytest.raises(TypeError, match="^`image_size` must be an int, got float 4.0$"):
        error_projection(torch.zeros(1, 4, 4, 4), candidate_viewpoints(90), image_size=4.0)
    with pytest.raises(TypeError, match="^`n` must be an int, got bool True$"):
        top_bins(torch.zeros(1, 4), True)
    with pytest.raises(TypeError, match=r"^`scores` must be a torch.Tensor of shape \(B, V\), got list$"):
        top_bins([[0.0, 1.0]], 1)
    with pytest.raises(ValueError, match=r"^`threshold` must be a number in \[0, 1\], got 1.5$"):
        error_volume(torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2), threshold=1.5)


# ------------------------------------------------------------------------------ occlusion culling
def _solid_shapes(res: int) -> torch.Tensor:
    """A ball, an axis-aligned box touching the grid's border and a slanted slab: solid, with big interiors."""
    c = voxel_centers(res, torch.float64)
    ball = (c - torch.tensor([0.05, -0.1, 0.0], dtype=torch.float64)).norm(dim=-1) < 0.42
    box = (c[..., 0] > -0.5) & (c[..., 0] < 0.2) & (c[..., 1].abs() < 0.3) & (c[..., 2] < 0.35)
    slab = ((c @ torch.tensor([0.6, 0.48, 0.64], dtype=torch.float64)).abs() < 0.15) & (c.norm(dim=-1) < 0.45)
    return torch.stack([ball, box, slab]).double()


@pytest.mark.parametrize("device", DEVICES)
def test_culling_the_occluded_voxels_changes_no_first_hit_on_solids(device):
    # The score functions leave out voxels whose 2x2x2 block towards the cameras is full; the projection must
    # stay the plain loops' one, also from axis-aligned views (a flat depth direction), in small images where
    # some centres fall outside (half_extent 0.45), and with pixels half a voxel wide (half_extent 0.3, 12
    # pixels), where a full block often leaves a voxel visible and only the table's occludable flags keep it.
    res = 10
    vols = _solid_shapes(res)
    vols[2] = vols[2] * torch.linspace(0.2, 1.0, res**3, dtype=torch.float64).view(res, res, res)  # soft values
    gen = torch.Generator().manual_seed(5)
    random_views = torch.rand(6, 2, generator=gen, dtype=torch.float64) * torch.tensor([360.0, 180.0]) - torch.tensor(
        [180.0, 90.0]
    )
    axis_views = torch.tensor([[0.0, 0.0], [90.0, 0.0], [-180.0, 0.0], [30.0, 90.0], [0.0, -90.0], [45.0, 35.26]])
    views = torch.cat([candidate_viewpoints(60).double(), axis_views.double(), random_views])
    for half_extent, size in ((math.sqrt(3) / 2, res), (0.45, 7), (0.3, 12)):
        got = error_projection(vols.to(device), views.to(device), image_size=size, half_extent=half_extent).cpu()
        for b in range(vols.shape[0]):
            ref = reference_projection(vols[b].numpy(), views, size, half_extent, 0.0)
            np.testing.assert_allclose(got[b].numpy(), ref, rtol=0, atol=1e-7)


def test_every_interior_voxel_is_culled_for_the_candidate_views():
    # For the selector's candidate views, each octant's voxels with all 7 neighbours towards the cameras
    # inside the grid are occludable: a solid's interior never reaches the scatter.
    from lightning_vtr.selection.first_hit import projection_table

    res = 12
    table = projection_table(res, candidate_viewpoints(30), res, math.sqrt(3) / 2, torch.device("cpu"))
    assert len(table.groups) == 8 and sorted(len(g.views) for g in table.groups) == [9] * 8
    assert torch.equal(torch.sort(torch.cat([g.views for g in table.groups])).values, torch.arange(72))
    ijk = torch.stack(torch.meshgrid(*[torch.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)
    block_steps = torch.tensor([(res + 1) ** 2, res + 1, 1])
    for group in table.groups:
        towards = torch.tensor([(group.block_offset // int(s)) % (res + 1) for s in block_steps]) * 2 - 1
        interior = ((ijk + towards >= 0) & (ijk + towards < res)).all(-1)
        assert bool(group.occludable[interior].all())
        assert not bool(group.occludable[~interior].all())  # the front border cannot be hidden by a full block


def test_scores_are_the_same_in_one_thread_and_in_several():
    # The scores must not depend on the thread count (ATen reductions may split their work by it).
    vols = _solid_shapes(12)
    soft = vols * torch.rand(vols.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    views = candidate_viewpoints(30)
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 4):
            torch.set_num_threads(count)
            results.append(
                (
                    projection_scores(soft, views, reduction="mean"),
                    projection_scores(vols > 0, views, binary=True),
                    error_projection(soft, views),
                )
            )
    finally:
        torch.set_num_threads(threads)
    for one, several in zip(*results):
        assert torch.equal(one, several)
    assert float(results[0][1].min()) > 0  # every view sees each solid


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["binary", "soft"])
def test_visible_scores_equal_the_loop_reference_on_solids(mode, device):
    # The binary "visible" score reads the error bit carried in the first-hit keys, the soft one gathers
    # values: both must equal the plain loops' first hit on prediction-or-truth, valued by the error there.
    from lightning_vtr.selection.projection import visible_error_scores

    res = 10
    target = _solid_shapes(res).float()
    gen = torch.Generator().manual_seed(11)
    noise = torch.rand(target.shape, generator=gen)
    predicted = torch.where(noise < 0.15, 1.0 - target, target) * 0.8 + 0.1 * noise  # ~15 % wrong, soft values
    views = torch.cat([candidate_viewpoints(60), torch.tensor([[0.0, 0.0], [30.0, 90.0], [12.0, -37.0]])])
    got = visible_error_scores(
        predicted.to(device), target.to(device), views.to(device), threshold=0.4, mode=mode
    ).cpu()
    occupied_pred, occupied_gt = predicted >= 0.4, target >= 0.5
    error = (occupied_pred != occupied_gt).double() if mode == "binary" else (predicted - target).abs().double()
    # values 1 + error on the surface: the reference's first-hit map minus its hit mask is the error seen
    surface_values = torch.where(occupied_pred | occupied_gt, 1.0 + error, torch.zeros((), dtype=torch.float64))
    for b in range(target.shape[0]):
        seen = reference_projection(surface_values[b].numpy(), views, res, math.sqrt(3) / 2, 0.0)
        expected = (seen - (seen > 0)).sum(axis=(1, 2))
        np.testing.assert_allclose(got[b].numpy(), expected, rtol=1e-5, atol=1e-4)
    assert float(got.sum()) > 0

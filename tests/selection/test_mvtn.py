"""The differentiable voxel projection and MVTNSelector."""

from __future__ import annotations

import pytest
import torch
from helpers import one_thread

from lightning_vtr.geometry import angular_distance, camera_center, voxel_centers, wrap_yaw
from lightning_vtr.selection.base import ViewSelector
from lightning_vtr.selection.differentiable_projection import soft_error_projection
from lightning_vtr.selection.mvtn import MVTNSelector
from lightning_vtr.selection.projection import error_projection, error_volume

# These tensors are tiny: on the shared 2-core machine intra-op threads only add contention.
_one_thread = pytest.fixture(autouse=True, name="_one_thread")(one_thread)


# ------------------------------------------------------------------------------------- projection
def _first_hit_along(volume: torch.Tensor, dim: int, from_high: bool) -> torch.Tensor:
    """Reference first hit along a grid axis: the value of the first non-zero voxel met from one end."""
    v = volume.flip(dim) if from_high else volume
    hit = v > 0
    first = hit.to(torch.uint8).argmax(dim, keepdim=True)
    value = v.gather(dim, first).squeeze(dim)
    return torch.where(hit.any(dim), value, torch.zeros_like(value))


def test_hard_projection_matches_hand_derived_axis_views():
    # With half_extent = 0.5 and S = R a pixel is exactly a voxel face, so axis-aligned views are
    # index permutations of the grid (derived by hand from the camera convention of geometry.py).
    g = torch.Generator().manual_seed(0)
    r = 6
    vol = torch.rand(2, r, r, r, generator=g) * (torch.rand(2, r, r, r, generator=g) < 0.3)
    views = torch.tensor([[0.0, 0.0], [90.0, 0.0], [0.0, 90.0]])
    maps = soft_error_projection(vol, views, half_extent=0.5, hard=True)
    for b in range(2):
        # yaw 0: camera on +x; right = +y (col = j), up = +z (row = R-1-k); first hit = largest i.
        front = _first_hit_along(vol[b], 0, from_high=True)  # (j, k)
        assert torch.equal(maps[b, 0], front.T.flip(0))
        # yaw 90: camera on +y; right = -x (col = R-1-i), up = +z; first hit = largest j.
        side = _first_hit_along(vol[b], 1, from_high=True)  # (i, k)
        assert torch.equal(maps[b, 1], side.flip(0).T.flip(0))
        # pitch 90: camera on +z; right = +y (col = j), up = -x (row = i); first hit = largest k.
        top = _first_hit_along(vol[b], 2, from_high=True)  # (i, j)
        assert torch.equal(maps[b, 2], top)


def _solids(r: int) -> torch.Tensor:
    c = voxel_centers(r)
    ball = (c - torch.tensor([0.1, -0.05, 0.0])).norm(dim=-1) < 0.3
    box = (c.abs() < torch.tensor([0.35, 0.2, 0.1])).all(-1)
    ellipsoid = (c / torch.tensor([0.4, 0.25, 0.15])).norm(dim=-1) < 1
    return torch.stack([ball, box, ellipsoid]).float()


def test_sharp_soft_projection_matches_error_projection_silhouettes():
    g = torch.Generator().manual_seed(1)
    vp = torch.stack([torch.rand(12, generator=g) * 360 - 180, torch.rand(12, generator=g) * 180 - 90], -1)
    vol = _solids(32)
    reference = error_projection(vol, vp) > 0  # the package's first-hit projection (voxel centres)
    soft = soft_error_projection(vol, vp, density=5.0) > 0.5
    iou = (soft & reference).sum((-1, -2)).float() / (soft | reference).sum((-1, -2)).float()
    assert iou.min().item() >= 0.9, iou


def test_soft_tends_to_hard_for_an_axis_aligned_block():
    r = 8
    vol = torch.zeros(1, r, r, r)
    vol[0, 2:6, 3:7, 1:4] = 1.0
    hard = soft_error_projection(vol, torch.tensor([[0.0, 0.0]]), half_extent=0.5, hard=True)
    # Rays through the block cross 4 voxels of error: 1 - exp(-density * 4) with samples at voxel spacing.
    soft = soft_error_projection(vol, torch.tensor([[0.0, 0.0]]), half_extent=0.5, density=50.0, num_samples=64)
    inside = hard[0, 0] > 0
    assert torch.allclose(soft[0, 0][inside], torch.ones(int(inside.sum())), atol=1e-6)
    # Away from the block's border (trilinear blur reaches half a voxel) the soft map is empty.
    far = torch.nn.functional.max_pool2d(hard[:, :1], 3, stride=1, padding=1)[0, 0] == 0
    assert soft[0, 0][far].abs().max().item() < 1e-6


def test_gradcheck_in_volume_and_angles():
    g = torch.Generator().manual_seed(2)
    vol = torch.rand(1, 4, 4, 4, generator=g, dtype=torch.float64).requires_grad_()
    vp = torch.tensor([[[23.0, 17.0], [-140.0, -52.0]]], dtype=torch.float64, requires_grad=True)

    def fn(volumes, viewpoints):
        return soft_error_projection(volumes, viewpoints, image_size=3, num_samples=6, density=0.7)

    assert torch.autograd.gradcheck(fn, (vol, vp), eps=1e-6, atol=1e-5)


def test_projection_checks_inputs():
    with pytest.raises(ValueError, match="volumes"):
        soft_error_projection(torch.zeros(2, 4, 4, 5), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="viewpoints"):
        soft_error_projection(torch.zeros(2, 4, 4, 4), torch.zeros(3, 1, 2))
    with pytest.raises(ValueError, match="density"):
        soft_error_projection(torch.zeros(2, 4, 4, 4), torch.zeros(1, 2), density=0.0)


# ------------------------------------------------------------------------------------------- MVTN
BLOB_DIRECTION = torch.tensor([40.0, 0.0])  # (yaw, pitch) degrees of the side holding the error


def _plate_error(r: int = 16, batch: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Prediction / target whose error is a flat patch on one side, facing BLOB_DIRECTION.

    A flat patch is seen largest face-on, so the error a view covers grows as the view turns toward it.
    """
    c = voxel_centers(r)
    n = camera_center(BLOB_DIRECTION)
    depth = (c * n).sum(-1)
    radial = (c - depth[..., None] * n).norm(dim=-1)
    plate = ((depth - 0.3).abs() < 0.07) & (radial < 0.3)
    predicted = (0.9 * plate.float()).expand(batch, r, r, r).clone()  # predicted where nothing is
    return predicted, torch.zeros(batch, r, r, r)


def test_training_turns_a_view_toward_the_error():
    predicted, target = _plate_error()
    selector = MVTNSelector(steps=10, lr=1e-2)
    assert isinstance(selector, ViewSelector) and selector.uses_pool is False and selector.needs_context is False
    base = selector.base_views()
    views = selector.select(predicted, target, ["a", "b"])
    error = error_volume(predicted, target)
    before = selector.coverage(error, base).sum(1)
    after = selector.coverage(error, views).sum(1)
    assert (after > 1.15 * before).all(), (before, after)
    start = angular_distance(base[0], BLOB_DIRECTION).item()  # ~48 degrees
    end = angular_distance(views[:, 0], BLOB_DIRECTION)
    assert (end < 0.5 * start).all(), end


def test_untrained_network_returns_the_base_views():
    predicted, target = _plate_error(batch=3)
    selector = MVTNSelector(steps=0, base_pitch=20.0)
    views = selector.select(predicted, target, ["a"] * 3)
    expected = torch.tensor([[0.0, 20.0], [120.0, 20.0], [-120.0, 20.0]])
    assert torch.allclose(views, expected.expand(3, -1, -1), atol=1e-4)


def test_outputs_stay_bounded():
    predicted, target = _plate_error(batch=2)
    selector = MVTNSelector(steps=15, lr=0.3)  # a rate large enough to saturate the tanh bounds
    views = selector.select(predicted, target, ["a", "b"])
    assert views.shape == (2, 3, 2)
    assert (views[..., 0] >= -180).all() and (views[..., 0] < 180).all()
    assert (views[..., 1].abs() <= 90).all()
    offsets = wrap_yaw(views[..., 0] - torch.tensor([0.0, 120.0, 240.0]))
    assert (offsets.abs() <= 60.0 + 1e-3).all()


def test_deterministic_and_state_round_trip(tmp_path):
    predicted, target = _plate_error()
    first, twin = MVTNSelector(steps=3, seed=5), MVTNSelector(steps=3, seed=5)
    a = first.select(predicted, target, ["a", "b"])
    assert torch.equal(a, twin.select(predicted, target, ["a", "b"]))

    path = tmp_path / "mvtn.pt"
    torch.save(first.state_dict(), path)
    restored = MVTNSelector(steps=3, seed=99)
    restored.load_state_dict(torch.load(path, weights_only=False))
    # Continuing training from the restored weights and Adam moments matches the original.
    assert torch.equal(first.select(predicted, target, ["a", "b"]), restored.select(predicted, target, ["a", "b"]))
    fresh = MVTNSelector(steps=3, seed=99)
    assert not torch.equal(restored.select(predicted, target, ["a", "b"]), fresh.select(predicted, target, ["a", "b"]))

    with pytest.raises(ValueError, match="another number of base yaws"):
        MVTNSelector(base_yaw=(0.0, 180.0)).load_state_dict(first.state_dict())


def test_trains_under_inference_mode():
    # The callback may run selectors under torch.inference_mode(); MVTN still has to learn.
    predicted, target = _plate_error()
    selector = MVTNSelector(steps=3)
    with torch.inference_mode():
        views = selector.select(predicted, target, ["a", "b"])
    assert not torch.allclose(views, selector.base_views().expand(2, -1, -1))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"base_pitch": 90.0}, "base_pitch"),
        ({"base_yaw": []}, "base_yaw"),
        ({"input": "mesh"}, "input"),
        ({"lr": -1.0}, "lr"),
        ({"max_yaw_offset": 200.0}, "max_yaw_offset"),
        ({"steps": -1}, "steps"),
    ],
)
def test_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MVTNSelector(**kwargs)

"""The conventions module against hand-computed values, poles included."""

from __future__ import annotations

import math

import pytest
import torch

from lightning_vtr import geometry as g

S = math.sqrt(0.5)  # sin 45 = cos 45


def _t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


# (yaw, pitch) -> (centre, up, right), worked out from the module docstring:
# centre (cos p cos y, cos p sin y, sin p), up (-sin p cos y, -sin p sin y, cos p), right = forward x up.
HAND = [
    ((0.0, 0.0), (1, 0, 0), (0, 0, 1), (0, 1, 0)),
    ((90.0, 0.0), (0, 1, 0), (0, 0, 1), (-1, 0, 0)),
    ((180.0, 0.0), (-1, 0, 0), (0, 0, 1), (0, -1, 0)),
    ((-180.0, 0.0), (-1, 0, 0), (0, 0, 1), (0, -1, 0)),
    ((0.0, 90.0), (0, 0, 1), (-1, 0, 0), (0, 1, 0)),
    ((0.0, -90.0), (0, 0, -1), (1, 0, 0), (0, 1, 0)),
    ((45.0, 90.0), (0, 0, 1), (-S, -S, 0), (-S, S, 0)),
    ((0.0, 45.0), (S, 0, S), (-S, 0, S), (0, 1, 0)),
]


@pytest.mark.parametrize(("vp", "centre", "up", "right"), HAND)
def test_camera_frame_hand_computed(vp, centre, up, right):
    vp = _t(vp)
    torch.testing.assert_close(g.camera_center(vp), _t(centre), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.camera_center(vp, radius=2.5), 2.5 * _t(centre), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.camera_up(vp), _t(up), atol=1e-12, rtol=0)
    torch.testing.assert_close(g.view_direction(vp), -_t(centre), atol=1e-12, rtol=0)
    basis = g.camera_basis(vp)
    torch.testing.assert_close(basis[0], _t(right), atol=1e-12, rtol=0)
    torch.testing.assert_close(basis[1], _t(up), atol=1e-12, rtol=0)
    torch.testing.assert_close(basis[2], _t(centre), atol=1e-12, rtol=0)  # backward = -forward
    pose = g.camera_pose(vp, radius=3.0)
    torch.testing.assert_close(pose[:3, 3], 3.0 * _t(centre), atol=1e-12, rtol=0)
    torch.testing.assert_close(pose[:3, :3], basis.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(pose[3], _t([0, 0, 0, 1]), atol=0, rtol=0)


def test_random_bases_are_orthonormal_right_handed_and_look_at_the_origin():
    vp = torch.cat(
        [
            g.sample_uniform_viewpoints(200, generator=torch.Generator().manual_seed(0)).double(),
            _t([[10, 90], [-77, -90]]),
        ]
    )
    basis = g.camera_basis(vp)
    torch.testing.assert_close(
        basis @ basis.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(len(vp), 3, 3), atol=1e-12, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(basis), torch.ones(len(vp), dtype=torch.float64), atol=1e-12, rtol=0)
    # The origin maps to the optical axis: camera coordinates (0, 0, -r) for a camera at distance r.
    pose = g.camera_pose(vp, radius=2.0)
    origin_cam = torch.linalg.inv(pose) @ _t([0, 0, 0, 1])
    torch.testing.assert_close(origin_cam[:, :3], _t([0, 0, -2.0]).expand(len(vp), 3), atol=1e-12, rtol=0)
    # Away from the poles, image up points toward +Z (no roll).
    mid = vp[:, 1].abs() < 89
    assert (basis[mid, 1, 2] > 0).all() and basis[mid, 0, 2].abs().max() < 1e-12


def test_orthographic_pixel_coords_hand_computed():
    # From (0, 0): right = +Y, up = +Z. S = 4, s = 1: pixel (row, col) = (1 - z) * 2, (y + 1) * 2.
    pts = _t([[0.0, 0.0, 0.0], [0.3, 0.5, 0.25], [-0.2, -1.0, 1.0]])
    out = g.orthographic_pixel_coords(pts, _t([[0.0, 0.0]]), 4, 1.0)[0]
    torch.testing.assert_close(out, _t([[2.0, 2.0, 0.0], [1.5, 3.0, -0.3], [0.0, 0.0, 0.2]]), atol=1e-12, rtol=0)


def test_wrap_and_clamp_edge_cases():
    torch.testing.assert_close(
        g.wrap_yaw(_t([180.0, -180.0, 540.0, -181.0, 179.5, 360.0])), _t([-180.0, -180.0, -180.0, 179.0, 179.5, 0.0])
    )
    torch.testing.assert_close(g.clamp_pitch(_t([95.0, -90.0, -100.0, 12.0])), _t([90.0, -90.0, -90.0, 12.0]))
    torch.testing.assert_close(
        g.normalize_viewpoints(_t([[190.0, 100.0], [-180.0, -90.0]])), _t([[-170.0, 90.0], [-180.0, -90.0]])
    )
    with pytest.raises(ValueError, match="viewpoints"):
        g.check_viewpoints(_t([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="NaN"):
        g.check_viewpoints(_t([[float("nan"), 0.0]]))


def test_bins_for_k30():
    yaw, pitch = g.angle_bins(30)
    assert yaw.shape == (12,) and pitch.shape == (6,)
    assert (yaw[0].item(), yaw[-1].item(), pitch[0].item(), pitch[-1].item()) == (-165.0, 165.0, -75.0, 75.0)
    cands = g.candidate_viewpoints(30)
    assert cands.shape == (72, 2)
    # Pitch-major: index = i_pitch * 12 + i_yaw.
    assert (
        cands[0].tolist() == [-165.0, -75.0]
        and cands[13].tolist() == [-135.0, -45.0]
        and cands[-1].tolist() == [165.0, 75.0]
    )
    assert g.candidate_viewpoints(90).tolist() == [
        [-135.0, -45.0],
        [-45.0, -45.0],
        [45.0, -45.0],
        [135.0, -45.0],
        [-135.0, 45.0],
        [-45.0, 45.0],
        [45.0, 45.0],
        [135.0, 45.0],
    ]


@pytest.mark.parametrize("k", [7, 0, -30, 2.5, 360])
def test_bad_bin_intervals(k):
    with pytest.raises(ValueError, match=rf"^`k` must be a bin interval K in degrees that divides 180, got {k}$"):
        g.check_bin_interval(k)


@pytest.mark.parametrize("k", [True, "30", None])
def test_bin_interval_of_a_wrong_type(k):
    with pytest.raises(TypeError, match="^`k` must be a bin interval K in degrees"):
        g.check_bin_interval(k)


def test_integral_float_bin_interval_is_accepted():
    assert g.check_bin_interval(30.0) == 30 and type(g.check_bin_interval(30.0)) is int


def test_default_half_extent_is_the_bounding_radius_everywhere():
    from lightning_vtr import renderer
    from lightning_vtr.selection import differentiable_projection

    # the circumsphere of [-0.5, 0.5]^3: a corner is sqrt(3) / 2 from the centre
    assert pytest.approx(float(torch.tensor([0.5, 0.5, 0.5]).norm())) == g.DEFAULT_HALF_EXTENT
    assert renderer.DEFAULT_HALF_EXTENT is g.DEFAULT_HALF_EXTENT
    assert differentiable_projection.DEFAULT_HALF_EXTENT is g.DEFAULT_HALF_EXTENT


def test_uniform_sampling_angle_vs_area():
    n = 40_000
    gen = torch.Generator().manual_seed(1)
    angle = g.sample_uniform_viewpoints(n, mode="angle", generator=gen)
    area = g.sample_uniform_viewpoints(n, mode="area", generator=gen)
    # P(|pitch| > 60): angle-uniform 60/180 = 1/3; area-uniform 1 - sin 60 = 0.134.
    assert (angle[:, 1].abs() > 60).double().mean().item() == pytest.approx(1 / 3, abs=0.01)
    assert (area[:, 1].abs() > 60).double().mean().item() == pytest.approx(1 - math.sin(math.radians(60)), abs=0.01)
    for vp in (angle, area):
        assert vp[:, 0].min() >= -180 and vp[:, 0].max() < 180 and vp[:, 1].abs().max() <= 90
        assert vp[:, 0].mean().item() == pytest.approx(0.0, abs=3.0)
        assert vp[:, 0].std().item() == pytest.approx(360 / math.sqrt(12), rel=0.02)
    hemi = g.sample_uniform_viewpoints(n, pitch_range=(0.0, 90.0), generator=gen)
    # Area-uniform on the upper hemisphere: sin(pitch) uniform in [0, 1], so P(pitch > 30) = 1/2.
    assert hemi[:, 1].min() >= 0 and (hemi[:, 1] > 30).double().mean().item() == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="pitch_range"):
        g.sample_uniform_viewpoints(3, pitch_range=(-100.0, 0.0))
    with pytest.raises(ValueError, match="mode"):
        g.sample_uniform_viewpoints(3, mode="volume")
    with pytest.raises(ValueError, match=r"^`yaw_range` must satisfy .*low <= high.*, got \(30, 10\)$"):
        g.sample_uniform_viewpoints(3, yaw_range=(30, 10))
    with pytest.raises(ValueError, match="^`n` must be an int >= 0, got -1$"):
        g.sample_uniform_viewpoints(-1)
    with pytest.raises(TypeError, match="^`n` must be an int, got float 2.0$"):
        g.sample_uniform_viewpoints(2.0)


def test_gaussian_sampling_std_and_wrapping():
    n = 20_000
    centres = _t([[10.0, 0.0]]).expand(n, 2)
    out = g.sample_gaussian_viewpoints(centres, sigma=5.0, generator=torch.Generator().manual_seed(2))
    assert out[:, 0].std().item() == pytest.approx(5.0, rel=0.03) and out[:, 1].std().item() == pytest.approx(
        5.0, rel=0.03
    )
    assert out[:, 0].mean().item() == pytest.approx(10.0, abs=0.15)
    edge = g.sample_gaussian_viewpoints(
        _t([[175.0, 88.0]]).expand(n, 2), sigma=5.0, generator=torch.Generator().manual_seed(3)
    )
    assert edge[:, 0].min() >= -180 and edge[:, 0].max() < 180 and (edge[:, 0] < 0).any()  # wrapped past 180
    assert edge[:, 1].max() == 90.0 and (edge[:, 1] == 90.0).double().mean().item() == pytest.approx(0.345, abs=0.02)


def test_angular_distance():
    a = _t([[0.0, 0.0], [0.0, 0.0], [30.0, 90.0], [0.0, 45.0], [-179.0, 0.0]])
    b = _t([[90.0, 0.0], [180.0, 0.0], [-100.0, 90.0], [180.0, 45.0], [179.0, 0.0]])
    torch.testing.assert_close(g.angular_distance(a, b), _t([90.0, 180.0, 0.0, 90.0, 2.0]), atol=1e-6, rtol=0)


def test_voxel_centers_and_index_inverse():
    c = g.voxel_centers(4)
    assert c.shape == (4, 4, 4, 3)
    assert c[0, 0, 0].tolist() == [-0.375, -0.375, -0.375]
    assert c[3, 1, 2].tolist() == [0.375, -0.125, 0.125]  # (i, j, k) -> (x, y, z)
    assert torch.equal(
        g.world_to_voxel_index(c, 4), torch.stack(torch.meshgrid(*[torch.arange(4)] * 3, indexing="ij"), -1)
    )
    assert g.world_to_voxel_index(_t([[0.5, -0.5, 0.0]]), 4).tolist() == [[4, 0, 2]]


def test_rotate_directions_broadcasts():
    rot = g.camera_basis(_t([[90.0, 0.0], [0.0, 90.0]]))
    out = g.rotate_directions(_t([0.0, 1.0, 0.0]), rot)
    # In camera coordinates world +Y is straight back at (90, 0) and straight right at (0, 90).
    torch.testing.assert_close(out, _t([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), atol=1e-12, rtol=0)

"""Tests for the Zero-1-to-3 relative pose and the nearest-source choice."""

from __future__ import annotations

import math

import pytest
import torch

from lightning_vtr.geometry import camera_center
from lightning_vtr.synthesis.pose import (
    nearest_source_view,
    relative_pose,
    relative_spherical,
    spherical_coordinates,
)


def test_spherical_coordinates_match_camera_center():
    # independent reference: spherical coordinates of the geometry module's camera centre
    vp = torch.tensor([[0.0, 30.0], [90.0, 0.0], [-135.0, -45.0], [170.0, 10.0], [-30.0, 80.0]], dtype=torch.float64)
    c = camera_center(vp)
    polar_ref = torch.rad2deg(torch.atan2(torch.linalg.norm(c[:, :2], dim=1), c[:, 2]))
    azim_ref = torch.rad2deg(torch.atan2(c[:, 1], c[:, 0]))
    polar, azim = spherical_coordinates(vp)
    torch.testing.assert_close(polar, polar_ref)
    torch.testing.assert_close(azim, azim_ref)


def test_zero123_hand_computed():
    # source (yaw 0, pitch 30) -> polar 60; target (90, 0) -> polar 90: d_polar = +30 deg, d_azimuth = +90 deg
    t = relative_pose(torch.tensor([0.0, 30.0]), torch.tensor([90.0, 0.0]), "zero123")
    expected = torch.tensor([math.pi / 6, 1.0, 0.0, 0.0])
    torch.testing.assert_close(t, expected, atol=1e-6, rtol=0)


def test_zero123_radius_and_sign_of_polar():
    # moving the camera up (pitch 0 -> 45) lowers the polar angle: negative first entry
    t = relative_pose(
        torch.tensor([[10.0, 0.0]]), torch.tensor([[10.0, 45.0]]), "zero123", source_radius=1.5, target_radius=2.0
    )
    torch.testing.assert_close(t, torch.tensor([[-math.pi / 4, 0.0, 1.0, 0.5]]), atol=1e-6, rtol=0)


def test_stable_hand_computed():
    # same move; the 4th entry is the source polar angle 60 deg in radians
    t = relative_pose(torch.tensor([0.0, 30.0]), torch.tensor([90.0, 0.0]), "stable")
    torch.testing.assert_close(t, torch.tensor([math.pi / 6, 1.0, 0.0, math.pi / 3]), atol=1e-6, rtol=0)
    # a horizon source gives the constant deg2rad(90) common ports use
    t0 = relative_pose(torch.tensor([0.0, 0.0]), torch.tensor([-60.0, 20.0]), "stable")
    expected = [-math.radians(20), math.sin(math.radians(-60)), math.cos(math.radians(-60)), math.pi / 2]
    torch.testing.assert_close(t0, torch.tensor(expected), atol=1e-6, rtol=0)


def test_azimuth_wraps_across_the_seam():
    d_polar, d_azim = relative_spherical(torch.tensor([170.0, 0.0]), torch.tensor([-170.0, 0.0]))
    assert d_polar.item() == pytest.approx(0.0)
    assert d_azim.item() == pytest.approx(20.0)
    d_polar, d_azim = relative_spherical(torch.tensor([-170.0, 0.0]), torch.tensor([170.0, 0.0]))
    assert d_azim.item() == pytest.approx(-20.0)
    t = relative_pose(torch.tensor([170.0, 0.0]), torch.tensor([-170.0, 0.0]))
    torch.testing.assert_close(t[1:3], torch.tensor([math.sin(math.radians(20)), math.cos(math.radians(20))]))


def test_broadcast_and_shape():
    src = torch.tensor([0.0, 0.0])
    tgt = torch.tensor([[0.0, 0.0], [180.0, 0.0], [0.0, 90.0]])
    t = relative_pose(src, tgt)
    assert t.shape == (3, 4)
    torch.testing.assert_close(t[0], torch.tensor([0.0, 0.0, 1.0, 0.0]))
    torch.testing.assert_close(t[1], torch.tensor([0.0, 0.0, -1.0, 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(t[2], torch.tensor([-math.pi / 2, 0.0, 1.0, 0.0]), atol=1e-6, rtol=0)


def test_bad_embedding_and_shape():
    with pytest.raises(ValueError, match="embedding"):
        relative_pose(torch.zeros(2), torch.zeros(2), "xl")
    with pytest.raises(ValueError, match="source"):
        relative_pose(torch.zeros(3), torch.zeros(2))


def test_nearest_source_view():
    src = torch.tensor([[0.0, 0.0], [90.0, 0.0], [0.0, 90.0]])
    tgt = torch.tensor([[80.0, 5.0], [-10.0, 10.0], [45.0, 80.0], [179.0, 0.0], [100.0, -5.0]])

    # reference: brute-force great-circle angle via dot products of unit vectors
    def unit(v):
        y, p = math.radians(v[0]), math.radians(v[1])
        return (math.cos(p) * math.cos(y), math.cos(p) * math.sin(y), math.sin(p))

    expected = []
    for t in tgt.tolist():
        dots = [sum(a * b for a, b in zip(unit(t), unit(s))) for s in src.tolist()]
        expected.append(max(range(len(dots)), key=lambda i: dots[i]))
    idx = nearest_source_view(src, tgt)
    assert idx.tolist() == expected == [1, 0, 2, 1, 1]


def test_nearest_source_view_wraps_yaw():
    # -175 is 10 degrees from 175 across the seam, but 175 degrees from 0
    idx = nearest_source_view(torch.tensor([[0.0, 0.0], [175.0, 0.0]]), torch.tensor([[-175.0, 0.0]]))
    assert idx.tolist() == [1]


def test_nearest_source_view_rejects_empty_sources():
    with pytest.raises(ValueError, match="source_viewpoints"):
        nearest_source_view(torch.zeros(0, 2), torch.zeros(1, 2))

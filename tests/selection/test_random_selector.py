"""Tests of RandomSelector: ranges, angle vs area uniformity, determinism, validation."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.selection import RandomSelector


def _select(selector, batch, seed=0):
    vol = torch.zeros(batch, 4, 4, 4)
    return selector.select(vol, vol, ["c"] * batch, generator=torch.Generator().manual_seed(seed))


def test_angle_mode_is_uniform_in_pitch():
    views = _select(RandomSelector(num_views=3, mode="angle"), 2000)
    assert views.shape == (2000, 3, 2) and RandomSelector.uses_pool is False
    pitch = views[..., 1].flatten()
    assert bool((pitch >= -90).all() and (pitch <= 90).all())
    # U(-90, 90): std 90 / sqrt(3) = 51.96; a quarter of samples above 45 degrees
    assert abs(float(pitch.std()) - 51.96) < 1.5
    assert abs(float((pitch > 45).float().mean()) - 0.25) < 0.02
    yaw = views[..., 0].flatten()
    assert bool((yaw >= -180).all() and (yaw < 180).all()) and abs(float(yaw.mean())) < 4.0


def test_area_mode_is_uniform_on_the_sphere():
    pitch = _select(RandomSelector(mode="area"), 2000)[..., 1].flatten()
    # area above 45 degrees: (1 - sin 45) / 2 = 0.1464
    assert abs(float((pitch > 45).float().mean()) - 0.1464) < 0.02


def test_ranges_are_respected_and_draws_deterministic():
    selector = RandomSelector(num_views=2, yaw_range=(-10, 20), pitch_range=(0, 30))
    a, b = _select(selector, 100, seed=5), _select(selector, 100, seed=5)
    assert torch.equal(a, b)
    assert bool((a[..., 0] >= -10).all() and (a[..., 0] <= 20).all())
    assert bool((a[..., 1] >= 0).all() and (a[..., 1] <= 30).all())
    assert _select(selector, 0).shape == (0, 2, 2)


def test_validation():
    with pytest.raises(ValueError, match="`num_views`.*0"):
        RandomSelector(num_views=0)
    with pytest.raises(ValueError, match="`mode`.*'disk'"):
        RandomSelector(mode="disk")
    with pytest.raises(ValueError, match=r"`pitch_range`.*\(-100, 0\)"):
        RandomSelector(pitch_range=(-100, 0))
    with pytest.raises(ValueError, match=r"`yaw_range`.*\(30, 10\)"):
        RandomSelector(yaw_range=(30, 10))
    with pytest.raises(ValueError, match=r"predicted \(1, 4, 4, 4\) and target \(1, 5, 5, 5\)"):
        RandomSelector().select(torch.zeros(1, 4, 4, 4), torch.zeros(1, 5, 5, 5), ["c"])

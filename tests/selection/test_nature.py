"""Tests of NatureSelector: the natural viewing band, per-category pitch, jitter, validation."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.selection import NatureSelector


def _select(selector, categories, seed=0):
    vol = torch.zeros(len(categories), 4, 4, 4)
    return selector.select(vol, vol, categories, generator=torch.Generator().manual_seed(seed))


def test_default_band_is_the_horizon_with_uniform_yaw():
    views = _select(NatureSelector(), ["car"] * 500)
    assert views.shape == (500, 3, 2) and NatureSelector.uses_pool is False
    assert bool((views[..., 1] == 0).all())
    yaw = views[..., 0].flatten()
    assert abs(float(yaw.std()) - 360 / 12**0.5) < 4.0  # U(-180, 180): std 103.9


def test_per_category_pitch_and_jitter():
    selector = NatureSelector(num_views=2, pitch={"lamp": 30.0, "plane": 85.0}, pitch_jitter=10.0)
    views = _select(selector, ["lamp", "plane", "car"] * 300)
    lamp, plane, car = views[0::3, :, 1], views[1::3, :, 1], views[2::3, :, 1]
    assert float(lamp.min()) >= 20.0 and float(lamp.max()) <= 40.0 and abs(float(lamp.mean()) - 30.0) < 1.0
    assert float(plane.max()) == 90.0 and float(plane.min()) >= 75.0  # clamped at the pole
    assert float(car.min()) >= -10.0 and float(car.max()) <= 10.0  # categories not listed: pitch 0
    assert abs(float(car.std()) - 20 / 12**0.5) < 0.6  # uniform over [-10, 10]
    assert torch.equal(views, _select(selector, ["lamp", "plane", "car"] * 300))


def test_validation():
    with pytest.raises(ValueError, match="`pitch`.*95"):
        NatureSelector(pitch=95)
    with pytest.raises(ValueError, match=r"`pitch\['car'\]`.*-91"):
        NatureSelector(pitch={"car": -91})
    with pytest.raises(ValueError, match="`pitch_jitter`.*-1"):
        NatureSelector(pitch_jitter=-1)
    with pytest.raises(ValueError, match="`categories`.*1 for a batch of 2"):
        NatureSelector().select(torch.zeros(2, 4, 4, 4), torch.zeros(2, 4, 4, 4), ["a"])
    assert _select(NatureSelector(), []).shape == (0, 3, 2)

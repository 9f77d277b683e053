"""Tests of ViewpointPool: transfer preference, fallbacks, capacity, state and JSON round trips."""

from __future__ import annotations

import json

import pytest
import torch

from lightning_vtr.selection import ViewpointPool


def views(value: float, n: int = 3) -> torch.Tensor:
    return torch.tensor([[value, value / 4]] * n)


def test_sampling_prefers_sets_found_on_other_objects():
    pool = ViewpointPool(num_views=3)
    pool.add("chair", "a", views(10.0))
    pool.add("chair", "b", views(20.0))
    pool.add("table", "c", views(30.0))
    gen = torch.Generator().manual_seed(0)
    drawn = {float(pool.sample("chair", "a", gen)[0, 0]) for _ in range(30)}
    assert drawn == {20.0}  # never its own set while another object's exists
    drawn = {float(pool.sample("chair", None, gen)[0, 0]) for _ in range(60)}
    assert drawn == {10.0, 20.0}  # no object given: any set of the category
    # only its own set: falls back to it
    assert torch.equal(pool.sample("table", "c", gen), views(30.0))


def test_empty_category_falls_back_to_uniform():
    pool = ViewpointPool(num_views=2, fallback="area")
    pool.add("chair", "a", views(10.0, 2))
    a = pool.sample("lamp", "x", torch.Generator().manual_seed(1))
    b = pool.sample("lamp", "x", torch.Generator().manual_seed(1))
    assert a.shape == (2, 2) and torch.equal(a, b)
    assert not torch.equal(a, views(10.0, 2))
    draws = torch.stack([pool.sample("lamp", generator=torch.Generator().manual_seed(s)) for s in range(300)])
    s = torch.sin(torch.deg2rad(draws[..., 1]))
    assert abs(float(s.mean())) < 0.1  # sin(pitch) ~ U(-1, 1)


def test_capacity_drops_oldest_per_category():
    pool = ViewpointPool(capacity=2, num_views=3)
    for i in range(4):
        pool.add("chair", f"o{i}", views(float(i)))
    pool.add("table", "t", views(9.0))
    ids, sets = pool.view_sets("chair")
    assert ids == ["o2", "o3"] and sets[:, 0, 0].tolist() == [2.0, 3.0]
    assert len(pool) == 3 and pool.categories() == ["chair", "table"]


def test_add_normalises_and_validates():
    pool = ViewpointPool(num_views=2)
    pool.add("c", 7, torch.tensor([[190.0, 95.0], [-190.0, -10.0]]))
    ids, sets = pool.view_sets("c")
    assert ids == ["7"] and sets[0].tolist() == [[-170.0, 90.0], [170.0, -10.0]]
    with pytest.raises(ValueError, match=r"object 'x'.*\(2, 2\), got \(3, 2\)"):
        pool.add("c", "x", torch.zeros(3, 2))
    with pytest.raises(ValueError, match="`capacity`.*0"):
        ViewpointPool(capacity=0)
    with pytest.raises(ValueError, match="`num_views`.*0"):
        ViewpointPool(num_views=0)


def test_extend_and_sample_batch():
    pool = ViewpointPool(num_views=3)
    pool.extend(["a", "a", "b"], ["1", "2", "3"], torch.stack([views(1.0), views(2.0), views(3.0)]))
    out = pool.sample_batch(["a", "a", "b"], ["1", "2", "3"], torch.Generator().manual_seed(0))
    assert out.shape == (3, 3, 2) and out[:, 0, 0].tolist() == [2.0, 1.0, 3.0]
    assert pool.sample_batch([], []).shape == (0, 3, 2)
    with pytest.raises(ValueError, match="3 categories and 2 object ids"):
        pool.extend(["a", "a", "b"], ["1", "2"], torch.zeros(3, 3, 2))


def _filled_pool() -> ViewpointPool:
    pool = ViewpointPool(capacity=5, num_views=3)
    gen = torch.Generator().manual_seed(0)
    for i in range(12):
        cat = ["chair", "table", "lamp"][i % 3]
        pool.add(
            cat, f"obj{i}", torch.rand(3, 2, generator=gen) * torch.tensor([360.0, 180.0]) - torch.tensor([180.0, 90.0])
        )
    return pool


def _draws(pool: ViewpointPool) -> torch.Tensor:
    gen = torch.Generator().manual_seed(42)
    return torch.stack([pool.sample(c, f"obj{i}", gen) for i, c in enumerate(["chair", "table", "lamp", "sofa"] * 5)])


def test_state_dict_round_trip_restores_sampling():
    pool = _filled_pool()
    state = pool.state_dict()
    assert state["entries"]["chair"]["viewpoints"].shape == (4, 3, 2)
    restored = ViewpointPool(num_views=3)
    restored.load_state_dict(state)
    assert restored.capacity == 5 and len(restored) == len(pool) == 12
    assert restored.categories() == pool.categories()
    assert torch.equal(_draws(restored), _draws(pool))
    with pytest.raises(ValueError, match="3 views, this pool expects 2"):
        ViewpointPool(num_views=2).load_state_dict(state)


def test_json_round_trip(tmp_path):
    pool = _filled_pool()
    path = tmp_path / "pool.json"
    pool.to_json(path)
    data = json.loads(path.read_text())
    assert data["num_views"] == 3 and len(data["entries"]["table"]["viewpoints"]) == 4
    restored = ViewpointPool.from_json(path)
    for cat in pool.categories():
        assert restored.view_sets(cat)[0] == pool.view_sets(cat)[0]
        assert torch.equal(restored.view_sets(cat)[1], pool.view_sets(cat)[1])  # float32 exact through JSON
    assert torch.equal(_draws(restored), _draws(pool))
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="bad.json"):
        ViewpointPool.from_json(tmp_path / "bad.json")

"""Tests for the on-disk synthesis cache and the misses-only wrapper."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.synthesis.cache import CachedSynthesizer, SynthesisCache, viewpoint_key


def _image(seed: int, size: int = 8) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(size, size, 4), dtype=np.uint8)


class CountingSynthesizer(Synthesizer):
    """Deterministic fake: pixel values encode (object, yaw, pitch); records every target it is asked for."""

    image_size = 8

    def __init__(self, tag: str = "a") -> None:
        self.tag = tag
        self.calls: list[list[tuple[str, float, float]]] = []

    def config_key(self) -> str:
        return f"Counting({self.tag})"

    def synthesize(self, requests):
        call, out = [], []
        for req in requests:
            imgs = []
            for yaw, pitch in torch.as_tensor(req.target_viewpoints).tolist():
                call.append((req.object_id, yaw, pitch))
                img = np.zeros((8, 8, 4), dtype=np.uint8)
                img[..., 0] = int(yaw) % 256
                img[..., 1] = int(pitch) % 256
                img[..., 2] = len(req.object_id)
                img[..., 3] = 255
                imgs.append(img)
            out.append(np.stack(imgs) if imgs else np.zeros((0, 8, 8, 4), np.uint8))
        self.calls.append(call)
        return out


def _request(object_id: str, targets: list[tuple[float, float]]) -> SynthesisRequest:
    return SynthesisRequest(
        object_id=object_id,
        category="chair",
        source_images=np.zeros((1, 8, 8, 4), np.uint8),
        source_viewpoints=torch.zeros(1, 2),
        target_viewpoints=torch.tensor(targets, dtype=torch.float32),
    )


def test_put_get_roundtrip_and_rounding(tmp_path):
    cache = SynthesisCache(tmp_path)
    img = _image(0)
    assert cache.get("obj/1", (10.0, 20.0), "k") is None
    cache.put("obj/1", (10.0, 20.0), "k", img)
    np.testing.assert_array_equal(cache.get("obj/1", (10.0, 20.0), "k"), img)
    # within the 1e-3 degree rounding: same entry; beyond it: a miss
    np.testing.assert_array_equal(cache.get("obj/1", torch.tensor([10.0002, 19.9998]), "k"), img)
    assert cache.get("obj/1", (10.002, 20.0), "k") is None
    # yaw 180 is yaw -180
    cache.put("obj/1", (180.0, 0.0), "k", img)
    np.testing.assert_array_equal(cache.get("obj/1", (-180.0, 0.0), "k"), img)
    # the object id with a slash stays one directory level
    assert cache.path("obj/1", (0.0, 0.0), "k").parent.parent == cache.config_dir("k")


def test_different_config_different_key(tmp_path):
    cache = SynthesisCache(tmp_path)
    cache.put("o", (0.0, 0.0), "steps=50", _image(1))
    assert cache.get("o", (0.0, 0.0), "steps=2") is None
    assert cache.path("o", (0.0, 0.0), "steps=50") != cache.path("o", (0.0, 0.0), "steps=2")
    assert (cache.config_dir("steps=50") / "config_key.txt").read_text() == "steps=50"


def test_leftover_tmp_file_is_not_a_hit(tmp_path):
    cache = SynthesisCache(tmp_path)
    path = cache.path("o", (5.0, 5.0), "k")
    path.parent.mkdir(parents=True)
    # what a run killed mid-write leaves behind
    (path.parent / f".{path.name}.deadbeef.tmp").write_bytes(b"\x89PNG partial")
    assert cache.get("o", (5.0, 5.0), "k") is None
    # a truncated final file (e.g. written by something else) is a miss too, not a crash
    path.write_bytes(b"\x89PNG\r\n\x1a\n")
    assert cache.get("o", (5.0, 5.0), "k") is None
    cache.put("o", (5.0, 5.0), "k", _image(2))
    np.testing.assert_array_equal(cache.get("o", (5.0, 5.0), "k"), _image(2))
    # put() leaves no temporary files of its own
    assert sorted(p.name for p in path.parent.iterdir() if p.name.endswith(".tmp")) == [f".{path.name}.deadbeef.tmp"]


def test_put_rejects_bad_image(tmp_path):
    with pytest.raises(ValueError, match="image"):
        SynthesisCache(tmp_path).put("o", (0.0, 0.0), "k", np.zeros((8, 8, 3), np.uint8))


def test_a_failed_put_keeps_the_previous_entry_and_leaves_no_temporary(tmp_path, monkeypatch):
    cache = SynthesisCache(tmp_path)
    path = cache.put("o", (5.0, 5.0), "k", _image(3))

    def broken_save(self, fp, *args, **kwargs):
        fp.write(b"\x89PNG half")
        raise OSError("disk full")

    monkeypatch.setattr("PIL.Image.Image.save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        cache.put("o", (5.0, 5.0), "k", _image(4))
    np.testing.assert_array_equal(cache.get("o", (5.0, 5.0), "k"), _image(3))
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_key_arguments_are_checked(tmp_path):
    cache = SynthesisCache(tmp_path)
    with pytest.raises(TypeError, match="^`object_id` must be a str, got int 7$"):
        cache.path(7, (0.0, 0.0), "k")
    with pytest.raises(ValueError, match="^`object_id` must be a non-empty string, got ''$"):
        cache.path("", (0.0, 0.0), "k")
    with pytest.raises(ValueError, match="^`config_key` must be a non-empty string, got ''$"):
        cache.config_dir("")
    with pytest.raises(TypeError, match="^`synthesizer` must be a Synthesizer, got str 'render'$"):
        CachedSynthesizer("render", tmp_path)


def test_viewpoint_key_normalises_and_rounds_to_millidegrees():
    assert viewpoint_key((10.0, 20.0)) == "10000_20000"
    assert viewpoint_key((180.0, 0.0)) == viewpoint_key((-180.0, -0.0)) == "-180000_0"
    assert viewpoint_key(torch.tensor([370.0004, 95.0])) == "10000_90000"  # wrapped, clamped, rounded
    assert viewpoint_key(np.array([-0.0004, -12.3456])) == "0_-12346"
    with pytest.raises(ValueError, match=r"`viewpoint` must be one \(yaw, pitch\) pair in degrees, got shape \(2, 2\)"):
        viewpoint_key(torch.zeros(2, 2))


def test_cached_synthesizer_sends_only_misses(tmp_path):
    inner = CountingSynthesizer()
    synth = CachedSynthesizer(inner, tmp_path)
    first = synth.synthesize([_request("a", [(0.0, 0.0), (30.0, 10.0)]), _request("bb", [(60.0, -20.0)])])
    assert inner.calls == [[("a", 0.0, 0.0), ("a", 30.0, 10.0), ("bb", 60.0, -20.0)]]
    # a re-run with one new view asks only for that view, and returns cached ones unchanged
    second = synth.synthesize([_request("a", [(30.0, 10.0), (90.0, 0.0), (0.0, 0.0)]), _request("bb", [(60.0, -20.0)])])
    assert inner.calls[1] == [("a", 90.0, 0.0)]
    np.testing.assert_array_equal(second[0][0], first[0][1])
    np.testing.assert_array_equal(second[0][2], first[0][0])
    np.testing.assert_array_equal(second[1], first[1])
    assert second[0][1][0, 0, 0] == 90 and second[0][1][0, 0, 2] == 1
    # everything cached: the wrapped synthesizer is not called at all
    synth.synthesize([_request("a", [(90.0, 0.0)])])
    assert len(inner.calls) == 2


def test_cached_synthesizer_resumes_from_disk_and_respects_config(tmp_path):
    CachedSynthesizer(CountingSynthesizer("a"), tmp_path).synthesize([_request("o", [(1.0, 2.0)])])
    resumed = CountingSynthesizer("a")
    CachedSynthesizer(resumed, tmp_path).synthesize([_request("o", [(1.0, 2.0)])])
    assert resumed.calls == []
    other = CountingSynthesizer("b")
    CachedSynthesizer(other, tmp_path).synthesize([_request("o", [(1.0, 2.0)])])
    assert other.calls == [[("o", 1.0, 2.0)]]

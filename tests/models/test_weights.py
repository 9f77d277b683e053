"""Weight resolution: local files, file:// URLs through torch.hub's cache, "imagenet", offline errors."""

from __future__ import annotations

import hashlib
import shutil
from urllib.error import URLError

import pytest
import torch

from lightning_vtr.models.weights import (
    IMAGENET_WEIGHTS,
    WeightsDownloadError,
    fetch_weights,
    is_restoring_checkpoint,
    load_weights,
    restoring_checkpoint,
    weights_cache_dir,
)


def _state() -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    return {"conv.weight": torch.rand(4, 3, 3, 3, generator=gen), "bn.num_batches_tracked": torch.tensor(5)}


def _assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.fixture
def torch_home(tmp_path, monkeypatch):
    home = tmp_path / "torch_home"
    monkeypatch.setenv("TORCH_HOME", str(home))
    return home


def test_file_url_downloads_once_into_the_torch_home_cache(tmp_path, torch_home):
    source = tmp_path / "served" / "tiny_weights.pth"
    source.parent.mkdir()
    torch.save(_state(), source)
    assert weights_cache_dir() == torch_home / "hub" / "checkpoints"

    _assert_same(load_weights(source.as_uri(), progress=False), _state())
    cached = torch_home / "hub" / "checkpoints" / "tiny_weights.pth"
    assert cached.is_file()
    # The second call reads the cache: the served file is gone.
    source.unlink()
    assert fetch_weights(source.as_uri(), progress=False) == cached
    _assert_same(load_weights(source.as_uri(), progress=False), _state())


def test_failed_download_names_the_url_and_the_cache_path(torch_home, monkeypatch):
    calls = []

    def offline(url, dst, hash_prefix=None, progress=True):
        calls.append((url, hash_prefix))
        raise URLError("[Errno -3] Temporary failure in name resolution")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    url = "https://download.pytorch.org/models/resnet50-0676ba61.pth"
    cached = torch_home / "hub" / "checkpoints" / "resnet50-0676ba61.pth"
    with pytest.raises(WeightsDownloadError) as info:
        load_weights("imagenet", kind="resnet50", progress=False)
    message = str(info.value)
    assert url in message and str(cached) in message
    assert "Temporary failure in name resolution" in message and "TORCH_HOME" in message
    assert "copy it to" in message
    assert calls == [(url, "0676ba61")]  # the hash prefix of torchvision's file name is checked
    assert not cached.exists()
    assert isinstance(info.value, OSError)


def test_imagenet_resolves_per_kind_and_reads_the_deit_wrapper(torch_home, monkeypatch):
    requested = []

    def serve(url, dst, hash_prefix=None, progress=True):
        requested.append(url)
        torch.save({"model": _state(), "epoch": 300}, dst)

    monkeypatch.setattr(torch.hub, "download_url_to_file", serve)
    state = load_weights("imagenet", kind="deit_base_distilled", progress=False)
    _assert_same(state, _state())  # the release's {"model": ...} wrapper is removed
    assert requested == ["https://dl.fbaipublicfiles.com/deit/deit_base_distilled_patch16_224-df68dfff.pth"]
    assert (torch_home / "hub" / "checkpoints" / "deit_base_distilled_patch16_224-df68dfff.pth").is_file()
    assert IMAGENET_WEIGHTS["resnet50"] == "https://download.pytorch.org/models/resnet50-0676ba61.pth"


def test_hash_in_the_file_name_is_checked(tmp_path, torch_home):
    served = tmp_path / "weights.pth"
    torch.save(_state(), served)
    digest = hashlib.sha256(served.read_bytes()).hexdigest()
    good = tmp_path / f"weights-{digest[:8]}.pth"
    bad = tmp_path / "weights-deadbeef.pth"
    shutil.copy(served, good)
    shutil.copy(served, bad)
    _assert_same(load_weights(good.as_uri(), progress=False), _state())
    with pytest.raises(WeightsDownloadError, match=r"invalid hash value \(expected \"deadbeef\""):
        load_weights(bad.as_uri(), progress=False)
    _assert_same(load_weights(bad.as_uri(), check_hash=False, progress=False), _state())


def test_local_paths_and_wrappers(tmp_path):
    path = tmp_path / "w.pth"
    torch.save({"state_dict": _state()}, path)
    _assert_same(load_weights(path), _state())
    _assert_same(load_weights(str(path)), _state())
    _assert_same(load_weights(_state()), _state())


def test_bad_sources(tmp_path, torch_home):
    with pytest.raises(FileNotFoundError, match=r"resnet50 weights file not found: 'nope.pth'"):
        load_weights("nope.pth", kind="resnet50")
    with pytest.raises(TypeError, match=r"`source` must be a path, a URL, 'imagenet' or a state dict, got int 3"):
        load_weights(3)
    with pytest.raises(ValueError, match=r"`kind` must be one of 'resnet50', 'deit_base_distilled', got None"):
        load_weights("imagenet")
    with pytest.raises(ValueError, match=r"`kind` must be one of 'resnet50', 'deit_base_distilled', got 'vgg16'"):
        load_weights("imagenet", kind="vgg16")
    path = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], path)
    with pytest.raises(ValueError, match=r"list.pth must hold a state dict .*got list"):
        load_weights(path)


def test_restoring_checkpoint_is_scoped():
    assert not is_restoring_checkpoint()
    with pytest.raises(RuntimeError), restoring_checkpoint():  # noqa: PT012 (the flag inside the raising block)
        assert is_restoring_checkpoint()
        raise RuntimeError
    assert not is_restoring_checkpoint()

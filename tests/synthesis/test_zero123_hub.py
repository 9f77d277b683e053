"""Hub ids for Zero-1-to-3 checkpoints, without the network: a fake Hub cache and replaced download calls."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from helpers import one_thread

from lightning_vtr.synthesis import zero123_hub
from lightning_vtr.synthesis.zero123 import Zero123CheckpointError, Zero123Synthesizer
from lightning_vtr.synthesis.zero123_hub import (
    cached_snapshot,
    download_command,
    is_hub_id,
    resolve_checkpoint,
    select_hub_files,
)

FAST = dict(num_inference_steps=1, image_size=32)
COMMIT_1, COMMIT_2 = "1" * 40, "2" * 40

_one_thread = pytest.fixture(scope="module", autouse=True, name="_one_thread")(one_thread)


def _files(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


class FakeHub:
    """Stands in for the two network calls: a repository listing and ``snapshot_download``.

    ``repos`` maps a repo id to a local folder playing the remote repository. ``snapshot_download`` copies
    the allowed files into the Hub cache layout (symlinked blobs) and returns the snapshot, as the real one does.
    """

    def __init__(self, add_to_hub_cache, repos: dict[str, Path], commit: str = COMMIT_1) -> None:
        self.add_to_hub_cache, self.repos, self.commit = add_to_hub_cache, repos, commit
        self.listed: list[tuple] = []
        self.downloads: list[dict] = []

    def list_repo_files(self, repo_id, revision, token):
        self.listed.append((repo_id, revision, token))
        if repo_id not in self.repos:
            raise _repository_not_found(f"404 Client Error: Repository Not Found for url: .../{repo_id}")
        return _files(self.repos[repo_id])

    def snapshot_download(self, repo_id, revision, cache_dir, token, allow_patterns):
        self.downloads.append(
            dict(repo_id=repo_id, revision=revision, cache_dir=cache_dir, token=token, allow_patterns=allow_patterns)
        )
        staging = Path(cache_dir) / ".staging" / repo_id.replace("/", "--")
        for rel in allow_patterns:
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(self.repos[repo_id] / rel, staging / rel)
        return str(self.add_to_hub_cache(Path(cache_dir), repo_id, staging, self.commit))


def _repository_not_found(message: str) -> Exception:
    """huggingface_hub's error for an unknown repository, built without an HTTP response (its constructor wants one)."""
    from huggingface_hub.utils import RepositoryNotFoundError

    err = RepositoryNotFoundError.__new__(RepositoryNotFoundError)
    Exception.__init__(err, message)
    return err


@pytest.fixture
def online(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)


@pytest.fixture
def no_network(monkeypatch):
    """Fails the test if anything tries the network."""

    def refuse(*args, **kwargs):
        raise AssertionError("the network was used")

    monkeypatch.setattr(zero123_hub, "_list_repo_files", refuse)
    monkeypatch.setattr(zero123_hub, "_snapshot_download", refuse)


# ---------------------------------------------------------------- names and commands


def test_is_hub_id():
    for value in ("kxic/zero123-xl", "bennyguo/zero123-xl-diffusers", "ashawkey/stable-zero123-diffusers", "a/b.c"):
        assert is_hub_id(value), value
    for value in ("zero123-xl", "/weights/zero123", "./x/y", "a/b/c", "../x", "a/zero123.ckpt", "a/..", ""):
        assert not is_hub_id(value), value


def test_download_command():
    cmd = download_command("kxic/zero123-xl")
    assert cmd.startswith("hf download kxic/zero123-xl --include model_index.json 'unet/*' 'vae/*' 'image_encoder/*'")
    assert "'cc_projection/*' 'clip_camera_projection/*' 'scheduler/*' 'feature_extractor/*'" in cmd
    cmd = download_command("kxic/zero123-xl", revision="v2", cache_dir="/data/hf cache")
    assert "hf download kxic/zero123-xl --revision v2 --cache-dir '/data/hf cache' --include" in cmd


# ---------------------------------------------------------------- a fake Hub cache, offline


@pytest.mark.parametrize(
    ("repo_id", "layout", "pose"),
    [
        ("ashawkey/stable-zero123-diffusers", "layout_b", "stable"),
        ("bennyguo/zero123-xl-diffusers", "layout_b", "zero123"),
        ("kxic/zero123-xl", "layout_a", "zero123"),
        ("kxic/stable-zero123", "layout_a", "stable"),
    ],
)
def test_hub_id_from_the_cache(tiny_zero123, zero123_files, tmp_path, no_network, repo_id, layout, pose):
    # HF_HUB_OFFLINE=1 (tests/synthesis/conftest.py): the cache alone must do, without trying the network
    snapshot = zero123_files.add_to_hub_cache(tmp_path, repo_id, getattr(tiny_zero123, layout), COMMIT_1)
    assert (snapshot / "unet" / "config.json").is_symlink()
    synth = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=tmp_path, **FAST)
    assert synth.pose_embedding == pose
    assert synth.weights_id.startswith(f"{repo_id}@{COMMIT_1}#")
    ref = tiny_zero123.components["projection"]
    torch.testing.assert_close(synth.projection.weight, ref.weight, rtol=0, atol=0)
    # the same files in a local folder: same weights fingerprint, different identity
    local = Zero123Synthesizer.from_pretrained(getattr(tiny_zero123, layout), **FAST)
    assert local.weights_id.split("#")[1] == synth.weights_id.split("#")[1]


def test_revision_picks_the_snapshot(tiny_zero123, zero123_files, tmp_path, no_network):
    repo_id = "bennyguo/zero123-diffusers"
    zero123_files.add_to_hub_cache(tmp_path, repo_id, tiny_zero123.layout_b, COMMIT_1, refs=("main",))
    zero123_files.add_to_hub_cache(tmp_path, repo_id, tiny_zero123.layout_a, COMMIT_2, refs=("v2",))
    main = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=tmp_path, **FAST)
    tagged = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=tmp_path, revision="v2", **FAST)
    pinned = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=tmp_path, revision=COMMIT_1, **FAST)
    assert main.weights_id.startswith(f"{repo_id}@{COMMIT_1}#")
    assert tagged.weights_id.startswith(f"{repo_id}@{COMMIT_2}#")
    assert pinned.weights_id == main.weights_id
    # v2 holds layout (a): its feature extractor was read, and the keys differ
    assert main.config_key() != tagged.config_key()
    assert cached_snapshot(repo_id, "v3", tmp_path) is None


def test_offline_and_not_cached_names_the_id_and_the_command(tmp_path, no_network):
    with pytest.raises(FileNotFoundError) as err:
        Zero123Synthesizer.from_pretrained("kxic/zero123-xl", cache_dir=tmp_path)
    msg = str(err.value)
    assert "`path` 'kxic/zero123-xl' is neither a local directory nor a Zero-1-to-3 checkpoint" in msg
    assert f"Hugging Face Hub cache ({tmp_path}, revision 'main')" in msg
    assert "not cached, and HF_HUB_OFFLINE is set" in msg
    assert f"hf download kxic/zero123-xl --cache-dir {tmp_path} --include model_index.json 'unet/*'" in msg


def test_local_files_only_never_reaches_the_network(tmp_path, online, no_network):
    with pytest.raises(FileNotFoundError, match=r"not cached, and local_files_only=True"):
        Zero123Synthesizer.from_pretrained("kxic/zero123-xl", cache_dir=tmp_path, local_files_only=True)


def test_not_a_path_nor_an_id(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"checkpoint directory or a Hub id 'owner/name', got '.*/missing'"):
        Zero123Synthesizer.from_pretrained(tmp_path / "missing")


# ---------------------------------------------------------------- online, with the download calls replaced


def _remote_repo(tiny_zero123, zero123_files, tmp_path: Path) -> Path:
    """What bennyguo/zero123-xl-diffusers-like repositories hold: more than the synthesizer reads."""
    remote = tmp_path / "remote"
    shutil.copytree(tiny_zero123.layout_b, remote)
    half = zero123_files.save_layout(
        zero123_files.half_copy(tiny_zero123.components), tmp_path / "half", "clip_camera_projection", variant="fp16"
    )
    for file in (half / "unet").glob("*.fp16.*"):
        shutil.copy(file, remote / "unet" / file.name)
    (remote / "zero123-xl.ckpt").write_bytes(b"15 GB of original weights")
    (remote / "safety_checker").mkdir()
    (remote / "safety_checker" / "config.json").write_text("{}")
    (remote / "README.md").write_text("# zero123-xl")
    return remote


def test_online_downloads_only_what_is_read(tiny_zero123, zero123_files, tmp_path, online, monkeypatch):
    repo_id = "bennyguo/zero123-xl-diffusers"
    hub = FakeHub(zero123_files.add_to_hub_cache, {repo_id: _remote_repo(tiny_zero123, zero123_files, tmp_path)})
    monkeypatch.setattr(zero123_hub, "_list_repo_files", hub.list_repo_files)
    monkeypatch.setattr(zero123_hub, "_snapshot_download", hub.snapshot_download)
    cache = tmp_path / "cache"
    synth = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=cache, revision="main", token="hf_x", **FAST)
    assert hub.listed == [(repo_id, "main", "hf_x")]
    (download,) = hub.downloads
    assert (download["repo_id"], download["revision"], download["cache_dir"], download["token"]) == (
        repo_id,
        "main",
        cache,
        "hf_x",
    )
    assert sorted(download["allow_patterns"]) == [
        "clip_camera_projection/config.json",
        "clip_camera_projection/diffusion_pytorch_model.safetensors",
        "image_encoder/config.json",
        "image_encoder/model.safetensors",
        "model_index.json",
        "scheduler/scheduler_config.json",
        "unet/config.json",
        "unet/diffusion_pytorch_model.safetensors",
        "vae/config.json",
        "vae/diffusion_pytorch_model.safetensors",
    ]
    assert synth.pose_embedding == "zero123"
    assert synth.weights_id.startswith(f"{repo_id}@{COMMIT_1}#")
    # the fp16 variant, asked for: the UNet's fp16 file instead, plain files where there is no fp16 one
    hub.commit = COMMIT_2
    half = Zero123Synthesizer.from_pretrained(repo_id, cache_dir=cache, variant="fp16", **FAST)
    patterns = hub.downloads[-1]["allow_patterns"]
    assert "unet/diffusion_pytorch_model.fp16.safetensors" in patterns
    assert "unet/diffusion_pytorch_model.safetensors" not in patterns
    assert "vae/diffusion_pytorch_model.safetensors" in patterns
    assert not torch.equal(half.unet.conv_in.weight, synth.unet.conv_in.weight)


def test_online_sharded_repository_brings_every_shard(tiny_zero123, zero123_files, tmp_path):
    remote = zero123_files.save_layout(
        tiny_zero123.components, tmp_path / "remote", "clip_camera_projection", max_shard_size="100KB"
    )
    selected = select_hub_files(_files(remote), None, "'o/n'")
    unet_files = [f for f in _files(remote) if f.startswith("unet/")]
    assert sorted(f for f in selected if f.startswith("unet/")) == unet_files  # config, index, all shards
    assert "unet/diffusion_pytorch_model.safetensors.index.json" in selected


def test_online_unknown_repository(tmp_path, online, monkeypatch, zero123_files):
    hub = FakeHub(zero123_files.add_to_hub_cache, {})
    monkeypatch.setattr(zero123_hub, "_list_repo_files", hub.list_repo_files)
    with pytest.raises(
        FileNotFoundError, match=r"`path` 'kxic/zero124' is neither a local directory nor a Hub repository"
    ):
        Zero123Synthesizer.from_pretrained("kxic/zero124", cache_dir=tmp_path)


def test_online_repository_without_a_diffusers_checkpoint(tmp_path, online, monkeypatch, zero123_files):
    remote = tmp_path / "stable-zero123"
    remote.mkdir()
    (remote / "stable_zero123.ckpt").write_bytes(b"ckpt")
    (remote / "README.md").write_text("")
    hub = FakeHub(zero123_files.add_to_hub_cache, {"stabilityai/stable-zero123": remote})
    monkeypatch.setattr(zero123_hub, "_list_repo_files", hub.list_repo_files)
    monkeypatch.setattr(zero123_hub, "_snapshot_download", hub.snapshot_download)
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer.from_pretrained("stabilityai/stable-zero123", cache_dir=tmp_path)
    msg = str(err.value)
    assert "'stabilityai/stable-zero123' (revision 'main') is not a diffusers-format Zero-1-to-3 checkpoint" in msg
    assert "top level has ['README.md', 'stable_zero123.ckpt']" in msg
    assert "unet/: expected config.json; folder missing" in msg
    assert "It holds original latent-diffusion checkpoints ['stable_zero123.ckpt']: download one, convert it" in msg
    assert hub.downloads == []  # nothing fetched


def test_hub_unreachable_falls_back_to_the_cache(tiny_zero123, zero123_files, tmp_path, online, monkeypatch):
    def unreachable(*args, **kwargs):
        raise ConnectionError("Name or service not known")

    monkeypatch.setattr(zero123_hub, "_list_repo_files", unreachable)
    with pytest.raises(FileNotFoundError, match=r"the Hub could not be reached \(ConnectionError: Name or service"):
        Zero123Synthesizer.from_pretrained("kxic/zero123-xl", cache_dir=tmp_path)
    zero123_files.add_to_hub_cache(tmp_path, "kxic/zero123-xl", tiny_zero123.layout_a, COMMIT_1)
    synth = Zero123Synthesizer.from_pretrained("kxic/zero123-xl", cache_dir=tmp_path, **FAST)
    assert synth.weights_id.startswith(f"kxic/zero123-xl@{COMMIT_1}#")


def test_hf_hub_offline_is_read_at_call_time(tiny_zero123, zero123_files, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(zero123_hub, "_list_repo_files", lambda *a: calls.append(a) or [])
    monkeypatch.setattr(zero123_hub, "_snapshot_download", lambda *a: calls.append(a))
    zero123_files.add_to_hub_cache(tmp_path, "kxic/zero123-xl", tiny_zero123.layout_a, COMMIT_1)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    source = resolve_checkpoint("kxic/zero123-xl", cache_dir=tmp_path)
    assert calls == [] and source.folder.name == COMMIT_1
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    with pytest.raises(Zero123CheckpointError, match="not a diffusers-format"):  # the (empty) listing was asked for
        resolve_checkpoint("kxic/zero123-xl", cache_dir=tmp_path)
    assert calls == [("kxic/zero123-xl", None, None)]


def test_a_local_folder_shadows_an_id(tiny_zero123, tmp_path, monkeypatch, no_network):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "kxic").mkdir()
    shutil.copytree(tiny_zero123.layout_a, tmp_path / "kxic" / "zero123-xl")
    source = resolve_checkpoint("kxic/zero123-xl")
    assert source.folder == Path("kxic/zero123-xl") and source.name == "zero123-xl"


def test_incomplete_cached_snapshot_says_how_to_complete_it(tiny_zero123, zero123_files, tmp_path, no_network):
    partial = tmp_path / "partial"
    shutil.copytree(tiny_zero123.layout_b, partial)
    shutil.rmtree(partial / "unet")
    zero123_files.add_to_hub_cache(tmp_path / "cache", "bennyguo/zero123-diffusers", partial, COMMIT_1)
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer.from_pretrained("bennyguo/zero123-diffusers", cache_dir=tmp_path / "cache")
    msg = str(err.value)
    assert "unet/: expected config.json + weights named diffusion_pytorch_model" in msg
    assert "folder missing [UNet2DConditionModel]" in msg
    assert "Fetch what is missing with\n    hf download bennyguo/zero123-diffusers --cache-dir" in msg

"""Fixtures for the Zero-1-to-3 tests: a tiny random model saved in both checkpoint layouts found in the wild."""

from __future__ import annotations

import copy
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

# no test may touch the network; must be set before huggingface_hub is imported
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import sys

import pytest
import torch
from torch import nn

#: sizes of a 64x64 model (UNet sample size 8, VAE factor 8)
TINY_CLIP_DIM = 32
TINY_CROSS_DIM = 32


def build_tiny_components(seed: int = 0) -> dict:
    """A randomly initialised UNet / VAE / CLIP vision encoder / 36->32 projection / DDIM scheduler: the tiny
    architecture ``benchmarks/gpu_check.py`` also runs on a GPU (one definition, loaded from that script)."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"
    spec = importlib.util.spec_from_file_location("_gpu_check_tiny_zero123", script)
    assert spec is not None and spec.loader is not None
    module = sys.modules.get(spec.name)
    if module is None:  # registered before it runs: its dataclasses look their module up there
        module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module.tiny_zero123_components(seed)


def half_copy(components: dict) -> dict:
    """A float16 copy of the model components (what ``*.fp16.*`` variant files hold); the originals are untouched."""
    out = {name: copy.deepcopy(module) for name, module in components.items()}
    for name in ("unet", "vae", "image_encoder", "projection"):
        out[name] = out[name].half()
    return out


def _save_projection(proj: nn.Linear, folder: Path, layer: str, ext: str, variant: str | None, sharded: bool) -> None:
    from safetensors.torch import save_file

    tensors = {
        f"{layer}.weight": proj.weight.detach().clone().contiguous(),
        f"{layer}.bias": proj.bias.detach().clone(),
    }
    infix = f".{variant}" if variant else ""

    def write(state: dict, name: str) -> None:
        if ext == "safetensors":
            save_file(state, str(folder / name))
        else:
            torch.save(state, folder / name)

    if not sharded:
        write(tensors, f"diffusion_pytorch_model{infix}.{ext}")
        return
    # one tensor per shard, named as diffusers names them
    names = [f"diffusion_pytorch_model{infix}-0000{i + 1}-of-00002.{ext}" for i in range(2)]
    weight_map = {}
    for (key, value), name in zip(tensors.items(), names):
        write({key: value}, name)
        weight_map[key] = name
    index = {"metadata": {"total_size": 0}, "weight_map": weight_map}
    (folder / f"diffusion_pytorch_model.{ext}.index{infix}.json").write_text(json.dumps(index))


def save_layout(
    components: dict,
    root: Path,
    layout: str,
    *,
    variant: str | None = None,
    max_shard_size: str | None = None,
) -> Path:
    """Write ``components`` as a diffusers-format checkpoint: ``layout`` is ``"cc_projection"`` or ``"clip_camera_projection"``.

    ``variant`` names every weight file ``*.{variant}.*`` (as fp16-only Hub repositories do); ``max_shard_size``
    shards the models' weights (and splits the projection into two shards) with ``*.index.json`` files.
    """
    root.mkdir(parents=True, exist_ok=True)
    save_kwargs: dict = {"variant": variant}
    if max_shard_size is not None:
        save_kwargs["max_shard_size"] = max_shard_size
    components["unet"].save_pretrained(root / "unet", **save_kwargs)
    components["vae"].save_pretrained(root / "vae", **save_kwargs)
    components["image_encoder"].save_pretrained(root / "image_encoder", **save_kwargs)
    components["scheduler"].save_pretrained(root / "scheduler")
    proj: nn.Linear = components["projection"]
    folder = root / layout
    folder.mkdir()
    sharded = max_shard_size is not None
    if layout == "cc_projection":
        # layout (a): a config without sizes, linear "projection", a .bin state dict
        (folder / "config.json").write_text(
            json.dumps({"_class_name": "CCProjection", "_diffusers_version": "0.15.0.dev0"})
        )
        _save_projection(proj, folder, "projection", "bin", variant, sharded)
        # a feature extractor with CLIP's normalisation and crop size
        fe = root / "feature_extractor"
        fe.mkdir()
        (fe / "preprocessor_config.json").write_text(
            json.dumps(
                {
                    "crop_size": {"height": 224, "width": 224},
                    "do_center_crop": True,
                    "do_normalize": True,
                    "do_resize": True,
                    "image_mean": [0.48145466, 0.4578275, 0.40821073],
                    "image_processor_type": "CLIPImageProcessor",
                    "image_std": [0.26862954, 0.26130258, 0.27577711],
                    "resample": 3,
                    "size": {"shortest_edge": 224},
                }
            )
        )
        index_name = "cc_projection"
    else:
        # layout (b): sizes in the config, linear "proj", safetensors
        (folder / "config.json").write_text(
            json.dumps(
                {
                    "_class_name": "CLIPCameraProjection",
                    "embedding_dim": proj.out_features,
                    "additional_embeddings": proj.in_features - proj.out_features,
                }
            )
        )
        _save_projection(proj, folder, "proj", "safetensors", variant, sharded)
        index_name = "clip_camera_projection"
    (root / "model_index.json").write_text(
        json.dumps(
            {
                "_class_name": "Zero1to3StableDiffusionPipeline",
                "unet": ["diffusers", "UNet2DConditionModel"],
                "vae": ["diffusers", "AutoencoderKL"],
                "image_encoder": ["transformers", "CLIPVisionModelWithProjection"],
                "scheduler": ["diffusers", "DDIMScheduler"],
                index_name: [None, None],
            }
        )
    )
    return root


def add_to_hub_cache(
    cache_dir: Path, repo_id: str, folder: Path, commit: str, refs: tuple[str, ...] = ("main",)
) -> Path:
    """Put ``folder`` into a Hugging Face Hub cache as ``huggingface_hub`` lays it out, without the network.

    Files go to ``models--owner--name/blobs/<sha256>``; ``snapshots/<commit>/<path>`` are relative symlinks
    to them; ``refs/<ref>`` hold the commit. Returns the snapshot folder.
    """
    repo = cache_dir / f"models--{repo_id.replace('/', '--')}"
    snapshot = repo / "snapshots" / commit
    (repo / "blobs").mkdir(parents=True, exist_ok=True)
    for file in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = file.read_bytes()
        blob = repo / "blobs" / hashlib.sha256(data).hexdigest()
        if not blob.exists():
            blob.write_bytes(data)
        link = snapshot / file.relative_to(folder)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    for ref in refs:
        (repo / "refs" / ref).parent.mkdir(parents=True, exist_ok=True)
        (repo / "refs" / ref).write_text(commit)
    return snapshot


@dataclass
class TinyZero123:
    components: dict
    layout_a: Path
    layout_b: Path
    #: layout (b) in a folder whose name says "stable" (Stable Zero123's pose)
    stable: Path


@pytest.fixture(scope="session")
def tiny_zero123(tmp_path_factory) -> TinyZero123:
    """One tiny random model, saved once per session in layout (a), layout (b) and as a "stable" folder."""
    components = build_tiny_components()
    root = tmp_path_factory.mktemp("zero123")
    return TinyZero123(
        components=components,
        layout_a=save_layout(components, root / "layout_a", "cc_projection"),
        layout_b=save_layout(components, root / "layout_b", "clip_camera_projection"),
        stable=save_layout(components, root / "stable-zero123-diffusers", "clip_camera_projection"),
    )


@pytest.fixture
def zero123_files() -> SimpleNamespace:
    """The checkpoint writers above, for tests that need a checkpoint of their own (``conftest`` is not importable
    by name from here: pytest's root ``conftest.py`` shadows it)."""
    return SimpleNamespace(save_layout=save_layout, half_copy=half_copy, add_to_hub_cache=add_to_hub_cache)

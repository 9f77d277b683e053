"""Loading Zero-1-to-3 checkpoints as people have them: pose by name, fp16-only and sharded folders, the
noise schedule check, original ``.ckpt`` files."""

from __future__ import annotations

import json
import logging
import shutil
import warnings

import numpy as np
import pytest
import torch
from helpers import one_thread

from lightning_vtr.synthesis.cache import SynthesisCache
from lightning_vtr.synthesis.zero123 import Zero123CheckpointError, Zero123Synthesizer
from lightning_vtr.synthesis.zero123_checkpoint import (
    REFERENCE_DDIM,
    WeightFiles,
    checkpoint_name,
    noise_schedule_mismatches,
    pose_embedding_for,
    says_stable,
    select_weight_files,
)

FAST = dict(num_inference_steps=1, image_size=32)

_one_thread = pytest.fixture(scope="module", autouse=True, name="_one_thread")(one_thread)


class _Records(logging.Handler):
    """Collects the messages of ``rank_zero_info`` (lightning's rank-zero logger), whatever its propagation."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture
def pose_log():
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    handler, level = _Records(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield handler.messages
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _assert_same_weights(module: torch.nn.Module, reference: torch.nn.Module, half: bool = False) -> None:
    ref = reference.state_dict()
    for name, value in module.state_dict().items():
        expected = ref[name].half().float() if half and ref[name].is_floating_point() else ref[name]
        torch.testing.assert_close(value.float(), expected.float(), rtol=0, atol=0, msg=name)


# ---------------------------------------------------------------- pose by name


@pytest.mark.parametrize(
    ("name", "stable"),
    [
        ("stable-zero123-diffusers", True),
        ("ashawkey/stable-zero123-diffusers", True),
        ("kxic/stable-zero123", True),
        ("StableZero123", True),
        ("my_stable_zero123", True),
        ("zero123-xl-diffusers", False),
        ("bennyguo/zero123-diffusers", False),
        ("kxic/zero123-xl", False),
        ("kxic/zero123-105000", False),
        ("kxic/zero123-165000", False),
        ("bennyguo/zero123-xl-diffusers", False),
        ("ashawkey/zero123-xl-diffusers", False),
        ("unstable-build", False),
    ],
)
def test_pose_from_name(name, stable):
    assert says_stable(name.rsplit("/", 1)[-1]) is stable
    pose, reason = pose_embedding_for("auto", name)
    assert pose == ("stable" if stable else "zero123")
    assert name.rsplit("/", 1)[-1] in reason
    # asking wins over the name
    assert pose_embedding_for("zero123", name) == ("zero123", "asked for")
    assert pose_embedding_for("stable", name) == ("stable", "asked for")


def test_only_the_repository_name_counts_not_the_owner():
    assert pose_embedding_for("auto", "stabilityai-mirror/zero123-xl")[0] == "zero123"


def test_checkpoint_name_of_a_hub_cache_snapshot(tmp_path):
    snapshot = tmp_path / "models--ashawkey--stable-zero123-diffusers" / "snapshots" / ("a" * 40)
    snapshot.mkdir(parents=True)
    assert checkpoint_name(snapshot) == "ashawkey/stable-zero123-diffusers"
    assert checkpoint_name(tmp_path / "zero123-xl") == "zero123-xl"


@pytest.mark.parametrize("layout", ["layout_a", "layout_b"])
def test_both_layouts_default_to_zero123_and_log_it(tiny_zero123, layout, pose_log):
    synth = Zero123Synthesizer.from_pretrained(getattr(tiny_zero123, layout), **FAST)
    assert synth.pose_embedding == "zero123"
    (message,) = [m for m in pose_log if "pose embedding" in m]
    assert f"{layout}: pose embedding 'zero123' (4th entry: radius difference)" in message
    assert "does not say 'stable'" in message


@pytest.mark.parametrize("layout", ["cc_projection", "clip_camera_projection"])
def test_stable_in_the_folder_name_gives_stables_pose(tiny_zero123, tmp_path, layout, pose_log, zero123_files):
    # kxic/stable-zero123 uses layout (a), ashawkey/stable-zero123-diffusers layout (b)
    path = zero123_files.save_layout(tiny_zero123.components, tmp_path / "stable_zero123", layout)
    synth = Zero123Synthesizer.from_pretrained(path, **FAST)
    assert synth.pose_embedding == "stable"
    assert any("stable_zero123: pose embedding 'stable' (4th entry: source polar angle)" in m for m in pose_log)
    # asked for, the name does not matter
    pose_log.clear()
    assert Zero123Synthesizer.from_pretrained(path, pose_embedding="zero123", **FAST).pose_embedding == "zero123"
    assert any("pose embedding 'zero123'" in m and "asked for" in m for m in pose_log)


def test_the_cache_key_keeps_the_pose(tiny_zero123, tmp_path):
    # one folder, two poses: an image cached under one must not be served for the other
    plain = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_b, **FAST)
    stable = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_b, pose_embedding="stable", **FAST)
    assert plain.weights_id == stable.weights_id
    assert "pose=zero123" in plain.config_key() and "pose=stable" in stable.config_key()
    cache = SynthesisCache(tmp_path / "cache")
    image = np.full((32, 32, 4), 200, dtype=np.uint8)
    cache.put("chair_0001", (30.0, 0.0), plain.config_key(), image)
    np.testing.assert_array_equal(cache.get("chair_0001", (30.0, 0.0), plain.config_key()), image)
    assert cache.get("chair_0001", (30.0, 0.0), stable.config_key()) is None


def test_bad_pose_embedding_names_the_argument(tiny_zero123):
    with pytest.raises(ValueError, match="`pose_embedding` must be one of 'auto', 'zero123', 'stable', got 'xl'"):
        Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, pose_embedding="xl")
    with pytest.raises(TypeError, match="`variant` must be a str, got int 16"):
        Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, variant=16)


# ---------------------------------------------------------------- variants and shards


@pytest.mark.parametrize("layout", ["cc_projection", "clip_camera_projection"])
def test_fp16_only_folder_is_detected(tiny_zero123, tmp_path, layout, pose_log, zero123_files):
    c = tiny_zero123.components
    path = zero123_files.save_layout(zero123_files.half_copy(c), tmp_path / "zero123-fp16", layout, variant="fp16")
    ext = "bin" if layout == "cc_projection" else "safetensors"
    assert sorted(p.name for p in (path / layout).iterdir()) == ["config.json", f"diffusion_pytorch_model.fp16.{ext}"]
    assert (path / "unet" / "diffusion_pytorch_model.fp16.safetensors").is_file()
    assert (path / "image_encoder" / "model.fp16.safetensors").is_file()
    synth = Zero123Synthesizer.from_pretrained(path, **FAST)
    # float16 values, run in float32 on the CPU
    assert synth.dtype == torch.float32
    out = synth([np.zeros((16, 16, 4), np.uint8)], torch.zeros(1, 2), torch.tensor([[30.0, 0.0]]), output_type="pt")
    assert out.shape == (1, 3, 64, 64) and bool(torch.isfinite(out).all())
    assert next(synth.unet.parameters()).dtype == torch.float32
    for name in ("unet", "vae", "image_encoder", "projection"):
        _assert_same_weights(getattr(synth, name), c[name], half=True)
    assert any(
        f"weight variants {{'unet': 'fp16', 'vae': 'fp16', 'image_encoder': 'fp16', '{layout}': 'fp16'}}" in m
        for m in pose_log
    )
    # asking for the variant that is there gives the same model
    assert Zero123Synthesizer.from_pretrained(path, variant="fp16", **FAST).weights_id == synth.weights_id


def test_variant_choice_in_a_folder_holding_both(tiny_zero123, tmp_path, zero123_files):
    c = tiny_zero123.components
    path = zero123_files.save_layout(c, tmp_path / "both", "clip_camera_projection")
    zero123_files.save_layout(zero123_files.half_copy(c), tmp_path / "fp16", "clip_camera_projection", variant="fp16")
    for sub in ("unet", "vae", "image_encoder", "clip_camera_projection"):
        for file in (tmp_path / "fp16" / sub).glob("*.fp16.*"):
            shutil.copy(file, path / sub / file.name)
    plain = Zero123Synthesizer.from_pretrained(path, **FAST)
    _assert_same_weights(plain.unet, c["unet"])  # plain files win by default
    half = Zero123Synthesizer.from_pretrained(path, variant="fp16", **FAST)
    _assert_same_weights(half.unet, c["unet"], half=True)
    _assert_same_weights(half.projection, c["projection"], half=True)
    assert not torch.equal(plain.unet.conv_in.weight, half.unet.conv_in.weight)
    # different weights, different cache keys
    assert plain.weights_id != half.weights_id and plain.config_key() != half.config_key()
    # a variant that is not there: plain files are the fallback
    bf16 = Zero123Synthesizer.from_pretrained(path, variant="bf16", **FAST)
    assert bf16.weights_id == plain.weights_id


def test_select_weight_files_rules():
    unet = ["config.json", "diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin"]
    assert select_weight_files(unet, "diffusers", None, "unet/") == WeightFiles(
        None, ("diffusion_pytorch_model.safetensors",)
    )
    only_bin = ["config.json", "pytorch_model.fp16.bin"]
    assert select_weight_files(only_bin, "transformers", None, "image_encoder/") == WeightFiles(
        "fp16", ("pytorch_model.fp16.bin",)
    )
    shards = [
        "diffusion_pytorch_model.safetensors.index.fp16.json",
        "diffusion_pytorch_model.fp16-00002-of-00002.safetensors",
        "diffusion_pytorch_model.fp16-00001-of-00002.safetensors",
    ]
    weights = select_weight_files(shards, "diffusers", None, "unet/")
    assert weights.variant == "fp16" and weights.sharded
    assert weights.files == (shards[0], shards[2], shards[1])
    # another library's names do not count
    with pytest.raises(Zero123CheckpointError, match=r"unet/: expected weights named diffusion_pytorch_model"):
        select_weight_files(["config.json", "model.safetensors"], "diffusers", None, "unet/")
    two = ["diffusion_pytorch_model.fp16.safetensors", "diffusion_pytorch_model.bf16.safetensors"]
    with pytest.raises(
        Zero123CheckpointError, match=r"vae/: holds several weight variants \['bf16', 'fp16'\].*`variant=`"
    ):
        select_weight_files(two, "diffusers", None, "vae/")
    assert select_weight_files(two, "diffusers", "bf16", "vae/").variant == "bf16"
    with pytest.raises(Zero123CheckpointError, match=r"expected weights of variant 'int8'.*\['bf16', 'fp16'\]"):
        select_weight_files(two, "diffusers", "int8", "vae/")


@pytest.mark.parametrize("variant", [None, "fp16"])
def test_sharded_folder_loads(tiny_zero123, tmp_path, variant, zero123_files):
    c = tiny_zero123.components
    components = c if variant is None else zero123_files.half_copy(c)
    path = zero123_files.save_layout(
        components, tmp_path / "sharded", "clip_camera_projection", variant=variant, max_shard_size="100KB"
    )
    infix = f".{variant}" if variant else ""
    assert (path / "unet" / f"diffusion_pytorch_model.safetensors.index{infix}.json").is_file()
    assert (path / "image_encoder" / f"model.safetensors.index{infix}.json").is_file()
    assert len(list((path / "unet").glob("*-of-*.safetensors"))) > 1
    assert len(list((path / "clip_camera_projection").glob("*-of-*.safetensors"))) == 2
    synth = Zero123Synthesizer.from_pretrained(path, **FAST)
    for name in ("unet", "vae", "image_encoder", "projection"):
        _assert_same_weights(getattr(synth, name), c[name], half=variant is not None)


def test_missing_shard_is_named(tiny_zero123, tmp_path, zero123_files):
    path = zero123_files.save_layout(
        tiny_zero123.components, tmp_path / "sharded", "clip_camera_projection", max_shard_size="100KB"
    )
    shard = sorted((path / "clip_camera_projection").glob("*-of-*.safetensors"))[1]
    shard.unlink()
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer.from_pretrained(path)
    msg = str(err.value)
    assert "clip_camera_projection/diffusion_pytorch_model.safetensors.index.json" in msg
    assert f"missing shards ['{shard.name}']" in msg


# ---------------------------------------------------------------- noise schedule


def test_noise_schedule_mismatches():
    assert noise_schedule_mismatches(REFERENCE_DDIM) == []
    # what the diffusers conversion script writes (its defaults, since it reads the YAML wrongly)
    converter = dict(REFERENCE_DDIM, beta_start=0.02, beta_end=0.085)
    assert noise_schedule_mismatches(converter) == [
        "beta_start: expected 0.00085, found 0.02",
        "beta_end: expected 0.012, found 0.085",
    ]
    # absent keys are DDIMScheduler's defaults: linear 1e-4 -> 0.02 with clipping
    assert noise_schedule_mismatches({"_class_name": "PNDMScheduler"}) == [
        "beta_start: expected 0.00085, found 0.0001",
        "beta_end: expected 0.012, found 0.02",
        "beta_schedule: expected 'scaled_linear', found 'linear'",
        "clip_sample: expected False, found True",
        "set_alpha_to_one: expected False, found True",
        "steps_offset: expected 1, found 0",
    ]
    assert noise_schedule_mismatches(dict(REFERENCE_DDIM, prediction_type="v_prediction")) == [
        "prediction_type: expected 'epsilon', found 'v_prediction'"
    ]


def test_bad_scheduler_config_warns_and_falls_back(tiny_zero123, tmp_path):
    from diffusers import DDIMScheduler

    path = tmp_path / "zero123-xl-diffusers"
    shutil.copytree(tiny_zero123.layout_b, path)
    config_file = path / "scheduler" / "scheduler_config.json"
    config = json.loads(config_file.read_text())
    config.update(beta_start=0.02, beta_end=0.085)
    config_file.write_text(json.dumps(config))
    with pytest.warns(UserWarning, match=r"scheduler_config.json departs from the SD 1.x") as record:
        synth = Zero123Synthesizer.from_pretrained(path, **FAST)
    (message,) = [str(w.message) for w in record if "SD 1.x" in str(w.message)]
    assert "beta_start: expected 0.00085, found 0.02; beta_end: expected 0.012, found 0.085" in message
    assert synth.scheduler.config.beta_start == 0.00085 and synth.scheduler.config.beta_end == 0.012
    reference = DDIMScheduler(**REFERENCE_DDIM)
    torch.testing.assert_close(synth.scheduler.alphas_cumprod, reference.alphas_cumprod, rtol=0, atol=0)
    # the wrong schedule would have been far off
    wrong = DDIMScheduler(**config)
    assert (wrong.alphas_cumprod - reference.alphas_cumprod).abs().max() > 0.1
    # same outputs as a folder with the right schedule (the cache key does not see the bad file)
    good = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_b, **FAST)
    assert synth.config_key().split("scheduler=")[1] == good.config_key().split("scheduler=")[1]


def test_good_scheduler_config_is_used_without_warning(tiny_zero123):
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        synth = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, **FAST)
    assert not [w for w in record if "SD 1.x" in str(w.message)]
    assert synth.scheduler.config.beta_schedule == "scaled_linear"


def test_explicit_scheduler_is_not_checked(tiny_zero123, tmp_path):
    from diffusers import DDIMScheduler

    mine = DDIMScheduler(**dict(REFERENCE_DDIM, timestep_spacing="trailing"))
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        synth = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, scheduler=mine, **FAST)
    assert synth.scheduler is mine
    assert not [w for w in record if "SD 1.x" in str(w.message)]


def test_unreadable_scheduler_config_is_listed(tiny_zero123, tmp_path):
    path = tmp_path / "ckpt"
    shutil.copytree(tiny_zero123.layout_a, path)
    (path / "scheduler" / "scheduler_config.json").write_text("{not json")
    with pytest.raises(Zero123CheckpointError, match=r"scheduler/: expected a readable scheduler_config.json"):
        Zero123Synthesizer.from_pretrained(path)


# ---------------------------------------------------------------- single files


def test_ldm_ckpt_gets_the_conversion_command(tmp_path):
    ckpt = tmp_path / "zero123-xl.ckpt"
    ckpt.write_bytes(b"not really a checkpoint")
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer.from_pretrained(ckpt)
    msg = str(err.value)
    assert f"got the single file {str(ckpt)!r}, an original latent-diffusion checkpoint" in msg
    assert f"python scripts/convert_zero123_to_diffusers.py --checkpoint_path {ckpt}" in msg
    assert "--original_config_file load/zero123/sd-objaverse-finetune-c_concat-256.yaml" in msg
    assert f"--dump_path {tmp_path / 'zero123-xl-diffusers'}" in msg
    assert "bennyguo/zero123-xl-diffusers" in msg
    # also as a string, and before anything is downloaded or imported from the Hub
    with pytest.raises(Zero123CheckpointError, match="convert_zero123_to_diffusers"):
        Zero123Synthesizer.from_pretrained(str(ckpt))


def test_missing_ckpt_and_other_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"got the missing file '.*zero123-xl.ckpt'"):
        Zero123Synthesizer.from_pretrained(tmp_path / "zero123-xl.ckpt")
    other = tmp_path / "weights.txt"
    other.write_text("")
    with pytest.raises(FileNotFoundError, match=r"`path` must be a Zero-1-to-3 checkpoint directory, got the file"):
        Zero123Synthesizer.from_pretrained(other)

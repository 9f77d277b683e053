"""Tests for the Zero-1-to-3 synthesizer with a tiny random model saved in both checkpoint layouts."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from helpers import one_thread

from lightning_vtr.synthesis.base import SynthesisRequest
from lightning_vtr.synthesis.pose import relative_pose
from lightning_vtr.synthesis.zero123 import CLIP_MEAN, CLIP_STD, Zero123CheckpointError, Zero123Synthesizer

# one DDIM step keeps the suite fast; tests that need several steps ask for them
FAST = dict(num_inference_steps=1, image_size=32)


def _sibling(synth: Zero123Synthesizer, **kwargs) -> Zero123Synthesizer:
    """Another synthesizer on the same (already loaded) modules and weights id, with some settings changed."""
    settings = dict(pose_embedding=synth.pose_embedding, weights_id=synth.weights_id, **FAST)
    settings.update(kwargs)
    return Zero123Synthesizer(synth.unet, synth.vae, synth.image_encoder, synth.projection, synth.scheduler, **settings)


def _object_image(
    size: int = 48, box: tuple[int, int, int, int] = (10, 30, 14, 40), colour=(200, 40, 40)
) -> np.ndarray:
    """Transparent background with an opaque coloured rectangle (rows r0:r1, cols c0:c1)."""
    img = np.zeros((size, size, 4), dtype=np.uint8)
    r0, r1, c0, c1 = box
    img[r0:r1, c0:c1, :3] = colour
    img[r0:r1, c0:c1, 3] = 255
    return img


def _request(object_id="chair_0001", targets=((80.0, 0.0), (10.0, 40.0))) -> SynthesisRequest:
    return SynthesisRequest(
        object_id=object_id,
        category="chair",
        source_images=np.stack([_object_image(), _object_image(colour=(30, 160, 60))]),
        source_viewpoints=torch.tensor([[0.0, 30.0], [180.0, 0.0]]),
        target_viewpoints=torch.as_tensor(targets, dtype=torch.float32),
    )


# the tiny model's ops are too small to split; with busy cores, 2-thread OpenMP barriers made it ~20x slower
_one_thread = pytest.fixture(scope="module", autouse=True, name="_one_thread")(one_thread)


@pytest.fixture(scope="module")
def synth_a(tiny_zero123) -> Zero123Synthesizer:
    return Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, **FAST)


@pytest.fixture(scope="module")
def synth_b(tiny_zero123) -> Zero123Synthesizer:
    return Zero123Synthesizer.from_pretrained(tiny_zero123.layout_b, **FAST)


@pytest.fixture(scope="module")
def synth_stable(tiny_zero123) -> Zero123Synthesizer:
    return Zero123Synthesizer.from_pretrained(tiny_zero123.stable, **FAST)


# ---------------------------------------------------------------- loading


@pytest.mark.parametrize(
    ("fixture", "pose"), [("synth_a", "zero123"), ("synth_b", "zero123"), ("synth_stable", "stable")]
)
def test_loads_both_layouts_with_inferred_projection(tiny_zero123, fixture, pose, request):
    # the layout does not tell the pose: only a name saying "stable" gives Stable Zero123's
    synth = request.getfixturevalue(fixture)
    ref = tiny_zero123.components["projection"]
    assert (synth.projection.in_features, synth.projection.out_features) == (36, 32)
    torch.testing.assert_close(synth.projection.weight, ref.weight, rtol=0, atol=0)
    torch.testing.assert_close(synth.projection.bias, ref.bias, rtol=0, atol=0)
    assert synth.pose_embedding == pose
    assert synth.resolution == 64  # sample_size 8 x VAE factor 8
    ref_unet = tiny_zero123.components["unet"].state_dict()
    for name, value in synth.unet.state_dict().items():
        torch.testing.assert_close(value, ref_unet[name], rtol=0, atol=0)
    assert synth.device == torch.device("cpu") and synth.dtype == torch.float32
    assert synth.scheduler.config.beta_schedule == "scaled_linear"


def test_pose_embedding_override(tiny_zero123):
    synth = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, pose_embedding="stable", **FAST)
    assert synth.pose_embedding == "stable"


def test_feature_extractor_config_is_used(tiny_zero123, tmp_path):
    path = tmp_path / "ckpt"
    shutil.copytree(tiny_zero123.layout_a, path)
    cfg_file = path / "feature_extractor" / "preprocessor_config.json"
    cfg = json.loads(cfg_file.read_text())
    cfg["image_mean"], cfg["crop_size"] = [0.5, 0.5, 0.5], {"height": 112, "width": 112}
    cfg_file.write_text(json.dumps(cfg))
    synth = Zero123Synthesizer.from_pretrained(path)
    assert synth.image_mean == (0.5, 0.5, 0.5) and synth.clip_size == 112
    # without the folder: CLIP's own normalisation at 224
    shutil.rmtree(path / "feature_extractor")
    synth = Zero123Synthesizer.from_pretrained(path)
    assert synth.image_mean == CLIP_MEAN and synth.image_std == CLIP_STD and synth.clip_size == 224


def test_missing_components_listed_in_one_error(tiny_zero123, tmp_path):
    path = tmp_path / "broken"
    shutil.copytree(tiny_zero123.layout_b, path)
    shutil.rmtree(path / "vae")
    shutil.rmtree(path / "clip_camera_projection")
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer.from_pretrained(path)
    msg = str(err.value)
    assert "vae/: expected config.json + weights named diffusion_pytorch_model" in msg
    assert "folder missing [AutoencoderKL]" in msg
    assert "cc_projection/ or clip_camera_projection/" in msg and "neither folder exists" in msg
    assert "unet/" not in msg  # only what is wrong is listed


def test_projection_with_wrong_keys_or_sizes(tiny_zero123, tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "badproj"
    shutil.copytree(tiny_zero123.layout_b, path)
    weights = path / "clip_camera_projection" / "diffusion_pytorch_model.safetensors"
    save_file({"linear.weight": torch.zeros(32, 36)}, str(weights))
    with pytest.raises(
        Zero123CheckpointError, match=r"clip_camera_projection/.*'proj.weight'.*found keys \['linear.weight'\]"
    ):
        Zero123Synthesizer.from_pretrained(path)
    # sizes disagreeing with config.json
    save_file({"proj.weight": torch.zeros(32, 40), "proj.bias": torch.zeros(32)}, str(weights))
    with pytest.raises(Zero123CheckpointError, match=r"config.json says \(out, in\) = \(32, 36\).*\(32, 40\)"):
        Zero123Synthesizer.from_pretrained(path)


def test_mismatched_components_from_the_constructor(tiny_zero123):
    c = tiny_zero123.components
    with pytest.raises(Zero123CheckpointError) as err:
        Zero123Synthesizer(c["unet"], c["vae"], c["image_encoder"], torch.nn.Linear(33, 16))
    msg = str(err.value)
    assert "in_features = image_encoder projection_dim + 4 = 36, found 33" in msg
    assert "out_features = unet cross_attention_dim = 32, found 16" in msg


def test_missing_directory():
    with pytest.raises(FileNotFoundError, match="checkpoint directory"):
        Zero123Synthesizer.from_pretrained("/nonexistent/zero123")


def test_bad_arguments(tiny_zero123):
    c = tiny_zero123.components
    with pytest.raises(ValueError, match="num_inference_steps"):
        Zero123Synthesizer(**c, num_inference_steps=0)
    with pytest.raises(ValueError, match="eta"):
        Zero123Synthesizer(**c, eta=1.5)
    with pytest.raises(ValueError, match="float16 is not supported on CPU"):
        Zero123Synthesizer(**c, device="cpu", dtype=torch.float16)


# ---------------------------------------------------------------- preprocessing


def test_preprocess_centres_on_white(synth_a):
    # object rows 10..29 (20 px), cols 14..39 (26 px): side = ceil(26 / 0.8) = 33
    img = _object_image()
    pixels, side = synth_a.preprocess(img)
    assert side == 33 and pixels.shape == (3, 64, 64)
    # reference: paste the crop centred on a white 33x33 canvas by hand, then resize
    canvas = np.ones((33, 33, 3), dtype=np.float32)
    top, left = (33 - 20) // 2, (33 - 26) // 2
    canvas[top : top + 20, left : left + 26] = np.array([200, 40, 40]) / 255.0
    ref = torch.nn.functional.interpolate(
        torch.from_numpy(canvas).permute(2, 0, 1)[None], size=(64, 64), mode="bilinear", antialias=True
    )[0]
    torch.testing.assert_close(pixels, ref, atol=1e-5, rtol=0)
    assert pixels[:, 0, 0].tolist() == [1.0, 1.0, 1.0]  # white background
    # an opaque image on white: the non-white pixels define the box
    opaque = img.copy()
    opaque[..., :3][img[..., 3] == 0] = 255
    opaque[..., 3] = 255
    pixels2, side2 = synth_a.preprocess(opaque)
    assert side2 == 33
    torch.testing.assert_close(pixels2, pixels, atol=1e-5, rtol=0)


def test_preprocess_composites_on_white_as_the_float32_formula(synth_a):
    # A random semi-transparent object: the white composite is rgb * a + (1 - a), then centred and resized.
    from lightning_vtr.synthesis.zero123 import _center_fit, _resize

    rgba = np.zeros((48, 48, 4), dtype=np.uint8)
    rgba[10:30, 14:40] = np.random.default_rng(5).integers(1, 256, (20, 26, 4), dtype=np.uint8)
    pixels, side = synth_a.preprocess(rgba)
    x = torch.from_numpy(rgba).permute(2, 0, 1).float() / 255.0
    rgb = x[:3] * x[3:] + (1.0 - x[3:])
    expected = _resize(_center_fit(rgb[:, 10:30, 14:40], side), 64).clamp(0.0, 1.0)
    assert side == 33 and torch.equal(pixels, expected)


def test_postprocess_restores_scale_and_alpha(synth_a):
    # a model image of a dark square in the centre half; input crop spanned 33 px of a 48 px source
    rgb = torch.ones(3, 64, 64)
    rgb[:, 16:48, 16:48] = 0.2
    out = synth_a.postprocess(rgb, side=33, source_size=48, output_size=48)
    assert out.shape == (48, 48, 4) and out.dtype == np.uint8
    # span 33 px centred at offset (48 - 33) // 2 = 7; the square is half of it
    dark = out[..., 3] == 255
    rows = np.nonzero(dark.any(axis=1))[0]
    assert rows[0] in (14, 15) and rows[-1] in (31, 32)
    assert out[0, 0].tolist() == [255, 255, 255, 0]
    assert out[24, 24].tolist() == [51, 51, 51, 255]


# ---------------------------------------------------------------- generation


def test_synthesize_shapes_dtype_and_ranges(synth_a, synth_b):
    requests = [_request(), _request("table_0002", ((45.0, -10.0),))]
    for synth in (synth_a, synth_b):
        out = synth.synthesize(requests)
        assert [o.shape for o in out] == [(2, 32, 32, 4), (1, 32, 32, 4)]
        assert all(o.dtype == np.uint8 for o in out)
        assert set(np.unique(out[0][..., 3])) <= {0, 255}
        # alpha follows the near-white rule exactly
        rgb = out[0][..., :3].astype(np.float32) / 255.0
        expected_alpha = np.where((rgb >= synth.background_threshold - 1e-3).all(-1), 0, 255)
        assert np.mean(expected_alpha == out[0][..., 3]) > 0.99
    decoded = synth_a([_object_image()], torch.tensor([[0.0, 0.0]]), torch.tensor([[30.0, 0.0]]), output_type="pt")
    assert decoded.shape == (1, 3, 64, 64) and decoded.dtype == torch.float32
    assert float(decoded.min()) >= 0.0 and float(decoded.max()) <= 1.0


def test_determinism_under_seed(tiny_zero123, synth_a):
    a = synth_a.synthesize([_request()])[0]
    b = synth_a.synthesize([_request()])[0]
    np.testing.assert_array_equal(a, b)
    c = _sibling(synth_a, seed=1).synthesize([_request()])[0]
    assert not np.array_equal(a, c)
    # explicit seeds in the pipeline call
    args = ([_object_image()], torch.tensor([[0.0, 0.0]]), torch.tensor([[30.0, 0.0]]))
    x1 = synth_a(*args, seeds=[7], num_inference_steps=2, output_type="pt")
    x2 = synth_a(*args, seeds=[7], num_inference_steps=2, output_type="pt")
    x3 = synth_a(*args, seeds=[8], num_inference_steps=2, output_type="pt")
    torch.testing.assert_close(x1, x2, rtol=0, atol=0)
    assert (x1 - x3).abs().max() > 1e-4


def test_batching_does_not_change_outputs(synth_a):
    one, many = _sibling(synth_a, batch_size=1), _sibling(synth_a, batch_size=8)
    requests = [_request(), _request("lamp_0003", ((-120.0, 60.0),))]
    for x, y in zip(one.synthesize(requests), many.synthesize(requests)):
        # per-pair noise: batch composition only changes float rounding
        assert np.abs(x.astype(int) - y.astype(int)).max() <= 2


def test_pose_reaches_the_projection(synth_a, synth_b, synth_stable):
    assert [s.pose_embedding for s in (synth_a, synth_b, synth_stable)] == ["zero123", "zero123", "stable"]
    for synth in (synth_a, synth_b, synth_stable):
        seen = []
        handle = synth.projection.register_forward_hook(
            lambda m, inp, out, seen=seen: seen.append(inp[0].detach().clone())
        )
        try:
            synth.synthesize([_request()])
        finally:
            handle.remove()
        assert len(seen) == 1
        token_in = seen[0]
        assert token_in.shape == (2, 1, 36)
        # both targets (80, 0) and (10, 40) are nearer (0, 30) than (180, 0): d_polar = +30 and -10 deg
        if synth.pose_embedding == "zero123":
            expected = [
                [math.radians(30), math.sin(math.radians(80)), math.cos(math.radians(80)), 0.0],
                [math.radians(-10), math.sin(math.radians(10)), math.cos(math.radians(10)), 0.0],
            ]
        else:
            expected = [
                [math.radians(30), math.sin(math.radians(80)), math.cos(math.radians(80)), math.radians(60)],
                [math.radians(-10), math.sin(math.radians(10)), math.cos(math.radians(10)), math.radians(60)],
            ]
        torch.testing.assert_close(token_in[:, 0, -4:], torch.tensor(expected), atol=1e-6, rtol=0)
        torch.testing.assert_close(
            token_in[:, 0, -4:],
            relative_pose(torch.tensor([0.0, 30.0]), torch.tensor([[80.0, 0.0], [10.0, 40.0]]), synth.pose_embedding),
        )


def test_nearest_source_image_is_used(synth_a):
    # the green source at (180, 0) must be the input for a target at (170, 5)
    seen = []
    handle = synth_a.vae.encoder.register_forward_hook(lambda m, inp, out: seen.append(inp[0].detach().clone()))
    try:
        synth_a.synthesize([_request(targets=((170.0, 5.0),))])
    finally:
        handle.remove()
    centre = (seen[0][0, :, 32, 32] + 1) / 2  # VAE input in [-1, 1]
    torch.testing.assert_close(centre, torch.tensor([30, 160, 60]) / 255.0, atol=1e-4, rtol=0)


def _count_unet_calls(synth, guidance):
    rows = []
    handle = synth.unet.register_forward_hook(lambda m, inp, out: rows.append(inp[0].shape[0]))
    try:
        synth(
            [_object_image()] * 3,
            torch.zeros(3, 2),
            torch.tensor([[30.0, 0.0]] * 3),
            guidance_scale=guidance,
            num_inference_steps=3,
            output_type="pt",
        )
    finally:
        handle.remove()
    return rows


def test_guidance_branches(synth_a):
    assert _count_unet_calls(synth_a, 1.0) == [3, 3, 3]  # no unconditional branch
    assert _count_unet_calls(synth_a, 3.0) == [6, 6, 6]  # unconditional + conditional in one call
    # as in the reference, only exactly 1 skips the unconditional branch
    assert _count_unet_calls(synth_a, 0.5) == [6, 6, 6]
    assert _count_unet_calls(synth_a, 0.0) == [6, 6, 6]


def test_guidance_below_one_mixes_toward_unconditional(synth_a):
    red, green = _object_image(), _object_image(colour=(30, 160, 60))
    source, target = torch.zeros(1, 2), torch.tensor([[30.0, 0.0]])

    def run(image, guidance, target=target):
        return synth_a(
            [image], source, target, seeds=[3], guidance_scale=guidance, num_inference_steps=2, output_type="pt"
        )

    # scale 0 is the unconditional prediction alone: zeros for the token and the image latent, so neither the
    # input image nor the pose can change the output
    torch.testing.assert_close(run(red, 0.0), run(green, 0.0), rtol=0, atol=0)
    torch.testing.assert_close(run(red, 0.0), run(red, 0.0, torch.tensor([[-90.0, 40.0]])), rtol=0, atol=0)
    # a scale in (0, 1) still sees the condition (it used to be dropped, giving the scale-1 image)
    assert (run(red, 0.5) - run(green, 0.5)).abs().max() > 1e-4
    assert (run(red, 0.5) - run(red, 1.0)).abs().max() > 1e-4


def test_clip_input_is_resized_as_the_reference(synth_a):
    # the reference (kornia): bicubic, align_corners=True, no antialiasing, then CLIP's mean/std
    seen = []
    handle = synth_a.image_encoder.register_forward_hook(
        lambda m, args, kwargs, out: seen.append(kwargs["pixel_values"].detach().clone()), with_kwargs=True
    )
    pixels, _ = synth_a.preprocess(_object_image())
    try:
        synth_a.encode_image(pixels[None], torch.zeros(1, 4))
    finally:
        handle.remove()
    ref = torch.nn.functional.interpolate(pixels[None], size=(224, 224), mode="bicubic", align_corners=True)
    ref = (ref - torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)) / torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    assert seen[0].shape == (1, 3, 224, 224)
    torch.testing.assert_close(seen[0], ref, rtol=0, atol=1e-6)
    # the previous resize (antialiased, align_corners=False) differs from it by far more than rounding
    old = torch.nn.functional.interpolate(pixels[None], size=(224, 224), mode="bicubic", antialias=True)
    old = (old - torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)) / torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    assert (seen[0] - old).abs().max() > 1e-2


def test_unconditional_branch_is_zeros(synth_a):
    tokens, latents = [], []

    def hook(module, args, kwargs, out):
        latents.append(args[0][:, 4:].clone())
        tokens.append(kwargs["encoder_hidden_states"].clone())

    handle = synth_a.unet.register_forward_hook(hook, with_kwargs=True)
    try:
        synth_a(
            [_object_image()], torch.zeros(1, 2), torch.tensor([[30.0, 0.0]]), num_inference_steps=1, output_type="pt"
        )
    finally:
        handle.remove()
    assert tokens[0].shape == (2, 1, 32) and latents[0].shape == (2, 4, 8, 8)
    assert torch.count_nonzero(tokens[0][0]) == 0 and torch.count_nonzero(latents[0][0]) == 0
    assert torch.count_nonzero(tokens[0][1]) > 0
    # the conditional image latent is the posterior mode, not scaled by the VAE factor
    pixels, _ = synth_a.preprocess(_object_image())
    mode = synth_a.vae.encode(pixels[None] * 2 - 1).latent_dist.mode()
    torch.testing.assert_close(latents[0][1:], mode, atol=1e-5, rtol=0)


def test_config_key_covers_outputs(tiny_zero123, synth_a, synth_b):
    base = synth_a.config_key()
    assert base == Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, **FAST).config_key()
    assert base != synth_b.config_key()
    assert _sibling(synth_a).config_key() == base
    changes = (
        dict(num_inference_steps=3),
        dict(guidance_scale=2.0),
        dict(eta=0.0),
        dict(seed=5),
        dict(image_size=48),
        dict(pose_embedding="stable"),
        dict(foreground_ratio=0.5),
        dict(dtype=torch.bfloat16),
    )
    for change in changes:
        assert _sibling(synth_a, **change).config_key() != base, change
    # batch size does not change outputs, so it does not change the key
    assert _sibling(synth_a, batch_size=3).config_key() == base
    # built from components: keyed by a parameter hash
    c = tiny_zero123.components
    k1 = Zero123Synthesizer(**c).config_key()
    assert k1 == Zero123Synthesizer(**c).config_key()


def test_check_inputs_errors(synth_a):
    with pytest.raises(ValueError, match=r"source_images\[0\]"):
        synth_a([np.zeros((8, 8, 3), np.uint8)], torch.zeros(1, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="one entry per pair"):
        synth_a([_object_image()], torch.zeros(2, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="output_type"):
        synth_a([_object_image()], torch.zeros(1, 2), torch.zeros(1, 2), output_type="pil")


def test_empty_requests(synth_a):
    out = synth_a.synthesize([_request(targets=torch.zeros(0, 2))])
    assert len(out) == 1 and out[0].shape == (0, 32, 32, 4)
    assert synth_a.synthesize([]) == []


def test_reduced_precision_path(synth_a):
    # the fp16-on-GPU path exercised with bfloat16 on the CPU: every input must be cast to the modules' dtype
    low = _sibling(synth_a, dtype=torch.bfloat16)
    try:
        out = low([_object_image()], torch.zeros(1, 2), torch.tensor([[30.0, 0.0]]), output_type="pt")
        assert next(low.unet.parameters()).dtype == torch.bfloat16
        assert out.dtype == torch.float32 and out.shape == (1, 3, 64, 64)
        assert torch.isfinite(out).all() and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    finally:
        synth_a._place()  # the sibling shares synth_a's modules: move them back
    assert next(synth_a.unet.parameters()).dtype == torch.float32

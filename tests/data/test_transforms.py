"""Image ops and recipes of lightning_vtr.data.transforms: hand-computed values, the plain path bit for bit,
the published recipes, and augmentation drawn from (seed, epoch, index) alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from lightning_vtr.data.transforms import (
    IMAGE_RECIPES,
    IMAGENET_PCA_EIGVAL,
    IMAGENET_PCA_EIGVEC,
    SHAPENET_RENDERING_CROP,
    ImageRecipe,
    ImageTransform,
    adjust_brightness,
    adjust_contrast,
    adjust_saturation,
    center_crop,
    hflip,
    normalize_image,
    pca_lighting,
    permute_channels,
    rgb_to_grayscale,
)
from lightning_vtr.utils.compositing import alpha_composite


def _original_transform(rgba, image_size, background, normalize):
    """The package's transform before recipes existed, verbatim in substance: the plain path must equal it."""
    single = rgba.ndim == 3
    batch = rgba[None] if single else rgba
    x = torch.from_numpy(np.ascontiguousarray(batch)).float() / 255.0
    if x.shape[-1] == 4:
        alpha = x[..., 3:]
        bg = torch.tensor(background, dtype=x.dtype) / 255.0
        x = x[..., :3] * alpha + bg * (1.0 - alpha)
    x = x.permute(0, 3, 1, 2)
    if x.shape[-1] != image_size or x.shape[-2] != image_size:
        x = F.interpolate(x, size=(image_size, image_size), mode="bilinear", antialias=True, align_corners=False)
        x = x.clamp(0.0, 1.0)
    if normalize == "imagenet":
        mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
        std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
        x = (x - mean) / std
    return x[0] if single else x


def _rgba(rgb, alpha=255):
    """A ``(1, H, W, 4)`` uint8 image of ``(H, W, 3)`` colours with one alpha everywhere."""
    rgb = np.asarray(rgb, np.uint8)
    return np.concatenate([rgb, np.full((*rgb.shape[:-1], 1), alpha, np.uint8)], axis=-1)[None]


# ---------------------------------------------------------------------------------------------- the plain path
@pytest.mark.parametrize("image_size", [24, 40, 64])
@pytest.mark.parametrize("normalize", ["imagenet", None])
@pytest.mark.parametrize("background", [(255, 255, 255), (0, 51, 240)])
def test_default_transform_is_the_original_bit_for_bit(image_size, normalize, background):
    rgba = np.random.default_rng(0).integers(0, 256, (3, 40, 40, 4), dtype=np.uint8)
    rgba[:, :5, :, 3] = 0  # fully transparent rows
    expected = _original_transform(rgba, image_size, background, normalize)
    transform = ImageTransform(image_size, background, normalize)
    assert not transform.is_random
    assert torch.equal(transform(rgba), expected)
    assert torch.equal(transform(rgba, key=(0, 1, 2)), expected)  # a key changes nothing without random ops
    assert torch.equal(transform(rgba[0]), expected[0])
    assert torch.equal(
        IMAGE_RECIPES["plain"].train_transform(image_size)(rgba),
        _original_transform(rgba, image_size, (255, 255, 255), "imagenet"),
    )


def test_pm1_is_x_times_2_minus_1_and_the_same_as_mean_std_one_half():
    x = torch.arange(256, dtype=torch.float32).div(255.0).view(1, 1, 1, 256).expand(1, 3, 1, 256)
    out = normalize_image(x, "pm1")
    assert out[0, :, 0, 0].tolist() == [-1.0] * 3 and out[0, :, 0, -1].tolist() == [1.0] * 3
    assert normalize_image(torch.full((3, 1, 1), 0.5), "pm1").tolist() == [[[0.0]]] * 3
    assert torch.equal(out, (x - 0.5) / 0.5)  # Pix2Vox++'s mean = std = 0.5, bit for bit
    assert torch.equal(normalize_image(x, None), x)
    imagenet = normalize_image(x, "imagenet")
    assert torch.allclose(
        imagenet[0, :, 0, 0], -torch.tensor([0.485, 0.456, 0.406]) / torch.tensor([0.229, 0.224, 0.225])
    )


# ---------------------------------------------------------------------------------------------- each op
def test_brightness_scales_and_the_transform_clamps_unless_told_not_to():
    x = torch.full((3, 2, 2), 0.5)
    assert torch.equal(adjust_brightness(x, 1.5), torch.full((3, 2, 2), 0.75))
    assert torch.equal(adjust_brightness(x, 0.5), torch.full((3, 2, 2), 0.25))
    per_image = adjust_brightness(torch.full((2, 3, 1, 1), 0.5), torch.tensor([0.5, 1.5]))
    assert per_image.flatten().tolist() == [0.25] * 3 + [0.75] * 3
    grey = _rgba(np.full((4, 4, 3), 200))
    for key in [(0, 0, i) for i in range(20)]:
        clamped = ImageTransform(4, normalize=None, brightness=0.4)
        factor = clamped.draw(key, 1).factors[0]
        assert 0.6 <= factor <= 1.4
        expected = min(200 / 255 * factor, 1.0)
        assert torch.allclose(clamped(grey, key=key), torch.full((1, 3, 4, 4), expected), atol=1e-6)
        unclamped = ImageTransform(4, normalize=None, brightness=0.4, clamp=False)(grey, key=key)
        assert torch.allclose(unclamped, torch.full((1, 3, 4, 4), 200 / 255 * factor), atol=1e-6)


def test_contrast_blends_with_the_mean_luma_of_the_image():
    x = torch.tensor([0.2, 0.6]).view(1, 1, 2).expand(3, 1, 2)  # two grey pixels, mean luma 0.4
    assert torch.allclose(adjust_contrast(x, 0.5), torch.tensor([0.3, 0.5]).view(1, 1, 2).expand(3, 1, 2))
    assert torch.allclose(adjust_contrast(x, 0.0), torch.full((3, 1, 2), 0.4))
    red = torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)
    assert torch.allclose(adjust_contrast(red, 0.0), torch.full((3, 1, 1), 0.299))
    assert torch.allclose(adjust_contrast(red, 2.0), torch.tensor([2 - 0.299, -0.299, -0.299]).view(3, 1, 1))
    # The mean is per image: two images of one call keep their own.
    both = adjust_contrast(torch.stack([torch.zeros(3, 1, 1), torch.ones(3, 1, 1)]), 0.0)
    assert both.flatten().tolist() == [0.0] * 3 + [1.0] * 3


def test_saturation_blends_with_each_pixels_luma():
    assert torch.allclose(
        rgb_to_grayscale(torch.eye(3).view(3, 3, 1)), torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1)
    )
    red = torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)
    assert torch.allclose(adjust_saturation(red, 0.0), torch.full((3, 1, 1), 0.299))
    assert torch.allclose(adjust_saturation(red, 2.0), torch.tensor([2 - 0.299, -0.299, -0.299]).view(3, 1, 1))
    grey = torch.full((3, 2, 2), 0.3)
    assert torch.allclose(adjust_saturation(grey, 1.7), grey)  # grey has nothing to saturate
    with pytest.raises(ValueError, match=r"`image` must be \(\.\.\., 3, H, W\), got shape \(4, 1, 1\)"):
        adjust_saturation(torch.zeros(4, 1, 1), 0.5)


def test_pca_lighting_adds_eigvec_times_alpha_eigval_per_channel():
    eigval, eigvec = np.array(IMAGENET_PCA_EIGVAL), np.array(IMAGENET_PCA_EIGVEC)
    first = pca_lighting(torch.zeros(3, 2, 2), (1.0, 0.0, 0.0))
    assert torch.allclose(first[:, 0, 0], torch.tensor([-0.5675, -0.5808, -0.5836]) * 0.2175)
    alpha = (0.3, -1.2, 2.0)
    expected = [sum(eigvec[c, j] * alpha[j] * eigval[j] for j in range(3)) for c in range(3)]  # by hand
    out = pca_lighting(torch.full((3, 2, 2), 0.5), alpha)
    assert torch.allclose(out, 0.5 + torch.tensor(expected, dtype=torch.float32).view(3, 1, 1))
    assert torch.equal(pca_lighting(torch.full((3, 2, 2), 0.5), (0.0, 0.0, 0.0)), torch.full((3, 2, 2), 0.5))
    per_image = pca_lighting(torch.zeros(2, 3, 1, 1), torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    assert torch.allclose(per_image[0, :, 0, 0], first[:, 0, 0]) and per_image[1].abs().max() == 0
    with pytest.raises(ValueError, match=r"`alpha` must be \(\.\.\., 3\)"):
        pca_lighting(torch.zeros(3, 1, 1), (1.0, 2.0))


def test_hflip_reverses_the_width_axis_and_permute_channels_permutes():
    x = torch.arange(2 * 3 * 2 * 4, dtype=torch.float32).view(2, 3, 2, 4)
    assert torch.equal(hflip(x), x[..., [3, 2, 1, 0]])
    assert torch.equal(permute_channels(x, (2, 0, 1)), torch.stack([x[:, 2], x[:, 0], x[:, 1]], dim=1))
    with pytest.raises(ValueError, match=r"`permutation` must be a permutation of range\(3\), got \[0, 0, 1\]"):
        permute_channels(x, (0, 0, 1))


def test_center_crop_keeps_the_references_128_of_137_px():
    rows, cols = np.meshgrid(np.arange(137), np.arange(137), indexing="ij")
    pattern = torch.from_numpy(np.stack([rows, cols, rows + cols]).astype(np.float32))
    crop = center_crop(pattern, SHAPENET_RENDERING_CROP)
    assert crop.shape == (3, 128, 128)
    assert torch.equal(crop, pattern[:, 4:132, 4:132])  # 4 px off the top/left, 5 off the bottom/right
    assert center_crop(torch.zeros(3, 96, 96), SHAPENET_RENDERING_CROP).shape == (3, 90, 90)  # our 96 px renders
    assert torch.equal(center_crop(pattern, 1.0), pattern)
    with pytest.raises(ValueError, match=r"`fraction` must be a number in \(0, 1\], got 0.0"):
        center_crop(pattern, 0.0)


def test_crop_and_resize_of_a_known_pattern():
    # A 137 px image: a red band of 4 px at the top/left and 5 px at the bottom/right around green. The crop
    # must cut exactly the band, so after the resize to 224 px no red is left anywhere.
    rgb = np.zeros((137, 137, 3), np.uint8)
    rgb[..., 0] = 255
    rgb[4:132, 4:132] = (0, 255, 0)
    out = ImageTransform(224, normalize=None, crop=SHAPENET_RENDERING_CROP)(_rgba(rgb))
    assert out.shape == (1, 3, 224, 224)
    assert torch.equal(out[0], torch.tensor([0.0, 1.0, 0.0]).view(3, 1, 1).expand(3, 224, 224))
    # Without the crop the band shows; the crop-only path is a plain slice of the composited image.
    assert ImageTransform(224, normalize=None)(_rgba(rgb))[0, 0].max() > 0.5
    ramp = np.repeat(np.arange(137, dtype=np.uint8)[None, :, None], 137, axis=0).repeat(3, axis=2)
    sliced = ImageTransform(128, normalize=None, crop=SHAPENET_RENDERING_CROP)(_rgba(ramp))
    assert torch.equal(sliced[0, 0, 0], torch.arange(4, 132, dtype=torch.float32) / 255.0)
    # A horizontal ramp stays a ramp under a 2x bilinear upscale (away from the clamped borders).
    up = ImageTransform(256, normalize=None, crop=SHAPENET_RENDERING_CROP)(_rgba(ramp))[0, 0, 0]
    steps = (up[1:] - up[:-1])[2:-2] * 255.0
    assert torch.allclose(steps, torch.full_like(steps, 0.5), atol=1e-4)


# ---------------------------------------------------------------------------------------------- the recipes
def test_reference_recipes_hold_the_published_values():
    pix2vox, lrgt = IMAGE_RECIPES["pix2vox"], IMAGE_RECIPES["lrgt"]
    assert pix2vox.crop == lrgt.crop == 128 / 137
    assert pix2vox.background == lrgt.background == (240, 240, 240)
    assert pix2vox.background_range == lrgt.background_range == ((225, 255),) * 3
    assert (pix2vox.brightness, pix2vox.contrast, pix2vox.saturation, pix2vox.lighting_std) == (0.4, 0.4, 0.4, 0.1)
    assert pix2vox.hflip and pix2vox.permute_rgb and not pix2vox.clamp
    assert pix2vox.normalize == lrgt.normalize == "pm1"
    assert (lrgt.brightness, lrgt.contrast, lrgt.saturation, lrgt.lighting_std) == (0.0, 0.0, 0.0, 0.0)
    assert not (lrgt.hflip or lrgt.permute_rgb)
    assert IMAGE_RECIPES["plain"] == ImageRecipe() and not ImageRecipe().is_random
    with pytest.raises(TypeError):
        IMAGE_RECIPES["lab"] = ImageRecipe()  # the registry is read-only


@pytest.mark.parametrize("name", ["pix2vox", "lrgt"])
def test_reference_test_transform_is_crop_resize_background_240_pm1(name):
    transparent = np.zeros((2, 137, 137, 4), np.uint8)
    test = IMAGE_RECIPES[name].eval_transform(224)
    assert not test.is_random
    assert torch.allclose(test(transparent), torch.full((2, 3, 224, 224), 240 / 255 * 2 - 1), atol=1e-6)
    train = IMAGE_RECIPES[name].train_transform(224)
    assert train.is_random
    with pytest.raises(ValueError, match=r"`key` must be given for a random transform"):
        train(transparent)


def test_lrgt_training_draws_one_background_per_sample_in_225_255():
    transform = IMAGE_RECIPES["lrgt"].train_transform(4)
    seen = set()
    for index in range(200):
        out = transform(np.zeros((3, 16, 16, 4), np.uint8), key=(0, 0, index))
        colour = (out[0, :, 0, 0] + 1) / 2 * 255
        assert torch.allclose(out, out[0, :, 0, 0].view(1, 3, 1, 1).expand_as(out))  # every view, every pixel
        assert torch.allclose(colour, colour.round(), atol=1e-4)  # an int colour
        seen.update(round(c) for c in colour.tolist())
    assert min(seen) == 225 and max(seen) == 255  # both ends of the inclusive range


def test_pix2vox_draws_share_a_sample_and_flips_are_per_image():
    transform = IMAGE_RECIPES["pix2vox"].train_transform(16)
    draws = [transform.draw((3, 7, index), 24) for index in range(300)]
    for draw in draws:
        assert all(0.6 <= f <= 1.4 for f in draw.factors) and sorted(draw.order) == [0, 1, 2]
        assert all(225 <= c <= 255 for c in draw.background)
    assert len({d.channels for d in draws}) == 6 and len({d.order for d in draws}) == 6
    assert 0.4 < np.mean([f for d in draws for f in d.flips]) < 0.6
    assert all(len(set(d.flips)) == 2 for d in draws[:50])  # 24 views of a sample flip independently
    lighting = np.array([d.lighting for d in draws])
    assert 0.07 < lighting.std() < 0.13
    # Switching an op off leaves the draws of the others unchanged.
    no_jitter = dataclasses.replace(IMAGE_RECIPES["pix2vox"], brightness=0.0).train_transform(16)
    assert no_jitter.draw((3, 7, 0), 24).background == draws[0].background
    assert no_jitter.draw((3, 7, 0), 24).flips == draws[0].flips


def test_pix2vox_training_applies_the_drawn_ops_in_order():
    rgba = np.random.default_rng(1).integers(0, 256, (2, 137, 137, 4), dtype=np.uint8)
    rgba[..., 3] = np.where(rgba[..., 3] > 128, 255, 0)
    transform = IMAGE_RECIPES["pix2vox"].train_transform(64)
    key = (0, 4, 11)
    draw = transform.draw(key, 2)
    x = torch.from_numpy(rgba).float().div(255.0).permute(0, 3, 1, 2)
    x = alpha_composite(x, torch.tensor(draw.background) / 255.0, channels_first=True)
    x = F.interpolate(center_crop(x, 128 / 137), size=(64, 64), mode="bilinear", antialias=True).clamp(0, 1)
    ops = (adjust_brightness, adjust_contrast, adjust_saturation)
    for op in draw.order:
        x = ops[op](x, draw.factors[op])
    x = pca_lighting(x, draw.lighting)
    x = torch.stack([hflip(v) if f else v for v, f in zip(x, draw.flips)])
    x = permute_channels(x, draw.channels) * 2 - 1
    assert torch.allclose(transform(rgba, key=key), x, atol=1e-5)


# ---------------------------------------------------------------------------------------------- determinism
def test_augmentation_is_a_function_of_the_key_alone():
    rgba = np.random.default_rng(2).integers(0, 256, (3, 40, 40, 4), dtype=np.uint8)
    transform = IMAGE_RECIPES["pix2vox"].train_transform(32)
    keys = [(0, epoch, index) for epoch in range(3) for index in range(4)]
    forward = {k: transform(rgba, key=k) for k in keys}
    torch.manual_seed(123)
    np.random.seed(123)  # global random states play no part
    backward = {k: IMAGE_RECIPES["pix2vox"].train_transform(32)(rgba, key=k) for k in reversed(keys)}
    assert all(torch.equal(forward[k], backward[k]) for k in keys)
    assert not torch.equal(forward[(0, 0, 0)], forward[(0, 1, 0)])  # another epoch
    assert not torch.equal(forward[(0, 0, 0)], forward[(0, 0, 1)])  # another sample
    assert not torch.equal(forward[(0, 0, 0)], transform(rgba, key=(1, 0, 0)))  # another seed


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"crop": 0.0}, ValueError, r"`crop` must be a number in \(0, 1\], got 0.0"),
        ({"crop": 1.5}, ValueError, r"`crop` must be a number in \(0, 1\], got 1.5"),
        ({"brightness": 1.2}, ValueError, r"`brightness` must be a number in \[0, 1\], got 1.2"),
        ({"contrast": -0.1}, ValueError, r"`contrast` must be a number in \[0, 1\], got -0.1"),
        ({"lighting_std": -1.0}, ValueError, r"`lighting_std` must be a number >= 0, got -1.0"),
        ({"hflip": 1}, TypeError, r"`hflip` must be a bool, got int 1"),
        ({"normalize": "half"}, ValueError, r"`normalize` must be one of 'imagenet', 'pm1', None, got 'half'"),
        ({"background_range": (200, 300)}, ValueError, r"`background_range\[0\]\[1\]` must be an int in \[0, 255\]"),
        ({"background_range": (250, 240)}, ValueError, r"`background_range\[0\]` must satisfy low <= high"),
        ({"background_range": ((0, 1), (0, 1))}, ValueError, r"`background_range` must be a pair \(low, high\)"),
        ({"background_range": 240}, TypeError, r"`background_range` must be a pair \(low, high\)"),
    ],
)
def test_recipe_rejects_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        ImageRecipe(**kwargs)
    with pytest.raises(error, match=match):
        ImageTransform(8, **kwargs)


def test_recipe_normalises_its_fields():
    recipe = ImageRecipe(background=np.array([1, 2, 3]), background_range=[[0, 10], [5, 5], [7, 9]], crop=1)
    assert recipe.background == (1, 2, 3) and recipe.background_range == ((0, 10), (5, 5), (7, 9))
    assert recipe.crop == 1.0 and isinstance(recipe.crop, float)
    assert ImageRecipe(background_range=(225, 255)) == ImageRecipe(background_range=[(225, 255)] * 3)
    fixed = ImageRecipe(background_range=(240, 240), normalize=None)
    assert not fixed.is_random  # a one-colour range draws nothing, but is the training background
    out = fixed.train_transform(2)(np.zeros((2, 2, 4), np.uint8))
    assert torch.allclose(out, torch.full((3, 2, 2), 240 / 255))
    assert torch.equal(fixed.eval_transform(2)(np.zeros((2, 2, 4), np.uint8)), torch.ones(3, 2, 2))

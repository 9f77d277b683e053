"""lightning_vtr.utils.compositing: one alpha-compositing formula for numpy and torch, uint8 and float, both layouts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lightning_vtr.utils.compositing import alpha_composite


def _rgba(shape=(2, 5, 7, 4), seed=0) -> np.ndarray:
    rgba = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    rgba[..., 0, :, 3] = 0  # a transparent row ...
    rgba[..., 1, :, 3] = 255  # ... and an opaque one
    return rgba


def test_uint8_numpy_is_the_float32_formula_rounded_half_to_even():
    rgba = _rgba()
    for background in [(255, 255, 255), (0, 51, 240)]:
        alpha = rgba[..., 3:4].astype(np.float32) / 255.0
        bg = np.asarray(background, dtype=np.float32)
        expected = np.rint(rgba[..., :3].astype(np.float32) * alpha + bg * (1.0 - alpha)).astype(np.uint8)
        got = alpha_composite(rgba, background)
        assert got.dtype == np.uint8 and np.array_equal(got, expected)
    white = alpha_composite(rgba)
    assert np.array_equal(white, alpha_composite(rgba, 255))
    assert np.array_equal(white[..., 0, :, :], np.full_like(white[..., 0, :, :], 255))  # transparent: background
    assert np.array_equal(white[..., 1, :, :], rgba[..., 1, :, :3])  # opaque: the image


def test_uint8_tensor_equals_uint8_numpy():
    rgba = _rgba()
    got = alpha_composite(torch.from_numpy(rgba), (0, 51, 240))
    assert got.dtype == torch.uint8
    assert np.array_equal(got.numpy(), alpha_composite(rgba, (0, 51, 240)))
    first = alpha_composite(torch.from_numpy(rgba).permute(0, 3, 1, 2), (0, 51, 240), channels_first=True)
    assert torch.equal(first.permute(0, 2, 3, 1), got)


def test_float_input_blends_in_its_dtype_unrounded():
    x = torch.from_numpy(_rgba()).float() / 255.0
    bg = torch.tensor([0.1, 0.2, 0.3])
    expected = x[..., :3] * x[..., 3:] + bg * (1.0 - x[..., 3:])
    assert torch.equal(alpha_composite(x, bg), expected)
    assert np.array_equal(alpha_composite(x.numpy(), bg.numpy()), expected.numpy())
    assert alpha_composite(x.double(), bg).dtype == torch.float64
    on_white = x[..., :3] * x[..., 3:] + (1.0 - x[..., 3:])
    assert torch.equal(alpha_composite(x), on_white)


def test_background_images_and_one_colour_per_image():
    x = torch.from_numpy(_rgba()).float() / 255.0  # (2, 5, 7, 4)
    images = torch.rand(2, 5, 7, 3)
    assert torch.equal(alpha_composite(x, images), x[..., :3] * x[..., 3:] + images * (1.0 - x[..., 3:]))
    colours = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    per_image = alpha_composite(x, colours)
    for i in range(2):
        assert torch.equal(per_image[i], alpha_composite(x[i], colours[i]))


def test_channels_first_blends_with_straight_alpha():
    rgba = torch.tensor([[1.0, 0.0, 0.2], [0.0, 0.0, 0.4], [0.0, 1.0, 0.6], [1.0, 0.0, 0.5]]).view(4, 1, 3)
    out = alpha_composite(rgba, (0.2, 0.4, 1.0), channels_first=True)
    assert out.shape == (3, 1, 3)
    assert out[:, 0, 0].tolist() == [1.0, 0.0, 0.0]  # opaque: the image
    assert torch.allclose(out[:, 0, 1], torch.tensor([0.2, 0.4, 1.0]))  # transparent: the background
    assert torch.allclose(out[:, 0, 2], 0.5 * torch.tensor([0.2, 0.4, 0.6]) + 0.5 * torch.tensor([0.2, 0.4, 1.0]))
    per_image = alpha_composite(
        torch.zeros(2, 4, 1, 1), torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]), channels_first=True
    )
    assert torch.allclose(per_image[:, :, 0, 0], torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]))
    with pytest.raises(ValueError, match=r"`rgba` must be \(\.\.\., 4, H, W\), got shape \(3, 1, 3\)"):
        alpha_composite(out, (0.0, 0.0, 0.0), channels_first=True)
    with pytest.raises(ValueError, match=r"`background` must be \(\.\.\., 3\) RGB"):
        alpha_composite(rgba, (0.0, 0.0), channels_first=True)


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"`rgba` must be \(\.\.\., H, W, 4\), got shape \(2, 2, 3\)"):
        alpha_composite(np.zeros((2, 2, 3), dtype=np.uint8))
    with pytest.raises(TypeError, match="`rgba` must be a numpy array or torch tensor, got list"):
        alpha_composite([[[0, 0, 0, 0]]])
    with pytest.raises(TypeError, match="`rgba` must hold uint8 or floating-point values, got int64"):
        alpha_composite(np.zeros((1, 1, 4), dtype=np.int64))
    with pytest.raises(ValueError, match=r"`background` must be \(\.\.\., 3\) RGB colours, .* got shape \(2, 2, 2\)"):
        alpha_composite(np.zeros((2, 2, 4), dtype=np.uint8), np.zeros((2, 2, 2)))

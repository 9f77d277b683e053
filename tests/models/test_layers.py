"""The fast layers compute what the layers they replace compute, and old checkpoints load into the models."""

from __future__ import annotations

import copy

import pytest
import torch
from helpers import one_thread
from torch import nn

from lightning_vtr.models import LRGT, Pix2VoxPlusPlus
from lightning_vtr.models import layers as layers_module
from lightning_vtr.models import lrgt_decoder as lrgt_decoder_module
from lightning_vtr.models import pix2vox as pix2vox_module
from lightning_vtr.models.layers import VolumeHead, VolumeHeadTransposed, channels_last_3d

_one_thread = pytest.fixture(autouse=True)(one_thread)


def _outputs_and_grads(layer: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    x = x.clone().requires_grad_(True)
    y = layer(x)
    weights = torch.randn(y.shape, generator=torch.Generator().manual_seed(1))
    (y * weights).sum().backward()
    return y.detach(), x.grad, layer.weight.grad


@pytest.mark.parametrize(
    ("head_class", "plain_class", "channels"),
    [(VolumeHead, nn.Conv3d, c) for c in (1, 4, 8)] + [(VolumeHeadTransposed, nn.ConvTranspose3d, c) for c in (1, 3)],
)
def test_a_volume_head_equals_the_one_output_1x1x1_layer_it_replaces(head_class, plain_class, channels):
    torch.manual_seed(0)
    head = head_class(channels)
    plain = plain_class(channels, 1, 1, bias=False)
    plain.weight.data.copy_(head.weight.data)
    x = torch.randn(3, channels, 5, 6, 7)
    for got, expected in zip(_outputs_and_grads(head, x), _outputs_and_grads(plain, x)):
        assert got.shape == expected.shape
        torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


def test_channels_last_3d_keeps_values_and_changes_only_the_layout():
    x = torch.randn(2, 3, 4, 5, 6)
    y = channels_last_3d(x)
    assert torch.equal(x, y)
    assert y.is_contiguous(memory_format=torch.channels_last_3d) and not x.is_contiguous(
        memory_format=torch.channels_last_3d
    )
    assert channels_last_3d(y) is y  # no copy when already in the layout


# ------------------------------------------------------------------------------ whole models, old layout
def _reference(model: nn.Module, monkeypatch: pytest.MonkeyPatch) -> nn.Module:
    """``model`` as the previous release computed it: plain 1^3 heads, default layout everywhere."""
    reference = copy.deepcopy(model)
    for module in list(reference.modules()):
        for child_name, child in list(module.named_children()):
            if isinstance(child, VolumeHead):
                plain = nn.Conv3d(child.in_channels, 1, 1, bias=False)
            elif isinstance(child, VolumeHeadTransposed):
                plain = nn.ConvTranspose3d(child.in_channels, 1, 1, bias=False)
            else:
                continue
            plain = plain.to(child.weight.dtype)
            plain.weight.data.copy_(child.weight.data)
            setattr(module, child_name, plain)
    with torch.no_grad():
        for p in reference.parameters():
            p.data = p.data.contiguous()
    for module in (layers_module, pix2vox_module, lrgt_decoder_module):
        if hasattr(module, "channels_last_3d"):
            monkeypatch.setattr(module, "channels_last_3d", lambda x: x)
    return reference


def _train_step_results(model: nn.Module, images: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    model.train()
    model.zero_grad()
    outputs = model(images)
    loss = model.loss(outputs, target)
    loss.backward()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    model.eval()
    with torch.no_grad():
        predicted = model.predict_voxels(images)
    return {"loss": loss.detach(), "voxels": outputs["voxels"].detach(), "predicted": predicted, **grads}


@pytest.mark.parametrize("factory", [lambda: Pix2VoxPlusPlus(preset="tiny"), lambda: LRGT(preset="tiny")])
def test_a_training_step_equals_the_previous_layout(factory, monkeypatch):
    # In float64, so that float32 rounding (which the layouts' different summation orders change, and which grows
    # through BatchNorm's batch statistics) cannot hide a real difference or pass for one.
    torch.manual_seed(0)
    model = factory().double()
    generator = torch.Generator().manual_seed(0)
    images = torch.randn(2, 3, 3, model.image_size, model.image_size, generator=generator, dtype=torch.float64)
    target = (torch.rand(2, 32, 32, 32, generator=generator) > 0.7).double()
    before = copy.deepcopy(model)  # before the step updates BatchNorm's running statistics
    got = _train_step_results(model, images, target)
    expected = _train_step_results(_reference(before, monkeypatch), images, target)
    assert got.keys() == expected.keys() and len(got) > 20
    largest = max(g.abs().max().item() for g in expected.values())
    for key in got:
        torch.testing.assert_close(
            got[key], expected[key], atol=1e-9 * largest, rtol=1e-6, msg=lambda m, key=key: f"{key}: {m}"
        )


@pytest.mark.parametrize("factory", [lambda: Pix2VoxPlusPlus(preset="tiny"), lambda: LRGT(preset="tiny")])
def test_a_state_dict_saved_in_the_default_layout_loads_strictly_and_predicts_the_same(factory, tmp_path):
    torch.manual_seed(0)
    trained = factory().eval()
    # what a checkpoint of the previous release holds: the same names and shapes, default-layout tensors
    old_state = {key: value.contiguous() for key, value in trained.state_dict().items()}
    torch.save(old_state, tmp_path / "old.pt")
    torch.manual_seed(1)
    restored = factory().eval()
    restored.load_state_dict(torch.load(tmp_path / "old.pt"), strict=True)
    images = torch.randn(2, 4, 3, trained.image_size, trained.image_size)
    with torch.no_grad():
        torch.testing.assert_close(restored.predict_voxels(images), trained.predict_voxels(images), atol=1e-6, rtol=0)
    # the restored 3-D weights keep the fast layout
    five_d = [p for p in restored.parameters() if p.ndim == 5 and p.shape[1] > 1 and p.shape[2] > 1]
    assert five_d and all(p.is_contiguous(memory_format=torch.channels_last_3d) for p in five_d)

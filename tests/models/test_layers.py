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
from lightning_vtr.models.layers import BatchNorm3d, VolumeHead, VolumeHeadTransposed, channels_last_3d

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
    expected_values = _outputs_and_grads(plain, x)
    for layout in (x, channels_last_3d(x)):  # a broadcast product and sum, or a contraction
        head.zero_grad()
        for got, expected in zip(_outputs_and_grads(head, layout), expected_values):
            assert got.shape == expected.shape
            torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("channels", "momentum"), [(4, 0.1), (5, None), (16, 0.3)])
def test_batch_norm_equals_torch_batch_norm_in_training_and_evaluation(channels, momentum):
    torch.manual_seed(0)
    fast, plain = BatchNorm3d(channels, momentum=momentum), nn.BatchNorm3d(channels, momentum=momentum)
    with torch.no_grad():
        for layer in (fast, plain):
            layer.weight.copy_(torch.linspace(0.5, 2.0, channels))
            layer.bias.copy_(torch.linspace(-1.0, 1.0, channels))
    assert fast.state_dict().keys() == plain.state_dict().keys()
    generator = torch.Generator().manual_seed(0)
    for step in range(2):  # the second step moves the running statistics again (a cumulative mean if momentum=None)
        x = channels_last_3d(3 * torch.randn(4, channels, 6, 7, 8, generator=generator) + step)
        got = _outputs_and_grads(fast, x)
        expected = _outputs_and_grads(plain, x.contiguous())  # torch's exact kernel on the default layout
        for g, e in zip(got, expected):
            torch.testing.assert_close(g, e, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(fast.bias.grad, plain.bias.grad, atol=1e-5, rtol=1e-5)
        for name in ("running_mean", "running_var", "num_batches_tracked"):
            torch.testing.assert_close(getattr(fast, name), getattr(plain, name), atol=1e-5, rtol=1e-5)
        fast.zero_grad(), plain.zero_grad()
    assert plain.num_batches_tracked.item() == 2 and not torch.equal(plain.running_mean, torch.zeros(channels))
    fast.eval(), plain.eval()
    x = channels_last_3d(torch.randn(2, channels, 5, 5, 5, generator=generator))
    with torch.no_grad():
        torch.testing.assert_close(fast(x), plain(x.contiguous()), atol=1e-6, rtol=1e-6)


def test_batch_norm_gives_few_channel_volumes_in_the_default_layout_and_keeps_others_as_they_are():
    few, many = channels_last_3d(torch.randn(2, 4, 3, 3, 3)), channels_last_3d(torch.randn(2, 8, 3, 3, 3))
    assert BatchNorm3d(4)(few).is_contiguous()
    assert BatchNorm3d(8)(many).is_contiguous(memory_format=torch.channels_last_3d)


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
    """``model`` as the previous release computed it: plain 1^3 heads and BatchNorm, default layout everywhere."""
    reference = copy.deepcopy(model)
    for module in list(reference.modules()):
        for child_name, child in list(module.named_children()):
            if isinstance(child, BatchNorm3d):
                plain = nn.BatchNorm3d(child.num_features, child.eps, child.momentum)
                plain.load_state_dict(child.state_dict())
            elif isinstance(child, VolumeHead):
                plain = nn.Conv3d(child.in_channels, 1, 1, bias=False)
            elif isinstance(child, VolumeHeadTransposed):
                plain = nn.ConvTranspose3d(child.in_channels, 1, 1, bias=False)
            else:
                continue
            plain = plain.to(child.weight.dtype)
            plain.load_state_dict(child.state_dict())
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


@pytest.mark.parametrize("stride", [1, 2])
def test_the_merger_equals_scoring_the_joined_raw_volumes(stride):
    # The merger pools features and volumes apart and joins them after; before, the decoder joined them into one
    # raw tensor (features, then the volume as the last channel) that the merger pooled and sliced.
    torch.manual_seed(0)
    merger = pix2vox_module._ContextAwareMerger(5, stride).double().train()
    before = copy.deepcopy(merger)
    features, volumes = torch.randn(6, 4, 8, 8, 8).double(), torch.rand(2, 3, 8, 8, 8).double()
    got = merger(features, volumes)
    raw = torch.cat([features, volumes.flatten(0, 1).unsqueeze(1)], dim=1)
    x = torch.nn.functional.avg_pool3d(raw, stride) if stride > 1 else raw
    stages = []
    for layer in before.context:
        x = layer(x)
        stages.append(x)
    scores = before.score(torch.cat(stages, dim=1))
    if stride > 1:
        scores = torch.nn.functional.interpolate(scores, scale_factor=stride, mode="nearest")
    weights = torch.softmax(scores.view(2, 3, 8, 8, 8), dim=1)
    expected = (raw.view(2, 3, 5, 8, 8, 8)[:, :, -1] * weights).sum(dim=1).clamp(0, 1)
    torch.testing.assert_close(got, expected, atol=1e-12, rtol=1e-12)
    assert got.min() > 0 and got.max() < 1 and got.std() > 0.01

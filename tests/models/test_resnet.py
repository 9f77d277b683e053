"""ResNet-50 stem: torchvision key layout, loading from a local file, a hand-computed value."""

from __future__ import annotations

import pytest
import torch

from lightning_vtr.models.resnet import ResNet50Stem, load_torchvision_resnet50


def _torchvision_resnet50_shapes() -> dict[str, tuple[int, ...]]:
    """Keys and shapes of torchvision's ``resnet50().state_dict()``, written out from the architecture."""
    shapes: dict[str, tuple[int, ...]] = {}

    def bn(prefix: str, c: int) -> None:
        for name in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{name}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    shapes["conv1.weight"] = (64, 3, 7, 7)
    bn("bn1", 64)
    in_c = 64
    for layer, (planes, blocks) in enumerate([(64, 3), (128, 4), (256, 6), (512, 3)], start=1):
        for b in range(blocks):
            p = f"layer{layer}.{b}"
            shapes[f"{p}.conv1.weight"] = (planes, in_c, 1, 1)
            bn(f"{p}.bn1", planes)
            shapes[f"{p}.conv2.weight"] = (planes, planes, 3, 3)
            bn(f"{p}.bn2", planes)
            shapes[f"{p}.conv3.weight"] = (planes * 4, planes, 1, 1)
            bn(f"{p}.bn3", planes * 4)
            if b == 0:
                shapes[f"{p}.downsample.0.weight"] = (planes * 4, in_c, 1, 1)
                bn(f"{p}.downsample.1", planes * 4)
            in_c = planes * 4
    shapes["fc.weight"] = (1000, 2048)
    shapes["fc.bias"] = (1000,)
    return shapes


def _random_state(shapes: dict[str, tuple[int, ...]]) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    return {
        k: torch.tensor(7) if k.endswith("num_batches_tracked") else torch.rand(s, generator=gen) + 0.5
        for k, s in shapes.items()
    }


def test_full_resnet50_state_dict_loads_from_file(tmp_path):
    state = _random_state(_torchvision_resnet50_shapes())
    assert len(state) == 320  # torchvision resnet50 has 320 state-dict entries
    path = tmp_path / "resnet50.pth"
    torch.save(state, path)
    module = ResNet50Stem()
    load_torchvision_resnet50(module, path)
    own = module.state_dict()
    assert set(own) == {k for k in state if not k.startswith(("layer3.", "layer4.", "fc."))}
    for k, v in own.items():
        torch.testing.assert_close(v, state[k])


def test_missing_and_unexpected_keys_are_listed():
    state = _random_state(_torchvision_resnet50_shapes())
    del state["layer2.3.bn3.weight"]
    state["layer2.9.conv1.weight"] = torch.zeros(1)
    with pytest.raises(
        ValueError, match=r"missing keys \['layer2.3.bn3.weight'\].*unexpected keys \['layer2.9.conv1.weight'\]"
    ):
        load_torchvision_resnet50(ResNet50Stem(), state)
    state = _random_state(_torchvision_resnet50_shapes())
    state["conv1.weight"] = torch.zeros(64, 3, 3, 3)
    with pytest.raises(ValueError, match=r"conv1.weight: expected \(64, 3, 7, 7\), found \(64, 3, 3, 3\)"):
        load_torchvision_resnet50(ResNet50Stem(), state)
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        load_torchvision_resnet50(ResNet50Stem(), "nope.pth")


def test_conv1_bn1_value_and_output_shape():
    module = ResNet50Stem().eval()
    with torch.no_grad():
        module.conv1.weight.zero_()
        module.conv1.weight[:, 0, 3, 3] = 2.0  # each filter reads the red pixel at its centre, x2
        module.bn1.running_mean.fill_(1.0)
        module.bn1.running_var.fill_(4.0 - module.bn1.eps)
        module.bn1.weight.fill_(3.0)
        module.bn1.bias.fill_(0.5)
    x = torch.zeros(1, 3, 8, 8)
    x[0, 0, 2, 4] = 1.5  # stride 2: lands on output pixel (1, 2)
    y = module.bn1(module.conv1(x))
    # (2 * 1.5 - 1) / sqrt(4) * 3 + 0.5 = 3.5 there; elsewhere (0 - 1) / 2 * 3 + 0.5 = -1.
    assert y[0, :, 1, 2].eq(3.5).all()
    y[0, :, 1, 2] = -1.0
    torch.testing.assert_close(y, torch.full_like(y, -1.0))
    assert module(torch.zeros(2, 3, 224, 224)).shape == (2, 512, 28, 28)


def test_loads_from_a_file_url_through_the_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    state = _random_state(_torchvision_resnet50_shapes())
    path = tmp_path / "served" / "resnet50.pth"
    path.parent.mkdir()
    torch.save(state, path)
    module = ResNet50Stem()
    load_torchvision_resnet50(module, path.as_uri(), progress=False)
    assert (tmp_path / "home" / "hub" / "checkpoints" / "resnet50.pth").is_file()
    torch.testing.assert_close(module.layer2[3].bn3.weight.detach(), state["layer2.3.bn3.weight"])

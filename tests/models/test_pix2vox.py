"""Pix2Vox++: presets, any view count, input errors, checkpoints (ours, portable, released), recipe, overfitting."""

from __future__ import annotations

import math

import lightning as L
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import one_thread
from torch import nn
from torch.utils.data import DataLoader

from lightning_vtr.metrics import voxel_iou
from lightning_vtr.models.layers import channels_last_3d
from lightning_vtr.models.pix2vox import PIX2VOX_PRESETS, Pix2VoxPlusPlus, _Decoder
from lightning_vtr.models.resnet import ResNet50Stem
from lightning_vtr.protocol import ReconstructionModel

R = 32

# One torch thread for the 120-epoch overfitting run: its tensors are tiny, and on the shared 2-core test machine
# a second intra-op thread only adds contention (about 3x slower under load).
_one_thread = pytest.fixture(name="_one_thread")(one_thread)


@pytest.fixture(scope="module")
def tiny() -> Pix2VoxPlusPlus:
    torch.manual_seed(0)
    return Pix2VoxPlusPlus(preset="tiny").eval()


def test_paper_preset_parameter_count_and_output_shape():
    model = Pix2VoxPlusPlus(preset="paper").eval()
    n_params = sum(p.numel() for p in model.parameters())
    assert abs(n_params - 96.3e6) / 96.3e6 < 0.02
    assert (model.image_size, model.num_views, model.voxel_resolution) == (224, 3, 32)
    with torch.no_grad():
        out = model(torch.randn(1, 3, 3, 224, 224))
    assert out["voxels"].shape == (1, R, R, R) and out["view_voxels"].shape == (1, 3, R, R, R)
    assert out["voxels"].min() >= 0 and out["voxels"].max() <= 1


@pytest.mark.parametrize("views", [1, 5])
def test_any_number_of_views(tiny, views):
    assert isinstance(tiny, ReconstructionModel)
    with torch.no_grad():
        out = tiny(torch.randn(2, views, 3, 64, 64))
        probs = out["voxels"]
    assert probs.shape == (2, R, R, R) and out["view_voxels"].shape == (2, views, R, R, R)
    assert probs.min() >= 0 and probs.max() <= 1
    if views == 1:
        # One view: the softmax over views gives it weight 1, so the merged volume is that view's.
        torch.testing.assert_close(out["coarse_voxels"], out["view_voxels"][:, 0])


def test_merger_is_view_order_invariant(tiny):
    images = torch.randn(1, 3, 3, 64, 64)
    with torch.no_grad():
        a = tiny.predict_voxels(images)
        b = tiny.predict_voxels(images[:, [2, 0, 1]])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(
    ("images", "match"),
    [
        (torch.zeros(1, 3, 3, 224, 224), r"64x64 pixels.*got 224x224"),
        (torch.zeros(1, 3, 1, 64, 64), r"3 \(RGB\) channels.*got 1"),
        (torch.zeros(3, 3, 64, 64), r"\(B, V, 3, 64, 64\)"),
        (torch.full((1, 3, 3, 64, 64), float("inf")), "NaN or infinite"),
    ],
)
def test_bad_inputs(tiny, images, match):
    with pytest.raises(ValueError, match=match):
        tiny.predict_voxels(images)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"`preset` must be one of 'paper', 'tiny', got 'huge'"):
        Pix2VoxPlusPlus(preset="huge")
    with pytest.raises(ValueError, match="`backbone_weights` must be None for preset 'tiny'"):
        Pix2VoxPlusPlus(preset="tiny", backbone_weights="resnet50.pth")


def test_model_keeps_its_preset_spec(tiny):
    assert tiny.spec is PIX2VOX_PRESETS["tiny"]
    assert (tiny.spec.image_size, tiny.spec.backbone, tiny.spec.merger_stride, tiny.spec.feature_size) == (
        64,
        "small",
        4,
        4,
    )
    assert tiny.hparams.merger_stride == tiny.merger.stride == 4


def test_merger_stride_is_a_hyperparameter_and_old_checkpoints_keep_theirs(tmp_path):
    torch.manual_seed(0)
    old = Pix2VoxPlusPlus(preset="tiny", merger_stride=2).eval()  # what "tiny" was until 0.3
    assert (old.spec.merger_stride, old.merger.stride, old.hparams.merger_stride) == (2, 2, 2)
    x = torch.randn(2, 3, 3, 64, 64)
    with torch.no_grad():
        expected = old.predict_voxels(x)
    # A checkpoint written before 0.4 has no `merger_stride` hyperparameter: it is read with the stride of its
    # time, 2, not the preset's present 4, and predicts what it did.
    hparams = {k: v for k, v in old.hparams.items() if k != "merger_stride"}
    path = tmp_path / "tiny_0.3.ckpt"
    torch.save(
        {"state_dict": old.state_dict(), "hyper_parameters": hparams, "pytorch-lightning_version": "2.5.0"}, path
    )
    restored = Pix2VoxPlusPlus.load_from_checkpoint(path).eval()
    assert (restored.merger.stride, restored.hparams.merger_stride, restored.spec.merger_stride) == (2, 2, 2)
    with torch.no_grad():
        torch.testing.assert_close(restored.predict_voxels(x), expected, rtol=0, atol=0)
    # The stride matters: the same weights scored on the present tiny grid fuse the views differently.
    features, volumes = torch.randn(2 * 3, 4, R, R, R), torch.rand(2, 3, R, R, R)
    with torch.no_grad():
        on_16 = restored.merger(channels_last_3d(features), volumes)
        restored._set_merger_stride(4)
        on_8 = restored.merger(channels_last_3d(features), volumes)
    assert restored.hparams.merger_stride == 4 and (on_8 - on_16).abs().max() > 1e-3
    # A checkpoint that records its stride keeps it too.
    path = tmp_path / "tiny_stride_8.ckpt"
    wide = Pix2VoxPlusPlus(preset="tiny", merger_stride=8)
    torch.save(
        {"state_dict": wide.state_dict(), "hyper_parameters": dict(wide.hparams), "pytorch-lightning_version": "2.5.0"},
        path,
    )
    assert Pix2VoxPlusPlus.load_from_checkpoint(path).merger.stride == 8
    # An override wins over the checkpoint's stride, for old and new checkpoints alike ...
    assert Pix2VoxPlusPlus.load_from_checkpoint(path, merger_stride=4).merger.stride == 4
    assert Pix2VoxPlusPlus.load_from_checkpoint(tmp_path / "tiny_0.3.ckpt", merger_stride=4).merger.stride == 4
    # ... and resuming a fit into a model built with the default brings the checkpoint's (the hook a Trainer calls).
    resumed = Pix2VoxPlusPlus(preset="tiny")
    resumed.on_load_checkpoint(torch.load(path, weights_only=False))
    assert (resumed.merger.stride, resumed.hparams.merger_stride) == (8, 8)


@pytest.mark.parametrize(
    ("stride", "error", "match"),
    [
        (3, ValueError, "divide the volume side 32, got 3"),
        (0, ValueError, "merger_stride"),
        (2.0, TypeError, "must be an int"),
    ],
)
def test_bad_merger_stride(stride, error, match):
    with pytest.raises(error, match=match):
        Pix2VoxPlusPlus(preset="tiny", merger_stride=stride)


def test_checkpoint_from_another_preset_errors(tiny, tmp_path):
    path = tmp_path / "paper.ckpt"
    torch.save(
        {
            "state_dict": tiny.state_dict(),
            "hyper_parameters": {**tiny.hparams, "preset": "paper"},
            "pix2vox_preset": "paper",
            "pytorch-lightning_version": L.__version__,
        },
        path,
    )
    with pytest.raises(ValueError, match="preset 'paper'; this model has preset 'tiny'"):
        Pix2VoxPlusPlus.load_from_checkpoint(path, preset="tiny")
    # Resuming a Trainer (or any caller of the hook) with a checkpoint of another preset.
    with pytest.raises(ValueError, match="preset 'paper'.*expected 'tiny'"):
        tiny.on_load_checkpoint({"hyper_parameters": {"preset": "paper"}})


def test_checkpoint_roundtrip_same_preset(tiny, tmp_path):
    path = tmp_path / "tiny.ckpt"
    torch.save(
        {
            "state_dict": tiny.state_dict(),
            "hyper_parameters": dict(tiny.hparams),
            "pytorch-lightning_version": L.__version__,
        },
        path,
    )
    loaded = Pix2VoxPlusPlus.load_from_checkpoint(path).eval()
    x = torch.randn(1, 3, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(loaded.predict_voxels(x), tiny.predict_voxels(x))


def _loss_case() -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor]:
    """Outputs, target, and the hand-computed BCE(refined) and 10 (BCE(coarse) + BCE(refined))."""
    target = torch.zeros(1, R, R, R)
    target[0, :16] = 1
    outputs = {"voxels": torch.full((1, R, R, R), 0.25), "coarse_voxels": torch.full((1, R, R, R), 0.5)}
    # Half the cells are occupied: BCE = (-log 0.25 - log 0.75) / 2 for the refined volume, log 2 for the coarse.
    refined = -(torch.log(torch.tensor(0.25)) + torch.log(torch.tensor(0.75))) / 2
    return outputs, target, refined, 10 * (torch.log(torch.tensor(2.0)) + refined)


def test_two_stage_loss_weighting():
    outputs, target, refined, two_stage = _loss_case()
    model = Pix2VoxPlusPlus(preset="tiny", two_stage_loss=True)
    torch.testing.assert_close(model.loss(outputs, target), two_stage)
    model.hparams.two_stage_loss = False
    torch.testing.assert_close(model.loss(outputs, target), refined)
    # The tiny preset keeps 0.1's default, BCE(refined).
    default = Pix2VoxPlusPlus(preset="tiny")
    assert default.hparams.two_stage_loss is False
    torch.testing.assert_close(default.loss(outputs, target), refined)


def test_optimizer_groups_follow_published_rates():
    model = Pix2VoxPlusPlus(preset="tiny", milestones=(3,), gamma=0.5)
    config = model.configure_optimizers()
    lrs = [g["lr"] for g in config["optimizer"].param_groups]
    assert lrs == [1e-3, 1e-3, 1e-4, 1e-3]  # encoder, decoder, merger, refiner
    scheduler = config["lr_scheduler"]["scheduler"]
    for _ in range(3):
        scheduler.step()
    assert [g["lr"] for g in config["optimizer"].param_groups] == pytest.approx([5e-4, 5e-4, 5e-5, 5e-4])


def _shapes() -> torch.Tensor:
    """Six simple solids on a 32^3 grid: cube, bar, sphere, L, cylinder, table."""
    g = torch.zeros(6, R, R, R)
    c = torch.arange(R) + 0.5 - R / 2
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    g[0, 8:24, 8:24, 8:24] = 1
    g[1, 4:28, 12:20, 6:14] = 1
    g[2] = (x**2 + y**2 + z**2 <= 100).float()
    g[3, 6:26, 6:12, 4:28] = 1
    g[3, 6:26, 6:26, 4:10] = 1
    g[4] = ((x**2 + y**2 <= 36) & (z.abs() < 12)).float()
    g[5, 2:30, 2:30, 2:6] = 1
    g[5, 12:20, 12:20, 6:26] = 1
    return g


@pytest.mark.slow
@pytest.mark.usefixtures("_one_thread")
def test_tiny_preset_overfits_a_handful_of_objects():
    torch.manual_seed(0)
    voxels = _shapes()
    # One view whose three channels are the silhouettes along x, y and z: they determine these shapes.
    silhouettes = torch.stack([voxels.amax(dim=d) for d in (1, 2, 3)], dim=1)
    images = (F.interpolate(silhouettes, size=(64, 64), mode="nearest") * 2 - 1).unsqueeze(1)
    batch = {"images": images, "voxels": voxels, "category": ["shape"] * 6, "object_id": list("abcdef")}
    model = Pix2VoxPlusPlus(preset="tiny", num_views=1, lr=5e-3, merger_lr=5e-3, validation_fscore=False)
    trainer = L.Trainer(
        max_epochs=120, logger=False, enable_progress_bar=False, enable_checkpointing=False, enable_model_summary=False
    )
    trainer.fit(model, DataLoader([batch], batch_size=None))
    model.eval()
    with torch.no_grad():
        iou = voxel_iou(model.predict_voxels(images), voxels, thresholds=(0.4,))
    assert iou.min() >= 0.9, iou.squeeze(1).tolist()


# ---------------------------------------------------------------------- the Pix2Vox++ recipe (paper preset)
def _stem_weights() -> dict[str, torch.Tensor]:
    """A torchvision-layout ResNet-50 state dict up to layer2 with values no initialisation produces."""
    gen = torch.Generator().manual_seed(1)
    return {
        k: torch.tensor(7) if k.endswith("num_batches_tracked") else torch.rand(v.shape, generator=gen) + 0.5
        for k, v in ResNet50Stem().state_dict().items()
    }


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """A fresh paper-preset model built from a weight file: (model, weight file, its state dict)."""
    path = tmp_path_factory.mktemp("weights") / "resnet50.pth"
    weights = _stem_weights()
    torch.save(weights, path)
    torch.manual_seed(0)
    return Pix2VoxPlusPlus(preset="paper", backbone_weights=str(path)), path, weights


def _non_backbone(model: Pix2VoxPlusPlus) -> list[nn.Module]:
    modules = [model.encoder.layer1, model.encoder.layer2, model.encoder.layer3]
    return [m for top in (*modules, model.decoder, model.merger, model.refiner) for m in top.modules()]


def test_paper_preset_uses_the_reference_initialisation_and_keeps_the_backbone(paper):
    model, _, weights = paper
    assert model.hparams.init == "reference" and PIX2VOX_PRESETS["paper"].init == "reference"
    for k, v in model.encoder.backbone.state_dict().items():
        assert torch.equal(v, weights[k]), k  # loaded, then left alone by the initialisation
    layers = _non_backbone(model)
    norms = [m for m in layers if isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d))]
    assert len(norms) == 3 + 4 + 6 + 5  # encoder, decoder, merger, refiner (up3 has none)
    assert all(m.weight.eq(1).all() and m.bias.eq(0).all() for m in norms)
    biases = [m.bias for m in layers if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.Linear)) and m.bias is not None]
    assert len(biases) == 3 + 6 + 3 + 2 and all(b.eq(0).all() for b in biases)
    # Kaiming-normal, fan_in: std sqrt(2 / fan_in); PyTorch's default would give 1 / sqrt(3 fan_in).
    for weight, fan_in, tol in [
        (model.encoder.layer1[0].weight, 512 * 9, 0.02),
        (model.decoder.layers[0][0].weight, 512 * 64, 0.02),  # ConvTranspose3d: fan_in from dim 1 (outputs)
        (model.merger.context[0][0].weight, 9 * 27, 0.1),
        (model.refiner.down3[0].weight, 64 * 64, 0.02),
    ]:
        assert weight.std().item() == pytest.approx(math.sqrt(2 / fan_in), rel=tol)
        assert abs(weight.mean().item()) < 0.05 * math.sqrt(2 / fan_in)
    for linear in (model.refiner.fc[0], model.refiner.fc[2]):
        assert linear.weight.std().item() == pytest.approx(0.01, rel=0.01)


def test_volume_head_is_initialised_as_the_released_transposed_convolution():
    decoder = _Decoder(8, (4096,))
    torch.manual_seed(0)
    decoder.reference_init_()
    # Released: ConvTranspose3d(4096, 1, 1), Kaiming fan_in = 1 output channel -> std sqrt(2), not sqrt(2 / 4096).
    assert decoder.to_volume.weight.std().item() == pytest.approx(math.sqrt(2), rel=0.05)


def test_tiny_preset_keeps_torch_initialisation_unless_asked():
    assert (PIX2VOX_PRESETS["tiny"].init, PIX2VOX_PRESETS["tiny"].two_stage_loss) == ("torch", False)
    torch.manual_seed(0)
    default = Pix2VoxPlusPlus(preset="tiny")
    assert default.hparams.init == "torch"
    assert default.encoder.layer1[0].bias.abs().sum() > 0  # PyTorch's default biases are uniform, not 0
    reference = Pix2VoxPlusPlus(preset="tiny", init="reference")
    for conv in (reference.encoder.backbone[0], reference.encoder.layer1[0], reference.merger.score[1][0]):
        assert conv.bias.eq(0).all()  # the small backbone is not pretrained: it is initialised too
    assert reference.refiner.fc[0].weight.std().item() == pytest.approx(0.01, rel=0.05)
    with pytest.raises(ValueError, match=r"`init` must be one of 'reference', 'torch', got 'xavier'"):
        Pix2VoxPlusPlus(preset="tiny", init="xavier")


def test_backbone_trains_by_default_and_can_be_frozen(paper):
    model, _, _ = paper
    backbone = list(model.encoder.backbone.parameters())
    assert model.hparams.freeze_backbone is False and all(p.requires_grad for p in backbone)
    encoder_group = model.configure_optimizers()["optimizer"].param_groups[0]["params"]
    assert {id(p) for p in backbone} <= {id(p) for p in encoder_group}

    frozen = Pix2VoxPlusPlus(preset="tiny", freeze_backbone=True)
    assert not any(p.requires_grad for p in frozen.encoder.backbone.parameters())
    assert all(p.requires_grad for p in frozen.encoder.layer1.parameters())
    trained = {id(p) for g in frozen.configure_optimizers()["optimizer"].param_groups for p in g["params"]}
    assert not trained & {id(p) for p in frozen.encoder.backbone.parameters()}
    # 0.1's `None` (freeze exactly when weights are given) still works, with a warning.
    with pytest.warns(DeprecationWarning, match="freeze_backbone=None"):
        legacy = Pix2VoxPlusPlus(preset="tiny", freeze_backbone=None)
    assert legacy.hparams.freeze_backbone is False and all(p.requires_grad for p in legacy.parameters())


def test_paper_preset_pretrains_with_the_two_stage_loss(paper):
    model, _, _ = paper
    outputs, target, _refined, two_stage = _loss_case()
    assert model.hparams.two_stage_loss is True
    torch.testing.assert_close(model.loss(outputs, target), two_stage)


def test_loss_runs_in_float32_under_autocast(tiny, monkeypatch):
    calls = []
    bce = F.binary_cross_entropy

    def spy(input, target, *args, **kwargs):
        # CUDA autocast refuses BCE; CPU autocast would quietly upcast, so check what the loss hands it.
        calls.append((torch.is_autocast_enabled("cpu"), input.dtype, target.dtype))
        return bce(input, target, *args, **kwargs)

    torch.manual_seed(0)
    target = (torch.rand(1, R, R, R) > 0.6).float()
    monkeypatch.setattr(F, "binary_cross_entropy", spy)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outputs = tiny(torch.randn(1, 2, 3, 64, 64))
        losses = {}
        for two_stage in (False, True):
            tiny.hparams.two_stage_loss = two_stage
            losses[two_stage] = tiny.loss(outputs, target)
    tiny.hparams.two_stage_loss = False
    assert calls == [(False, torch.float32, torch.float32)] * 3  # refined; refined and coarse
    monkeypatch.undo()
    assert outputs["voxels"].dtype == torch.bfloat16  # the network did run in bfloat16
    refined = F.binary_cross_entropy(outputs["voxels"].float(), target)
    coarse = F.binary_cross_entropy(outputs["coarse_voxels"].float(), target)
    assert losses[False].dtype == losses[True].dtype == torch.float32
    assert torch.equal(losses[False], refined)
    assert torch.equal(losses[True], 10 * (coarse + refined))


def test_checkpoint_loads_without_the_backbone_weight_file(paper, tmp_path):
    model, weights_path, _ = paper
    ckpt = tmp_path / "paper.ckpt"
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": dict(model.hparams),
            "pix2vox_preset": "paper",
            "pytorch-lightning_version": L.__version__,
        },
        ckpt,
    )
    weights_path.unlink()  # another machine: the checkpoint travelled, the weight file did not
    with pytest.raises(FileNotFoundError, match="resnet50.pth"):
        Pix2VoxPlusPlus(preset="paper", backbone_weights=str(weights_path))  # building from the file needs it

    loaded = Pix2VoxPlusPlus.load_from_checkpoint(ckpt)
    assert loaded.hparams.backbone_weights == str(weights_path)  # kept for the record
    own = model.state_dict()
    assert all(torch.equal(v, own[k]) for k, v in loaded.state_dict().items())
    assert all(p.requires_grad for p in loaded.parameters())
    # A 0.1 checkpoint recorded freeze_backbone=None: its backbone stays frozen, as it was trained.
    with pytest.warns(DeprecationWarning, match="freeze_backbone=None"):
        legacy = Pix2VoxPlusPlus.load_from_checkpoint(ckpt, freeze_backbone=None)
    assert not any(p.requires_grad for p in legacy.encoder.backbone.parameters())


# ---------------------------------------------------------------------- released checkpoints
# Our names -> the released ones, written out from the reference model definitions.
_RELEASED_TINY_BACKBONE = {f"backbone.{i}.": f"resnet.{i}." for i in (0, 1, 3, 4)}
_RELEASED_RESNET = {"backbone.conv1.": "resnet.0.", "backbone.bn1.": "resnet.1.", "backbone.layer1.": "resnet.4."}
_RELEASED_RESNET["backbone.layer2."] = "resnet.5."
_RELEASED = {
    "encoder": {"layer1.": "layer1.", "layer2.": "layer2.", "layer3.": "layer3."},
    "decoder": {"layers.0.": "layer1.", "layers.1.": "layer2.", "layers.2.": "layer3.", "layers.3.": "layer4."},
    "merger": {
        **{f"context.{i}.": f"layer{i + 1}." for i in range(4)},
        "score.0.": "layer5.",
        "score.1.": "layer6.",
    },
    "refiner": {
        "down1.": "layer1.",
        "down2.": "layer2.",
        "down3.": "layer3.",
        "fc.0.": "layer4.0.",
        "fc.2.": "layer5.0.",
        "up1.": "layer6.",
        "up2.": "layer7.",
        "up3.": "layer8.",
    },
}


def _released(model: Pix2VoxPlusPlus, backbone: dict[str, str]) -> dict[str, object]:
    """``model``'s weights in the released layout, as DataParallel saved them, with the solver entries."""
    out: dict[str, object] = {"epoch_idx": 250, "best_iou": np.float64(0.7128), "best_epoch": 231}
    for part in ("encoder", "decoder", "merger", "refiner"):
        table = {**backbone, **_RELEASED["encoder"]} if part == "encoder" else _RELEASED[part]
        released = {}
        for key, value in getattr(model, part).state_dict().items():
            if part == "decoder" and key == "to_volume.weight":
                released["module.layer5.0.weight"] = value.transpose(0, 1).clone()  # ConvTranspose3d(C, 1, 1)
                continue
            ours = next(p for p in table if key.startswith(p))
            released["module." + table[ours] + key[len(ours) :]] = value.clone()
        out[f"{part}_state_dict"] = released
        out[f"{part}_solver_state_dict"] = {"state": {}, "param_groups": [{"lr": 1e-3, "params": [0, 1]}]}
    return out


def _perturbed_tiny(seed: int) -> Pix2VoxPlusPlus:
    torch.manual_seed(seed)
    model = Pix2VoxPlusPlus(preset="tiny")
    with torch.no_grad():
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point():  # BatchNorm weights and statistics away from 1 / 0 too
                tensor.copy_(torch.rand_like(tensor) + 0.1 if "running_var" in name else torch.randn_like(tensor))
    return model.eval()


def test_official_checkpoint_loads_into_the_tiny_preset(tmp_path):
    source = _perturbed_tiny(seed=1)
    path = tmp_path / "Pix2Vox++-A-ShapeNet.pth"
    torch.save(_released(source, _RELEASED_TINY_BACKBONE), path)
    loaded = Pix2VoxPlusPlus.from_official_checkpoint(path, preset="tiny", lr=5e-4).eval()
    assert loaded.hparams.lr == 5e-4
    own = source.state_dict()
    assert all(torch.equal(v, own[k]) for k, v in loaded.state_dict().items())
    images = torch.randn(2, 3, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(loaded.predict_voxels(images), source.predict_voxels(images))


def test_official_checkpoint_maps_the_released_paper_names(paper):
    model, weights_path, _ = paper
    released = _released(model, _RELEASED_RESNET)
    # Shapes from the reference definitions.
    encoder, decoder = released["encoder_state_dict"], released["decoder_state_dict"]
    assert encoder["module.resnet.5.3.bn3.weight"].shape == (512,)
    assert encoder["module.layer1.0.weight"].shape == (512, 512, 3, 3)
    assert decoder["module.layer1.0.weight"].shape == (1568, 512, 4, 4, 4)
    assert decoder["module.layer5.0.weight"].shape == (8, 1, 1, 1, 1)
    assert released["merger_state_dict"]["module.layer5.0.weight"].shape == (9, 36, 3, 3, 3)
    assert released["refiner_state_dict"]["module.layer4.0.weight"].shape == (2048, 8192)
    assert released["refiner_state_dict"]["module.layer8.0.weight"].shape == (32, 1, 4, 4, 4)
    # No torchvision weights are read for a released checkpoint, even when named.
    loaded = Pix2VoxPlusPlus.from_official_checkpoint(released, backbone_weights=str(weights_path) + ".absent")
    own = model.state_dict()
    assert loaded.preset == "paper"
    assert all(torch.equal(v, own[k]) for k, v in loaded.state_dict().items())


def test_official_checkpoint_errors_name_the_file_and_keys(tmp_path):
    released = _released(_perturbed_tiny(seed=2), _RELEASED_TINY_BACKBONE)
    path = tmp_path / "broken.pth"

    torch.save({k: v for k, v in released.items() if k != "merger_state_dict"}, path)
    with pytest.raises(
        ValueError, match=r"broken.pth is not a released Pix2Vox\+\+ checkpoint.*missing \['merger_state_dict'\]"
    ):
        Pix2VoxPlusPlus.from_official_checkpoint(path, preset="tiny")

    lightning_style = {"state_dict": {}, "hyper_parameters": {}}
    with pytest.raises(ValueError, match=r"found keys \['hyper_parameters', 'state_dict'\]"):
        Pix2VoxPlusPlus.from_official_checkpoint(lightning_style, preset="tiny")

    refiner = dict(released["refiner_state_dict"])
    del refiner["module.layer4.0.weight"]
    refiner["module.layer9.0.weight"] = torch.zeros(1)
    torch.save({**released, "refiner_state_dict": refiner}, path)
    with pytest.raises(
        ValueError, match=r"broken.pth: keys without a counterpart .*refiner_state_dict: module.layer9.0.weight"
    ):
        Pix2VoxPlusPlus.from_official_checkpoint(path, preset="tiny")
    del refiner["module.layer9.0.weight"]
    torch.save({**released, "refiner_state_dict": refiner}, path)
    with pytest.raises(ValueError, match=r"broken.pth does not match .*missing keys \['refiner.fc.0.weight'\]"):
        Pix2VoxPlusPlus.from_official_checkpoint(path, preset="tiny")

    with pytest.raises(ValueError, match=r"shape mismatches \['encoder.layer1.0.weight: expected \(32, 32, 3, 3\)"):
        Pix2VoxPlusPlus.from_official_checkpoint(
            _released(_perturbed_tiny(seed=2), _RELEASED_TINY_BACKBONE)
            | {
                "encoder_state_dict": {
                    **released["encoder_state_dict"],
                    "module.layer1.0.weight": torch.zeros(32, 32, 1, 1),
                }
            },
            preset="tiny",
        )
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        Pix2VoxPlusPlus.from_official_checkpoint(tmp_path / "nope.pth")


def test_a_checkpoint_recording_no_stride_choice_loads_with_the_presets(tmp_path):
    """LightningCLI records the argument's default, ``merger_stride: None``: the preset's stride, as built."""
    model = Pix2VoxPlusPlus(preset="tiny")
    hparams = {**model.hparams, "merger_stride": None}
    path = tmp_path / "cli.ckpt"
    torch.save(
        {"state_dict": model.state_dict(), "hyper_parameters": hparams, "pytorch-lightning_version": "2.6.0"}, path
    )
    restored = Pix2VoxPlusPlus.load_from_checkpoint(path)
    assert restored.merger.stride == restored.spec.merger_stride == model.merger.stride == 4

"""Pix2Vox++: presets, any view count, input errors, preset-checked checkpoints, overfitting."""

from __future__ import annotations

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from lightning_vtr.metrics import voxel_iou
from lightning_vtr.models.pix2vox import PIX2VOX_PRESETS, Pix2VoxPlusPlus
from lightning_vtr.protocol import ReconstructionModel

R = 32


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
    assert 0 <= out["voxels"].min() and out["voxels"].max() <= 1


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
        2,
        4,
    )


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


def test_two_stage_loss_weighting():
    model = Pix2VoxPlusPlus(preset="tiny", two_stage_loss=True)
    target = torch.zeros(1, R, R, R)
    target[0, :16] = 1
    outputs = {"voxels": torch.full((1, R, R, R), 0.25), "coarse_voxels": torch.full((1, R, R, R), 0.5)}
    # Half the cells are occupied: BCE = (-log 0.25 - log 0.75) / 2 for the refined volume, log 2 for the coarse.
    refined = -(torch.log(torch.tensor(0.25)) + torch.log(torch.tensor(0.75))) / 2
    expected = 10 * (torch.log(torch.tensor(2.0)) + refined)
    torch.testing.assert_close(model.loss(outputs, target), expected)
    model.hparams.two_stage_loss = False
    torch.testing.assert_close(model.loss(outputs, target), refined)


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

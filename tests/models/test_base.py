"""VoxelReconstructionModule: input checks and per-view-set / per-category test logging."""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from lightning_vtr.evaluation.tables import results_from_test_output
from lightning_vtr.models.base import VoxelReconstructionModule, build_adam
from lightning_vtr.models.weights import is_restoring_checkpoint
from lightning_vtr.protocol import ReconstructionModel


class _PassThrough(VoxelReconstructionModule):
    """Predicts voxel (i, j, k) = image[0, 0, i, j] of the first view, for every k."""

    def __init__(self, **kwargs):
        super().__init__(image_size=8, num_views=1, voxel_resolution=4, fscore_points=256, **kwargs)
        self.w = torch.nn.Parameter(torch.zeros(()))
        self.built_while_restoring = is_restoring_checkpoint()

    def reconstruct(self, images):
        return {"voxels": images[:, 0, 0, :4, :4, None].expand(-1, 4, 4, 4) + 0 * self.w}

    def loss(self, outputs, target):
        return ((outputs["voxels"] - target) ** 2).mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _sample(rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Target: rows 0-1 of the i axis; prediction: rows 0..rows-1. IoU = min(rows, 2) / max(rows, 2)."""
    image = torch.zeros(1, 3, 8, 8)
    image[0, 0, :rows, :4] = 1
    voxels = torch.zeros(4, 4, 4)
    voxels[:2] = 1
    return image, voxels


def _batch(rows, view_sets, categories):
    images, voxels = zip(*(_sample(r) for r in rows))
    return {"images": torch.stack(images), "voxels": torch.stack(voxels), "view_set": view_sets, "category": categories}


def test_satisfies_protocol():
    model = _PassThrough()
    assert isinstance(model, ReconstructionModel)
    assert (model.image_size, model.num_views, model.voxel_resolution) == (8, 1, 4)


def test_test_logging_per_view_set_and_category():
    batches = [
        _batch([2, 4], ["aligned", "spherical"], ["chair", "lamp"]),  # IoU 1, 0.5
        _batch([1, 3, 2], ["aligned", "aligned", "spherical"], ["lamp", "lamp", "lamp"]),  # 0.5, 2/3, 1
    ]
    trainer = L.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False)
    out = trainer.test(_PassThrough(), DataLoader(batches, batch_size=None), verbose=False)
    results = results_from_test_output(out)
    assert set(results) == {"aligned", "spherical", "aligned/chair", "aligned/lamp", "spherical/lamp"}
    assert results["aligned"]["iou@0.4"] == pytest.approx((1 + 0.5 + 2 / 3) / 3)
    assert results["aligned"]["iou@0.2"] == pytest.approx((1 + 0.5 + 2 / 3) / 3)
    assert results["aligned/chair"]["iou@0.4"] == pytest.approx(1.0)
    assert results["aligned/lamp"]["iou@0.5"] == pytest.approx((0.5 + 2 / 3) / 2)
    assert results["spherical"]["iou@0.3"] == pytest.approx(0.75)
    assert results["spherical/lamp"]["iou@0.4"] == pytest.approx(0.75)
    assert "hemispherical" not in results  # no samples: nothing logged
    assert 0 <= results["spherical"]["fscore"] <= 1
    assert "fscore" in results["aligned/lamp"]


def test_validation_logs_iou():
    batches = [_batch([2, 4], ["aligned"] * 2, ["a", "a"])]
    model = _PassThrough(validation_fscore=False)
    trainer = L.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False)
    out = trainer.validate(model, DataLoader(batches, batch_size=None), verbose=False)[0]
    assert out["val/iou@0.4"] == pytest.approx(0.75)
    assert "val/fscore" not in out and "val/loss" in out


@pytest.mark.parametrize(
    ("images", "match"),
    [
        (torch.zeros(2, 3, 8, 8), r"\(B, V, 3, 8, 8\).*\(2, 3, 8, 8\)"),
        (torch.zeros(2, 1, 4, 8, 8), r"3 \(RGB\) channels.*got 4"),
        (torch.zeros(2, 1, 3, 8, 6), r"8x8 pixels.*got 8x6"),
        (torch.full((1, 1, 3, 8, 8), float("nan")), "NaN"),
        (torch.zeros(1, 1, 3, 8, 8, dtype=torch.uint8), "floating-point"),
    ],
)
def test_bad_images_raise(images, match):
    with pytest.raises(ValueError, match=match):
        _PassThrough().predict_voxels(images)


def test_one_bad_pixel_is_found_and_finite_pixels_whose_sum_overflows_pass():
    model = _PassThrough()
    one_bad = torch.zeros(2, 1, 3, 8, 8)
    one_bad[1, 0, 2, 7, 7] = float("-inf")
    with pytest.raises(ValueError, match="NaN or infinite"):
        model.predict_voxels(one_bad)
    # Every pixel finite, their float32 sum infinite: the sum alone would refuse them.
    huge = torch.full((1, 1, 3, 8, 8), 3e38)
    assert torch.isinf(huge.sum())
    assert torch.equal(model.predict_voxels(huge), huge[:, 0, 0, :4, :4, None].expand(-1, 4, 4, 4))


def test_bad_targets_and_view_sets_raise():
    model = _PassThrough()
    batch = _batch([2], ["aligned"], ["a"])
    with pytest.raises(ValueError, match=r"\(1, 4, 4, 4\), got \(1, 5, 5, 5\)"):
        model.training_step({**batch, "voxels": torch.zeros(1, 5, 5, 5)}, 0)
    with pytest.raises(
        ValueError,
        match=r"`batch\['view_set'\]` must be one of 'aligned', 'hemispherical', 'spherical', got 'sideways'",
    ):
        model.test_step({**batch, "view_set": ["sideways"]}, 0)


def test_load_from_checkpoint_builds_the_model_while_restoring(tmp_path):
    model = _PassThrough()
    assert not model.built_while_restoring
    with torch.no_grad():
        model.w.fill_(2.5)
    path = tmp_path / "m.ckpt"
    torch.save({"state_dict": model.state_dict(), "pytorch-lightning_version": L.__version__}, path)
    loaded = _PassThrough.load_from_checkpoint(path)
    assert loaded.built_while_restoring and loaded.w.item() == 2.5
    assert not is_restoring_checkpoint()  # the flag ends with the call
    assert not _PassThrough().built_while_restoring


def test_log_sheets_logs_the_first_validation_objects_sheets_as_png_for_a_csv_logger(tmp_path):
    from PIL import Image

    batches = [_batch([2, 4, 3], ["aligned"] * 3, ["a", "a", "b"]), _batch([1], ["aligned"], ["a"])]
    with pytest.raises(ValueError, match="`log_sheets` must be"):
        _PassThrough(log_sheets=-1)

    def validate(log_sheets: int, root):
        logger = L.pytorch.loggers.CSVLogger(str(root), name="", version="")
        trainer = L.Trainer(logger=logger, enable_progress_bar=False, enable_model_summary=False)
        model = _PassThrough(log_sheets=log_sheets, validation_fscore=False)
        trainer.validate(model, DataLoader(batches, batch_size=None), verbose=False)
        assert model._sheet_batch is None  # released after logging
        return sorted((root / "images").rglob("*.png")) if (root / "images").exists() else []

    assert validate(0, tmp_path / "off") == []  # off by default
    one, two = validate(1, tmp_path / "one"), validate(2, tmp_path / "two")
    assert len(one) == len(two) == 1 and two[0].parent.name == "sheets"
    one, two = np.asarray(Image.open(one[0])), np.asarray(Image.open(two[0]))
    # one sheet row per object, the same panels side by side
    assert two.shape[1] == one.shape[1] and two.shape[0] > 1.8 * one.shape[0]


@pytest.mark.parametrize("optimizer_class", [torch.optim.Adam, torch.optim.AdamW])
def test_build_adam_fuses_and_steps_like_the_loop_also_with_gradients_in_another_layout(optimizer_class):
    # torch's fused kernel alone updates a channels_last_3d weight whose gradient is in the default layout against
    # the wrong elements (off by a whole step); build_adam's hook copies such a gradient into the weight's layout.
    torch.manual_seed(0)
    shapes = [(4, 6, 4, 4, 4), (8, 3, 2, 2, 2), (5,)]
    start = [torch.randn(s) for s in shapes]
    start[0] = start[0].contiguous(memory_format=torch.channels_last_3d)
    grads = [[torch.randn(s) for s in shapes] for _ in range(3)]  # default layout
    results = []
    for build in (lambda ps: build_adam(optimizer_class, ps, lr=0.01), lambda ps: optimizer_class(ps, lr=0.01)):
        params = [torch.nn.Parameter(t.clone(memory_format=torch.preserve_format)) for t in start]
        optimizer = build(params)
        for step in grads:
            for p, g in zip(params, step, strict=True):
                p.grad = g.clone()
            optimizer.step()
        results.append((optimizer.defaults["fused"], params))
    (fused, got), (looped, want) = results
    assert fused is True and not looped
    assert got[0].is_contiguous(memory_format=torch.channels_last_3d)
    for a, b, t in zip(got, want, start, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
        assert (a - t).abs().max() > 0.02  # three steps of lr 0.01 moved every weight


def test_build_adam_leaves_integer_or_meta_parameters_to_torchs_default():
    with torch.device("meta"):
        meta = torch.nn.Parameter(torch.zeros(3))
    assert build_adam(torch.optim.Adam, [meta], lr=0.1).defaults["fused"] is None
    groups = [{"params": [torch.nn.Parameter(torch.zeros(2))], "lr": 0.1}]
    assert build_adam(torch.optim.AdamW, groups).defaults["fused"] is True

"""``lightning-vtr predict``: a dataset split or image folders -> binvox, meshes, sheets, predictions.json and
index.html; and the LightningCLI ``predict`` with the prediction writer."""

from __future__ import annotations

import json
import re

import lightning as L
import numpy as np
import pytest
import torch
import trimesh
from helpers import one_thread, save_tiny_checkpoint
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.cli.dispatch import goes_to_lightning
from lightning_vtr.data.binvox import read_binvox, write_binvox
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation.predict import read_view_folder
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.models.registry import load_model

_one_thread = pytest.fixture(autouse=True)(one_thread)
BLOCK = np.zeros((32, 32, 32), np.float32)
BLOCK[8:24, 8:24, 8:24] = 0.9  # 4096 cells


def _sheet_shape(rows, columns, panel=128):
    """compose_sheet's layout: a title line, then rows of captioned panels beside a label column."""
    return (22 + rows * (14 + panel + 4) + 4, 112 + columns * (panel + 4) + 4, 3)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny Pix2Vox++ checkpoint whose datamodule normalised with ``pm1`` (so predict must read it back)."""
    return save_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", normalize="pm1")


@pytest.fixture
def fixed_block(monkeypatch):
    """Every prediction is :data:`BLOCK`; the inputs the model got are recorded."""
    seen = []

    def predict_voxels(self, images):
        seen.append(images.detach().clone())
        return torch.from_numpy(BLOCK).expand(len(images), 32, 32, 32).clone()

    monkeypatch.setattr(Pix2VoxPlusPlus, "predict_voxels", predict_voxels)
    return seen


def test_predict_on_the_test_split(tiny_dataset, checkpoint, fixed_block, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["predict", "--ckpt", str(checkpoint), "--data", str(tiny_dataset), "--view-sets", "spherical"]
    assert main([*argv, "--limit", "3", "--out", str(out)]) == 0

    listing = json.loads((out / "predictions.json").read_text())
    # --limit 3 spreads over the categories (round-robin, fixed order); names are <view set>/<category>/<object>
    assert [e["name"].split("/")[:2] for e in listing] == [["spherical", c] for c in ("airplane", "chair", "table")]
    dm = VTRDataModule(str(tiny_dataset))
    dm.setup()
    for entry in listing:
        folder = out / entry["name"]
        assert read_binvox(folder / "prediction.binvox").sum() == 4096 == entry["facts"]["occupied voxels"]
        mesh = trimesh.load(folder / "prediction.obj", force="mesh")
        # the surface crosses 0.4 between the empty centre of cell 7 and the 0.9 of cell 8: 0.4 / 0.9 of the way
        assert len(mesh.faces) > 0 and mesh.bounds[0][0] == pytest.approx((7.5 + 0.4 / 0.9) / 32 - 0.5, abs=1e-5)
        truth = read_binvox(dm.record(*entry["name"].split("/")[1:]).voxel_path)
        expected_iou = (truth & (BLOCK >= 0.4)).sum() / (truth | (BLOCK >= 0.4)).sum()
        assert entry["facts"]["IoU@0.4"] == pytest.approx(expected_iou)
        assert entry["facts"]["true voxels"] == truth.sum()
        # five rows: 3 input views, prediction, truth, error, error projection at the 3 error-guided views
        assert np.asarray(Image.open(folder / "sheet.png")).shape == _sheet_shape(5, 3)
    page = (out / "index.html").read_text()
    assert page.count("<img ") == 3 and 'src="spherical/airplane/' in page
    # the checkpoint's normalisation (pm1): the white background is 1.0, not ImageNet's 2.25
    images = torch.cat(fixed_block)
    assert images.shape == (3, 3, 3, 64, 64) and images[:, :, :, 0, 0].eq(1.0).all()
    assert f"Wrote 3 objects to {out}" in capsys.readouterr().out
    # an object's views do not depend on which others --limit keeps: they are the test loader's. Without a limit
    # the first chair is the third of the split's 6 test objects (2 per category); with --limit 3 the second.
    assert main([*argv, "--out", str(tmp_path / "all")]) == 0
    assert fixed_block[-1].shape[0] == 6
    torch.testing.assert_close(fixed_block[-1][2], images[1], rtol=0, atol=0)


def _disc(height, width, rgba=True, background=(255, 255, 255)):
    yy, xx = np.mgrid[:height, :width]
    inside = (yy - height / 2) ** 2 + (xx - width / 2) ** 2 < (min(height, width) / 3) ** 2
    picture = np.zeros((height, width, 4), np.uint8)
    picture[...] = (*background, 0 if rgba else 255)
    picture[inside] = (200, 40, 40, 255)
    return picture if rgba else picture[..., :3]


def test_read_view_folder_alpha_from_rgba_mask_or_key(tmp_path):
    Image.fromarray(_disc(40, 60)).save(tmp_path / "a.png")  # RGBA, landscape
    Image.fromarray(_disc(30, 30, rgba=False)).save(tmp_path / "b.png")  # RGB on white: keyed
    Image.fromarray(_disc(20, 20, rgba=False, background=(0, 255, 0))).save(tmp_path / "c.png")  # RGB + mask
    mask = np.zeros((20, 20), np.uint8)
    mask[5:15, 5:15] = 255
    Image.fromarray(mask).save(tmp_path / "c_mask.png")
    pictures, names, truth = read_view_folder(tmp_path, background_key=(255, 255, 255))
    assert names == ["a.png", "b.png", "c.png"] and truth is None
    assert [p.shape for p in pictures] == [(60, 60, 4), (30, 30, 4), (20, 20, 4)]  # padded to squares
    assert (pictures[0][:10, :, 3] == 0).all()  # the padding is transparent
    assert pictures[1][0, 0, 3] == 0 and pictures[1][15, 15, 3] == 255  # white keyed out, the disc kept
    np.testing.assert_array_equal(pictures[2][..., 3], mask)  # the mask is the alpha


def test_read_view_folder_errors_name_the_folder_and_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(f"no pictures in the image folder '{tmp_path}'")):
        read_view_folder(tmp_path)
    Image.fromarray(_disc(20, 20)).save(tmp_path / "v.png")
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(tmp_path / "v_mask.png")
    with pytest.raises(
        ValueError, match=re.escape("the mask 'v_mask.png' must have the size of 'v.png' (20x20), got 10x10")
    ):
        read_view_folder(tmp_path)


def test_predict_on_image_folders(checkpoint, fixed_block, tmp_path):
    rgba, rgb = tmp_path / "mug", tmp_path / "lamp"
    rgba.mkdir()
    rgb.mkdir()
    for i, (h, w) in enumerate([(40, 60), (64, 64), (90, 30)]):  # any count, any size
        Image.fromarray(_disc(h, w)).save(rgba / f"view{i}.png")
    for i in range(2):
        Image.fromarray(_disc(48, 48, rgba=False)).save(rgb / f"{i}.png")
    write_binvox(rgb / "truth.binvox", BLOCK[::-1] >= 0.4)  # the truth: the block flipped (the same block)
    out = tmp_path / "out"
    argv = ["predict", "--ckpt", str(checkpoint), "--images", str(rgba), str(rgb), "--out", str(out)]
    assert main([*argv, "--background-key", "255,255,255", "--mesh-format", "ply"]) == 0

    assert [tuple(images.shape) for images in fixed_block] == [(1, 3, 3, 64, 64), (1, 2, 3, 64, 64)]
    listing = {e["name"]: e for e in json.loads((out / "predictions.json").read_text())}
    assert listing["mug"]["facts"] == {"occupied voxels": 4096}  # no ground truth
    assert listing["lamp"]["facts"]["IoU@0.4"] == 1.0
    assert sorted(p.name for p in (out / "mug").iterdir()) == ["prediction.binvox", "prediction.ply", "sheet.png"]
    assert np.asarray(Image.open(out / "mug" / "sheet.png")).shape == _sheet_shape(2, 3)  # views, prediction
    assert np.asarray(Image.open(out / "lamp" / "sheet.png")).shape == _sheet_shape(5, 3)  # 3 error-guided views
    assert (out / "index.html").read_text().count("<img ") == 2


def test_the_real_forward_pass_is_what_gets_exported(checkpoint, tmp_path):
    folder = tmp_path / "obj"
    folder.mkdir()
    for i in range(3):
        Image.fromarray(_disc(64, 64)).save(folder / f"{i}.png")
    out = tmp_path / "out"
    assert main(["predict", "--ckpt", str(checkpoint), "--images", str(folder), "--out", str(out), "--no-sheets"]) == 0
    model = Pix2VoxPlusPlus.load_from_checkpoint(checkpoint).eval()
    transform = ImageTransform(64, normalize="pm1")
    images = torch.stack([transform(_disc(64, 64)) for _ in range(3)])[None]
    with torch.no_grad():
        expected = model.predict_voxels(images)[0] >= 0.4
    np.testing.assert_array_equal(read_binvox(out / "obj" / "prediction.binvox"), expected.numpy())
    assert not (out / "obj" / "sheet.png").exists()


def test_load_model_finds_the_class_and_names_the_file(checkpoint, tmp_path):
    assert isinstance(load_model(checkpoint), Pix2VoxPlusPlus)
    assert isinstance(load_model(checkpoint, "pix2vox"), Pix2VoxPlusPlus)
    with pytest.raises(ValueError, match="no model class loads the checkpoint .*LRGT: "):
        load_model(checkpoint, "lrgt")
    with pytest.raises(
        FileNotFoundError, match="`--ckpt` must be a checkpoint file, got '.*nope.ckpt' \\(no such file\\)"
    ):
        load_model(tmp_path / "nope.ckpt")


def test_a_user_error_is_one_line_and_status_2(tmp_path, capsys):
    assert main(["predict", "--ckpt", str(tmp_path / "x.ckpt"), "--images", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("lightning-vtr predict: error: `--ckpt` must be a checkpoint file")


@pytest.mark.parametrize(
    ("words", "lightning"),
    [
        (["predict", "--ckpt", "a.ckpt", "--images", "d", "--out", "o"], False),
        (["predict", "--help"], False),
        (["predict", "--config", "c.yaml"], True),
        (["predict", "--print_config"], True),
        (["predict", "--ckpt_path=a.ckpt", "--model=x.Y"], True),
        (["predict", "--trainer.logger=false"], True),
        (["fit", "--ckpt", "a"], True),
        (["report"], False),
    ],
)
def test_predict_is_the_package_command_unless_lightning_words_are_used(words, lightning):
    assert goes_to_lightning(words) is lightning


def test_lightning_cli_predict_writes_through_the_prediction_writer(tiny_dataset, tmp_path):
    out = tmp_path / "out"
    main(
        [
            "predict",
            "--model=lightning_vtr.models.pix2vox.Pix2VoxPlusPlus",
            "--model.preset=tiny",
            f"--data.root={tiny_dataset}",
            "--data.image_size=64",
            "--data.test_view_sets=[hemispherical]",
            "--trainer.logger=false",
            "--trainer.enable_progress_bar=false",
            f"--trainer.default_root_dir={tmp_path}",
            "--trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter",
            f"--trainer.callbacks.output_dir={out}",
            "--trainer.callbacks.panel_size=32",
            "--return_predictions=false",
        ]
    )
    listing = json.loads((out / "predictions.json").read_text())
    # the datamodule's test loaders stand in for a predict loader: 2 test objects in each of the 3 categories
    assert len(listing) == 6 and all(e["name"].startswith("hemispherical/") for e in listing)
    assert all(0.0 <= e["facts"]["IoU@0.4"] <= 1.0 for e in listing)
    assert (out / "index.html").read_text().count("<img ") == 6


def test_an_unknown_model_class_is_named(checkpoint):
    message = "`--model` must be an importable class path module.Class, got 'no.such.Model': module 'no' not found"
    with pytest.raises(ValueError, match=re.escape(message)):
        load_model(checkpoint, "no.such.Model")


def test_a_checkpoint_no_class_loads_names_the_model_option(tmp_path):

    from lightning_vtr.errors import DataError

    torch.save(
        {"state_dict": {"grid": torch.zeros(2)}, "pytorch-lightning_version": L.__version__}, tmp_path / "m.ckpt"
    )
    with pytest.raises(DataError) as error:
        load_model(tmp_path / "m.ckpt")
    assert "needs `--model pix2vox`, `--model lrgt` or `--model module.Class`" in str(error.value)
    assert "Pix2VoxPlusPlus: " in str(error.value) and "LRGT: " in str(error.value)

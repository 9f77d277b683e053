"""``lightning-vtr pix3d`` and ``lightning-vtr evaluate-folder``: checkpoints -> the Table 5 markdown, CSV and JSON,
with values computed by hand; the frame check; user errors."""

from __future__ import annotations

import csv
import json

import lightning as L
import numpy as np
import pytest
import scipy.io
import torch
from helpers import one_thread
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.cli.pix3d import checkpoint_argument
from lightning_vtr.data.binvox import write_binvox
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

_one_thread = pytest.fixture(autouse=True)(one_thread)
# Package-frame predictions (32^3): A is the lower-middle slab Z 8..23 (exactly the chairs' voxels below), B Z 0..15.
BLOCK_A = np.zeros((32, 32, 32), np.float32)
BLOCK_A[:, :, 8:24] = 0.9
BLOCK_B = np.zeros((32, 32, 32), np.float32)
BLOCK_B[:, :, :16] = 0.9


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two tiny Pix2Vox++ checkpoints (pm1 normalisation) told apart by one weight: 1.0 -> BLOCK_A, 0.0 -> BLOCK_B."""
    folder = tmp_path_factory.mktemp("ckpt")
    model = Pix2VoxPlusPlus(preset="tiny")
    dm = VTRDataModule(None, image_size=64, normalize="pm1", batch_size=4)
    paths = []
    for name, mark in (("a.ckpt", 1.0), ("b.ckpt", 0.0)):
        with torch.no_grad():
            model.encoder.backbone[0].bias[0] = mark
        ckpt = {
            "state_dict": {k: v.clone() for k, v in model.state_dict().items()},
            "hyper_parameters": dict(model.hparams),
            "datamodule_hyper_parameters": dict(dm.hparams),
            "pytorch-lightning_version": L.__version__,
        }
        model.on_save_checkpoint(ckpt)
        torch.save(ckpt, folder / name)
        paths.append(folder / name)
    return paths


@pytest.fixture
def fixed_blocks(monkeypatch):
    """Predictions are BLOCK_A or BLOCK_B by the checkpoint's marked weight; the inputs are recorded."""
    seen = []

    def predict_voxels(self, images):
        seen.append(images.detach().clone())
        block = BLOCK_A if float(self.encoder.backbone[0].bias[0]) > 0.5 else BLOCK_B
        return torch.from_numpy(block).expand(len(images), 32, 32, 32).clone()

    monkeypatch.setattr(Pix2VoxPlusPlus, "predict_voxels", predict_voxels)
    return seen


def write_box_pix3d(root):
    """Two chairs and a table, boxes seen face-on. voxel.mat (x_v, y_v, z_v): the chair fills x and y and half of
    z (up), so in the package frame (fitted to the grid) it is Z 8..23; the table fills x and z and half of y_v
    (outward), package X = y_v 8..23. Seen face-on (rot_mat = I: the model frame's x right-left, y up) the chair
    is twice as wide as tall and the table square, as their masks are."""
    chair = np.zeros((64, 64, 64), np.uint8)
    chair[:, :, 16:48] = 1
    table = np.zeros((64, 64, 64), np.uint8)
    table[:, 16:48, :] = 1
    entries = []
    for category, grid, stem, (w, h) in (
        ("chair", chair, "0001", (20, 10)),
        ("chair", chair, "0002", (24, 12)),
        ("table", table, "0003", (16, 16)),
    ):
        (root / "model" / category / "BOX").mkdir(parents=True, exist_ok=True)
        scipy.io.savemat(root / "model" / category / "BOX" / "voxel.mat", {"voxel": grid})
        for kind in ("img", "mask"):
            (root / kind / category).mkdir(parents=True, exist_ok=True)
        image = np.full((30, 40, 3), 90, np.uint8)
        mask = np.zeros((30, 40), np.uint8)
        x0, y0 = 20 - w // 2, 15 - h // 2
        mask[y0 : y0 + h, x0 : x0 + w] = 255
        image[mask > 0] = (200, 50, 50)
        Image.fromarray(image).save(root / "img" / category / f"{stem}.jpg", quality=100)
        Image.fromarray(mask).save(root / "mask" / category / f"{stem}.png")
        entries.append(
            {
                "img": f"img/{category}/{stem}.jpg",
                "mask": f"mask/{category}/{stem}.png",
                "voxel": f"model/{category}/BOX/voxel.mat",
                "category": category,
                "img_size": [40, 30],
                "bbox": [x0, y0, x0 + w - 1, y0 + h - 1],
                "rot_mat": np.eye(3).tolist(),
                "trans_mat": [0.0, 0.0, 12.0],
                "focal_length": 60.0,
                "truncated": False,
                "occluded": False,
                "slightly_occluded": False,
            }
        )
    (root / "pix3d.json").write_text(json.dumps(entries))
    return root


def test_pix3d_command_writes_table5_with_hand_computed_values(checkpoints, fixed_blocks, tmp_path, capsys):
    root = write_box_pix3d(tmp_path / "Pix3D")
    out = tmp_path / "out"
    argv = ["pix3d", "--root", str(root), "--checkpoint", f"Ours={checkpoints[0]}", "--checkpoint", str(checkpoints[1])]
    argv += ["--per-category", "--frame-check", "3", "--fscore-points", "2048", "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    # Chair truth Z 8..23 (16 of 32 layers), table truth X 8..23.
    # A: chairs IoU 1, table 16*16 / (2*16*32 - 16*16) = 1/3.
    # B (Z 0..15): chairs 8/24 = 1/3; table 16*16 / (16*32 + 16*32 - 16*16) = 1/3. Overall: mean over the 3 photographs.
    table = (out / "table.md").read_text()
    assert "| Method | mIoU | F-score | chair mIoU | chair F-score | table mIoU | table F-score |" in table
    rows = {line.split(" | ")[0][2:]: line.split(" | ") for line in table.splitlines() if line.startswith("| ")}
    assert (rows["Ours"][1], rows["Ours"][3], rows["Ours"][5]) == ("77.78", "100.00", "33.33")
    assert (rows["b"][1], rows["b"][3], rows["b"][5]) == ("33.33", "33.33", "33.33")
    assert float(rows["Ours"][4]) > float(rows["b"][4]) + 10  # A's chairs are exact, B's are shifted
    assert "Ours: 3 objects (chair 2, table 1)" in table and table.splitlines()[0] == "# Pix3D"
    assert "| Ours | 77.78 |" in printed
    with open(out / "results.csv", newline="") as f:
        csv_rows = list(csv.DictReader(f))
    assert [(r["method"], r["category"], r["count"]) for r in csv_rows] == [
        ("Ours", "all", "3"),
        ("Ours", "chair", "2"),
        ("Ours", "table", "1"),
        ("b", "all", "3"),
        ("b", "chair", "2"),
        ("b", "table", "1"),
    ]
    assert abs(float(csv_rows[0]["iou@0.4"]) - 7 / 9) < 1e-6 and float(csv_rows[3]["iou@0.5"]) == pytest.approx(1 / 3)
    assert json.loads((out / "results.json").read_text())["b"]["best_threshold"] == 0.2
    # The inputs: one view of 64 px (the checkpoint's size), pm1-normalised, white (1.0) outside the mask.
    assert [tuple(x.shape) for x in fixed_blocks] == [(3, 1, 3, 64, 64)] * 2
    torch.testing.assert_close(fixed_blocks[0][:, 0, :, 0, 0], torch.ones(3, 3))
    assert float(fixed_blocks[0][0, 0, 0, 32, 32]) > 0.5 > float(fixed_blocks[0][0, 0, 1, 32, 32])  # red object
    # The frame check: boxes seen face-on match their masks.
    frame = (out / "frame_check.csv").read_text().splitlines()
    assert frame[0] == "photograph,iou" and [line.split(",")[0] for line in frame[1:]] == [
        "chair/0001",
        "chair/0002",
        "table/0003",
    ]
    assert min(float(line.split(",")[1]) for line in frame[1:]) > 0.9
    assert "frame check on 3 record(s): mean IoU" in printed


def test_pix3d_command_filters_and_user_errors(checkpoints, fixed_blocks, tmp_path, capsys):
    root = write_box_pix3d(tmp_path / "Pix3D")
    out = tmp_path / "out"
    assert (
        main(
            [
                "pix3d",
                "--root",
                str(root),
                "--checkpoint",
                str(checkpoints[0]),
                "--category",
                "table",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "| a | 33.33 |" in (out / "table.md").read_text() and len(fixed_blocks) == 1
    assert main(["pix3d", "--root", str(root), "--checkpoint", str(tmp_path / "x.ckpt"), "--out", str(out)]) == 2
    assert "`--checkpoint` must be a checkpoint file, got" in capsys.readouterr().err
    assert main(["pix3d", "--root", str(tmp_path), "--checkpoint", str(checkpoints[0]), "--out", str(out)]) == 2
    assert "pix3d.json' does not exist: `root` must hold Pix3D's pix3d.json" in capsys.readouterr().err
    assert checkpoint_argument("Ours (LRGT)=runs/x.ckpt")[0] == "Ours (LRGT)"
    assert checkpoint_argument("runs/vtr.ckpt")[0] == "vtr"


def test_evaluate_folder_command(checkpoints, fixed_blocks, tmp_path, capsys):
    images, voxels = tmp_path / "Hemispherical", tmp_path / "ShapeNetVox32"
    truths = {"m1": BLOCK_A > 0.5, "m2": BLOCK_B > 0.5}
    for model, truth in truths.items():
        (images / "03001627" / model).mkdir(parents=True)
        for i in range(4):
            Image.fromarray(np.full((16, 16, 4), (60 * i, 60 * i, 60 * i, 255), np.uint8)).save(
                images / "03001627" / model / f"{i:02d}.png"
            )
        (voxels / "03001627" / model).mkdir(parents=True)
        write_binvox(voxels / "03001627" / model / "model.binvox", truth, up_axis="y")
    out = tmp_path / "out"
    argv = ["evaluate-folder", "--images", str(images), "--voxels", str(voxels), "--checkpoint", f"A={checkpoints[0]}"]
    assert main([*argv, "--views", "2", "--view-choice", "spread", "--out", str(out)]) == 0
    # A predicts BLOCK_A: m1 IoU 1, m2 (Z 0..15 vs 8..23) 8/24.
    table = (out / "table.md").read_text()
    assert "| A | 66.67 |" in table and "hemispherical): 2 objects, 2 view(s) each (spread)" in table
    assert [tuple(x.shape) for x in fixed_blocks] == [(2, 2, 3, 64, 64)]
    # Views 00 and 02 (spread over 4): grey 0 and 120, pm1-normalised.
    expected = torch.tensor([-1.0, 2 * 120 / 255 - 1]).view(1, 2, 1).expand(2, 2, 3)
    torch.testing.assert_close(fixed_blocks[0][:, :, :, 0, 0], expected)

"""``lightning-vtr robustness``: two checkpoints measured on the same objects and view sets; the CSV files, the
difference, the pictures and index.html."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from helpers import one_thread, save_tiny_checkpoint

from lightning_vtr.cli import main
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.evaluation.predict import make_datamodule
from lightning_vtr.evaluation.robustness import RobustnessMap, read_bins_csv, robustness_map
from lightning_vtr.evaluation.robustness_callback import ObjectSubset
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.models.registry import load_model

_one_thread = pytest.fixture(autouse=True)(one_thread)
K = 90  # 2 x 4 = 8 bins


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two tiny Pix2Vox++ checkpoints with different weights (``a.ckpt``, ``b.ckpt``)."""
    folder = tmp_path_factory.mktemp("robustness_ckpt")
    paths = []
    for seed, name in ((0, "a"), (1, "b")):
        paths.append(save_tiny_checkpoint(folder / f"{name}.ckpt", seed=seed))
    return paths


@pytest.fixture(autouse=True)
def view_dependent(monkeypatch):
    """An untrained tiny Pix2Vox++ predicts nearly the same grid from any views; this one depends on the views
    (the contrast of the first view against the mean) and on the weights (the first parameter's sum shifts a
    fixed random field), so the bins and the two checkpoints differ."""
    field = torch.randn(32, 32, 32, generator=torch.Generator().manual_seed(0))

    def predict_voxels(self, images):
        level = images.float().mean(dim=(2, 3, 4))
        contrast = level[:, 0] - level.mean(dim=1)
        offset = next(self.parameters()).detach().flatten()[:64].sum().cpu()
        return torch.sigmoid(30 * contrast[:, None, None, None] + field + 4 * offset)

    monkeypatch.setattr(Pix2VoxPlusPlus, "predict_voxels", predict_voxels)


def _library_map(path, root, records):
    """The map the library measures for one checkpoint on ``records``, seed 0."""
    model = load_model(path)
    subset = ObjectSubset(make_datamodule(path, model, root), records)
    return model, subset, robustness_map(model, subset, k=K, seed=0, progress=False)


def test_two_checkpoints_give_the_library_maps_and_their_difference(tiny_dataset, checkpoints, tmp_path, capsys):
    a, b = checkpoints
    out = tmp_path / "out"
    argv = ["robustness", "--ckpt", f"A={a}", "--ckpt", f"B={b}", "--data", str(tiny_dataset), "--split", "test"]
    code = main([*argv, "--out", str(out), "--k", str(K), "--objects", "2", "--no-progress"])
    assert code == 0, capsys.readouterr().err

    # the objects: 2 of the test split, round-robin over the sorted categories
    dm = VTRDataModule(str(tiny_dataset))
    test = dm.split_records("test")
    records = [next(r for r in test if r.category == c) for c in ("airplane", "chair")]
    _, _, map_a = _library_map(a, tiny_dataset, records)
    _, _, map_b = _library_map(b, tiny_dataset, records)
    assert not np.array_equal(map_a.iou, map_b.iou)  # two different models
    assert not np.array_equal(map_a.iou[:, 0], map_a.iou[:, 5])  # bins differ

    # bins.csv: a checkpoint column, then each map's rows (all objects, then per category), the library's values
    with open(out / "bins.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:3] == ["checkpoint", "category", "bin"]
    assert len(rows) == 2 * 3 * 8  # 2 checkpoints x (all, airplane, chair) x 8 bins
    for name, rmap in (("A", map_a), ("B", map_b)):
        for category in (None, "airplane", "chair"):
            label = category or "all"
            got = [float(r["mean_iou"]) for r in rows if r["checkpoint"] == name and r["category"] == label]
            np.testing.assert_array_equal(got, rmap.mean(category))
    # each map's own folder reads back as the library's map
    again = RobustnessMap.from_csv(out / "maps" / "A")
    np.testing.assert_array_equal(again.iou, map_a.iou)
    assert again.object_ids == [r.object_id for r in records] and again.seed == 0 and again.k == K
    assert [row["mean_iou"] for row in read_bins_csv(out / "maps" / "B" / "bins.csv")][:8] == list(map_b.mean())

    # difference.csv: first minus second, per bin
    with open(out / "difference.csv", newline="") as f:
        diff = list(csv.DictReader(f))
    np.testing.assert_array_equal([float(r["difference"]) for r in diff], map_a.mean() - map_b.mean())
    np.testing.assert_array_equal([float(r["first"]) for r in diff], map_a.mean())

    # pictures and the page
    for png in ("A.png", "B.png", "A_minus_B.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (out / "B_minus_A.png").exists()
    page = (out / "index.html").read_text()
    assert 'src="A_minus_B.png"' in page
    assert f"<td>A</td><td>{map_a.overall():.3f}</td>" in page
    printed = capsys.readouterr().out
    assert f"A: IoU over the sphere {map_a.overall():.4f} (2 objects, 8 bins)" in printed


def test_an_earlier_output_may_be_written_again_and_k_must_divide_180(tiny_dataset, checkpoints, tmp_path, capsys):
    a, _ = checkpoints
    out = tmp_path / "out"
    argv = ["robustness", "--ckpt", str(a), "--data", str(tiny_dataset), "--out", str(out), "--no-progress"]
    assert main([*argv, "--k", "90", "--objects", "1"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "bins.csv", "index.html", "maps"]  # one map, no diff
    assert main([*argv, "--k", "90", "--objects", "1", "--seed", "1"]) == 0  # its bins.csv marks it as ours
    assert read_bins_csv(out / "maps" / "a" / "bins.csv")[0]["objects"] == 1
    capsys.readouterr()
    assert main([*argv, "--k", "40"]) == 2
    assert capsys.readouterr().err.strip() == (
        "lightning-vtr robustness: error: `--k` must be a bin interval K in degrees that divides 180, got 40"
    )

"""Exports of a prediction: binvox, marching-cubes meshes, PNG sheets, the HTML page and the prediction writer."""

from __future__ import annotations

import json
import re

import lightning as L
import numpy as np
import pytest
import torch
import trimesh
from helpers import one_thread
from PIL import Image
from torch import nn

from lightning_vtr.data.binvox import read_binvox
from lightning_vtr.export import (
    VoxelPredictionWriter,
    export_binvox,
    export_mesh,
    export_prediction,
    save_png,
    voxels_to_mesh,
    write_index_html,
)

_one_thread = pytest.fixture(autouse=True)(one_thread)


def _block(r=8, lo=2, hi=6, value=1.0):
    grid = np.zeros((r, r, r), np.float32)
    grid[lo:hi, lo:hi, lo:hi] = value
    return grid


def test_mesh_of_a_block_spans_its_cells_and_is_closed():
    mesh = voxels_to_mesh(_block(), threshold=0.5)  # cells 2..5 of 8: x in [2/8 - .5, 6/8 - .5] at the 0.5 level
    np.testing.assert_allclose(mesh.bounds, [[-0.25] * 3, [0.25] * 3], atol=1e-6)
    assert mesh.is_watertight and mesh.volume > 0  # outward normals
    # at 0.4 the 0 -> 1 step is crossed 0.6 of a cell from the empty centre: 0.1 cell (1/80) further out
    np.testing.assert_allclose(voxels_to_mesh(_block()).bounds, [[-0.2625] * 3, [0.2625] * 3], atol=1e-6)
    # probabilities: the surface sits where they cross the threshold, so 0.45 is in at 0.4 and out at 0.5
    assert len(voxels_to_mesh(_block(value=0.45), threshold=0.4).faces) > 0
    assert len(voxels_to_mesh(_block(value=0.45), threshold=0.5).faces) == 0
    # a bool grid: the surface halfway between occupied and empty cell centres
    np.testing.assert_allclose(voxels_to_mesh(_block() > 0).bounds, mesh.bounds, atol=1e-6)
    with pytest.raises(ValueError, match=re.escape("`threshold` must be a number in (0, 1), got 1.0")):
        voxels_to_mesh(_block(), threshold=1.0)


def test_binvox_export_keeps_the_thresholded_grid(tmp_path):
    probs = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)
    path = export_binvox(tmp_path / "a" / "p.binvox", torch.from_numpy(probs), threshold=0.4)
    grid = read_binvox(path)
    np.testing.assert_array_equal(grid, probs >= 0.4)
    assert grid.sum() == (probs >= 0.4).sum() > 0


@pytest.mark.parametrize("suffix", ["obj", "ply"])
def test_mesh_files_reload_with_the_same_surface(tmp_path, suffix):
    path = export_mesh(tmp_path / f"m.{suffix}", _block())
    loaded = trimesh.load(path, force="mesh")
    expected = voxels_to_mesh(_block())
    assert len(loaded.faces) == len(expected.faces) > 0
    np.testing.assert_allclose(loaded.bounds, expected.bounds, atol=1e-5)
    with pytest.raises(
        ValueError, match=re.escape("`path` must end in one of .obj, .ply, .stl, .off, .glb, got 'm.xyz'")
    ):
        export_mesh(tmp_path / "m.xyz", _block())


def test_export_prediction_writes_every_file(tmp_path):
    sheet = np.full((5, 7, 3), 9, np.uint8)
    paths = export_prediction(tmp_path / "obj", _block(), mesh_format="ply", sheet=sheet)
    assert {k: p.name for k, p in paths.items()} == {
        "binvox": "prediction.binvox",
        "mesh": "prediction.ply",
        "sheet": "sheet.png",
    }
    assert read_binvox(paths["binvox"]).sum() == 4**3
    np.testing.assert_array_equal(np.asarray(Image.open(paths["sheet"])), sheet)
    empty = export_prediction(tmp_path / "empty", np.zeros((8, 8, 8), np.float32), mesh_format="obj")
    assert read_binvox(empty["binvox"]).sum() == 0 and "sheet" not in empty
    with pytest.raises(ValueError, match=re.escape("`image` must be an (H, W, 3) uint8 array, got (5, 7) uint8")):
        save_png(tmp_path / "x.png", sheet[..., 0])


def test_index_page_links_every_sheet_relative_and_escapes_names(tmp_path):
    files = {"sheet": tmp_path / "a b" / "sheet.png", "binvox": tmp_path / "a b" / "prediction.binvox"}
    page = write_index_html(
        tmp_path, [{"name": "<chair> & co", "files": files, "facts": {"IoU@0.4": 0.5}}], title="T", summary="one"
    ).read_text()
    assert '<img src="a%20b/sheet.png"' in page and '<a href="a%20b/prediction.binvox">binvox</a>' in page
    assert "&lt;chair&gt; &amp; co" in page and "<chair>" not in page
    assert "IoU@0.4: 0.5000" in page and "<title>T</title>" in page


class _FixedModel(L.LightningModule):
    """Predicts the block of :func:`_block` for every sample (``predict_step`` as the package's models have it)."""

    def __init__(self):
        super().__init__()
        self.p = nn.Parameter(torch.zeros(()))

    def predict_step(self, batch, batch_idx, dataloader_idx=0):
        return torch.from_numpy(_block(value=0.9)).expand(len(batch["images"]), 8, 8, 8) + 0 * self.p


def test_prediction_writer_exports_each_object_and_the_page(tmp_path):
    truth = [_block(), _block(lo=3)]  # IoU of the predicted block with them: 1 and 27 / 64
    items = [
        {
            "images": torch.rand(2, 3, 16, 16),
            "voxels": torch.from_numpy(t),
            "category": "chair",
            "object_id": f"o{i}",
            "view_set": "spherical",
            "viewpoints": torch.tensor([[0.0, 10.0], [90.0, -20.0]]),
        }
        for i, t in enumerate(truth)
    ]
    writer = VoxelPredictionWriter(tmp_path / "out", panel_size=32)
    trainer = L.Trainer(logger=False, callbacks=[writer], enable_progress_bar=False, enable_model_summary=False)
    trainer.predict(_FixedModel(), torch.utils.data.DataLoader(items, batch_size=2), return_predictions=False)

    listing = json.loads((tmp_path / "out" / "predictions.json").read_text())
    assert [e["name"] for e in listing] == ["spherical/chair/o0", "spherical/chair/o1"]
    assert [e["facts"]["IoU@0.4"] for e in listing] == pytest.approx([1.0, 27 / 64])
    assert [e["facts"]["occupied voxels"] for e in listing] == [64, 64]
    for entry in listing:
        folder = tmp_path / "out" / entry["name"]
        assert read_binvox(folder / "prediction.binvox").sum() == 64
        assert len(trimesh.load(folder / "prediction.obj", force="mesh").faces) > 0
        # the sheet: title + 5 rows (views, prediction, truth, error, projection) of 32 px panels
        assert np.asarray(Image.open(folder / "sheet.png")).shape == (22 + 5 * 50 + 4, 112 + 2 * 36 + 4, 3)
    page = (tmp_path / "out" / "index.html").read_text()
    assert page.count("<img ") == 2 and "mean IoU@0.4 0.7109 over the 2 with ground truth" in page

"""Folder test sets (the VTR authors' ``<set>/<taxonomy>/<model>/NN.png`` + ShapeNetVox32): which pictures an item
uses, the voxels in the package frame, the errors, and the evaluation helper."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from helpers import one_thread
from PIL import Image

from lightning_vtr.data.binvox import write_binvox
from lightning_vtr.data.folder_test_set import FolderTestSet, choose_views
from lightning_vtr.data.shapenet_rendering import ShapeNetRenderingSource
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation.dataset import evaluate_folder, evaluation_rows, format_evaluation_table

_one_thread = pytest.fixture(autouse=True)(one_thread)
RAW = ImageTransform(8, normalize=None)  # 8 px pictures stay 8 px: pixel values come through unchanged


def l_shape(offset: int) -> np.ndarray:
    """An L in the package frame (+Z up): a bar along +X at the bottom and a post at +X's end, moved by ``offset``."""
    grid = np.zeros((8, 8, 8), bool)
    grid[1:7, 2 + offset, 1] = True
    grid[6, 2 + offset, 1:6] = True
    return grid


MODELS = {  # taxonomy -> {model: (picture names, package-frame voxels or None when the file is missing)}
    "03001627": {
        "chair_a": ([f"{i:02d}" for i in range(24)], l_shape(0)),
        "chair_b": ([str(i) for i in range(12)], l_shape(1)),
    },
    "04379243": {"table_a": ([f"{i:02d}" for i in range(6)], l_shape(2)), "table_x": (["00", "01", "02"], None)},
}


def picture_value(model: str, name: str) -> int:
    """The grey level of a picture: says which model and which file it is."""
    return 10 * (int(name) + 1) + (100 if model.endswith("b") else 0)


@pytest.fixture(scope="module")
def test_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("vtr_test")
    images, voxels = root / "Spherical", root / "ShapeNetVox32"
    for taxonomy, models in MODELS.items():
        for model, (names, grid) in models.items():
            folder = images / taxonomy / model
            folder.mkdir(parents=True)
            for name in names:
                value = picture_value(model, name)
                Image.fromarray(np.full((8, 8, 4), (value, value, value, 255), np.uint8)).save(folder / f"{name}.png")
            if grid is not None:
                (voxels / taxonomy / model).mkdir(parents=True)
                write_binvox(voxels / taxonomy / model / "model.binvox", grid, up_axis="y")  # ShapeNetVox32: +Y up
    return images, voxels


def first_pixels(item) -> list[int]:
    return [round(float(v) * 255) for v in item["images"][:, 0, 0, 0]]


def test_view_choice_rules_pick_the_documented_files(test_set):
    images, voxels = test_set
    with pytest.warns(UserWarning, match=r"Skipped 1 object\(s\) .*04379243/table_x/model\.binvox"):
        first = FolderTestSet(images, voxels, num_views=3, transform=RAW)
    assert [r.object_id for r in first.records] == ["chair_a", "chair_b", "table_a"]
    assert [r.category for r in first.records] == ["chair", "chair", "table"]
    assert first.view_set == "spherical"  # from the folder's name
    assert [p.name for p in first.view_paths(1)] == ["0.png", "1.png", "2.png"]
    assert first_pixels(first[1]) == [110, 120, 130]
    spread = FolderTestSet(images, voxels, num_views=3, view_choice="spread", transform=RAW, missing="skip")
    assert [p.name for p in spread.view_paths(0)] == ["00.png", "08.png", "16.png"]
    assert [p.name for p in spread.view_paths(1)] == ["0.png", "4.png", "8.png"]  # numeric order, not 10 < 2
    assert first_pixels(spread[1]) == [110, 150, 190]
    assert [p.name for p in spread.view_paths(2)] == ["00.png", "02.png", "04.png"]
    assert choose_views(24, 4, "spread").tolist() == [0, 6, 12, 18]


def test_random_choice_depends_only_on_the_object_and_the_seed(test_set):
    images, voxels = test_set
    all_objects = FolderTestSet(images, voxels, num_views=3, view_choice="random", transform=RAW, missing="skip")
    chairs = FolderTestSet(images, voxels, num_views=3, view_choice="random", transform=RAW, categories=["chair"])
    picks = all_objects.view_indices(0)
    assert len(set(picks.tolist())) == 3 and np.array_equal(chairs.view_indices(0), picks)
    expected = np.random.default_rng([0, __import__("zlib").crc32(b"03001627/chair_a")]).choice(24, 3, replace=False)
    assert picks.tolist() == expected.tolist()
    other_seed = FolderTestSet(
        images, voxels, num_views=3, view_choice="random", transform=RAW, categories=["chair"], seed=1
    )
    assert not np.array_equal(other_seed.view_indices(0), picks)


def test_voxels_are_what_was_written_in_the_package_frame(test_set):
    images, voxels = test_set
    dataset = FolderTestSet(images, voxels, num_views=2, transform=RAW, missing="skip")
    for index, (taxonomy, model) in enumerate(
        [("03001627", "chair_a"), ("03001627", "chair_b"), ("04379243", "table_a")]
    ):
        item = dataset[index]
        np.testing.assert_array_equal(item["voxels"].numpy(), MODELS[taxonomy][model][1].astype(np.float32))
        assert item["voxels"].dtype == torch.float32 and item["images"].shape == (2, 3, 8, 8)
        assert torch.isnan(item["viewpoints"]).all() and item["viewpoints"].shape == (2, 2)
        assert (item["category"], item["object_id"], item["view_set"]) == (
            dataset.records[index].category,
            model,
            "spherical",
        )
    # The same file through the ShapeNetRendering reader's records lands in the same grid.
    split = images.parent / "split.json"
    split.write_text(json.dumps([{"taxonomy_id": "03001627", "taxonomy_name": "chair", "test": ["chair_a"]}]))
    render = images.parent / "rendering" / "03001627" / "chair_a" / "rendering"
    render.mkdir(parents=True, exist_ok=True)
    (render / "rendering_metadata.txt").write_text("0 30 0 0.8 25\n")
    Image.new("RGBA", (8, 8)).save(render / "00.png")
    (record,) = ShapeNetRenderingSource(images.parent / "rendering", voxels, split).records()
    from lightning_vtr.data.dataset import load_voxels

    np.testing.assert_array_equal(load_voxels(record).numpy(), dataset[0]["voxels"].numpy())


def test_filters_and_errors_name_the_folder(test_set, tmp_path):
    images, voxels = test_set
    split = tmp_path / "split.json"
    split.write_text(json.dumps([{"taxonomy_id": "03001627", "test": ["chair_b"], "train": ["chair_a"]}]))
    listed = FolderTestSet(images, voxels, split_file=split, transform=RAW, view_set="aligned")
    assert [r.object_id for r in listed.records] == ["chair_b"] and listed.view_set == "aligned"
    with pytest.raises(FileNotFoundError, match=r"'.*table_x' has no voxels: '.*table_x/model\.binvox' does not exist"):
        FolderTestSet(images, voxels, categories=["table"], missing="error")
    with pytest.raises(ValueError, match=r"`num_views` must be at most .* got 4; '.*04379243/table_x' has 3"):
        FolderTestSet(images, voxels, num_views=4, categories=["04379243"])
    with pytest.raises(ValueError, match=r"unknown \['sofa'\]"):
        FolderTestSet(images, voxels, categories=["sofa"])
    with pytest.raises(FileNotFoundError, match="`voxel_root` must be a directory"):
        FolderTestSet(images, tmp_path / "nope")


class FixedModel:
    num_views, image_size = 2, 8

    def __init__(self, grid: np.ndarray) -> None:
        self.grid = torch.from_numpy(grid.astype(np.float32))
        self.seen = []

    def predict_voxels(self, images):
        self.seen.append(images.clone())
        return self.grid.expand(images.shape[0], *self.grid.shape).clone()


def test_evaluate_folder_and_its_table(test_set):
    images, voxels = test_set
    predicted = l_shape(0) * 0.9  # exactly chair_a; chair_b and table_a are the same L moved by 1 and 2 cells
    model = FixedModel(predicted)
    with pytest.warns(UserWarning, match="Skipped 1 object"):
        results = evaluate_folder(model, images, voxels, transform=RAW, batch_size=2)
    assert [tuple(x.shape) for x in model.seen] == [(2, 2, 3, 8, 8), (1, 2, 3, 8, 8)]
    assert [round(float(v) * 255) for v in model.seen[0][0, :, 0, 0, 0]] == [10, 20]  # views 00, 01 of chair_a
    cells = l_shape(0).sum()  # 10; a shift by one cell keeps no cell in common (the L lies in one y-slice)
    assert cells == 10
    chair = (1.0 + 0.0) / 2
    for key in ("iou@0.2", "iou@0.5"):
        assert math.isclose(results["categories"]["chair"][key], chair)
        assert results["categories"]["table"][key] == 0.0
        assert math.isclose(results["overall"][key], 1 / 3, rel_tol=1e-6)  # float32 metrics
    assert results["categories"]["chair"]["count"] == 2 and results["overall"]["count"] == 3
    table = format_evaluation_table({"Fixed": results}, categories=["chair", "table"])
    lines = table.splitlines()
    assert lines[0] == "| Method | mIoU | F-score | chair mIoU | chair F-score | table mIoU | table F-score |"
    f_all, f_chair, f_table = (g["fscore"] for g in (results["overall"], *results["categories"].values()))
    assert f_chair > f_table and math.isclose(f_all, (2 * f_chair + f_table) / 3, rel_tol=1e-5)
    assert (
        lines[2] == f"| Fixed | 33.33 | {100 * f_all:.2f} | 50.00 | {100 * f_chair:.2f} | 0.00 | {100 * f_table:.2f} |"
    )
    rows = evaluation_rows({"Fixed": results})
    assert [(r["method"], r["category"], r["count"]) for r in rows] == [
        ("Fixed", "all", 3),
        ("Fixed", "chair", 2),
        ("Fixed", "table", 1),
    ]
